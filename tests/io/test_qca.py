"""Qualisys .qca calibrations: conventions checked on the real Pose2Sim demo (its calibration,
its 3D keypoints, its checkerboard images), conversion to our model, errors."""

import numpy as np
import pytest

from carapost.core.camera import project
from carapost.core.lens_models import brown_distort
from carapost.io.calibration import CalibrationError, load_calibration, save_calibration
from carapost.io.qca import QUALISYS_TO_CAMERA, parse_qca

W, H = 1088, 1920  # portrait video frames: width 1088, height 1920


@pytest.fixture(scope="module")
def demo(real_data):
    d = real_data / "pose2sim-demo"
    if not (d / "calibration" / "Calib.qca.txt").exists():
        pytest.skip("Pose2Sim demo not available")
    return d


@pytest.fixture(scope="module")
def calib(demo):
    return load_calibration(demo / "calibration" / "Calib.qca.txt")


@pytest.fixture(scope="module")
def keypoints(demo):
    """TRC keypoints (frames, 21, 3) in the calibration's world frame, mm.

    The TRC is Pose2Sim's OpenSim export: metres, tab separated, 5 header lines, Y up. Its
    axes are the calibration's (Z-up) axes permuted: TRC (X, Y, Z) = world (Y, Z, X).
    """
    trc = np.loadtxt(demo / "pose-3d" / "S00_P00_T01_BalancingTrial_0-100.trc", skiprows=5)
    xyz = trc[:, 2:].reshape(len(trc), -1, 3) * 1000.0
    assert xyz.shape == (100, 21, 3)
    return xyz[..., [2, 0, 1]]


def test_demo_file_reads(calib):
    assert calib.format == "qca" and calib.names == ["cam01", "cam02", "cam03", "cam04"]
    for cam in calib.cameras:
        intr = cam.intrinsics
        assert intr.sensor_size == (W, H)
        assert 1670 < intr.focal_length < 1685  # focalLengthU / 64
        assert 500 < intr.principal_point[0] < 560 and 930 < intr.principal_point[1] < 980
        assert abs(intr.aspect - 1) < 1e-3
        assert cam.n_keyframes == 1 and 0.3 < cam.world_error[0] < 0.6  # avg-residual, mm
    c0 = calib.cameras[0].intrinsics
    assert c0.focal_length == 107599.671875 / 64
    assert c0.aspect == 107599.671875 / 107588.828125
    # the transform's x y z is the camera centre (mm)
    np.testing.assert_allclose(calib.cameras[0].centres[0], [1460.2323709212087, -1909.1590482454608,
                                                              1896.5058524092062], atol=1e-9)


def _pose_readings(cam):
    """Our reading and three wrong ones, as (R, t) with the same centre."""
    R = cam.R[0]
    M = QUALISYS_TO_CAMERA @ R  # the file's matrix
    C = cam.centres[0]
    out = {}
    for name, Rr in (("ours", R), ("no flip", M), ("transposed", QUALISYS_TO_CAMERA @ M.T),
                     ("flip about y", np.diag([-1.0, 1.0, -1.0]) @ M)):
        out[name] = (Rr, -Rr @ C)
    return out


def test_optical_axes_point_at_the_keypoints(calib, keypoints):
    target = keypoints[0].mean(axis=0)
    transposed = []
    for cam in calib.cameras:
        cos = {}
        for name, (R, t) in _pose_readings(cam).items():
            d = target - cam.centres[0]
            cos[name] = float(R[2] @ d / np.linalg.norm(d))
        assert cos["ours"] > 0.95, (cam.name, cos)
        assert cos["no flip"] < 0, (cam.name, cos)
        transposed.append(cos["transposed"])
    assert min(transposed) < 0.5, transposed  # reading the matrix as camera-to-world fails


