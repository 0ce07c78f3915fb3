"""Refining static cameras' poses from static landmarks (synthetic, known truth)."""

import numpy as np
import pytest

from carapost.core.camera import Intrinsics, project, rodrigues
from carapost.core.scene_refine import pose_change, refine_poses
from carapost.synth.rig import look_at


def _rig(seed: int = 1):
    """Four cameras 3.5 m around a walkway, 14 landmarks on and above it; the 'file' poses of
    cameras 1-3 turned by ~1 degree and moved by ~60 mm."""
    rng = np.random.default_rng(seed)
    intr = [Intrinsics(1680.0, (540.0, 950.0), sensor_size=(1088, 1920)) for _ in range(4)]
    ang = np.radians([20.0, 70.0, 200.0, 250.0])
    C = np.c_[3500 * np.cos(ang), 3500 * np.sin(ang), np.full(4, 2000.0)]
    R = np.stack([look_at(c, np.zeros(3), np.array([0.0, 0.0, 1.0])) for c in C])
    t = -np.einsum("cij,cj->ci", R, C)
    X = np.c_[rng.uniform(-1500, 1500, 14), rng.uniform(-700, 700, 14), rng.uniform(0, 400, 14)]
    xy = np.stack([project(X, intr[c], R[c], t[c]) for c in range(4)], 1) + rng.normal(0, 0.5, (14, 4, 2))
    xy[3, 1] = np.nan  # some landmarks not seen by every camera
    xy[7, 2] = np.nan
    Rf, tf = R.copy(), t.copy()
    for c in (1, 2, 3):
        w = rng.normal(0, 1, 3)
        Rf[c] = rodrigues(np.radians(1.0) * w / np.linalg.norm(w)) @ R[c]
        d = rng.normal(0, 1, 3)
        tf[c] = -Rf[c] @ (C[c] + 60.0 * d / np.linalg.norm(d))
    return intr, R, t, Rf, tf, xy


def test_refine_recovers_poses():
    intr, R, t, Rf, tf, xy = _rig()
    r = refine_poses(xy, intr, Rf, tf, fixed=0)
    assert np.nanmedian(r.initial_residuals) > 5.0
    assert np.nanmedian(r.residuals) < 0.8, np.nanmedian(r.residuals)
    turned0, moved0 = pose_change(R, t, Rf, tf)
    turned, moved = pose_change(R, t, r.R, r.t)
    assert np.all(turned[1:] < 0.35 * turned0[1:]), (turned, turned0)
    assert np.allclose(r.R[0], Rf[0]) and np.allclose(r.t[0], tf[0])
    assert np.all(r.turned_deg[1:] > 0.5)  # reported changes from the starting poses


def test_held_out_landmark_predicted():
    intr, R, t, Rf, tf, xy = _rig(2)
    keep = np.ones(len(xy), bool)
    keep[5] = False
    r = refine_poses(xy[keep], intr, Rf, tf, fixed=0)
    from carapost.core.triangulate import triangulate
    X0 = triangulate(xy[5:6], intr, Rf, tf).xyz
    X1 = triangulate(xy[5:6], intr, r.R, r.t).xyz
    e0 = np.nanmedian([np.linalg.norm(project(X0, intr[c], Rf[c], tf[c]) - xy[5:6, c]) for c in range(4)])
    e1 = np.nanmedian([np.linalg.norm(project(X1, intr[c], r.R[c], r.t[c]) - xy[5:6, c]) for c in range(4)])
    assert e1 < 1.0 and e1 < 0.25 * e0, (e0, e1)


def test_several_fixed_cameras_and_errors():
    intr, R, t, Rf, tf, xy = _rig()
    r = refine_poses(xy, intr, Rf, tf, fixed=(0, 1))
    assert np.allclose(r.R[1], Rf[1]) and r.turned_deg[1] == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError, match="fixed cameras"):
        refine_poses(xy, intr, Rf, tf, fixed=7)
    with pytest.raises(ValueError, match="do not describe the same cameras"):
        refine_poses(xy[:, :3], intr, Rf, tf)
    lone = np.full_like(xy, np.nan)
    lone[:, 0] = xy[:, 0]
    with pytest.raises(ValueError, match="no landmark is seen by two cameras"):
        refine_poses(lone, intr, Rf, tf)
