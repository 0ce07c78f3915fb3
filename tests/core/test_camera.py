import numpy as np
import pytest

from carapost.core.camera import (
    Intrinsics,
    backproject,
    camera_centre,
    distort,
    matrix_to_quat,
    project,
    quat_to_matrix,
    rodrigues,
    symmetric_epipolar_distance,
    undistort,
)
from carapost.core.triangulate import triangulate


def test_quaternion_real_part_last():
    # 90 degrees about z: (x, y, z, w) = (0, 0, sin45, cos45).
    s = np.sqrt(0.5)
    R = quat_to_matrix([0, 0, s, s])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix([0, 0, 0, 1]), np.eye(3))


def test_quaternion_roundtrip_random():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, 3:4])
    np.testing.assert_allclose(matrix_to_quat(quat_to_matrix(q)), q, atol=1e-12)


def test_rodrigues_matches_quaternion():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(50, 3))
    ang = np.linalg.norm(r, axis=1)
    axis = r / ang[:, None]
    q = np.concatenate([axis * np.sin(ang / 2)[:, None], np.cos(ang / 2)[:, None]], axis=1)
    np.testing.assert_allclose(rodrigues(r), quat_to_matrix(q), atol=1e-12)
    np.testing.assert_allclose(rodrigues(np.zeros(3)), np.eye(3))


def test_radial_correction_hand_computed():
    # dp = (100, 50), r^2 = 12500, s = 1 + 1e-7 * 12500 + 1e-12 * 12500^2 = 1.00140625
    intr = Intrinsics(1000.0, (320.0, 240.0), radial=(1e-7, 1e-12, 0.0))
    out = undistort(np.array([420.0, 290.0]), intr)
    s = 1 + 1e-7 * 12500 + 1e-12 * 12500**2
    np.testing.assert_allclose(out, [320 + 100 * s, 240 + 50 * s], rtol=0, atol=1e-12)


def test_radial_correction_aspect_and_centre():
    intr = Intrinsics(1000.0, (320.0, 240.0), aspect=2.0, radial=(1e-7, 0.0, 0.0),
                      distortion_centre=(300.0, 250.0))
    raw = np.array([350.0, 260.0])
    dx, dy = 50.0, 2.0 * 10.0
    s = 1 + 1e-7 * (dx * dx + dy * dy)
    np.testing.assert_allclose(undistort(raw, intr), [300 + s * dx, 250 + s * dy / 2.0])


@pytest.mark.parametrize("radial", [(2.7e-9, -2.0e-16, 0.0), (4.26e-9, -6.24e-16, 4.83e-23),
                                     (-3e-8, 1e-14, 0.0)])
def test_distort_inverts_undistort(radial):
    intr = Intrinsics(4000.0, (2076.0, 2043.0), sensor_size=(4096, 4096), radial=radial,
                      distortion_centre=(2070.0, 2050.0))
    g = np.stack(np.meshgrid(np.linspace(0, 4095, 60), np.linspace(0, 4095, 60)), -1).reshape(-1, 2)
    back = distort(undistort(g, intr), intr)
    assert np.max(np.abs(back - g)) < 1e-6


def test_project_hand_computed():
    # Camera at C = (0, 0, -1000) looking along +z with R = I: t = -R C = (0, 0, 1000).
    intr = Intrinsics(800.0, (320.0, 240.0), skew=0.0)
    R = np.eye(3)
    t = np.array([0.0, 0.0, 1000.0])
    xy = project(np.array([[100.0, -50.0, 0.0]]), intr, R, t)
    np.testing.assert_allclose(xy, [[320 + 80.0, 240 - 40.0]])
    np.testing.assert_allclose(camera_centre(R, t), [0, 0, -1000])


def test_project_behind_camera_is_nan():
    intr = Intrinsics(800.0, (320.0, 240.0))
    xy = project(np.array([[0.0, 0.0, -2000.0]]), intr, np.eye(3), np.array([0, 0, 1000.0]))
    assert np.isnan(xy).all()


