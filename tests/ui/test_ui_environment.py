"""The Qt binding must not drop references to None (PySide6 6.12.0 on Python 3.11 does: every
call of a void method decrements None's reference count, and the application aborts with
"none_dealloc" after a few thousand calls)."""

import sys

import pytest


@pytest.mark.skipif(sys.version_info >= (3, 12), reason="None is immortal from Python 3.12")
def test_void_calls_keep_none_alive(qapp):
    from PySide6.QtGui import QAction
    from PySide6.QtWidgets import QWidget

    w = QWidget()
    a = QAction("x", w)
    a.setEnabled(True)
    before = sys.getrefcount(None)
    for _ in range(200):
        a.setEnabled(True)
        w.update()
    assert sys.getrefcount(None) >= before - 5, \
        "this PySide6 build loses references to None (use PySide6-Essentials != 6.12.0 on Python 3.11)"
