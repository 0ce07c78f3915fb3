"""OpenCV-style calibration TOML (aniposelib, Pose2Sim): layouts, units, distortion conversion,
round trips, errors.

Real layouts (not copied here; these hand-made files follow them):

* aniposelib ``CameraGroup.dump`` (e.g. lambdaloop/aniposelib
  ``tests/data/calib/7cam-allen-mouse/calibration.toml``): tables ``[cam_0]`` ... with
  ``name = "cam088"``, ``size = [ 1440, 1080,]`` (ints), ``matrix`` (3x3, principal point
  ``719.5, 539.5`` = image centre in the pixel-centre convention), ``distortions`` with 5 values
  (often only k1 set), ``rotation`` (Rodrigues), ``translation`` in the board's unit (mm there,
  |t| up to ~1500), then ``[metadata] adjusted = true, error = 1.67``.
* Pose2Sim ``calib_qca_to_toml``: ``[cam_1]`` ..., ``size = [ 1088.0, 1920.0,]`` (floats),
  4 distortion values ``k1, k2, p1, p2``, translation in **metres**, ``fisheye = false``,
  ``[metadata] adjusted = false, error = 0.0``.
"""

import tomllib

import numpy as np
import pytest

from carapost.core.camera import Intrinsics, project, rodrigues
from carapost.io.calibration import (
    Calibration,
    CalibrationError,
    CameraCalibration,
    load_calibration,
    save_calibration,
)
from carapost.io.toml_calib import parse_toml, rotation_vector, toml_text, write_toml

ANIPOSE = """\
[cam_0]
name = "A"
size = [ 1440, 1080,]
matrix = [ [ 1850.0, 0.0, 719.5,], [ 0.0, 1850.0, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.05, 0.0, 0.0, 0.0, 0.0,]
rotation = [ 0.01, -0.02, 0.005,]
translation = [ 2.5, -2.75, -18.0,]

[cam_1]
name = "B"
size = [ 1440, 1080,]
matrix = [ [ 1930.0, 0.0, 719.5,], [ 0.0, 1930.0, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.2, 0.05, 0.001, -0.0005, 0.01,]
rotation = [ -0.22, -2.98, 0.39,]
translation = [ 117.0, 262.5, 1478.75,]

[metadata]
adjusted = true
error = 1.67
"""

POSE2SIM = """\
[cam_1]
name = "cam01"
size = [ 1088.0, 1920.0,]
matrix = [ [ 1681.2, 0.0, 533.0,], [ 0.0, 1681.1, 948.1,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.046, 0.14, 0.0006, 0.0007,]
rotation = [ 1.69, 1.05, -0.42,]
translation = [ 0.321, 0.956, 2.891,]
fisheye = false

[cam_2]
name = "cam02"
size = [ 1088.0, 1920.0,]
matrix = [ [ 1673.7, 0.0, 534.5,], [ 0.0, 1673.8, 963.2,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.048, 0.137, 0.00097, 0.00029,]
rotation = [ 1.35, 1.6, -1.2,]
translation = [ -0.2, 1.1, 2.7,]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"""


def _opencv_project(X, cam_dict):
    cv2 = pytest.importorskip("cv2")
    K = np.array(cam_dict["matrix"], dtype=float)
    d = np.array(cam_dict["distortions"], dtype=float)
    rv = np.array(cam_dict["rotation"], dtype=float)
    t = np.array(cam_dict["translation"], dtype=float)
    if cam_dict.get("fisheye"):
        uv, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rv, t, K, d)
    else:
        uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rv, t, K, d)
    return uv.reshape(-1, 2)


def _points_in_view(cam_dict, n=400, seed=0):
    """World points (n, 3) in front of the camera whose pinhole images fill its frame."""
    rng = np.random.default_rng(seed)
    K = np.array(cam_dict["matrix"], dtype=float)
    w, h = cam_dict["size"]
    px = rng.uniform([0, 0], [w - 1, h - 1], size=(n, 2))
    z = rng.uniform(500, 3000, size=n)
    xn = np.linalg.solve(K, np.c_[px, np.ones(n)].T).T
    Xc = xn * z[:, None]
    R = rodrigues(np.array(cam_dict["rotation"], dtype=float))
    return (Xc - np.array(cam_dict["translation"], dtype=float)) @ R  # R^T (Xc - t)