def _rig(n_cams=4, radial=(3e-8, -1e-14, 0.0), seed=0):
    """Cameras on a ring 200 mm from the origin, all looking at it."""
    rng = np.random.default_rng(seed)
    intr, Rs, ts = [], [], []
    for k in range(n_cams):
        ang = -0.6 + 1.2 * k / max(n_cams - 1, 1)
        C = np.array([200 * np.sin(ang), 20 * rng.normal(), -200 * np.cos(ang)])
        z = -C / np.linalg.norm(C)
        x = np.cross([0, 1, 0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        Rs.append(R)
        ts.append(-R @ C)
        intr.append(Intrinsics(900.0 + 20 * k, (640.0 + k, 360.0 - k), sensor_size=(1280, 720),
                               radial=radial))
    return intr, np.array(Rs), np.array(ts)


def test_backproject_ray_passes_through_point():
    intr, R, t = _rig()
    X = np.array([[10.0, -20.0, 15.0], [-30.0, 5.0, 0.0]])
    for v in range(4):
        xy = project(X, intr[v], R[v], t[v])
        o, d = backproject(xy, intr[v], R[v], t[v])
        # distance from X to the ray
        w = X - o
        perp = w - np.sum(w * d, -1, keepdims=True) * d
        assert np.max(np.linalg.norm(perp, axis=-1)) < 1e-6


def test_triangulate_exact_and_residuals():
    intr, R, t = _rig()
    rng = np.random.default_rng(3)
    X = rng.uniform(-50, 50, size=(200, 3))
    xy = np.stack([project(X, intr[v], R[v], t[v]) for v in range(4)], axis=1)  # (N, V, 2)
    xy[:50, 0] = np.nan  # some views missing
    xy[:10, 1] = np.nan
    xy[-5:, 1:] = np.nan  # single view: no point
    res = triangulate(xy, intr, R, t)
    good = np.arange(200) < 195
    np.testing.assert_allclose(res.xyz[good], X[good], atol=1e-7)
    assert np.isnan(res.xyz[~good]).all()
    assert np.nanmax(res.residuals[good]) < 1e-6
    assert np.isnan(res.residuals[:50, 0]).all()
    assert list(res.n_views[:3]) == [2, 2, 2]


def test_triangulate_noise_reduces_with_refinement():
    intr, R, t = _rig()
    rng = np.random.default_rng(4)
    X = rng.uniform(-50, 50, size=(2000, 3))
    xy = np.stack([project(X, intr[v], R[v], t[v]) for v in range(4)], axis=1)
    xy += rng.normal(scale=0.3, size=xy.shape)
    lin = triangulate(xy, intr, R, t, iterations=0)
    ref = triangulate(xy, intr, R, t)
    assert np.nanmean(ref.residuals ** 2) <= np.nanmean(lin.residuals ** 2) + 1e-12
    assert np.median(np.linalg.norm(ref.xyz - X, axis=1)) < 0.2


def test_triangulate_per_frame_poses_broadcast():
    intr, R, t = _rig()
    rng = np.random.default_rng(5)
    F, P = 3, 7
    X = rng.uniform(-40, 40, size=(F, P, 3))
    shift = np.array([[0, 0, 0], [1, 2, 3], [-5, 0, 2]], float)  # rig moves per frame
    Rf = np.broadcast_to(R, (F, 4, 3, 3))
    tf = t[None] + shift[:, None, :]
    xy = np.stack([project(X, intr[v], Rf[:, None, v], tf[:, None, v]) for v in range(4)], axis=2)
    res = triangulate(xy, intr, Rf[:, None], tf[:, None])
    np.testing.assert_allclose(res.xyz, X, atol=1e-7)


def test_triangulate_rejects_bad_shape():
    intr, R, t = _rig()
    with pytest.raises(ValueError, match="shape"):
        triangulate(np.zeros((5, 3, 2)), intr, R, t)


def test_symmetric_epipolar_distance():
    intr, R, t = _rig()
    rng = np.random.default_rng(6)
    X = rng.uniform(-50, 50, size=(30, 3))
    x0 = project(X, intr[0], R[0], t[0])
    x1 = project(X, intr[1], R[1], t[1])
    d = symmetric_epipolar_distance(x0, x1, intr[0], R[0], t[0], intr[1], R[1], t[1])
    assert np.max(d) < 1e-6
    table = symmetric_epipolar_distance(x0[:, None], x1[None], intr[0], R[0], t[0], intr[1], R[1], t[1])
    assert table.shape == (30, 30)
    np.testing.assert_allclose(np.diag(table), d, atol=1e-9)
    # moving a point 3 px perpendicular to its epipolar line gives ~3 px distance
    assert np.median(table[~np.eye(30, dtype=bool)]) > 3


def test_triangulate_blocks_match_unblocked(monkeypatch):
    import carapost.core.triangulate as tri

    intr, R, t = _rig()
    rng = np.random.default_rng(7)
    F, P = 40, 9
    X = rng.uniform(-40, 40, size=(F, P, 3))
    tf = t[None] + rng.normal(scale=2.0, size=(F, 1, 3))
    Rf = np.broadcast_to(R, (F, 4, 3, 3))
    xy = np.stack([project(X, intr[v], Rf[:, None, v], tf[:, None, v]) for v in range(4)], axis=2)
    xy[rng.random((F, P, 4)) < 0.3] = np.nan
    whole = triangulate(xy, intr, Rf[:, None], tf[:, None])
    monkeypatch.setattr(tri, "_CHUNK", 20)  # force the blocked path
    blocks = triangulate(xy, intr, Rf[:, None], tf[:, None])
    np.testing.assert_array_equal(np.isnan(whole.xyz), np.isnan(blocks.xyz))
    np.testing.assert_allclose(blocks.xyz, whole.xyz, atol=1e-9)
    np.testing.assert_allclose(blocks.residuals, whole.residuals, atol=1e-9)
    static = triangulate(xy, intr, R, tf[:, None])  # static R, per-frame t
    np.testing.assert_allclose(static.xyz, whole.xyz, atol=1e-9)
