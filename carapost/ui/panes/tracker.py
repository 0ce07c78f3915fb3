"""Tracker pane: the Target Tracker's buttons and its settings (generated from
:class:`~carapost.model.params.TrackerSettings`)."""

from __future__ import annotations

from PySide6.QtGui import QAction
from PySide6.QtWidgets import QFormLayout, QGridLayout, QGroupBox, QToolButton, QVBoxLayout, QWidget

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
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        grid = QGridLayout()
        self.buttons: dict[str, QToolButton] = {}
        for i, key in enumerate(BUTTONS):
            b = QToolButton()
            b.setDefaultAction(actions[key])
            if key in SHORT:
                b.setText(SHORT[key])
            b.setObjectName(key)
            grid.addWidget(b, 0 if key in SHORT else 1 + (i - 4) // 2, i if key in SHORT else (i - 4) % 2 * 2, 1,
                           1 if key in SHORT else 2)
            self.buttons[key] = b
        lay.addLayout(grid)
        self.settings_button = QToolButton()
        self.settings_button.setText("Settings")
        self.settings_button.setCheckable(True)
        self.settings_button.setChecked(True)
        lay.addWidget(self.settings_button)
        self.box = QGroupBox("Settings")
        form = QFormLayout(self.box)
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