def test_aniposelib_layout():
    cal = parse_toml(ANIPOSE, source="calibration.toml")
    assert cal.format == "toml" and cal.names == ["A", "B"]
    assert cal.extra["toml_units"] == "mm" and cal.extra["toml_units_detected"]
    assert cal.extra["toml_other"] == {"metadata": {"adjusted": True, "error": 1.67}}
    a = cal.cameras[0]
    assert a.intrinsics.focal_length == 1850.0 and a.intrinsics.principal_point == (719.5, 539.5)
    assert a.intrinsics.sensor_size == (1440, 1080) and a.intrinsics.aspect == 1.0
    np.testing.assert_array_equal(a.R[0], rodrigues(np.array([0.01, -0.02, 0.005])))
    np.testing.assert_array_equal(a.t[0], [2.5, -2.75, -18.0])
    assert a.extra["distortion_fit"]["max_residual_px"] < 0.05  # k1 only: almost exact
    assert a.intrinsics.distortion_centre is None  # no tangential terms, no centre shift
    assert cal.cameras[1].intrinsics.distortion_centre is not None  # tangential -> centre fitted


def test_pose2sim_layout_is_in_metres():
    cal = parse_toml(POSE2SIM, source="Calib.toml")
    assert cal.extra["toml_units"] == "m"
    np.testing.assert_allclose(cal.cameras[0].t[0], [321.0, 956.0, 2891.0], rtol=1e-15)
    assert cal.cameras[0].intrinsics.sensor_size == (1088, 1920)  # width 1088, height 1920
    assert cal.cameras[0].intrinsics.aspect == 1681.2 / 1681.1
    text, report = toml_text(cal)  # written back in the unit it was read in
    doc = tomllib.loads(text)
    assert list(doc) == ["cam_1", "cam_2", "metadata"]
    assert doc["cam_1"]["translation"] == pytest.approx([0.321, 0.956, 2.891], rel=1e-15)
    assert doc["cam_1"]["distortions"] == [-0.046, 0.14, 0.0006, 0.0007]  # as read
    assert doc["cam_1"]["fisheye"] is False and doc["metadata"] == {"adjusted": False, "error": 0.0}
    assert [r["distortion"] for r in report] == ["original", "original"]


@pytest.mark.parametrize("units, scale", [("mm", 1.0), ("cm", 10.0), ("m", 1000.0)])
def test_units_option(units, scale):
    cal = parse_toml(ANIPOSE, units=units)
    np.testing.assert_allclose(cal.cameras[1].t[0], np.array([117.0, 262.5, 1478.75]) * scale)
    assert not cal.extra["toml_units_detected"]


@pytest.mark.parametrize("text", [ANIPOSE, POSE2SIM])
def test_projection_matches_opencv_within_the_reported_residual(text):
    cal = parse_toml(text)
    doc = tomllib.loads(text)
    scale = 1000.0 if cal.extra["toml_units"] == "m" else 1.0
    for cam, key in zip(cal.cameras, [k for k in doc if k != "metadata"]):
        d = doc[key]
        X = _points_in_view(d)
        ref = _opencv_project(X, d)
        ours = project(X * scale, cam.intrinsics, cam.R[0], cam.t[0])
        w, h = cam.intrinsics.sensor_size
        inside = (ref[:, 0] >= 0) & (ref[:, 0] <= w - 1) & (ref[:, 1] >= 0) & (ref[:, 1] <= h - 1)
        err = np.linalg.norm(ours - ref, axis=1)[inside].max()
        assert err <= cam.extra["distortion_fit"]["max_residual_px"] + 1e-6, (key, err)


@pytest.mark.parametrize("f, limit", [(800.0, 1.0), (600.0, None)])
def test_fisheye_camera(f, limit):
    """OpenCV fisheye converts well up to ~110 degrees diagonal (f = 800 px on 1280 x 960:
    max 0.8 px), not at ~150 degrees (f = 600: 27 px at the corners, reported)."""
    d = {"name": "fe", "size": [1280, 960], "matrix": [[f, 0.0, 639.5], [0.0, f, 479.5], [0, 0, 1]],
         "distortions": [0.05, -0.01, 0.002, -0.0003], "rotation": [0.1, 0.2, 0.3],
         "translation": [10.0, 20.0, 30.0], "fisheye": True}
    text = "[cam_0]\n" + "\n".join(f"{k} = {v!r}".replace("True", "true").replace("'", '"') for k, v in d.items())
    cal = parse_toml(text, units="mm")
    cam = cal.cameras[0]
    fit = cam.extra["distortion_fit"]
    assert fit["from"] == "opencv fisheye"
    X = _points_in_view(d)
    ref = _opencv_project(X, d)
    ours = project(X, cam.intrinsics, cam.R[0], cam.t[0])
    inside = (ref[:, 0] >= 0) & (ref[:, 0] <= 1279) & (ref[:, 1] >= 0) & (ref[:, 1] <= 959)
    err = np.linalg.norm(ours - ref, axis=1)[inside].max()
    assert err <= fit["max_residual_px"] + 1e-6
    if limit is not None:
        assert fit["max_residual_px"] < limit
    else:
        assert fit["max_residual_px"] > 10  # honestly reported, not hidden
    out = tomllib.loads(toml_text(cal)[0])["cam_0"]
    assert out["fisheye"] is True and out["distortions"] == d["distortions"]


