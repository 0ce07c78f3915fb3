"""Selection pane: the explicit camera (channel) selection used by Detect Blobs, Detach
Detections, Rotate Selected Sensors..., and a summary of the selected points and detections."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QLabel, QListWidget, QListWidgetItem, QPushButton, QHBoxLayout, QVBoxLayout, QWidget

from ..document import Document

__all__ = ["SelectionPane"]


CHECKBOX_STYLE = ("QListWidget::indicator { width: 12px; height: 12px; border: 1px solid rgb(160, 162, 170);"
                  " border-radius: 2px; background: rgb(62, 64, 70); }"
                  " QListWidget::indicator:checked { background: rgb(255, 140, 0); border-color: rgb(255, 200, 120); }")


class SelectionPane(QWidget):
    def __init__(self, doc: Document, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        head = QLabel("Channels (explicit camera selection):")
        head.setWordWrap(True)   # a narrow dock wraps the text instead of widening the window
        lay.addWidget(head)
        self.cameras = QListWidget()
        self.cameras.setObjectName("selectionCameras")
        self.cameras.itemChanged.connect(self._changed)
        # the dark Fusion palette draws item check boxes in the list's own colour: make them visible
        self.cameras.setStyleSheet(CHECKBOX_STYLE)
        lay.addWidget(self.cameras, 1)
        row = QHBoxLayout()
        clear = QPushButton("Clear Channel Selection")
        clear.clicked.connect(lambda: doc.set_camera_selection([]))
        row.addWidget(clear)
        lay.addLayout(row)
        self.summary = QLabel()
        self.summary.setWordWrap(True)
        lay.addWidget(self.summary)
        self.points = QListWidget()
        self.points.setObjectName("selectionPoints")
        lay.addWidget(self.points, 2)
        doc.sessionChanged.connect(self.rebuild)
        doc.takeChanged.connect(self.refresh)
        doc.selectionChanged.connect(self.refresh)
        doc.activeCameraChanged.connect(self.refresh)
        self.rebuild()

    def rebuild(self) -> None:
        self.cameras.blockSignals(True)
        self.cameras.clear()
        if self.doc.has_take:
            for c, cam in enumerate(self.doc.take.cameras):
                item = QListWidgetItem(f"Channel {c}  {cam.name}")
                item.setFlags(item.flags() | Qt.ItemFlag.ItemIsUserCheckable)
                item.setCheckState(Qt.CheckState.Unchecked)
                self.cameras.addItem(item)
        self.cameras.blockSignals(False)
        self.refresh()

    def _changed(self, _item: QListWidgetItem) -> None:
        cams = [i for i in range(self.cameras.count())
                if self.cameras.item(i).checkState() == Qt.CheckState.Checked]
        self.doc.set_camera_selection(cams)

    def refresh(self) -> None:
        doc = self.doc
        self.cameras.blockSignals(True)
        for i in range(self.cameras.count()):
            self.cameras.item(i).setCheckState(Qt.CheckState.Checked if i in doc.sel_cameras
                                               else Qt.CheckState.Unchecked)
        self.cameras.blockSignals(False)
        self.points.clear()
        if not doc.has_take:
            self.summary.setText("No take open")
            return
        take = doc.take
        cols = doc.selected_columns()
        self.summary.setText(f"{len(cols)} point(s), {len(doc.sel_detections)} detection(s) selected; "
                             f"active camera view: {doc.active_camera if doc.active_camera is not None else '-'}")
        for c in cols[:500]:
            self.points.addItem(f"{take.points.name(c)}  (id {int(take.points.ids[c])})")
        for cam, f, i in doc.sel_detections[:500]:
            self.points.addItem(f"Detection {i}  sensor {cam}  frame {f}")
