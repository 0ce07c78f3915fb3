"""Automatic 3D initialization (no seeds): synthetic takes with ground truth, building blocks,
and (slow) the Pose2Sim demo footage."""

from pathlib import Path

import numpy as np
import pytest

from carapost.core.auto_init import auto_initialize, multi_view_hypotheses, select_hypotheses
from carapost.core.camera import Intrinsics, project
from carapost.core.epipolar_match import detection_arrays

from init3d_cases import score, truth_case


def _auto(case, **kw):
    return auto_initialize(case.dets, case.intrinsics, case.R, case.t, case.params, brim_xyz=case.brim_xyz, **kw)


@pytest.mark.parametrize("n", [35, 80, 156])
def test_auto_on_complete_detections(n):
    cov = []
    for seed in (11, 12, 13):
        case = truth_case(n, noise_px=0.1, drop=0.0, clutter=4, seed=seed)
        res = _auto(case)
        s = score(case, res)
        cov.append(s["coverage"])
        assert s["mismatched_detections"] == 0 and s["duplicates"] == 0, s
        # random false detections can pair up on an epipolar line within a few mm of the skin,
        # indistinguishable from a marker by geometry: a rare spurious point, not a mismatch
        assert s["spurious_points"] <= 1, s
        assert s["median_err_mm"] <= 0.2, s
        assert not res.from_seed.any()
        auto = res.report["auto"]
        assert auto["strict_views"] == 4 and auto["strict_points"] >= 10
    assert np.mean(cov) >= 0.97 and min(cov) >= 0.94, cov


@pytest.mark.parametrize("n", [35, 80, 156])
def test_auto_on_detector_like_detections(n):
    case = truth_case(n, seed=12)
    s = score(case, _auto(case))
    assert s["mismatched_detections"] == 0 and s["spurious_points"] <= 1, s
    assert s["coverage_caddy"] >= 0.93, s


def test_auto_without_growing_keeps_multi_view_points_only():
    case = truth_case(80, noise_px=0.1, drop=0.0, clutter=4, seed=13)
    res = _auto(case, grow=False)
    s = score(case, res)
    assert s["mismatched_detections"] == 0
    assert res.n_views.min() >= 3
    # the markers seen by three or four cameras
    assert s["initialized"] >= 0.9 * (case.truth.visible[0].sum(1) >= 3).sum()


def test_auto_validation():
    case = truth_case(35, noise_px=0.1, drop=0.0, clutter=0, seed=14)
    with pytest.raises(ValueError, match="min_views must be within 2..4"):
        _auto(case, min_views=5)
    with pytest.raises(ValueError, match="max_reprojection_px must be positive"):
        _auto(case, max_reprojection_px=0.0)
    with pytest.raises(ValueError, match="exclude has 1 masks for 4 cameras"):
        _auto(case, exclude=[np.zeros(3, bool)])


def _ring(n_cam=4, n_pts=30, seed=0):
    """Cameras on a ring looking at a cloud of points (a motion-capture room)."""
    rng = np.random.default_rng(seed)
    intr = [Intrinsics(900.0, (480.0, 360.0), (960, 720)) for _ in range(n_cam)]
    R, t = [], []
    for k in range(n_cam):
        a = 2 * np.pi * k / n_cam
        C = np.array([3000 * np.cos(a), 3000 * np.sin(a), 500.0])
        z = -C / np.linalg.norm(C)
        x = np.cross([0, 0, 1.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        Rk = np.stack([x, y, z])
        R.append(Rk)
        t.append(-Rk @ C)
    X = rng.uniform([-400, -400, -800], [400, 400, 800], (n_pts, 3))
    return intr, np.array(R), np.array(t), X


def test_multi_view_hypotheses_and_selection_on_a_ring():
    intr, R, t, X = _ring()
    rng = np.random.default_rng(1)
    dets, truth = [], []
    for c in range(4):
        xy = project(X, intr[c], R[c], t[c]) + rng.normal(0, 0.1, (len(X), 2))
        order = rng.permutation(len(X))
        dets.append(detection_arrays(xy[order], c))
        truth.append(np.argsort(order))  # truth[c][m] = detection index of point m
    usable = [np.ones(len(X), bool)] * 4
    det, rms = multi_view_hypotheses(dets, intr, R, t, usable, max_epipolar=2.0, tol=1.0, min_views=3)
    chosen = det[select_hypotheses(det, rms, [len(X)] * 4)]
    assert len(chosen) >= 0.9 * len(X)
    # every chosen hypothesis is one true point
    for row in chosen:
        ms = {int(np.flatnonzero(truth[c] == row[c])[0]) for c in range(4) if row[c] >= 0}
        assert len(ms) == 1
    res = auto_initialize([d.xy for d in dets], intr, R, t, caddies=(), bundle=False)
    assert res.n_points >= 0.9 * len(X)
    assert np.nanmedian(res.residuals) < 0.2


def test_select_hypotheses_rules():
    # cameras with 3 detections each; rows are hypotheses (detection per camera)
    det = np.array([
        [0, 0, 0, 0],    # 4 views
        [0, 0, 1, -1],   # 3 views, shares 0 and 1 with the first: loses
        [1, 1, -1, 1],   # 3 views
        [1, 2, -1, 2],   # 3 views, shares camera 0's detection 1 with the previous: ambiguous
        [2, -1, 2, -1],  # 2 views, alone
    ])
    rms = np.array([0.1, 0.05, 0.2, 0.1, 0.3])
    acc = select_hypotheses(det, rms, [3, 3, 3, 3])
    assert acc.tolist() == [True, False, False, False, True]
    # the rival gone, the survivor is accepted
    acc2 = select_hypotheses(det[[0, 2, 4]], rms[[0, 2, 4]], [3, 3, 3, 3])
    assert acc2.tolist() == [True, True, True]
    assert select_hypotheses(np.zeros((0, 4), np.int64), np.zeros(0), [3] * 4).shape == (0,)


POSE2SIM = "pose2sim-demo"


@pytest.mark.slow
def test_pose2sim_demo_frame0(real_data: Path):
    """Real footage: white retro-reflective body markers, Qualisys calibration."""
    root = real_data / POSE2SIM
    if not root.is_dir():
        pytest.skip("Pose2Sim demo not available")
    blobs = pytest.importorskip("carapost.core.blobs")
    from carapost.io.calibration import load_calibration
    from carapost.io.sources import open_source
    from carapost.model.params import BlobParameters

    from pose2sim_case import P2S_BLOBS, P2S_INIT, auto_kwargs

    cal = load_calibration(root / "calibration" / "Calib.qca.txt")
    R, t = cal.poses(1)
    dets = []
    for name in cal.names:
        img = open_source(root / "videos" / f"{name}.mp4").read(0)
        dets.append(blobs.detect_blobs(img, BlobParameters(**P2S_BLOBS)))
    res = auto_initialize(dets, cal.intrinsics, R[0], t[0], P2S_INIT, **auto_kwargs())
    r = res.residuals[np.isfinite(res.residuals)]
    assert res.n_points >= 10, res.report
    assert np.median(r) <= 1.0