def test_toml_round_trip_keeps_everything(tmp_path):
    src = tmp_path / "in.toml"
    src.write_text(ANIPOSE)
    cal = load_calibration(src)
    out = tmp_path / "out.toml"
    save_calibration(out, cal)
    a, b = tomllib.loads(ANIPOSE), tomllib.loads(out.read_text())
    assert list(a) == list(b)
    for key in a:
        if key == "metadata":
            assert a[key] == b[key]
            continue
        for field in ("name", "size", "matrix", "distortions", "translation"):
            assert a[key][field] == b[key][field], (key, field)
        np.testing.assert_allclose(rodrigues(np.array(b[key]["rotation"])),
                                   rodrigues(np.array(a[key]["rotation"])), atol=1e-15)
    back = load_calibration(out)
    for c0, c1 in zip(cal.cameras, back.cameras):
        assert c0.intrinsics == c1.intrinsics
        np.testing.assert_allclose(c1.R, c0.R, atol=1e-15)
        np.testing.assert_array_equal(c1.t, c0.t)


def _synthetic(radial, size=(2432, 2048), f=1900.0, n=2, centre=None):
    rng = np.random.default_rng(7)
    cams = []
    for i in range(n):
        intr = Intrinsics(f + i, (size[0] / 2 - 0.5 + 3 * i, size[1] / 2 - 0.5 - 2 * i), size,
                          aspect=1.0 + 1e-4 * i, skew=0.0, radial=radial, distortion_centre=centre)
        cams.append(CameraCalibration(f"cam_{i}", "", "", intr, np.array([0]),
                                      rodrigues(rng.normal(size=3))[None], rng.normal(size=(1, 3)) * 2000))
    return Calibration(cams)


def test_our_model_to_toml_gives_exact_pose_and_fitted_distortion(tmp_path):
    cal = _synthetic((2e-8, -5e-15, 0.0))
    report = write_toml(tmp_path / "c.toml", cal)
    assert [r["distortion"] for r in report] == ["fitted", "fitted"]
    assert all(r["max_residual_px"] < 0.5 for r in report)
    doc = tomllib.loads((tmp_path / "c.toml").read_text())
    assert list(doc) == ["cam_0", "cam_1"]
    for cam, key in zip(cal.cameras, doc):
        d = doc[key]
        np.testing.assert_array_equal(np.array(d["matrix"]), cam.intrinsics.K)  # exact
        np.testing.assert_allclose(rodrigues(np.array(d["rotation"])), cam.R[0], atol=1e-14)
        np.testing.assert_allclose(np.array(d["translation"]) * 1000.0, cam.t[0], rtol=1e-14)  # metres
        assert d["distortions"][2:4] == [0.0, 0.0] and len(d["distortions"]) == 5
        # OpenCV with the written coefficients lands where our model does, within the residual
        X = _points_in_view(d, seed=1)
        ours = project(X * 1000.0, cam.intrinsics, cam.R[0], cam.t[0])
        ref = _opencv_project(X, d)
        w, h = cam.intrinsics.sensor_size
        inside = (ours[:, 0] >= 0) & (ours[:, 0] <= w - 1) & (ours[:, 1] >= 0) & (ours[:, 1] <= h - 1)
        err = np.linalg.norm(ours - ref, axis=1)[inside].max()
        rep = report[list(doc).index(key)]
        assert err <= rep["max_residual_px"] + 1e-6


def test_rational_fit_for_strong_distortion():
    # the correction of a Vantage 5 in the real Nexus file (2432 x 2048, f = 1900 px)
    cal = _synthetic((6.6035542190405148e-08, -3.7741784429210515e-14, 2.7232439104507643e-20), n=1)
    _, five = toml_text(cal)
    text, eight = toml_text(cal, rational=True)
    assert len(tomllib.loads(text)["cam_0"]["distortions"]) == 8
    assert 2.0 < five[0]["max_residual_px"] < 5.0  # measured 3.7 px with k1, k2, k3
    assert eight[0]["max_residual_px"] < 0.1  # measured 0.06 px with the rational model


def test_moving_cameras_need_a_frame():
    cal = _synthetic((0.0, 0.0, 0.0), n=1)
    F = 10
    R = np.broadcast_to(np.eye(3), (F, 1, 3, 3)).copy()
    t = np.zeros((F, 1, 3))
    t[5:, 0, 0] = 100.0
    moving = cal.with_poses(R, t)
    with pytest.raises(CalibrationError, match="moves .* one pose per camera"):
        toml_text(moving)
    doc = tomllib.loads(toml_text(moving, frame=7, units="mm")[0])
    assert doc["cam_0"]["translation"] == [100.0, 0.0, 0.0]


