"""XCP calibration files: reading, writing, moving cameras, errors; the camera model on every
real calibration we have."""

import shutil

import numpy as np
import pytest
from lxml import etree

from carapost.core.camera import Intrinsics, backproject, project, quat_to_matrix, rodrigues
from carapost.core.lens_models import monotonic_radius
from carapost.io.calibration import (
    Calibration,
    CalibrationError,
    CameraCalibration,
    frames_from_poses,
    load_calibration,
    natural_sort_key,
    save_calibration,
)
from carapost.io.xcp import parse_xcp, xcp_bytes

# The reference guide's "Example Cameras node", verbatim as printed (PDF extraction split two
# VICON_RADIAL numbers across lines inside the attribute: "-2.6e-\n        016").
GUIDE_EXAMPLE = """<?xml version="1.0" encoding="UTF-8" standalone="no" ?>
<Cameras NAME="" VERSION="1.0">
  <Camera DEVICEID="17980" NAME="T160_17980" PIXEL_ASPECT_RATIO="1"
    SENSOR_SIZE="4704 3456" SKEW="0" >
    <KeyFrames>
      <KeyFrame FRAME="0" FOCAL_LENGTH="4570.1" IMAGE_ERROR="0.3"
        ORIENTATION="0.3 0.9 -0.2 0.1" POSITION="-27.1 33.4 63.1"
        PRINCIPAL_POINT="2400.4 1711.6" VICON_RADIAL="2.7e-009 -2.0e-016"/>
      <KeyFrame FRAME="11" FOCAL_LENGTH="4570.1" IMAGE_ERROR="0.3"
        ORIENTATION="0.3 0.9 -0.2 0.1" POSITION="-27.1 33.4 63.1"
        PRINCIPAL_POINT="2400.4 1711.6" VICON_RADIAL="2.7e-009 -2.0e-016"/>
    </KeyFrames>
  </Camera>
  <Camera DEVICEID="18912" NAME="T160_18912" PIXEL_ASPECT_RATIO="1"
    SENSOR_SIZE="4704 3456" SKEW="0">
    <KeyFrames>
      <KeyFrame FOCAL_LENGTH="4563.6" FRAME="0" IMAGE_ERROR="0.35"
        ORIENTATION="-0.1 0.6 -0.1 0.6" POSITION="72.4 31.3 -24.8"
        PRINCIPAL_POINT="2381.7 1711.2" VICON_RADIAL="2.7e-009 -2.6e-
        016"/>
      <KeyFrame FRAME="11" FOCAL_LENGTH="4570.1" IMAGE_ERROR="0.3"
        ORIENTATION="0.3 0.9 -0.2 0.1" POSITION="-27.1 33.4 63.1"
        PRINCIPAL_POINT="2400.4 1711.6" VICON_RADIAL="2.7e-009 -2.0e-
        016"/>
    </KeyFrames>
  </Camera>
</Cameras>
"""


@pytest.fixture
def real_xcp(real_data, tmp_path):
    src = real_data / "opencap-core" / "testCalibration.xcp"
    if not src.exists():
        pytest.skip("testCalibration.xcp not available")
    dst = tmp_path / "testCalibration.xcp"
    shutil.copyfile(src, dst)
    return dst


# --------------------------------------------------------------------------------------
# The guide's example
# --------------------------------------------------------------------------------------


def test_guide_example_parses():
    cal = parse_xcp(GUIDE_EXAMPLE, source="guide.xcp")
    assert cal.format == "xcp" and len(cal) == 2
    a, b = cal.cameras
    assert (a.name, a.device_id, b.name, b.device_id) == ("T160_17980", "17980", "T160_18912", "18912")
    np.testing.assert_array_equal(a.frames, [0, 11])
    np.testing.assert_array_equal(b.frames, [0, 11])
    assert a.intrinsics == Intrinsics(4570.1, (2400.4, 1711.6), (4704, 3456), 1.0, 0.0, (2.7e-9, -2.0e-16, 0.0))
    assert a.keyframe_intrinsics == ()  # both keyframes share the intrinsics
    # camera 2's keyframes differ (focal 4563.6 then 4570.1) and the split "-2.6e- 016" reads as -2.6e-16
    assert [k.focal_length for k in b.keyframe_intrinsics] == [4563.6, 4570.1]
    assert b.intrinsics_at(0).radial == (2.7e-9, -2.6e-16, 0.0)
    assert b.intrinsics_at(1).radial == (2.7e-9, -2.0e-16, 0.0)
    # ORIENTATION is x y z w (normalised here); POSITION is the centre
    np.testing.assert_allclose(a.R[0], quat_to_matrix([0.3, 0.9, -0.2, 0.1]), atol=1e-15)
    np.testing.assert_allclose(b.centres, [[72.4, 31.3, -24.8], [-27.1, 33.4, 63.1]], atol=1e-12)
    np.testing.assert_allclose(b.image_error, [0.35, 0.3])
    assert np.isnan(b.world_error).all()
    # run-length encoding: keyframe 0 holds frames 0..10, keyframe 1 from 11 on
    R, t = cal.poses(15)
    assert R.shape == (15, 2, 3, 3) and t.shape == (15, 2, 3)
    np.testing.assert_array_equal(t[:11, 1], np.broadcast_to(b.t[0], (11, 3)))
    np.testing.assert_array_equal(t[11:, 1], np.broadcast_to(b.t[1], (4, 3)))


