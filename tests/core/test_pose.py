"""Camera pose from known points (core/pose.py) against exact synthetic poses."""

import numpy as np
import pytest

from carapost.core.camera import Intrinsics, camera_centre, normalized_rays, project, rodrigues
from carapost.core.pose import (compose_relative, is_degenerate, is_planar, p3p_candidates, pnp_candidates,
                                refine_pose, reprojection_px, robust_pnp)

INTR = Intrinsics(focal_length=515.0, principal_point=(640.0, 360.0), sensor_size=(1280, 720),
                  radial=(4e-9, 1.5e-15, 0.0))


def random_pose(rng):
    R = rodrigues(rng.normal(0, 0.4, 3))
    t = np.array([*rng.uniform(-20, 20, 2), rng.uniform(120, 250)])
    return R, t


def normalised(X, R, t):
    c = X @ R.T + t
    return c[:, :2] / c[:, 2:]


def has_pose(cands, R, t, tol=1e-6):
    return any(np.abs(R2 - R).max() < tol and np.abs(t2 - t).max() < tol * 100 for R2, t2 in cands)


def test_p3p_finds_the_true_pose():
    rng = np.random.default_rng(0)
    counts = []
    for _ in range(200):
        X = rng.uniform(-50, 50, (3, 3)) * [1, 1, 0.2]
        R, t = random_pose(rng)
        uv = normalised(X, R, t)
        cands = p3p_candidates(X, uv)
        assert has_pose(cands, R, t)
        errs = [np.abs(normalised(X, R2, t2) - uv).max() for R2, t2 in cands]
        # exact solutions, plus the odd near-solution (a residual minimum just short of zero)
        assert all(e < 1e-9 or e < 1e-2 for e in errs)
        for R2, _ in cands:
            np.testing.assert_allclose(R2 @ R2.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(R2) == pytest.approx(1.0)
        counts.append(sum(e < 1e-9 for e in errs))
    assert 1 <= min(counts) and max(counts) <= 4  # at most four exact solutions


def test_p3p_near_double_root_keeps_a_near_solution():
    """Three dots of the v2.0 brim seen obliquely with 0.1 px of noise: with this noise draw
    the exact pair of roots disappears (OpenCV 5's P3P returns NaN, AP3P nothing); a
    near-solution close to the truth is still offered (the geometry is ill-conditioned:
    distances along the line of sight are only known to about 10 mm)."""
    X = np.array([[42.5, 12.0, 0.0], [0.0, 0.0, 0.0], [-25.5, -12.0, 0.0]])
    R = np.array([[0.84666825, 0.18172186, 0.50013002],
                  [0.07909007, -0.97241601, 0.21943533],
                  [0.52621064, -0.14623361, -0.83768616]])
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt  # exactly orthonormal
    t = np.array([11.688, -75.028, 159.717])
    rng = np.random.default_rng(1)
    xy = project(X, INTR, R, t) + rng.normal(0, 0.1, (3, 2))
    cands = p3p_candidates(X, normalized_rays(xy, INTR)[:, :2])
    best = min(np.linalg.norm(camera_centre(R2, t2) - camera_centre(R, t)) for R2, t2 in cands)
    assert best < 15.0


def test_pnp_candidates_planar_curved_and_general():
    rng = np.random.default_rng(1)
    for kind in ("planar", "curved", "general"):
        for _ in range(20):
            X = np.c_[rng.uniform(-50, 50, (6, 2)), np.zeros(6)]
            if kind == "curved":
                X[:, 2] = 150 * np.cos(X[:, 0] / 150) - 150
            elif kind == "general":
                X[:, 2] = rng.uniform(-30, 30, 6)
            R, t = random_pose(rng)
            assert is_planar(X) == (kind == "planar")
            cands = pnp_candidates(X[:4], normalised(X[:4], R, t))
            assert has_pose(cands, R, t, tol=1e-5), kind


def test_robust_pnp_leaves_out_a_wrong_correspondence():
    rng = np.random.default_rng(2)
    X = np.c_[rng.uniform(-50, 50, (7, 2)), np.zeros(7)]
    R, t = random_pose(rng)
    xy = project(X, INTR, R, t) + rng.normal(0, 0.1, (7, 2))
    xy_bad = xy.copy()
    xy_bad[3] += (30.0, -12.0)
    fits = robust_pnp(X, xy_bad, INTR, threshold_px=3.0)
    best = fits[0]
    np.testing.assert_array_equal(best.inliers, np.arange(7) != 3)
    assert best.errors[3] > 20 and best.rms < 0.3
    assert np.linalg.norm(camera_centre(best.R, best.t) - camera_centre(R, t)) < 1.0
    # exact data with four points: errors vanish
    exact = project(X[:4], INTR, R, t)
    f4 = robust_pnp(X[:4], exact, INTR, threshold_px=1.0)[0]
    assert f4.inliers.all() and f4.errors.max() < 1e-6
    with pytest.raises(ValueError, match="at least 4"):
        robust_pnp(X[:3], exact[:3], INTR, threshold_px=1.0)
    line = np.c_[np.linspace(-40, 40, 5), np.zeros(5), np.zeros(5)]
    assert robust_pnp(line, project(line, INTR, R, t), INTR, threshold_px=1.0) == []


def test_refine_pose_and_reprojection():
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-50, 50, (10, 2)), np.zeros(10)]
    R, t = random_pose(rng)
    R0, t0 = rodrigues(np.array([0.01, -0.02, 0.01])) @ R, t + (1.0, -2.0, 3.0)
    R1, t1 = refine_pose(X, normalised(X, R, t), R0, t0)
    np.testing.assert_allclose(R1, R, atol=1e-9)
    np.testing.assert_allclose(t1, t, atol=1e-7)
    xy = project(X, INTR, R, t)
    assert reprojection_px(X, xy, INTR, R, t).max() < 1e-9
    behind = reprojection_px(X, xy, INTR, R, -t)
    assert np.all(np.isinf(behind))


def test_degenerate_and_relative_poses():
    assert is_degenerate(np.c_[np.arange(5.0), 2 * np.arange(5.0), np.zeros(5)])
    assert not is_degenerate(np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0.0]]))
    rng = np.random.default_rng(4)
    Ra, ta = random_pose(rng)
    Rb, tb = random_pose(rng)
    R_rel, t_rel = Rb @ Ra.T, tb - Rb @ Ra.T @ ta
    R2, t2 = compose_relative(Ra, ta, R_rel, t_rel)
    np.testing.assert_allclose(R2, Rb, atol=1e-12)
    np.testing.assert_allclose(t2, tb, atol=1e-9)
