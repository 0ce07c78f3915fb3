import numpy as np
import pytest

from carapost.core.bundle import bundle_adjust
from carapost.core.bundle_scipy import BundleProblem as _Problem
from carapost.core.camera import Intrinsics, camera_centre, project, rodrigues


def rig(n_cams=4):
    intr, Rs, ts = [], [], []
    for k, ang in enumerate((-0.55, -0.3, 0.3, 0.55)[:n_cams]):
        C = np.array([200 * np.sin(ang), -30.0 + 40 * (k % 2), 200 * np.cos(ang)])
        z = -C / np.linalg.norm(C)
        x = np.cross([0, 1, 0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        intr.append(Intrinsics(1000.0 + 10 * k, (640.0, 360.0), (1280, 720), radial=(3e-8, -2e-14, 0.0)))
        Rs.append(R)
        ts.append(-R @ C)
    return intr, np.array(Rs), np.array(ts)


def scene(F=3, P=40, B=12, seed=0, flex=0.0):
    rng = np.random.default_rng(seed)
    intr, R, t = rig()
    gx, gy = np.meshgrid(np.linspace(-60, 60, B // 3), [80.0, 95.0, 110.0])
    brim = np.c_[gx.ravel(), gy.ravel(), rng.uniform(-3, 3, B)]  # a small card of dots
    face = np.c_[rng.uniform(-50, 50, (F, P)), rng.uniform(-70, 60, (F, P)), rng.uniform(-10, 25, (F, P))]
    X = np.concatenate([np.broadcast_to(brim, (F, B, 3)), face.reshape(F, P, 3)], axis=1)
    Rf = np.broadcast_to(R, (F, 4, 3, 3)).copy()
    tf = np.broadcast_to(t, (F, 4, 3)).copy()
    if flex:
        Rf = rodrigues(rng.normal(scale=flex * 1e-3, size=(F, 4, 3))) @ Rf
        tf = tf + rng.normal(scale=flex, size=(F, 4, 3))
    obs = np.stack([project(X, intr[c], Rf[:, None, c], tf[:, None, c]) for c in range(4)], axis=2)
    fixed = np.r_[np.ones(B, bool), np.zeros(P, bool)]
    return intr, Rf, tf, X, obs, fixed, rng


def perturb(R, t, rng, rot=0.01, trans=2.0):
    return rodrigues(rng.normal(scale=rot, size=R.shape[:-2] + (3,))) @ R, t + rng.normal(scale=trans, size=t.shape)


def test_recovers_poses_and_points_exactly_without_noise():
    intr, R, t, X, obs, fixed, rng = scene(flex=0.5)
    obs[rng.random(obs.shape[:3]) < 0.15] = np.nan
    R0, t0 = perturb(R, t, rng)
    X0 = X.copy()
    X0[:, ~fixed] += rng.normal(scale=1.0, size=X0[:, ~fixed].shape)
    res = bundle_adjust(obs, intr, R0, t0, X0, fixed_points=fixed, pose_prior=0.0)
    assert res.success
    seen = np.isfinite(obs).all(-1).sum(-1) >= 2
    err = np.linalg.norm(res.xyz - X, axis=-1)[seen & ~fixed[None]]
    assert np.max(err) < 1e-4
    np.testing.assert_allclose(camera_centre(res.R, res.t), camera_centre(R, t), atol=1e-4)
    assert np.nanmax(res.residuals[seen]) < 1e-4
    assert res.final_cost < 1e-8 < res.initial_cost


def test_noise_accuracy_and_per_camera_rms():
    intr, R, t, X, obs, fixed, rng = scene(F=2, P=60)
    obs = obs + rng.normal(scale=0.2, size=obs.shape)
    R0, t0 = perturb(R, t, rng)
    res = bundle_adjust(obs, intr, R0, t0, np.where(fixed[None, :, None], X, np.nan), fixed_points=fixed)
    err = np.linalg.norm(res.xyz - X, axis=-1)[:, ~fixed]
    assert np.median(err) < 0.15
    cerr = np.linalg.norm(camera_centre(res.R, res.t) - camera_centre(R, t), axis=-1)
    assert np.max(cerr) < 0.5
    assert res.rms_per_camera.shape == (4,)
    assert np.all(res.rms_per_camera < 0.35)


def test_shared_cameras_one_pose_for_all_frames():
    intr, R, t, X, obs, fixed, rng = scene(F=4)
    R0, t0 = perturb(R[:1], t[:1], rng)
    R0 = np.repeat(R0, 4, 0)
    t0 = np.repeat(t0, 4, 0)
    X0 = X.copy()
    X0[:, ~fixed] += 0.5
    res = bundle_adjust(obs, intr, R0, t0, X0, fixed_points=fixed, shared_cameras=True, pose_prior=0)
    np.testing.assert_allclose(res.R[0], res.R[3])
    np.testing.assert_allclose(camera_centre(res.R[0], res.t[0]), camera_centre(R[0], t[0]), atol=1e-4)


def test_robust_loss_resists_a_mismatch():
    intr, R, t, X, obs, fixed, rng = scene(F=1, P=40)
    obs = obs + rng.normal(scale=0.1, size=obs.shape)
    obs[0, 20, 1] += [25.0, -30.0]  # one mismatched detection
    R0, t0 = perturb(R, t, rng, rot=0.003, trans=0.5)
    plain = bundle_adjust(obs, intr, R0, t0, X, fixed_points=fixed)
    robust = bundle_adjust(obs, intr, R0, t0, X, fixed_points=fixed, loss="soft_l1", f_scale=1.0)
    e_plain = np.linalg.norm(plain.xyz - X, axis=-1)[0, ~fixed]
    e_rob = np.linalg.norm(robust.xyz - X, axis=-1)[0, ~fixed]
    assert np.median(e_rob) < np.median(e_plain)
    assert robust.residuals[0, 20, 1] > 20  # the outlier stays an outlier


def test_analytic_jacobian_matches_finite_differences():
    intr, R, t, X, obs, fixed, rng = scene(F=2, P=10)
    obs = obs + rng.normal(scale=0.3, size=obs.shape)
    prob = _Problem(obs, intr, R, t, X, fixed, False, np.zeros(4, bool), 1e-3)
    x = prob.x0() + rng.normal(scale=1e-3, size=prob.n_params)
    J = prob.jacobian(x).toarray()
    eps = 1e-6
    Jn = np.empty_like(J)
    for k in range(prob.n_params):
        d = np.zeros(prob.n_params)
        d[k] = eps
        Jn[:, k] = (prob.residuals(x + d) - prob.residuals(x - d)) / (2 * eps)
    np.testing.assert_allclose(J, Jn, atol=2e-4 * np.abs(Jn).max())


def test_missing_pose_is_an_error():
    intr, R, t, X, obs, fixed, rng = scene(F=1)
    R = R.copy()
    R[0, 2] = np.nan
    with pytest.raises(ValueError, match="camera 2 has observations in frame 0 but no initial pose"):
        bundle_adjust(obs, intr, R, t, X, fixed_points=fixed)


@pytest.mark.parametrize("solver,jac", [("scipy", "analytic"), ("scipy", "2-point")])
def test_scipy_paths_reach_the_same_minimum(solver, jac):
    intr, R, t, X, obs, fixed, rng = scene(F=2, P=20, flex=0.3)
    obs = obs + rng.normal(scale=0.2, size=obs.shape)
    R0, t0 = perturb(R, t, rng, rot=0.004, trans=1.0)
    lm = bundle_adjust(obs, intr, R0, t0, X, fixed_points=fixed)
    other = bundle_adjust(obs, intr, R0, t0, X, fixed_points=fixed, solver=solver, jac=jac)
    assert lm.final_cost <= other.final_cost * (1 + 1e-6)
    np.testing.assert_allclose(lm.xyz, other.xyz, atol=1e-4)


def test_cameras_only_with_every_point_fixed():
    """A brim-only bundle: all points fixed, only the poses move."""
    intr, R, t, X, obs, fixed, rng = scene(F=1, P=0)
    R0, t0 = perturb(R, t, rng, rot=0.003, trans=0.5)
    res = bundle_adjust(obs, intr, R0, t0, X, fixed_points=np.ones(X.shape[1], bool), pose_prior=0)
    np.testing.assert_allclose(camera_centre(res.R, res.t), camera_centre(R, t), atol=1e-4)
