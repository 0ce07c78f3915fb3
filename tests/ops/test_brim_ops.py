import numpy as np
import pytest

from carapost.core.camera import camera_centre
from carapost.model.take import CameraInfo, PointKind, Take
from carapost.ops.brim import initialize_default_brim, solve_brim_manual
from carapost.ops.session import Session


@pytest.fixture
def brim_take(tiny_synth):
    """Detections = truth brim dots then face markers (frame 0..F-1), nominal (flex-free) poses."""
    tr = tiny_synth.truth
    F, B, C = tr.brim_visible.shape
    cams = [CameraInfo(f"cam{c}", c, tr.intrinsics[c], (640, 360)) for c in range(C)]
    take = Take.new(cams, F, 60.0, R=tr.nominal_R, t=tr.nominal_t)
    brim_det = np.full((F, B, C), -1)
    for c in range(C):
        frames = {}
        for f in range(F):
            b = np.flatnonzero(tr.brim_visible[f, :, c])
            m = np.flatnonzero(tr.visible[f, :, c])
            xy = np.concatenate([tr.brim_centroid_xy[f, b, c], tr.centroid_xy[f, m, c]])
            brim_det[f, b, c] = np.arange(len(b))
            frames[f] = {"x": xy[:, 0], "y": xy[:, 1], "major": np.full(len(xy), 3.0),
                         "minor": np.full(len(xy), 3.0), "polarity": np.full(len(xy), -1), "score": np.ones(len(xy))}
        take.detections[c] = take.detections[c].with_frames(frames)
    return Session(take), brim_det


def test_initialize_default_brim(brim_take, tiny_synth, undo_check):
    s, _ = brim_take
    undo_check(s, initialize_default_brim(s.take, "v2.0"))
    cols = s.take.brim_points()
    assert len(cols) == len(s.take.brim) == len(tiny_synth.truth.brim_xyz)
    np.testing.assert_allclose(s.take.xyz[3, cols], tiny_synth.truth.brim_xyz)
    # re-initializing replaces the brim points
    undo_check(s, initialize_default_brim(s.take, "v1.0"))
    assert len(s.take.brim_points()) == len(s.take.brim)


def test_solve_brim_manual(brim_take, tiny_synth, undo_check):
    s, brim_det = brim_take
    s.apply(initialize_default_brim(s.take, "v2.0"))
    f = 2
    corr = {}
    for b in range(4):  # the user clicks 4 brim dots seen by every camera
        vis = brim_det[f, :, :] >= 0
        dot = np.flatnonzero(vis.all(1))[b * 2]
        corr[int(dot)] = {c: int(brim_det[f, dot, c]) for c in range(4)}
    change, res = solve_brim_manual(s.take, f, corr)
    assert res.solved.all()
    undo_check(s, change)
    err = np.linalg.norm(camera_centre(s.take.R[f], s.take.t[f]) - camera_centre(tiny_synth.truth.R[f],
                                                                                tiny_synth.truth.t[f]), axis=-1)
    assert err.max() < 0.1  # exact detections: the solved poses are the true (flexed) ones of frame f
    cols = s.take.brim_points()
    attached = (s.take.obs_det[f, cols] >= 0).sum()
    assert attached == (brim_det[f] >= 0).sum()


def test_solve_needs_a_brim(brim_take):
    s, _ = brim_take
    with pytest.raises(ValueError, match="initialize or import a calibration brim"):
        solve_brim_manual(s.take, 0, {})
