"""Dialogs: Relocate Files, and the window showing the calibration brim SVG."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QByteArray, Qt
from PySide6.QtWidgets import QDialog, QDialogButtonBox, QLabel, QPushButton, QTableWidget, QTableWidgetItem, \
    QVBoxLayout, QWidget

if TYPE_CHECKING:  # pragma: no cover
    from .main_window import MainWindow

__all__ = ["RelocateFilesDialog", "SvgWindow"]

log = logging.getLogger("carapost")


class RelocateFilesDialog(QDialog):
    """Edit > Relocate Files: point each camera at its (moved) ``.pico`` / video / image folder."""

    def __init__(self, window: "MainWindow") -> None:
        super().__init__(window)
        self.window_ = window
        self.setWindowTitle("Relocate Files")
        lay = QVBoxLayout(self)
        lay.addWidget(QLabel("Camera files of the project (missing ones in red). Browse to locate a file."))
        take = window.doc.take
        self.table = QTableWidget(take.n_cameras, 3)
        self.table.setHorizontalHeaderLabels(["Camera", "File", ""])
        self.table.horizontalHeader().setStretchLastSection(False)
        self.table.setColumnWidth(1, 420)
        lay.addWidget(self.table)
        self.refresh()
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Close)
        buttons.rejected.connect(self.reject)
        lay.addWidget(buttons)
        self.resize(680, 120 + 30 * take.n_cameras)

    def refresh(self) -> None:
        w = self.window_
        take, session = w.doc.take, w.doc.session
        for c, cam in enumerate(take.cameras):
            self.table.setItem(c, 0, QTableWidgetItem(f"{c}  {cam.name}"))
            item = QTableWidgetItem(cam.source.path if cam.source is not None else "(none)")
            if session is None or session.sources[c] is None:
                item.setForeground(Qt.GlobalColor.red)
            self.table.setItem(c, 1, item)
            b = QPushButton("Browse...")
            b.clicked.connect(lambda _c=False, cc=c: self._browse(cc))
            self.table.setCellWidget(c, 2, b)

    def _browse(self, camera: int) -> None:
        w = self.window_
        cam = w.doc.take.cameras[camera]
        start = str(Path(cam.source.path).parent) if cam.source is not None else w.last_dir()
        if cam.source is not None and cam.source.kind == "images":
            path = w.prompts.open_folder(f"Relocate camera {camera}", start)
        else:
            path = w.prompts.open_file(f"Relocate camera {camera}", "Camera files (*.pico *.avi *.mp4 *.mov *.mkv);;"
                                       "All files (*)", start)
        if path:
            try:
                w.relocate(camera, path)
            except ValueError as exc:
                log.error("%s", exc)
            self.refresh()


class SvgWindow(QWidget):
    """View > Show Calibration Brim SVG: a floating window with the brim drawing."""

    def __init__(self, svg: str, title: str, parent: QWidget | None = None) -> None:
        super().__init__(parent, Qt.WindowType.Window)
        from PySide6.QtSvgWidgets import QSvgWidget

        self.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose, True)
        self.setWindowTitle(title)
        lay = QVBoxLayout(self)
        self.svg = QSvgWidget()
        self.svg.load(QByteArray(svg.encode("utf-8")))
        self.svg.setStyleSheet("background: white")
        lay.addWidget(self.svg)
        size = self.svg.renderer().defaultSize()
        scale = min(900 / max(size.width(), 1), 600 / max(size.height(), 1))
        self.resize(max(200, int(size.width() * scale)), max(150, int(size.height() * scale)))
