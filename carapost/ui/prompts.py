"""Every question the GUI asks the user, in one replaceable object.

Commands never open a dialog directly; they call ``window.prompts``. Tests substitute an object
with the same methods that answers without a modal dialog.
"""

from __future__ import annotations

from PySide6.QtGui import QColor
from PySide6.QtWidgets import QColorDialog, QFileDialog, QInputDialog, QMessageBox, QWidget

__all__ = ["Prompts"]


class Prompts:
    """Modal dialogs parented to ``parent``; each returns None when the user cancels."""

    def __init__(self, parent: QWidget) -> None:
        self.parent = parent

    def open_file(self, title: str, filters: str, folder: str = "") -> str | None:
        path, _ = QFileDialog.getOpenFileName(self.parent, title, folder, filters)
        return path or None

    def open_files(self, title: str, filters: str, folder: str = "") -> list[str] | None:
        paths, _ = QFileDialog.getOpenFileNames(self.parent, title, folder, filters)
        return paths or None

    def open_folder(self, title: str, folder: str = "") -> str | None:
        return QFileDialog.getExistingDirectory(self.parent, title, folder) or None

    def save_file(self, title: str, filters: str, folder: str = "") -> str | None:
        path, _ = QFileDialog.getSaveFileName(self.parent, title, folder, filters)
        return path or None

    def get_int(self, title: str, label: str, value: int, lo: int, hi: int) -> int | None:
        v, ok = QInputDialog.getInt(self.parent, title, label, value, lo, hi)
        return int(v) if ok else None

    def get_text(self, title: str, label: str, text: str = "") -> str | None:
        v, ok = QInputDialog.getText(self.parent, title, label, text=text)
        return v if ok else None

    def get_colour(self, title: str, colour: tuple[int, int, int]) -> tuple[int, int, int] | None:
        c = QColorDialog.getColor(QColor(*colour), self.parent, title)
        return (c.red(), c.green(), c.blue()) if c.isValid() else None

    def save_discard_cancel(self, text: str) -> str:
        """``"save"``, ``"discard"`` or ``"cancel"``."""
        box = QMessageBox(QMessageBox.Icon.Warning, "Unsaved changes", text,
                          QMessageBox.StandardButton.Save | QMessageBox.StandardButton.Discard
                          | QMessageBox.StandardButton.Cancel, self.parent)
        box.setDefaultButton(QMessageBox.StandardButton.Save)
        res = box.exec()
        return {QMessageBox.StandardButton.Save: "save",
                QMessageBox.StandardButton.Discard: "discard"}.get(QMessageBox.StandardButton(res), "cancel")

    def info(self, title: str, text: str) -> None:
        QMessageBox.information(self.parent, title, text)