def test_guide_example_round_trips_with_keyframes_and_vicon_radial():
    cal = parse_xcp(GUIDE_EXAMPLE, source="guide.xcp")
    text = xcp_bytes(cal)
    assert b"VICON_RADIAL2" not in text and b'VICON_RADIAL="2.7e-09 -2.6e-16"' in text
    back = parse_xcp(text)
    for c0, c1 in zip(cal.cameras, back.cameras):
        np.testing.assert_array_equal(c0.frames, c1.frames)
        np.testing.assert_allclose(c0.R, c1.R, atol=1e-15)
        np.testing.assert_allclose(c0.t, c1.t, atol=1e-12)
        assert [c0.intrinsics_at(k) for k in range(2)] == [c1.intrinsics_at(k) for k in range(2)]
        np.testing.assert_array_equal(c0.image_error, c1.image_error)
    assert back.extra["xcp_root_attrib"] == {"NAME": "", "VERSION": "1.0"}


# --------------------------------------------------------------------------------------
# The real Nexus file
# --------------------------------------------------------------------------------------


def _convergence_point(C, D):
    """Point closest (least squares) to the lines C + s D."""
    M = np.eye(3)[None] - D[:, :, None] * D[:, None, :]
    return np.linalg.solve(M.sum(0), np.einsum("kij,kj->i", M, C))


def _median_cosine(R, C, target):
    d = target - C
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.median(np.einsum("ki,ki->k", R[:, 2], d)))


def test_real_position_is_the_camera_centre(real_xcp):
    cal = load_calibration(real_xcp)
    assert len(cal) == 25 and all(c.n_keyframes == 1 for c in cal.cameras)
    R = np.stack([c.R[0] for c in cal.cameras])
    position = np.stack([c.centres[0] for c in cal.cameras])  # = POSITION as read
    as_translation = -np.einsum("kji,kj->ki", R, position)  # centre if POSITION were t
    cos = {}
    for name, C in (("centre", position), ("translation", as_translation)):
        volume = _convergence_point(C, R[:, 2])  # where the optical axes meet
        floor = np.r_[C[:, :2].mean(0), 0.0]  # below the cameras' centroid, on the floor
        cos[name] = (_median_cosine(R, C, volume), _median_cosine(R, C, floor))
    # POSITION read as the camera centre: the cameras look into the volume (measured 0.969 / 0.967)
    assert min(cos["centre"]) >= 0.95, cos
    # the other reading fails (measured 0.59 / 0.45)
    assert max(cos["translation"]) < 0.8, cos