def test_keypoints_project_into_the_portrait_image_upright(calib, keypoints):
    names = ["RHip", "RKnee", "RAnkle", "RBigToe", "RSmallToe", "RHeel", "LHip", "LKnee", "LAnkle",
             "LBigToe", "LSmallToe", "LHeel", "Neck", "Head", "Nose", "RShoulder", "RElbow", "RWrist",
             "LShoulder", "LElbow", "LWrist"]
    head, ankles = names.index("Head"), [names.index("RAnkle"), names.index("LAnkle")]
    for cam in calib.cameras:
        uv = project(keypoints, cam.intrinsics, cam.R[0], cam.t[0])  # (100, 21, 2)
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
        assert inside[0].all(), (cam.name, uv[0])  # frame 0: all 21 keypoints land in the image
        assert inside.mean() > 0.99, cam.name  # and (nearly) all of every frame
        # the person stands upright in the portrait frame: head well above the ankles
        assert np.all(uv[:, head, 1] < uv[:, ankles, 1].max(axis=1) - 400), cam.name
        for name, (R, t) in _pose_readings(cam).items():
            if name != "ours":  # no other reading puts the person upright inside the image
                uvw = project(keypoints[0], cam.intrinsics, R, t)
                ok = np.isfinite(uvw).all(-1) & (uvw[:, 0] >= 0) & (uvw[:, 0] < W) & (uvw[:, 1] >= 0) & (uvw[:, 1] < H)
                assert not (ok.all() and uvw[head, 1] < uvw[ankles, 1].min()), (cam.name, name)


def test_distortion_fit_matches_the_full_qualisys_model(calib, keypoints):
    for cam in calib.cameras:
        fit = cam.extra["distortion_fit"]
        coeffs = cam.extra["opencv_distortion"]["coefficients"]
        assert fit["dropped_tangential"] == coeffs[2:4]
        # measured 0.99, 1.11, 0.86, 0.45 px over the whole image
        assert fit["max_residual_px"] < 1.2 and fit["rms_residual_px"] < 0.7
        # projection with our model vs the file's full Brown model (tangential included)
        intr = cam.intrinsics
        Xc = np.einsum("ij,fpj->fpi", cam.R[0], keypoints) + cam.t[0]
        xd = brown_distort(Xc[..., :2] / Xc[..., 2:], coeffs)
        ref = np.stack([intr.focal_length * xd[..., 0] + intr.principal_point[0],
                        intr.focal_length / intr.aspect * xd[..., 1] + intr.principal_point[1]], -1)
        ours = project(keypoints, intr, cam.R[0], cam.t[0])
        assert np.abs(ours - ref).max() <= fit["max_residual_px"] + 1e-6


def test_centre_fit_absorbs_the_tangential_terms(demo):
    path = demo / "calibration" / "Calib.qca.txt"
    with_centre = load_calibration(path)
    plain = load_calibration(path, fit_centre=False)
    for a, b in zip(with_centre.cameras, plain.cameras):
        assert b.intrinsics.distortion_centre is None and a.intrinsics.distortion_centre is not None
        assert a.extra["distortion_fit"]["max_residual_px"] < 0.7 * b.extra["distortion_fit"]["max_residual_px"]
    # the plain fit leaves about 2.2 px (cam01/cam02) at the corners
    assert max(c.extra["distortion_fit"]["max_residual_px"] for c in plain.cameras) > 1.5


@pytest.mark.slow  # ~4-7 s: checkerboard detection on 28 full-HD images
def test_distortion_is_in_normalised_units_not_subpixels(demo, calib):
    """Pose2Sim's converter divides the radial terms by 64; the checkerboards say otherwise.

    With the file's K held fixed, OpenCV's fit of k1, k2 to the demo's intrinsic checkerboard
    images (4 x 7 inner corners, 60 mm squares) gives k1 = -0.027, -0.065, -0.048, -0.059 and
    k2 = 0.045 .. 0.24: the file's -0.046 / 0.137 as written, 40-90 times the /64 values.
    """
    cv2 = pytest.importorskip("cv2")
    obj = np.zeros((28, 3), np.float32)
    obj[:, :2] = np.mgrid[0:4, 0:7].T.reshape(-1, 2) * 60.0
    for i, cam in enumerate(calib.cameras):
        images = sorted((demo / "calibration" / "intrinsics" / f"int_cam{i + 1:02d}_img").glob("*.jpg"))
        if not images:
            pytest.skip("checkerboard images not available")
        obj_pts, img_pts = [], []
        for f in images:
            g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            ok, corners = cv2.findChessboardCorners(g, (4, 7))
            if ok:
                corners = cv2.cornerSubPix(g, corners, (11, 11), (-1, -1),
                                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
                obj_pts.append(obj)
                img_pts.append(corners)
        assert len(img_pts) >= 5
        K = cam.intrinsics.K
        flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_FOCAL_LENGTH
                 | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3)
        rms, _, d, _, _ = cv2.calibrateCamera(obj_pts, img_pts, (W, H), K.copy(), np.zeros(5), flags=flags)
        k1, k2 = d.ravel()[:2]
        k1_file, k2_file = cam.extra["opencv_distortion"]["coefficients"][:2]
        assert rms < 1.2
        assert k1 < 0 and k2 > 0
        assert 0.4 < k1 / k1_file < 2.5, (cam.name, k1, k1_file)
        assert abs(k1) > 20 * abs(k1_file / 64)


