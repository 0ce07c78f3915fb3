"""The whole workflow through the GUI's actions, as an artist does it: detect blobs, initialize
the default brim, merge the hand-matched brim dots and face seeds (the seeds file stands in for
the user's clicks), solve the brim, Initialize 3D, track forwards, interpolate gaps, export C3D;
then undo everything back to the imported take and redo it all."""

import copy

import numpy as np

from carapost.io.seeds import read_seeds, snap_seeds
from carapost.model.take import PointKind
from carapost.ops.change import take_diff


def wait(qtbot, w):
    qtbot.waitUntil(lambda: not w.jobs.busy, timeout=120000)


def test_detect_to_export_then_undo_all(qtbot, loaded, tiny_files, tmp_path):
    synth, files = tiny_files
    w = loaded
    take = w.doc.take
    before = copy.deepcopy(take)

    w.panes["properties"].sections["blobs"].editors["black_min_radius"].setValue(1.5)  # 640x360 images
    w.actions["process.detect_range"].trigger()
    wait(qtbot, w)
    assert all(d.detected.all() for d in take.detections)

    w.doc.set_frame(0)
    w.actions["process.brim_v20"].trigger()
    seeds = read_seeds(files["seeds"])
    snapped = snap_seeds(seeds, [take.detections[c].xy(0) for c in range(take.n_cameras)])
    for b, per_cam in snapped.brim.items():         # a brim point and its detections -> Merge
        col = int(np.flatnonzero(take.points.brim_index == b)[0])
        w.doc.select([int(take.points.ids[col])], [(c, 0, i) for c, i in per_cam.items()])
        w.actions["edit.merge"].trigger()
    n_face = 0
    for _name, per_cam in snapped.face:             # detections in >= 2 cameras -> Merge: a seed point
        if len(per_cam) >= 2:
            w.doc.select((), [(c, 0, i) for c, i in per_cam.items()])
            w.actions["edit.merge"].trigger()
            n_face += 1
    assert n_face >= 4
    w.doc.clear_selection()

    w.actions["process.solve_brim"].trigger()
    wait(qtbot, w)
    w.actions["process.init3d"].trigger()
    wait(qtbot, w)
    face = np.flatnonzero(take.points.kind == PointKind.FACE)
    assert np.isfinite(take.xyz[0, face]).all(-1).sum() >= 20      # of 35 markers, small dots

    w.actions["process.track_fwd_seq"].trigger()
    wait(qtbot, w)
    w.actions["process.interpolate"].trigger()
    wait(qtbot, w)

    from carapost.synth.evaluate import score_points

    # The 640x360 take's dots are 1-3 px: blob recall, not the GUI, limits coverage here (the
    # accuracy targets are measured on full-size takes in tests/core and benchmarks/).
    ps = score_points(take, synth.truth)
    assert ps.swaps == 0 and ps.mismatched_observations <= 2
    assert ps.coverage >= 0.6 and ps.median_error_mm < 0.2
    out = tmp_path / "wf.c3d"
    w.prompts.answers["save_file"] = str(out)
    w.actions["file.export_c3d"].trigger()
    wait(qtbot, w)
    assert out.exists() and out.stat().st_size > 0

    after = copy.deepcopy(take)
    n = w.doc.undo.count()
    texts = [w.doc.undo.text(i) for i in range(n)]
    assert any(t.startswith("Track Forwards [Sequence]") for t in texts)
    while w.doc.undo.canUndo():
        w.doc.undo.undo()
    assert take_diff(take, before) == []
    while w.doc.undo.canRedo():
        w.doc.undo.redo()
    assert take_diff(take, after) == []
