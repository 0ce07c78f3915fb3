"""Labelling pane: the take's label list coloured by state (red: not assigned to a point;
grey: assigned; yellow: assigned but the point has no data in the current frame)."""

from __future__ import annotations

import logging

import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtGui import QAction, QColor
from PySide6.QtWidgets import QAbstractItemView, QLabel, QListWidget, QListWidgetItem, QPushButton, QVBoxLayout, \
    QWidget

from carapost.ops import labels as label_ops

from ..document import Document

__all__ = ["LabellingPane", "UNASSIGNED", "ASSIGNED", "ABSENT", "label_states"]

log = logging.getLogger("carapost")

UNASSIGNED, ASSIGNED, ABSENT = QColor(235, 70, 70), QColor(170, 170, 170), QColor(240, 220, 40)


def label_states(labels: list[str], point_labels: list[str], present: np.ndarray) -> list[str]:
    """State of each label: ``"unassigned"``, ``"assigned"`` or ``"absent"`` (assigned, but the
    point has no 3D data in the current frame). ``present (P,)`` flags points with data."""
    owner = {lab: i for i, lab in enumerate(point_labels) if lab}
    out = []
    for lab in labels:
        i = owner.get(lab, -1)
        out.append("unassigned" if i < 0 else "assigned" if present[i] else "absent")
    return out


class LabellingPane(QWidget):
    COLOURS = {"unassigned": UNASSIGNED, "assigned": ASSIGNED, "absent": ABSENT}

    def __init__(self, doc: Document, actions: dict[str, QAction], parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        row = QVBoxLayout()   # stacked: the pane stays narrow without clipping the guide's texts
        row.setSpacing(2)
        for key, text in (("edit.clear_labels", "Clear All Labels"), ("edit.delete_labels", "Delete Selected Labels")):
            b = QPushButton(text)
            b.setObjectName(key)
            b.clicked.connect(actions[key].trigger)
            row.addWidget(b)
        lay.addLayout(row)
        self.list = QListWidget()
        self.list.setObjectName("labelList")
        self.list.setSelectionMode(QAbstractItemView.SelectionMode.ExtendedSelection)
        self.list.setEditTriggers(QAbstractItemView.EditTrigger.DoubleClicked)
        self.list.itemChanged.connect(self._edited)
        lay.addWidget(self.list, 1)
        self.empty = QLabel("No labels yet: File > Import Labels From Text File (or From Cara File)")
        self.empty.setObjectName("labelsHint")
        self.empty.setWordWrap(True)
        self.empty.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.empty.setStyleSheet("color: rgb(175, 178, 185);")
        lay.addWidget(self.empty)
        self.assign = QPushButton("Assign To Selected Point")
        self.assign.setToolTip("Give the selected label to the (one) selected point")
        self.assign.clicked.connect(self.assign_selected)
        lay.addWidget(self.assign)
        for sig in (doc.takeChanged, doc.sessionChanged):
            sig.connect(self.rebuild)
        doc.frameChanged.connect(lambda _f: self.recolour())
        self.rebuild()

    def selected_labels(self) -> list[str]:
        return [it.data(Qt.ItemDataRole.UserRole) for it in self.list.selectedItems()]

    def rebuild(self) -> None:
        selected = set(self.selected_labels())
        self.list.blockSignals(True)
        self.list.clear()
        if self.doc.has_take:
            for lab in self.doc.take.labels:
                item = QListWidgetItem(lab)
                item.setData(Qt.ItemDataRole.UserRole, lab)
                item.setFlags(item.flags() | Qt.ItemFlag.ItemIsEditable)
                self.list.addItem(item)
                item.setSelected(lab in selected)
        self.list.blockSignals(False)
        self.empty.setVisible(self.list.count() == 0)
        self._states: list[str] = []   # the new items are coloured from scratch
        self.recolour()

    def states(self) -> list[str]:
        if not self.doc.has_take:
            return []
        take = self.doc.take
        present = np.isfinite(take.xyz[self.doc.frame]).all(-1) if take.n_points else np.zeros(0, bool)
        return label_states(take.labels, take.points.labels, present)

    def recolour(self) -> None:
        """Colour the labels by state; only items whose state changed are touched (this runs on
        every frame while scrubbing)."""
        self.list.blockSignals(True)
        states = self.states()
        known = self._states
        for i, state in enumerate(states):
            item = self.list.item(i)
            if item is not None and (i >= len(known) or known[i] != state):
                item.setForeground(self.COLOURS[state])
                item.setToolTip({"unassigned": "Not assigned to a point", "assigned": "Assigned",
                                 "absent": "Assigned; the point has no data in this frame"}[state])
        self._states = states
        self.list.blockSignals(False)

    def _edited(self, item: QListWidgetItem) -> None:
        old, new = item.data(Qt.ItemDataRole.UserRole), item.text()
        if new == old:
            return
        try:
            self.doc.apply(label_ops.rename_label(self.doc.take, old, new))
        except ValueError as exc:
            log.error("%s", exc)
        self.rebuild()

    def assign_selected(self) -> None:
        labels = self.selected_labels()
        cols = self.doc.selected_columns()
        if len(labels) != 1 or len(cols) != 1:
            log.error("Assign label: select one label and one point")
            return
        try:
            self.doc.apply(label_ops.assign_label(self.doc.take, cols[0], labels[0]))
        except ValueError as exc:
            log.error("%s", exc)
