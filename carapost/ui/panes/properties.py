"""Properties pane: every parameter section of the take, generated from the dataclasses, plus
the Shortcut section (read-only) and a preset chooser for dense / sparse marker sets."""

from __future__ import annotations

import logging

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QComboBox, QHBoxLayout, QHeaderView, QLabel, QTreeWidget, QTreeWidgetItem, QVBoxLayout, QWidget

from carapost.model.params import PRESETS, SECTIONS
from carapost.ops import settings as settings_ops

from ..document import Document
from .param_editors import SectionEditors, field_tooltip

__all__ = ["PropertiesPane"]

log = logging.getLogger("carapost")

#: Sections shown here (the Tracker pane shows the tracker settings).
PANE_SECTIONS = [k for k in SECTIONS if k != "tracker"]


class PropertiesPane(QWidget):
    """The Properties pane.

    Parameters
    ----------
    doc : Document
    shortcuts : list of (text, shortcut)
        The Shortcut section's rows.
    """

    def __init__(self, doc: Document, shortcuts: list[tuple[str, str]], parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        top = QHBoxLayout()
        top.addWidget(QLabel("Preset:"))
        self.preset = QComboBox()
        self.preset.addItems(["(choose)", *PRESETS])
        self.preset.setToolTip("The guide's parameter sets: default, dense (156 markers), sparse (35 markers)")
        self.preset.activated.connect(self._preset)
        top.addWidget(self.preset, 1)
        lay.addLayout(top)
        self.tree = QTreeWidget()
        self.tree.setColumnCount(2)
        self.tree.setHeaderLabels(["Property", "Value"])
        self.tree.setAlternatingRowColors(True)
        self.tree.setRootIsDecorated(True)
        lay.addWidget(self.tree, 1)
        self.sections: dict[str, SectionEditors] = {}
        for key in PANE_SECTIONS:
            ed = SectionEditors(doc, key)
            self.sections[key] = ed
            head = QTreeWidgetItem(self.tree, [ed.cls.title])
            head.setFirstColumnSpanned(True)
            for f in ed.fields():
                label = f.metadata["label"] + (f" ({f.metadata['unit']})" if f.metadata.get("unit") else "")
                item = QTreeWidgetItem(head, [label])
                item.setToolTip(0, field_tooltip(f))
                self.tree.setItemWidget(item, 1, ed.editors[f.name])
            head.setExpanded(key in ("display", "blobs", "tracking"))
            if key == "export":   # the guide lists Shortcut after Export
                self._shortcuts(shortcuts)
        # names take what the values leave: a narrow pane still shows every value
        header = self.tree.header()
        header.setStretchLastSection(False)
        header.setSectionResizeMode(0, QHeaderView.ResizeMode.Stretch)
        header.setSectionResizeMode(1, QHeaderView.ResizeMode.Fixed)
        header.resizeSection(1, 100)
        self.tree.setIndentation(12)
        header.setMinimumSectionSize(60)
        doc.takeChanged.connect(self.refresh)
        doc.sessionChanged.connect(self.refresh)
        doc.busyChanged.connect(lambda _b: self.refresh())
        self.refresh()

    def _shortcuts(self, shortcuts: list[tuple[str, str]]) -> None:
        head = QTreeWidgetItem(self.tree, ["Shortcut"])
        head.setFirstColumnSpanned(True)
        for text, key in shortcuts:
            item = QTreeWidgetItem(head, [text, key])
            item.setFlags(item.flags() & ~Qt.ItemFlag.ItemIsEditable)

    def refresh(self) -> None:
        for ed in self.sections.values():
            ed.refresh()
        self.preset.setEnabled(self.doc.has_take and not self.doc.busy)

    def _preset(self, index: int) -> None:
        name = self.preset.itemText(index)
        self.preset.setCurrentIndex(0)
        if name in PRESETS and self.doc.has_take:
            try:
                self.doc.apply(settings_ops.apply_preset(self.doc.take, name))
            except ValueError as exc:
                log.error("%s", exc)
