"""Tracker pane: the Target Tracker's buttons and its settings (generated from
:class:`~carapost.model.params.TrackerSettings`)."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtGui import QAction
from PySide6.QtWidgets import QFormLayout, QFrame, QGridLayout, QGroupBox, QScrollArea, QSizePolicy, QToolButton, QVBoxLayout, QWidget

from ..document import Document
from .param_editors import SectionEditors

__all__ = ["TrackerPane"]

BUTTONS = ("tracker.back_to_start", "tracker.back_one", "tracker.forward_one", "tracker.forward_to_end",
           "tracker.clear", "tracker.add_keyframe")
SHORT = {"tracker.back_to_start": "|<", "tracker.back_one": "<", "tracker.forward_one": ">",
         "tracker.forward_to_end": ">|"}


class TrackerPane(QWidget):
    """Buttons follow their actions (state, tooltips); the settings are take parameters."""

    def __init__(self, doc: Document, actions: dict[str, QAction], parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        outer = QVBoxLayout(self)
        outer.setContentsMargins(0, 0, 0, 0)
        scroll = QScrollArea()   # scrolls rather than widening the dock area in a small window
        scroll.setWidgetResizable(True)
        scroll.setFrameShape(QFrame.Shape.NoFrame)
        outer.addWidget(scroll)
        inner = QWidget()
        scroll.setWidget(inner)
        lay = QVBoxLayout(inner)
        lay.setContentsMargins(2, 2, 2, 2)
        grid = QGridLayout()
        grid.setSpacing(3)
        self.buttons: dict[str, QToolButton] = {}
        for i, key in enumerate(BUTTONS):
            act = actions[key]
            b = QToolButton()
            if key in SHORT:
                # the short arrow text stays (a default action would put its long text back)
                b.setText(SHORT[key])
                b.setToolTip(act.text().lstrip("<> "))
                b.clicked.connect(act.trigger)
                act.changed.connect(lambda b=b, a=act: b.setEnabled(a.isEnabled()))
                b.setEnabled(act.isEnabled())
                b.setMinimumWidth(36)
                grid.addWidget(b, 0, i)
            else:
                b.setDefaultAction(act)
                b.setToolButtonStyle(Qt.ToolButtonStyle.ToolButtonTextOnly)
                b.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Fixed)
                grid.addWidget(b, 1 + i - len(SHORT), 0, 1, len(SHORT))
            b.setObjectName(key)
            self.buttons[key] = b
        lay.addLayout(grid)
        self.settings_button = QToolButton()
        self.settings_button.setText("Settings")
        self.settings_button.setCheckable(True)
        self.settings_button.setChecked(True)
        lay.addWidget(self.settings_button)
        self.box = QGroupBox("Settings")
        form = QFormLayout(self.box)
        form.setRowWrapPolicy(QFormLayout.RowWrapPolicy.WrapLongRows)   # narrow pane: editor under its label
        self.editors = SectionEditors(doc, "tracker")
        for f in self.editors.fields():
            form.addRow(f.metadata["label"], self.editors.editors[f.name])
        lay.addWidget(self.box)
        lay.addStretch(1)
        self.settings_button.toggled.connect(self.box.setVisible)
        doc.takeChanged.connect(self.editors.refresh)
        doc.sessionChanged.connect(self.editors.refresh)
        doc.busyChanged.connect(lambda _b: self.editors.refresh())
        self.editors.refresh()
