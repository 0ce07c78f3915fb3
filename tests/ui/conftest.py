"""Fixtures for the offscreen GUI tests: isolated settings, a tiny synthetic take on disk, a main
window that must not leak windows, and dialogs answered without modal loops."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from uihelpers import FakePrompts, load_take

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

QT_IGNORE = ["This plugin does not support propagateSizeHints", "This plugin does not support raise",
             "This plugin does not support grabbing the keyboard"]


def pytest_collection_modifyitems(config, items):  # noqa: ARG001
    """Qt warnings fail the GUI tests (except the offscreen plugin's own notices)."""
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.qt_log_level_fail("WARNING"))
            item.add_marker(pytest.mark.qt_log_ignore(*QT_IGNORE))


@pytest.fixture(autouse=True)
def isolated_settings(qapp):
    """Settings go to Qt's test location and start empty in every test."""
    from PySide6.QtCore import QCoreApplication, QStandardPaths

    from carapost.ui.settings import APP, ORG, Settings

    QStandardPaths.setTestModeEnabled(True)
    QCoreApplication.setOrganizationName(ORG)
    QCoreApplication.setApplicationName(APP)
    Settings().q.clear()
    yield
    Settings().q.clear()


@pytest.fixture(scope="session")
def tiny_files(tmp_path_factory):
    """A 3-frame, 4-camera 640x360 synthetic take written as pico files + xcp."""
    from carapost.synth import SynthConfig, generate_take, write_take

    synth = generate_take(SynthConfig(n_markers=35, n_frames=3, width=640, height=360, seed=3))
    out = tmp_path_factory.mktemp("ui_take")
    paths = write_take(synth, out, "Tiny")
    return synth, paths


def _close(qtbot, w) -> None:  # noqa: ANN001
    import shiboken6
    from PySide6.QtCore import QCoreApplication, QEvent

    if shiboken6.isValid(w):
        w.doc.dirty_base = False
        w.doc.undo.setClean()
        w.close()
    for _ in range(3):
        QCoreApplication.sendPostedEvents(None, QEvent.Type.DeferredDelete)
        QCoreApplication.processEvents()


@pytest.fixture
def window(qtbot):
    """A shown main window with fake prompts; fails if any window is left open afterwards."""
    import shiboken6
    from PySide6.QtWidgets import QApplication

    from carapost.ui.main_window import MainWindow

    w = MainWindow()
    prompts = FakePrompts()
    w.prompts = prompts
    w.show()
    qtbot.waitExposed(w)
    w.activateWindow()
    yield w
    _close(qtbot, w)
    assert not shiboken6.isValid(w), "the main window was not deleted on close"
    leaked = [t for t in QApplication.topLevelWidgets() if t.isVisible()]
    assert not leaked, f"windows left open: {leaked}"


@pytest.fixture
def loaded(qtbot, window, tiny_files):
    load_take(qtbot, window, tiny_files)
    return window