def test_real_file_round_trips_unknown_content(real_xcp, tmp_path):
    cal = load_calibration(real_xcp)
    out = tmp_path / "out.xcp"
    save_calibration(out, cal)
    parser = etree.XMLParser(remove_blank_text=True)
    r0 = etree.parse(str(real_xcp), parser).getroot()
    r1 = etree.parse(str(out), parser).getroot()
    assert r0.attrib == r1.attrib
    assert len(r0) == len(r1) == 25
    for c0, c1 in zip(r0, r1):
        a0, a1 = dict(c0.attrib), dict(c1.attrib)
        assert a1.pop("SKEW") == "0"  # SKEW is part of our model and always written
        assert a0 == a1  # every other attribute, byte for byte, known or not
        assert list(c0.attrib.keys()) == [k for k in c1.attrib.keys() if k != "SKEW"]  # order too
        assert [ch.tag for ch in c0] == [ch.tag for ch in c1]
        for e0, e1 in zip(c0, c1):
            if e0.tag != "KeyFrames":  # ThresholdGrid, Calibration, Capture, ControlFrames, ...
                assert etree.tostring(e0) == etree.tostring(e1)
        k0, k1 = c0.find("KeyFrames/KeyFrame"), c1.find("KeyFrames/KeyFrame")
        assert list(k0.attrib.keys()) == list(k1.attrib.keys())
        for key, v0 in k0.attrib.items():
            if key == "VICON_RADIAL2":  # same values, written in the shortest exact form
                assert v0.split()[0] == k1.get(key).split()[0] == "Vicon3Parameter"
                assert [float(v) for v in v0.split()[1:]] == [float(v) for v in k1.get(key).split()[1:]]
            else:  # FRAME, FOCAL_LENGTH, ORIENTATION, POSITION, ... byte for byte
                assert k1.get(key) == v0, key
    back = load_calibration(out)
    for c0, c1 in zip(cal.cameras, back.cameras):
        assert c0.intrinsics == c1.intrinsics
        np.testing.assert_allclose(c1.R, c0.R, rtol=0, atol=1e-12)
        scale = np.abs(c0.t).max()
        np.testing.assert_allclose(c1.t, c0.t, rtol=0, atol=1e-12 * scale)  # |t| ~ 7000 mm
        np.testing.assert_array_equal(c0.image_error, c1.image_error)
        np.testing.assert_array_equal(c0.world_error, c1.world_error)
    # writing what we read back gives the same bytes: the format is a fixed point
    assert xcp_bytes(back) == out.read_bytes()


def test_real_calibration_converts_to_radial2_and_back(real_xcp):
    cal = load_calibration(real_xcp)
    c = cal.cameras[0].intrinsics
    assert c.distortion_centre is not None and c.radial[2] != 0  # VICON_RADIAL2 in this file
    assert b"VICON_RADIAL2=\"Vicon3Parameter 2076.158482997856 2043.3487558785741 " in xcp_bytes(cal)


# --------------------------------------------------------------------------------------
# Moving cameras
# --------------------------------------------------------------------------------------


def _static_calibration(n_cams=2):
    cams = []
    for c in range(n_cams):
        intr = Intrinsics(1000.0 + c, (320.0, 240.0), (640, 480), radial=(1e-8, 0.0, 0.0))
        cams.append(CameraCalibration(f"cam_{c}", str(100 + c), str(c), intr, np.array([0]),
                                      np.eye(3)[None], np.array([[0.0, 0.0, 500.0 + c]])))
    return Calibration(cams)


def test_moving_cameras_are_run_length_encoded_and_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    F = 30
    R = np.empty((F, 2, 3, 3))
    t = np.empty((F, 2, 3))
    changes = {0: [0, 5, 6, 20], 1: [0, 29]}
    for c, starts in changes.items():
        bounds = starts + [F]
        for s, e in zip(bounds[:-1], bounds[1:]):
            R[s:e, c] = rodrigues(rng.normal(size=3))
            t[s:e, c] = rng.normal(size=3) * 1000
    cal = _static_calibration().with_poses(R, t)
    assert [list(c.frames) for c in cal.cameras] == [changes[0], changes[1]]
    path = tmp_path / "moving.xcp"
    save_calibration(path, cal)
    back = load_calibration(path)
    assert [list(c.frames) for c in back.cameras] == [changes[0], changes[1]]
    R2, t2 = back.poses(F)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12 * np.abs(t).max())


def test_frames_from_poses_nan_and_tolerance():
    F = 10
    R = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
    t = np.zeros((F, 3))
    t[:, 0] = np.arange(F) * 0.4  # slow drift: 0.4 mm per frame
    t[:2] = np.nan  # unsolved leading frames take the first solved pose
    t[5] = np.nan  # an unsolved frame keeps the previous pose
    frames, Rk, tk = frames_from_poses(R, t, atol=1.0)
    # compared with the current keyframe (not the previous frame), drift starts new keyframes:
    # keyframe at 0 (pose of frame 2: 0.8), 5 holds 1.6 ... frame 5 is NaN -> 1.6; frame 6 = 2.4 > 1.8
    np.testing.assert_array_equal(frames, [0, 6, 9])
    np.testing.assert_allclose(tk[:, 0], [0.8, 2.4, 3.6])
    frames, _, _ = frames_from_poses(R, t)  # exact: every change
    np.testing.assert_array_equal(frames, [0, 3, 4, 6, 7, 8, 9])
    with pytest.raises(ValueError, match="no frame"):
        frames_from_poses(R, np.full((F, 3), np.nan))


