"""Frame offset between two videos from the epipolar agreement of moving markers (synthetic)."""

import numpy as np
import pytest

from carapost.core.camera import Intrinsics, project
from carapost.core.sync_offset import epipolar_offset_scores
from carapost.synth.rig import look_at


def _scene(delay: float, n_frames: int = 40, seed: int = 0):
    """Two cameras 2.5 m from 20 markers moving ~4 px/frame, 30 static clutter points; camera
    b's frame f shows time f - delay (so b's frame f + delay matches a's frame f)."""
    rng = np.random.default_rng(seed)
    intr = Intrinsics(1500.0, (540.0, 960.0), sensor_size=(1080, 1920))
    C = [np.array([2500.0, 0.0, 1000.0]), np.array([0.0, 2500.0, 1000.0])]
    R = np.stack([look_at(c, np.array([0.0, 0.0, 1000.0]), np.array([0.0, 0.0, 1.0])) for c in C])
    t = -np.einsum("cij,cj->ci", R, np.stack(C))
    base = rng.uniform(-300, 300, (20, 3)) + [0, 0, 1000]
    vel = rng.normal(0, 1, (20, 3))
    vel *= 8.0 / np.linalg.norm(vel, axis=1, keepdims=True)  # mm/frame: ~4-5 px/frame
    clutter = rng.uniform(-1500, 1500, (30, 3)) + [0, 0, 1000]

    def markers(time: float) -> np.ndarray:
        return base + vel * time + 40.0 * np.sin(0.2 * time + np.arange(20))[:, None]

    xy = [[], []]
    for f in range(n_frames):
        for c, tm in ((0, float(f)), (1, f - delay)):
            p = project(np.vstack([markers(tm), clutter]), intr, R[c], t[c]) + rng.normal(0, 0.2, (50, 2))
            xy[c].append(p)
    return intr, R, t, xy


@pytest.mark.parametrize("delay", [3, -2, 0])
def test_integer_offset_found(delay):
    intr, R, t, (xa, xb) = _scene(delay)
    s = epipolar_offset_scores(xa, xb, intr, R[0], t[0], intr, R[1], t[1], offsets=range(-6, 7), max_epipolar_px=1.5)
    assert s.best == delay, s.counts
    assert s.contrast > 1.5, s.counts
    assert abs(s.subframe - delay) < 0.25


def test_subframe_offset():
    intr, R, t, (xa, xb) = _scene(2.5)
    s = epipolar_offset_scores(xa, xb, intr, R[0], t[0], intr, R[1], t[1], offsets=range(-6, 7), max_epipolar_px=1.5)
    assert s.best in (2, 3), s.counts
    assert abs(s.subframe - 2.5) < 0.3, (s.subframe, s.counts)


def test_wrong_calibration_has_no_peak():
    intr, R, t, (xa, xb) = _scene(3)
    Rw = R.copy()
    a = np.radians(1.0)  # camera b turned by 1 degree: ~26 px
    Rw[1] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ R[1]
    s = epipolar_offset_scores(xa, xb, intr, R[0], t[0], intr, Rw[1], t[1], offsets=range(-6, 7), max_epipolar_px=1.5)
    good = epipolar_offset_scores(xa, xb, intr, R[0], t[0], intr, R[1], t[1], offsets=range(-6, 7), max_epipolar_px=1.5)
    assert s.counts.max() < 0.5 * good.counts.max(), (s.counts, good.counts)


def test_too_few_frames():
    intr, R, t, (xa, xb) = _scene(0, n_frames=5)
    with pytest.raises(ValueError, match="no frame of camera a"):
        epipolar_offset_scores(xa, xb, intr, R[0], t[0], intr, R[1], t[1], offsets=range(-10, 11))
