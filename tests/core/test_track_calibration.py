"""Refining a room rig's extrinsics from matched 2D marker tracks (synthetic, known truth)."""

import numpy as np
import pytest

from carapost.core.camera import Intrinsics, project, rodrigues
from carapost.core.scene_refine import pose_change
from carapost.core.track_calibration import (link_tracks, match_tracks, moving_tracks, refine_extrinsics,
                                             signed_epipolar_distance, track_pair_table)
from carapost.synth.rig import look_at

F = 60  # frames


def _rig(seed: int = 3):
    """Four cameras 3.5 m around a room; 10 markers on a walking, swaying body (a common drift
    plus their own smooth wobble, ~0.5 m over the frames), 12 static clutter points; the 'file'
    poses of cameras 2-4 turned by 0.8 degree and moved by 50 mm. Returns the cameras, the true
    and perturbed poses, per-camera detections per frame (0.2 px noise, 5 % missing) and the
    true marker paths (F, M, 3)."""
    rng = np.random.default_rng(seed)
    intr = [Intrinsics(1680.0, (540.0, 950.0), sensor_size=(1088, 1920)) for _ in range(4)]
    ang = np.radians([20.0, 70.0, 200.0, 250.0])
    C = np.c_[3500 * np.cos(ang), 3500 * np.sin(ang), np.full(4, 1800.0)]
    R = np.stack([look_at(c, np.array([0.0, 0.0, 1000.0]), np.array([0.0, 0.0, 1.0])) for c in C])
    t = -np.einsum("cij,cj->ci", R, C)
    s = np.linspace(0, 1, F)[:, None, None]
    body = np.c_[rng.uniform(-250, 250, 10), rng.uniform(-150, 150, 10), rng.uniform(400, 1600, 10)]
    drift = s * np.array([500.0, 150.0, 0.0])
    phase = rng.uniform(0, 2 * np.pi, (10, 3))
    wobble = 60.0 * np.sin(2 * np.pi * 1.3 * s + phase[None])
    X = body[None] + drift + wobble
    clutter = np.c_[rng.uniform(-2500, 2500, 12), rng.uniform(-2500, 2500, 12), rng.uniform(0, 2500, 12)]
    dets = []
    for c in range(4):
        frames = []
        for f in range(F):
            p = np.concatenate([project(X[f], intr[c], R[c], t[c]), project(clutter, intr[c], R[c], t[c])])
            p = p + rng.normal(0, 0.2, p.shape)
            keep = rng.random(len(p)) > 0.05
            frames.append(p[keep & np.isfinite(p).all(1)])
        dets.append(frames)
    Rf, tf = R.copy(), t.copy()
    for c in (1, 2, 3):
        w = rng.normal(0, 1, 3)
        Rf[c] = rodrigues(np.radians(0.8) * w / np.linalg.norm(w)) @ R[c]
        d = rng.normal(0, 1, 3)
        tf[c] = -Rf[c] @ (C[c] + 50.0 * d / np.linalg.norm(d))
    return intr, R, t, Rf, tf, dets, X


def _tracks(dets):
    out = []
    for frames in dets:
        T = link_tracks(frames)
        out.append(T[moving_tracks(T)])
    return out


def test_link_tracks_follows_markers_and_refuses_bad_input():
    a = np.array([[10.0, 10.0], [200.0, 50.0]])
    frames = [a + f * np.array([2.0, 1.0]) for f in range(10)]
    frames[4] = frames[4][:1]  # the second marker missing once: its track ends and restarts
    T = link_tracks(frames)
    n = np.isfinite(T[..., 0]).sum(1)
    assert sorted(n.tolist()) == [4, 5, 10]
    assert np.allclose(T[np.argmax(n), 9], a[0] + 9 * np.array([2.0, 1.0]))
    assert moving_tracks(T, min_frames=10, min_motion_px=15).sum() == 1
    with pytest.raises(ValueError, match="frame 1"):
        link_tracks([a, np.zeros(3)])