def test_frames_before_first_keyframe_use_the_first():
    cam = CameraCalibration("a", "", "", Intrinsics(1000.0, (0.0, 0.0)), np.array([10, 5]),
                            np.stack([np.eye(3), np.eye(3)]), np.array([[0, 0, 10.0], [0, 0, 5.0]]))
    np.testing.assert_array_equal(cam.frames, [5, 10])  # sorted
    _, t = Calibration([cam]).poses(12)
    np.testing.assert_array_equal(t[:, 0, 2], [5.0] * 10 + [10.0] * 2)


def test_camera_names_sort_numerically():
    names = ["cam_10", "cam_9", "Cam_1", "cam_2b", "cam_2a"]
    assert sorted(names, key=natural_sort_key) == ["Cam_1", "cam_2a", "cam_2b", "cam_9", "cam_10"]
    cal = _static_calibration(3)
    for c, n in zip(cal.cameras, ["cam_10", "cam_9", "cam_1"]):
        c.name = n
    assert cal.order_by_name() == [2, 1, 0]


# --------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------


def _four_cameras(orientation_of_camera_3):
    cams = []
    for i, name in enumerate(["A", "B", "C", "T160_17980"]):
        q = orientation_of_camera_3 if i == 3 else "0 0 0 1"
        cams.append(f'<Camera DEVICEID="{i}" NAME="{name}" PIXEL_ASPECT_RATIO="1" SENSOR_SIZE="10 10" SKEW="0">'
                    f'<KeyFrames><KeyFrame FRAME="0" FOCAL_LENGTH="100" ORIENTATION="{q}" POSITION="0 0 0" '
                    f'PRINCIPAL_POINT="5 5"/></KeyFrames></Camera>')
    return '<Cameras VERSION="1.0">' + "".join(cams) + "</Cameras>"


def test_error_message_names_file_camera_and_attribute():
    with pytest.raises(CalibrationError) as e:
        parse_xcp(_four_cameras("0.3 0.9"), source="/some/where/testCalibration.xcp")
    assert str(e.value) == ('testCalibration.xcp: camera 3 (T160_17980): ORIENTATION must have 4 numbers, '
                            'got "0.3 0.9"')
    assert isinstance(e.value, ValueError)


@pytest.mark.parametrize("text, message", [
    ("this is not xml", r"^bad\.xcp: not a valid XML file"),
    ("<calibration/>", r"^bad\.xcp: not an XCP file \(the root element is <calibration>"),
    ('<Cameras VERSION="1.0"></Cameras>', r"^bad\.xcp: the file has no <Camera> element"),
    (_four_cameras("0 0 0 0"), r"^bad\.xcp: camera 3 \(T160_17980\): ORIENTATION is a zero quaternion"),
    (_four_cameras("0 0 0 one"), r'^bad\.xcp: camera 3 \(T160_17980\): ORIENTATION must hold numbers, got "0 0 0 one"'),
    (_four_cameras("0 0 0 nan"), r"^bad\.xcp: camera 3 \(T160_17980\): ORIENTATION must be finite"),
    (_four_cameras("0 0 0 1").replace('FOCAL_LENGTH="100" ', "", 1),
     r"^bad\.xcp: camera 0 \(A\): FOCAL_LENGTH is missing"),
    (_four_cameras("0 0 0 1").replace('FOCAL_LENGTH="100"', 'FOCAL_LENGTH="-3"', 1),
     r"^bad\.xcp: camera 0 \(A\): FOCAL_LENGTH must be positive"),
    (_four_cameras("0 0 0 1").replace('PRINCIPAL_POINT="5 5"', 'PRINCIPAL_POINT="5"', 1),
     r'^bad\.xcp: camera 0 \(A\): PRINCIPAL_POINT must have 2 numbers, got "5"'),
    (_four_cameras("0 0 0 1").replace('PRINCIPAL_POINT="5 5"', 'PRINCIPAL_POINT="5 5" VICON_RADIAL2="Vicon5 1 2 3 4 5"', 1),
     r'^bad\.xcp: camera 0 \(A\): VICON_RADIAL2 must start with "Vicon3Parameter"'),
    (_four_cameras("0 0 0 1").replace('SENSOR_SIZE="10 10"', 'SENSOR_SIZE="10.5 10"', 1),
     r"^bad\.xcp: camera 0 \(A\): SENSOR_SIZE must be two non-negative integers"),
    (_four_cameras("0 0 0 1").replace("<KeyFrames>", "", 1).replace("</KeyFrames>", "", 1).replace(
        '<KeyFrame FRAME="0" FOCAL_LENGTH="100" ORIENTATION="0 0 0 1" POSITION="0 0 0" PRINCIPAL_POINT="5 5"/>', "", 1),
     r"^bad\.xcp: camera 0 \(A\): has no <KeyFrames> element"),
])
def test_malformed_files_raise_calibration_error(text, message):
    with pytest.raises(CalibrationError, match=message):
        parse_xcp(text, source="bad.xcp")


