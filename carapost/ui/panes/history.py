"""History pane: a view of the undo stack. Entries that can be undone are drawn in the normal
text colour, undone entries (that can be redone) in red; clicking an entry moves the history
there. "Clear History" frees the memory the entries hold."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtGui import QAction, QColor
from PySide6.QtWidgets import QListWidget, QListWidgetItem, QPushButton, QVBoxLayout, QWidget

from ..document import Document

__all__ = ["HistoryPane", "UNDONE"]

UNDONE = QColor(235, 70, 70)


class HistoryPane(QWidget):
    def __init__(self, doc: Document, actions: dict[str, QAction], parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        self.list = QListWidget()
        self.list.setObjectName("historyList")
        self.list.itemClicked.connect(self._clicked)
        # long entries ("Detect Blobs [Current Frame]: 296 detections") end in "…"; the tooltip has all
        self.list.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.list.setTextElideMode(Qt.TextElideMode.ElideRight)
        lay.addWidget(self.list, 1)
        clear = QPushButton("Clear History")
        clear.clicked.connect(actions["edit.clear_history"].trigger)
        lay.addWidget(clear)
        stack = doc.undo
        stack.indexChanged.connect(lambda _i: self.rebuild())
        stack.cleanChanged.connect(lambda _c: self.rebuild())
        doc.sessionChanged.connect(self.rebuild)
        self.rebuild()

    def entries(self) -> list[tuple[str, bool]]:
        """(text, applied) of every command, oldest first."""
        st = self.doc.undo
        return [(st.text(i), i < st.index()) for i in range(st.count())]

    def rebuild(self) -> None:
        self.list.clear()
        base = QListWidgetItem("<start>")
        base.setData(Qt.ItemDataRole.UserRole, 0)
        self.list.addItem(base)
        for i, (text, applied) in enumerate(self.entries()):
            item = QListWidgetItem(text)
            item.setData(Qt.ItemDataRole.UserRole, i + 1)
            item.setToolTip(text)
            if not applied:
                item.setForeground(UNDONE)
                item.setToolTip(f"{text}\nUndone: Edit > Redo (Ctrl+Y) applies it again")
            self.list.addItem(item)
        self.list.setCurrentRow(self.doc.undo.index())

    def _clicked(self, item: QListWidgetItem) -> None:
        if self.doc.busy:
            return
        self.doc.undo.setIndex(int(item.data(Qt.ItemDataRole.UserRole)))
