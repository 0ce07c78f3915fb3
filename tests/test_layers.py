"""Import contract: nothing below the UI imports Qt (see docs/architecture.md)."""

import re
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "carapost"
QT = re.compile(r"^\s*(from|import)\s+(PySide6|shiboken6|pyqtgraph|superqt)\b", re.M)


def test_core_model_io_ops_do_not_import_qt():
    offenders = []
    for layer in ("core", "model", "io", "ops", "synth"):
        for f in (PKG / layer).rglob("*.py"):
            if QT.search(f.read_text(encoding="utf-8")):
                offenders.append(str(f.relative_to(PKG)))
    assert not offenders, f"Qt imported below the UI layer: {offenders}"


def test_core_does_not_import_io_or_ui():
    pat = re.compile(r"^\s*(from|import)\s+carapost\.(io|ui|ops)\b", re.M)
    offenders = [str(f.relative_to(PKG)) for f in (PKG / "core").rglob("*.py") if pat.search(f.read_text())]
    assert not offenders