def test_section_names_sort_lexically_in_camera_order():
    cal = _synthetic((0.0, 0.0, 0.0), n=12)
    doc = tomllib.loads(toml_text(cal)[0])
    assert list(doc) == sorted(doc) == [f"cam_{i:02d}" for i in range(12)]  # aniposelib sorts keys
    assert [doc[k]["name"] for k in doc] == [f"cam_{i}" for i in range(12)]


def test_rotation_vector_inverts_rodrigues():
    rng = np.random.default_rng(5)
    r = rng.normal(size=(200, 3))
    r *= (rng.uniform(0, np.pi, 200) / np.linalg.norm(r, axis=1))[:, None]
    r[0] = [np.pi, 0, 0]  # half turn
    r[1] = [0, 0, 1e-14]  # tiny
    R = rodrigues(r)
    np.testing.assert_allclose(rodrigues(rotation_vector(R)), R, atol=1e-12)
    np.testing.assert_allclose(rotation_vector(R[2:]), r[2:], atol=1e-9)


def test_written_strings_are_escaped():
    cal = _synthetic((0.0, 0.0, 0.0), n=1)
    cal.cameras[0].name = 'odd "name" \\ with\ttab'
    doc = tomllib.loads(toml_text(cal)[0])
    assert doc["cam_0"]["name"] == 'odd "name" \\ with\ttab'


@pytest.mark.parametrize("text, message", [
    ("[cam_0\nname = 1", r"^b\.toml: not a valid TOML file"),
    ("[metadata]\nerror = 0.0\n", r"^b\.toml: no camera table"),
    (ANIPOSE.replace("[ 0.0, 0.0, 1.0,],]", "]", 1), r"^b\.toml: camera 0 \(A\): matrix must have shape \(3, 3\)"),
    (ANIPOSE.replace("[ 0.0, 0.0, 1.0,],]", "[ 0.0, 1.0, 1.0,],]", 1), r"^b\.toml: camera 0 \(A\): matrix is not a camera matrix"),
    (ANIPOSE.replace("-0.05, 0.0, 0.0, 0.0, 0.0,", "-0.05, 0.0, 0.0,", 1),
     r"^b\.toml: camera 0 \(A\): distortions must have shape"),
    (ANIPOSE.replace("rotation = [ 0.01, -0.02, 0.005,]", "rotation = [[1,0,0],[0,1,0],[0,0,2]]", 1),
     r"^b\.toml: camera 0 \(A\): rotation is a 3x3 matrix but not a rotation"),
    (ANIPOSE.replace("translation = [ 2.5, -2.75, -18.0,]", 'translation = [ 2.5, "x", -18.0,]', 1),
     r"^b\.toml: camera 0 \(A\): translation must be numbers"),
    (ANIPOSE.replace("translation = [ 2.5, -2.75, -18.0,]\n", "", 1), r"^b\.toml: camera 0 \(A\): translation is missing"),
])
def test_malformed_toml(text, message):
    with pytest.raises(CalibrationError, match=message):
        parse_toml(text, source="/p/b.toml")


def test_bad_units():
    with pytest.raises(CalibrationError, match="unknown units 'km'"):
        parse_toml(ANIPOSE, source="b.toml", units="km")
    with pytest.raises(CalibrationError, match="unknown units"):
        toml_text(parse_toml(ANIPOSE), units="inch")


def test_lens_models_match_opencv_and_invert():
    cv2 = pytest.importorskip("cv2")
    from carapost.core.lens_models import brown_distort, brown_undistort, fisheye_distort, fisheye_undistort
    rng = np.random.default_rng(11)
    xy = rng.uniform(-0.6, 0.6, size=(500, 2))
    X = np.c_[xy, np.ones(len(xy))]
    for coeffs in ([-0.2, 0.05, 0.001, -0.0005], [-0.2, 0.05, 0.001, -0.0005, 0.01],
                   [0.1, -0.05, 0.001, 0.002, 0.01, 0.05, -0.01, 0.003]):
        ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), np.eye(3), np.array(coeffs))
        np.testing.assert_allclose(brown_distort(xy, coeffs), ref.reshape(-1, 2), atol=1e-12)
        np.testing.assert_allclose(brown_undistort(brown_distort(xy, coeffs), coeffs), xy, atol=1e-9)
    fe = [0.05, -0.01, 0.002, -0.0003]
    ref, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.eye(3), np.array(fe))
    np.testing.assert_allclose(fisheye_distort(xy, fe), ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(fisheye_undistort(fisheye_distort(xy, fe), fe), xy, atol=1e-9)
    with pytest.raises(ValueError, match="4, 5 or 8"):
        brown_distort(xy, [0.1, 0.2, 0.3])