def test_signed_distance_and_track_pairs_tell_true_pairs():
    intr, R, t, Rf, tf, dets, X = _rig()
    d = signed_epipolar_distance(project(X[0], intr[0], R[0], t[0]), project(X[0], intr[1], R[1], t[1]),
                                 intr[0], R[0], t[0], intr[1], R[1], t[1])
    assert np.abs(d).max() < 1e-6
    # true tracks of each marker in cameras 0 and 2, with the perturbed poses
    ta = np.stack([project(X[:, m], intr[0], R[0], t[0]) for m in range(10)])
    tb = np.stack([project(X[:, m], intr[2], R[2], t[2]) for m in range(10)])
    tp = track_pair_table(ta, tb, intr[0], Rf[0], tf[0], intr[2], Rf[2], tf[2])
    true = np.eye(10, dtype=bool)
    assert np.abs(tp.bias[true]).max() > 3.0  # the pose error biases the true pairs ...
    assert np.median(tp.spread[true]) < 1.5  # ... but they stay consistent over time
    assert np.median(tp.sweep[~true] / tp.spread[~true]) < 2.0  # coincidences do not


def test_refine_extrinsics_recovers_poses():
    intr, R, t, Rf, tf, dets, X = _rig()
    tracks = _tracks(dets)
    label, edges = match_tracks(tracks, intr, Rf, tf)
    assert len(edges) >= 12
    r = refine_extrinsics(tracks, intr, Rf, tf, rounds=((30.0, 3.0), (6.0, 1.0)))
    turned0, moved0 = pose_change(R, t, Rf, tf)
    turned, moved = pose_change(R, t, r.R, r.t)
    assert np.allclose(r.R[0], Rf[0]) and np.allclose(r.t[0], tf[0])
    assert np.all(turned[1:] < 0.15), (turned, turned0)  # from 0.8 degree
    assert np.all(moved[1:] < 25.0), (moved, moved0)  # from 50 mm (the scale is the file's)
    assert np.nanmedian(r.residuals) < 0.5
    # held out: the true markers of a frame, projected with the truth, triangulate consistently
    from carapost.core.triangulate import triangulate
    xy = np.stack([project(X[F // 2], intr[c], R[c], t[c]) for c in range(4)], 1)
    for Rk, tk, bound in ((Rf, tf, None), (r.R, r.t, 0.5)):
        Y = triangulate(xy, intr, Rk, tk).xyz
        e = np.median([np.linalg.norm(project(Y, intr[c], Rk[c], tk[c]) - xy[:, c], axis=1) for c in range(4)])
        if bound is None:
            assert e > 3.0, e
        else:
            assert e < bound, e


def test_time_shifted_camera_finds_no_pairs():
    """Null control: camera 3's tracks shifted by 20 frames have no true partner."""
    intr, R, t, Rf, tf, dets, X = _rig()
    tracks = _tracks(dets)
    shifted = np.full_like(tracks[2], np.nan)
    shifted[:, 20:] = tracks[2][:, :-20]
    label, edges = match_tracks(tracks[:2] + [shifted] + tracks[3:], intr, Rf, tf)
    real = sum(1 for a, _, b, _, _ in match_tracks(tracks, intr, Rf, tf)[1] if 2 in (a, b))
    null = sum(1 for a, _, b, _, _ in edges if 2 in (a, b))
    assert real >= 8 and null <= 1, (real, null)


def test_refine_extrinsics_errors():
    intr, R, t, Rf, tf, dets, X = _rig()
    tracks = _tracks(dets)
    with pytest.raises(ValueError, match="intrinsics"):
        refine_extrinsics(tracks, intr[:3], Rf, tf)
    empty = [tr[:0] for tr in tracks]
    with pytest.raises(ValueError, match="no trajectory"):
        refine_extrinsics(empty, intr, Rf, tf)


def test_two_fixed_cameras_keep_their_baseline():
    intr, R, t, Rf, tf, dets, X = _rig()
    Rf[1], tf[1] = R[1], t[1]  # cameras 1-2 right, 3-4 off
    tracks = _tracks(dets)
    r = refine_extrinsics(tracks, intr, Rf, tf, fixed=(0, 1), rounds=((30.0, 3.0), (6.0, 1.0)))
    assert np.allclose(r.R[:2], Rf[:2]) and np.allclose(r.t[:2], tf[:2])
    turned, moved = pose_change(R, t, r.R, r.t)
    assert np.all(turned[2:] < 0.15) and np.all(moved[2:] < 25.0), (turned, moved)
    with pytest.raises(ValueError, match="fixed cameras"):
        refine_extrinsics(tracks, intr, Rf, tf, fixed=(0, 7))
