"""Process menu, Target Tracker and brim entries wired to the operations layer, run through the
GUI (worker threads, undo)."""

import copy

import numpy as np
import pytest
from PySide6.QtCore import QPoint, Qt

from carapost.model.take import ObsSource, PointKind, Recon
from carapost.ops.change import take_diff
from carapost.ops.settings import set_active_range
from carapost.ui.views.paths import affine

from uihelpers import inject_truth

LEFT, NO = Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier


def wait(qtbot, w):
    qtbot.waitUntil(lambda: not w.jobs.busy, timeout=60000)


def test_add_target_track_then_track_forward(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    w = loaded
    tr = synth.truth
    m = next(m for m in range(tr.visible.shape[1]) if tr.visible[:, m, 0].all())
    w.workspace.set_layout(1)
    view = w.workspace.slots[0].set_view("sensor", 0)
    view.resize(640, 360)
    view.fit_to_window()
    qtbot.keyClick(view, Qt.Key.Key_A, Qt.KeyboardModifier.ShiftModifier)
    assert w.point_edit_mode == "Add Target Track" and view.mode == "Add Target Track"
    assert w.actions["edit.add_target"].isChecked()
    xy = tr.xy[0, m, 0]
    qtbot.mouseClick(view, LEFT, NO, QPoint(*np.round(affine(view.image_to_widget(), xy)).astype(int)))
    take = w.doc.take
    assert take.n_points == 1 and len(take.keyframes) == 1
    assert take.obs_src[0, 0, 0] == ObsSource.KEYFRAME
    assert np.linalg.norm(take.obs_xy[0, 0, 0] - xy) < 1.5
    assert w.doc.sel_points == [int(take.points.ids[0])]
    qtbot.keyClick(view, Qt.Key.Key_S, Qt.KeyboardModifier.ShiftModifier)    # Stop Point Edit mode
    assert w.point_edit_mode == "" and view.mode == ""
    # The Tracker pane's "> Track forward one frame" runs in a worker and is one undo entry.
    n = w.doc.undo.count()
    w.panes["tracker"].buttons["tracker.forward_one"].click()
    wait(qtbot, w)
    assert w.doc.undo.count() == n + 1
    assert np.isfinite(take.obs_xy[1, 0, 0]).all()
    assert np.linalg.norm(take.obs_xy[1, 0, 0] - tr.xy[1, m, 0]) < 3.0
    # Next Key Frame wraps to the keyframe; Add Keyframe keys frame 1 too; Clear Tracked Points.
    w.doc.set_frame(1)
    w.actions["view.next_key"].trigger()
    assert w.doc.frame == 0
    w.doc.set_frame(1)
    w.actions["tracker.add_keyframe"].trigger()
    assert len(take.keyframes) == 2
    w.actions["tracker.clear"].trigger()
    assert len(take.keyframes) == 0 and not np.isfinite(take.obs_xy[:, 0]).any()


def test_gaps_to_keys_and_interpolate(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    w = loaded
    inject_truth(w, synth, markers=8)
    take = w.doc.take
    w.doc.select([int(take.points.ids[0])])
    w.doc.set_frame(1)
    w.actions["edit.clear_frame"].trigger()          # a one-frame gap in point 0
    assert not np.isfinite(take.xyz[1, 0]).any()
    before = copy.deepcopy(take)
    w.actions["process.interpolate"].trigger()
    wait(qtbot, w)
    assert np.isfinite(take.xyz[1, 0]).all() and take.recon[1, 0] == Recon.INTERPOLATED
    assert np.linalg.norm(take.xyz[1, 0] - synth.truth.xyz[1, np.flatnonzero(
        synth.truth.visible[:, :, :2].all((0, 2)))[0]]) < 5.0
    w.doc.undo.undo()
    assert take_diff(take, before) == []
    w.actions["edit.gaps_to_keys"].trigger()
    assert len(take.keyframes) > 0


def test_stabilize_and_align(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    w = loaded
    inject_truth(w, synth, markers=8)
    take = w.doc.take
    w.doc.select(take.points.ids[:4].tolist())
    w.actions["process.stabilize_manual"].trigger()
    wait(qtbot, w)
    assert np.isfinite(take.xyz_stabilized[:, :4]).all()
    w.actions["view.stabilized"].trigger()
    assert w.doc.show_stabilized
    w.doc.select(take.points.ids[:3].tolist())
    n = w.doc.undo.count()
    w.actions["process.align"].trigger()
    wait(qtbot, w)
    assert w.doc.undo.count() == n + 1


def test_default_brim_and_manual_solve(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    w = loaded
    tr = synth.truth
    take = w.doc.take
    # Brim dot detections from the truth (frame 0), before any history.
    for c in range(take.n_cameras):
        vis = np.flatnonzero(tr.brim_visible[0, :, c])
        take.detections[c] = take.detections[c].with_frames({0: {
            "x": tr.brim_xy[0, vis, c, 0], "y": tr.brim_xy[0, vis, c, 1], "major": np.full(len(vis), 3.0),
            "minor": np.full(len(vis), 3.0), "angle": np.zeros(len(vis)), "polarity": np.full(len(vis), -1),
            "score": np.ones(len(vis))}})
    w.doc.notify_take_changed()
    w.actions["process.brim_v20"].trigger()
    assert take.brim is not None and (take.points.kind == PointKind.BRIM).sum() == len(take.brim)
    np.testing.assert_allclose(take.brim.xyz, tr.brim_xyz, atol=1e-6)
    # The user's matches: six dots spread over the card, seen by every camera, merged into their brim points.
    seen = np.flatnonzero(tr.brim_visible[0].all(1))
    dots = seen[np.linspace(0, len(seen) - 1, 6).astype(int)]
    for b in dots:
        col = int(np.flatnonzero(take.points.brim_index == b)[0])
        dets = [(c, 0, int(np.flatnonzero(np.flatnonzero(tr.brim_visible[0, :, c]) == b)[0]))
                for c in range(take.n_cameras)]
        w.doc.select([int(take.points.ids[col])], dets)
        w.actions["edit.merge"].trigger()
    from carapost.ui.cmd_process import brim_correspondences

    corr = brim_correspondences(take, 0)
    assert sorted(corr) == sorted(int(b) for b in dots) and all(len(v) == 4 for v in corr.values())
    take.R[:] = np.nan                                   # forget the nominal poses: solve from scratch
    take.t[:] = np.nan
    w.actions["process.solve_brim"].trigger()
    wait(qtbot, w)
    assert np.isfinite(take.R[0]).all()
    angle = [np.degrees(np.arccos(np.clip((np.trace(take.R[0, c].T @ tr.R[0, c]) - 1) / 2, -1, 1)))
             for c in range(4)]
    assert max(angle) < 0.5


def test_track_forwards_single_frame_ctrl_w(qtbot, loaded, tiny_files):
    pytest.importorskip("carapost.ops.track")  # the tracker lands separately
    synth, _ = tiny_files
    w = loaded
    inject_truth(w, synth, markers=8)
    take = w.doc.take
    # Keep the points in frame 0 only (Clear Selected [Active Range] over frames 1-2).
    w.doc.select(take.points.ids.tolist())
    w.doc.apply(set_active_range(take, 1, 2))
    w.actions["edit.clear_range"].trigger()
    assert not np.isfinite(take.obs_xy[1]).any()
    truth0 = take.obs_xy[0].copy()
    n = w.doc.undo.count()
    w.doc.set_frame(0)
    qtbot.keyClick(w.workspace.slots[0].view, Qt.Key.Key_W, Qt.KeyboardModifier.ControlModifier)
    assert w.last_action == "process.track_fwd_1"
    wait(qtbot, w)
    assert w.doc.undo.count() == n + 1
    tracked = np.isfinite(take.obs_xy[1, :, :, 0])
    assert tracked.sum() >= 0.75 * np.isfinite(truth0[..., 0]).sum()
    w.doc.undo.undo()
    assert not np.isfinite(take.obs_xy[1]).any()


def test_initialize_3d_grows_from_seeds(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    w = loaded
    take = w.doc.take
    # Truth detections everywhere, six seed points in frame 0 (Merge), then Initialize 3D.
    inject_truth(w, synth, markers=6)
    n_points, n = take.n_points, w.doc.undo.count()
    w.doc.set_frame(0)
    w.actions["process.init3d"].trigger()
    wait(qtbot, w)
    assert w.doc.undo.count() == n + 1 and take.n_points > n_points + 10
    w.doc.undo.undo()
    assert take.n_points == n_points


def test_initialize_3d_automatic_and_caddies(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    w = loaded
    take = w.doc.take
    inject_truth(w, synth, markers=0)                # truth detections, no seeds
    n = w.doc.undo.count()
    w.doc.set_frame(0)
    w.actions["process.init3d_auto"].trigger()
    wait(qtbot, w)
    assert w.doc.undo.count() == n + 1 and take.n_points >= 20
    w.doc.undo.undo()
    assert take.n_points == 0
    # Caddies...: the prompt shows the take's, an answer sets them (undoable), a bad one changes nothing.
    w.prompts.answers["get_text"] = "none"
    w.actions["process.caddies"].trigger()
    assert take.caddies == [] and w.doc.undo.count() == n + 1
    w.prompts.answers["get_text"] = "0-1,1-2"
    w.actions["process.caddies"].trigger()
    assert take.caddies == [] and w.doc.undo.count() == n + 1
    w.doc.undo.undo()
    assert take.caddies == [(0, 1), (2, 3)]


@pytest.mark.parametrize("key", ["process.init_rom", "process.init_rom_brim"])
def test_initialize_from_rom_without_rom_reports_instead_of_failing(loaded, key):
    n = loaded.doc.undo.count()
    loaded.actions[key].trigger()
    assert loaded.last_action == key and loaded.doc.undo.count() == n