def test_duplicate_frames_and_keyframe_index_in_message():
    kf = '<KeyFrame FRAME="{f}" FOCAL_LENGTH="{fl}" ORIENTATION="0 0 0 1" POSITION="0 0 0" PRINCIPAL_POINT="5 5"/>'
    doc = ('<Cameras><Camera NAME="X"><KeyFrames>' + kf.format(f=0, fl=100) + kf.format(f=0, fl=100)
           + "</KeyFrames></Camera></Cameras>")
    with pytest.raises(CalibrationError, match=r"^d\.xcp: camera 0 \(X\): two KeyFrames have the same FRAME"):
        parse_xcp(doc, source="d.xcp")
    doc = ('<Cameras><Camera NAME="X"><KeyFrames>' + kf.format(f=0, fl=100) + kf.format(f=4, fl="x")
           + "</KeyFrames></Camera></Cameras>")
    with pytest.raises(CalibrationError, match=r"^d\.xcp: camera 0 \(X\), KeyFrame 1: FOCAL_LENGTH must hold numbers"):
        parse_xcp(doc, source="d.xcp")


def test_load_and_save_errors_name_the_file(tmp_path):
    with pytest.raises(CalibrationError, match=r"^missing\.xcp: cannot read the file"):
        load_calibration(tmp_path / "missing.xcp")
    odd = tmp_path / "notes.dat"
    odd.write_text("hello")
    with pytest.raises(CalibrationError, match=r"^notes\.dat: not a known calibration format"):
        load_calibration(odd)
    with pytest.raises(CalibrationError, match=r"^out\.qca: cannot save"):
        save_calibration(tmp_path / "out.qca", _static_calibration())


def test_content_sniffing_without_extension(tmp_path):
    p = tmp_path / "calib_noext"
    p.write_text(GUIDE_EXAMPLE)
    assert load_calibration(p).format == "xcp"


def test_save_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "cal.xcp"
    save_calibration(path, _static_calibration())
    before = path.read_bytes()
    assert load_calibration(path).names == ["cam_0", "cam_1"]
    with pytest.raises(CalibrationError):
        save_calibration(path, Calibration([]))  # nothing to write: the old file is untouched
    assert path.read_bytes() == before
    import carapost.io.calibration as calmod

    def boom(*a):
        raise OSError("disk full")
    monkeypatch.setattr(calmod.os, "replace", boom)
    with pytest.raises(OSError):
        save_calibration(path, _static_calibration(3))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.xcp"]  # no temporary left behind


# --------------------------------------------------------------------------------------
# The camera model on every real calibration
# --------------------------------------------------------------------------------------


def _real_calibrations(real_data):
    files = sorted(real_data.rglob("*.xcp")) + sorted(real_data.rglob("*.qca")) + sorted(real_data.rglob("*.qca.txt"))
    if not files:
        pytest.skip("no real calibration files")
    return files


def test_project_backproject_round_trip_on_every_real_calibration(real_data):
    n_cams = 0
    for path in _real_calibrations(real_data):
        cal = load_calibration(path)
        for cam in cal.cameras:
            intr = cam.intrinsics
            w, h = intr.sensor_size
            gx, gy = np.meshgrid(np.linspace(0, w - 1, 41), np.linspace(0, h - 1, 41))
            px = np.stack([gx.ravel(), gy.ravel()], axis=1)
            r = np.hypot(px[:, 0] - intr.centre[0], intr.aspect * (px[:, 1] - intr.centre[1]))
            valid = r < 0.99 * monotonic_radius(intr.radial)  # beyond it the XCP polynomial folds
            # the model is valid over (nearly) the whole sensor of every real camera
            assert valid.mean() > 0.97, (path.name, cam.label, valid.mean())
            px = px[valid]
            o, d = backproject(px, intr, cam.R[0], cam.t[0])
            X = o + 3000.0 * d  # 3 m along each ray
            back = project(X, intr, cam.R[0], cam.t[0])
            err = np.abs(back - px).max()
            assert err < 1e-6, (path.name, cam.label, err)
            n_cams += 1
    assert n_cams >= 29  # 25 Vicon cameras + 4 Qualisys