def test_binning_divides_the_intrinsics(demo, calib):
    half = load_calibration(demo / "calibration" / "Calib.qca.txt", binning=2)
    for a, b in zip(calib.cameras, half.cameras):
        assert b.intrinsics.sensor_size == (W // 2, H // 2)
        assert b.intrinsics.focal_length == pytest.approx(a.intrinsics.focal_length / 2, rel=1e-12)
        np.testing.assert_allclose(b.intrinsics.principal_point, np.divide(a.intrinsics.principal_point, 2))
        np.testing.assert_array_equal(a.R, b.R)


def test_qca_converts_to_xcp(calib, tmp_path):
    save_calibration(tmp_path / "demo.xcp", calib)
    back = load_calibration(tmp_path / "demo.xcp")
    assert back.names == calib.names
    for a, b in zip(calib.cameras, back.cameras):
        assert a.intrinsics == b.intrinsics
        np.testing.assert_allclose(b.R, a.R, atol=1e-12)
        np.testing.assert_allclose(b.t, a.t, atol=1e-9)


_CAM = ('<camera serial="c1" avg-residual="0.5"><fov_video left="0" top="0" right="99" bottom="199"/>'
        '<transform x="0" y="0" z="1000" r11="1" r12="0" r13="0" r21="0" r22="1" r23="0" r31="0" r32="0" r33="1"/>'
        '<intrinsic focalLengthU="6400" focalLengthV="6400" centerPointU="3200" centerPointV="6400" '
        'radialDistortion1="0" radialDistortion2="0" radialDistortion3="0" tangentalDistortion1="0" '
        'tangentalDistortion2="0" skew="0"/></camera>')


def _doc(cam=_CAM):
    return f"<calibration><cameras>{cam}</cameras></calibration>"


def test_minimal_document():
    cal = parse_qca(_doc(), source="m.qca.txt")
    intr = cal.cameras[0].intrinsics
    assert intr.focal_length == 100 and intr.principal_point == (50, 100) and intr.sensor_size == (100, 200)
    assert not intr.has_distortion and "distortion_fit" not in cal.cameras[0].extra
    # identity transform: the Qualisys camera looks down -z, ours along +z
    np.testing.assert_array_equal(cal.cameras[0].R[0], np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(cal.cameras[0].centres[0], [0, 0, 1000])


@pytest.mark.parametrize("doc, message", [
    ("not xml", r"^b\.qca\.txt: not a valid XML file"),
    ("<Cameras/>", r"^b\.qca\.txt: not a Qualisys calibration"),
    ("<calibration><cameras/></calibration>", r"^b\.qca\.txt: the file has no <cameras>/<camera>"),
    (_doc(_CAM.replace('r11="1"', 'r11="2"')), r"^b\.qca\.txt: camera 0 \(c1\): <transform> r11\.\.r33 is not a rotation"),
    (_doc(_CAM.replace(' x="0"', "")), r"^b\.qca\.txt: camera 0 \(c1\): <transform> x is missing"),
    (_doc(_CAM.replace('focalLengthU="6400"', 'focalLengthU="abc"')),
     r'^b\.qca\.txt: camera 0 \(c1\): <intrinsic> focalLengthU must be a number, got "abc"'),
    (_doc(_CAM.replace('<intrinsic', '<intrinsicX').replace("/></camera>", "/></camera>")),
     r"^b\.qca\.txt: camera 0 \(c1\): has no <intrinsic> element"),
])
def test_malformed_qca(doc, message):
    with pytest.raises(CalibrationError, match=message):
        parse_qca(doc, source="/x/b.qca.txt")
