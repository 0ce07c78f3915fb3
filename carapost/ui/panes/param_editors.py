"""Editors generated from the parameter dataclasses' field metadata (label, unit, range, help).

One :class:`SectionEditors` per Properties-pane section: a checkbox for a bool, a spin box for a
number (range from ``lo``/``hi``), a combo box for a text with ``choices``. A committed edit
becomes ``ops.settings.set_property`` pushed onto the undo stack; a rejected value is logged and
the editor shows the take's value again.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

from PySide6.QtGui import QColor, QPalette
from PySide6.QtWidgets import QAbstractSpinBox, QCheckBox, QComboBox, QDoubleSpinBox, QLineEdit, QSpinBox, QWidget

from carapost.model.params import SECTIONS, ParamSection
from carapost.ops import settings as settings_ops

from ..document import Document

__all__ = ["SectionEditors", "field_tooltip"]

log = logging.getLogger("carapost")


def field_tooltip(f: dataclasses.Field) -> str:
    md = f.metadata
    parts = [md.get("help") or md["label"]]
    rng = []
    if md.get("lo") is not None or md.get("hi") is not None:
        rng.append(f"range {md.get('lo', '')}..{md.get('hi', '') if md.get('hi') is not None else ''}")
    if md.get("unit"):
        rng.append(md["unit"])
    parts.append(f"Default {f.default}" + (f" ({', '.join(rng)})" if rng else ""))
    return "\n".join(parts)


class SectionEditors:
    """Editors for the fields of one parameter section.

    Parameters
    ----------
    doc : Document
    key : str
        Section key of :class:`~carapost.model.params.Parameters` (``"blobs"``, ``"tracker"``...).
    """

    def __init__(self, doc: Document, key: str) -> None:
        self.doc = doc
        self.key = key
        self.cls: type[ParamSection] = SECTIONS[key]
        self.editors: dict[str, QWidget] = {}
        defaults = self.cls()
        for f in self.cls.fields():
            self.editors[f.name] = self._make(f, getattr(defaults, f.name))

    def fields(self) -> tuple[dataclasses.Field, ...]:
        return self.cls.fields()

    # ------------------------------------------------------------------ building
    def _make(self, f: dataclasses.Field, value: Any) -> QWidget:
        md = f.metadata
        w: QWidget
        if isinstance(f.default, bool):
            w = QCheckBox()
            w.setChecked(bool(value))
            pal = w.palette()             # a visible box for unchecked values on the dark theme
            pal.setColor(QPalette.ColorRole.Base, QColor(88, 92, 102))
            w.setPalette(pal)
            w.toggled.connect(lambda on, n=f.name: self.commit(n, bool(on)))
        elif isinstance(f.default, int):
            w = QSpinBox()
            w.setRange(int(md["lo"]) if md["lo"] is not None else -10**9,
                       int(md["hi"]) if md["hi"] is not None else 10**9)
            w.setValue(int(value))
            w.setKeyboardTracking(False)
            w.valueChanged.connect(lambda v, n=f.name: self.commit(n, int(v)))
        elif isinstance(f.default, float):
            w = QDoubleSpinBox()
            w.setDecimals(3)
            w.setRange(float(md["lo"]) if md["lo"] is not None else -1e9,
                       float(md["hi"]) if md["hi"] is not None else 1e9)
            hi, lo = md["hi"], md["lo"]
            w.setSingleStep(0.05 if (hi is not None and lo is not None and hi - lo <= 1) else 0.5)
            w.setValue(float(value))
            w.setKeyboardTracking(False)
            w.valueChanged.connect(lambda v, n=f.name: self.commit(n, float(v)))
        elif md.get("choices"):
            w = QComboBox()
            w.addItems(list(md["choices"]))
            w.setCurrentText(str(value))
            w.currentTextChanged.connect(lambda v, n=f.name: self.commit(n, str(v)))
        else:
            w = QLineEdit(str(value))
            w.editingFinished.connect(lambda n=f.name, e=w: self.commit(n, e.text()))
        if md.get("unit") and isinstance(w, QAbstractSpinBox):
            w.setSuffix(f" {md['unit']}")  # type: ignore[attr-defined]
        w.setToolTip(field_tooltip(f))
        w.setObjectName(f"param_{self.key}_{f.name}")
        return w

    # ------------------------------------------------------------------ values
    def commit(self, name: str, value: Any) -> None:
        """An edit: push the property change (or log why it was rejected and revert)."""
        if not self.doc.has_take:
            return
        try:
            change = settings_ops.set_property(self.doc.take, self.key, name, value)
            change.new.validate()   # whole-section rules too (e.g. Min Radius <= Max Radius)
        except ValueError as exc:
            log.error("%s", exc)
            self.refresh()
            return
        if getattr(self.doc.take.params.section(self.key), name) == value:
            return
        if not self.doc.apply(change):
            self.refresh()

    def refresh(self) -> None:
        """Show the take's values (defaults without a take); editors disabled without a take."""
        section = self.doc.take.params.section(self.key) if self.doc.has_take else self.cls()
        for name, w in self.editors.items():
            v = getattr(section, name)
            w.blockSignals(True)
            if isinstance(w, QCheckBox):
                w.setChecked(bool(v))
            elif isinstance(w, (QSpinBox, QDoubleSpinBox)):
                w.setValue(v)
            elif isinstance(w, QComboBox):
                w.setCurrentText(str(v))
            elif isinstance(w, QLineEdit):
                w.setText(str(v))
            w.blockSignals(False)
            w.setEnabled(self.doc.has_take and not self.doc.busy)
