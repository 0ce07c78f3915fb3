"""Files (open, save, unsaved changes, recent files, imports, exports, relocate) and settings."""

import shutil

import numpy as np
import pytest
import shiboken6

from carapost.ops import settings as settings_ops
from carapost.ui.main_window import MainWindow
from carapost.ui.settings import MAX_RECENT, Settings

from uihelpers import FakePrompts, inject_truth, load_take


def test_close_with_unsaved_changes_asks(qtbot, loaded, tmp_path):
    w = loaded
    w.doc.apply(settings_ops.set_active_range(w.doc.take, 1, 2))
    assert w.isWindowModified() and w.windowTitle().endswith("[*] - CaraPost")
    w.prompts.answers["save_discard_cancel"] = "cancel"
    w.close()
    assert shiboken6.isValid(w) and w.isVisible()
    w.prompts.answers.update({"save_discard_cancel": "save", "save_file": str(tmp_path / "a.cara")})
    w.close()
    assert (tmp_path / "a.cara").exists()
    assert not shiboken6.isValid(w) or not w.isVisible()


def test_save_open_roundtrip_and_recent_files(qtbot, loaded, tmp_path):
    w = loaded
    w.doc.apply(settings_ops.set_active_range(w.doc.take, 1, 2))
    w.prompts.answers["save_file"] = str(tmp_path / "proj")
    w.actions["file.save"].trigger()
    assert (tmp_path / "proj.cara").exists() and not w.isWindowModified()
    assert w.windowTitle().startswith("proj.cara")
    assert Settings().recent_files()[0].endswith("proj.cara")
    assert [a.text() for a in w.recent_menu.actions()] == ["&1 proj.cara"]
    w.actions["file.clear"].trigger()
    assert not w.doc.has_take
    w.prompts.answers["open_file"] = str(tmp_path / "proj.cara")
    w.actions["file.open"].trigger()
    qtbot.waitUntil(lambda: w.doc.has_take and not w.jobs.busy, timeout=20000)
    assert w.doc.take.active_range == (1, 2) and w.doc.undo.count() == 0
    assert w.doc.image(0) is not None           # the videos were found again
    s = Settings()
    for i in range(MAX_RECENT + 3):
        s.add_recent(tmp_path / f"f{i}.cara")
    assert len(s.recent_files()) == MAX_RECENT and s.recent_files()[0].endswith(f"f{MAX_RECENT + 2}.cara")
    w.actions["file.clear_recent"].trigger()
    assert Settings().recent_files() == [] and not w.recent_menu.isEnabled()


def test_window_layout_is_restored(qtbot):
    w = MainWindow()
    w.prompts = FakePrompts()
    qtbot.addWidget(w)
    w.show()
    w.docks["history"].hide()
    w.workspace.set_layout(2)
    w.close()
    w2 = MainWindow()
    w2.prompts = FakePrompts()
    qtbot.addWidget(w2)
    w2.show()
    assert not w2.docks["history"].isVisible() and w2.docks["log"].isVisible()
    assert w2.workspace.n_views == 2
    w2.close()


def test_imports_exports(qtbot, loaded, tiny_files, tmp_path):
    synth, paths = tiny_files
    w = loaded
    inject_truth(w, synth, markers=4)
    labels = tmp_path / "labels.txt"
    labels.write_text("Chin Nose\nBrow\n", encoding="utf-8")
    w.prompts.answers["open_file"] = str(labels)
    w.actions["file.import_labels_text"].trigger()
    assert w.doc.take.labels == ["Chin", "Nose", "Brow"]
    w.prompts.answers["open_file"] = str(paths["brim_svg"])
    w.actions["file.import_brim_svg"].trigger()
    assert w.doc.take.brim is not None and len(w.doc.take.brim) > 4
    w.prompts.answers["open_file"] = str(paths["xcp"])
    R0 = w.doc.take.R.copy()
    w.actions["file.import_xcp"].trigger()
    np.testing.assert_allclose(w.doc.take.R, R0)   # the same calibration again
    for key, ext in (("file.export_c3d", ".c3d"), ("file.export_fbx", ".fbx"), ("file.export_xcp", ".xcp")):
        w.prompts.answers["save_file"] = str(tmp_path / f"out{ext}")
        w.actions[key].trigger()
        qtbot.waitUntil(lambda: not w.jobs.busy, timeout=20000)
        assert (tmp_path / f"out{ext}").stat().st_size > 100, key


def test_relocate_files(qtbot, window, tiny_files, tmp_path):
    synth, paths = tiny_files
    folder = tmp_path / "take"
    folder.mkdir()
    for k in ("pico_0", "pico_1", "pico_2", "pico_3", "xcp"):
        shutil.copy(paths[k], folder / paths[k].name)
    w = window
    load_take(qtbot, w, (synth, {"pico_0": folder / paths["pico_0"].name}))
    w.prompts.answers["save_file"] = str(tmp_path / "p.cara")
    assert w.save()
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.move(str(folder / paths["pico_2"].name), moved / paths["pico_2"].name)
    w.actions["file.clear"].trigger()
    w.open_path(tmp_path / "p.cara", ask=False)
    qtbot.waitUntil(lambda: w.doc.has_take and not w.jobs.busy, timeout=20000)
    assert w.doc.session.missing == [2] and w.doc.image(2) is None
    w.relocate(2, str(moved / paths["pico_2"].name))
    assert w.doc.session.missing == [] and w.doc.image(2) is not None
    assert w.isWindowModified()
    with pytest.raises(ValueError):
        w.relocate(1, str(tmp_path / "nope.pico"))


def test_increment_image_sequence_offset_follows_undo(qtbot, loaded):
    w = loaded
    img = w.doc.image(1, 1).copy()
    w.doc.set_camera_selection([1])
    w.actions["edit.increment_offset"].trigger()
    assert w.doc.take.cameras[1].frame_offset == 1
    np.testing.assert_array_equal(w.doc.image(1, 0), img)    # frame 0 now shows source frame 1
    w.doc.undo.undo()
    np.testing.assert_array_equal(w.doc.image(1, 1), img)
