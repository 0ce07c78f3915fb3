"""Exports (CSV, TRC, BVH, BVA, XCP [Current Frame], C3D through the dispatcher) and C3D import
as a take: round trips, hand-computed values, the real TRC / BVH / C3D files."""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np
import pytest
from lxml import etree

from carapost.core.camera import Intrinsics, camera_centre, project, quat_to_matrix
from carapost.io.bva import bva_text
from carapost.io.c3d import export_c3d, read_c3d
from carapost.io.c3d_take import take_from_c3d
from carapost.io.calibration import load_calibration
from carapost.io.csv_export import csv_2d_text, read_csv_3d
from carapost.io.export import (
    EXPORT_FORMATS,
    ExportError,
    axis_matrix,
    export_file,
    export_take,
    hold_gaps,
    prepare_export,
    to_export_space,
)
from carapost.io.trc import TRCError, read_trc
from carapost.model.params import ExportParameters
from carapost.model.take import CameraInfo, ObsSource, PointKind, Recon, Take

FPS = 60.0
FIRST = 100  # take.first_frame_number


# ------------------------------------------------------------------------------ test take
def make_take(n_frames: int = 30, *, moving: bool = True, seed: int = 0) -> Take:
    """4 cameras (camera 1 moves), 4 face points (one unlabelled, a repeated label), 2 brim
    points (one never reconstructed), gaps at the start, middle and end, 2D observations of
    every source, stabilized positions."""
    rng = np.random.default_rng(seed)
    cams = [CameraInfo(f"cam{i}", i, Intrinsics(1000.0 + 10 * i, (640.0, 360.0), sensor_size=(1280, 720),
                                                radial=(1e-8 * i, 0.0, 0.0)),
                       image_size=(1280, 720), device_id=str(17980 + i)) for i in range(4)]
    F = n_frames
    R0 = quat_to_matrix(rng.normal(size=(4, 4)))
    t0 = rng.normal(0.0, 50.0, (4, 3)) + np.array([0.0, 0.0, 400.0])
    R = np.broadcast_to(R0, (F, 4, 3, 3)).copy()
    t = np.broadcast_to(t0, (F, 4, 3)).copy()
    if moving:
        t[:, 1] += np.linspace(0.0, 5.0, F)[:, None]
    take = Take.new(cams, F, FPS, R=R, t=t, name="Test Take")
    take.add_points(4, labels=["Nose_Tip", "Chin", "", "Nose_Tip"])
    take.add_points(2, kind=PointKind.BRIM, brim_index=np.array([0, 3]))
    P = take.n_points
    take.xyz = rng.normal(0.0, 80.0, (F, P, 3))
    take.xyz[5:9, 1] = np.nan     # a gap in the middle
    take.xyz[0:3, 2] = np.nan     # at the start
    take.xyz[-1, 0] = np.nan      # at the end
    take.xyz[:, 5] = np.nan       # never reconstructed
    valid = np.isfinite(take.xyz[..., 0])
    take.recon[:] = np.where(valid, Recon.MULTI_VIEW, Recon.NONE)
    take.recon[10, 0] = Recon.INTERPOLATED
    take.xyz_stabilized = take.xyz + np.array([1.0, 2.0, 3.0])
    for c in range(4):
        xy = project(take.xyz, cams[c].intrinsics, R[:, c][:, None], t[:, c][:, None])
        take.obs_xy[:, :, c] = xy.astype(np.float32)
    take.obs_xy[:, :, 3] = np.nan          # camera 3 sees nothing
    take.obs_xy[12:14, 0, 0] = np.nan
    take.obs_src[:] = np.where(np.isfinite(take.obs_xy[..., 0]), ObsSource.BLOB, ObsSource.NONE)
    take.obs_src[:, 2, 1] = np.where(np.isfinite(take.obs_xy[:, 2, 1, 0]), ObsSource.TARGET, ObsSource.NONE)
    take.obs_q[:, 2, 1] = np.where(take.obs_src[:, 2, 1] == ObsSource.TARGET, 0.875, np.nan)
    take.first_frame_number = FIRST
    take.current_frame = 7
    return take


@pytest.fixture
def take() -> Take:
    return make_take()


# --------------------------------------------------------------------------- preparation
def test_axis_conversion_is_a_right_handed_rotation():
    Q = axis_matrix("Z")
    assert np.allclose(Q @ Q.T, np.eye(3)) and np.isclose(np.linalg.det(Q), 1.0)
    assert np.allclose(to_export_space(np.array([1.0, 2.0, 3.0]), up_axis="Z"), [1.0, -3.0, 2.0])
    assert np.allclose(to_export_space(np.array([1.0, 2.0, 3.0]), up_axis="Z", units="cm"), [0.1, -0.3, 0.2])
    assert np.allclose(to_export_space(np.array([[25.4, 0, 0]]), units="in"), [[1.0, 0, 0]])
    with pytest.raises(ValueError, match="up axis"):
        axis_matrix("X")


def test_prepare_export_follows_the_export_section(take):
    d = prepare_export(take)
    assert d.names == ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2", "Brim_4", "Brim_5"]
    assert np.array_equal(d.frame_numbers, FIRST + np.arange(30))
    assert np.allclose(d.times, (FIRST + np.arange(30)) / FPS)
    assert np.array_equal(d.valid, np.isfinite(take.xyz[..., 0]))
    assert np.allclose(d.xyz[d.valid], take.xyz[d.valid])
    opts = ExportParameters(units="cm", up_axis="Z", use_stabilized=True, include_brim=False)
    d = prepare_export(take, options=opts, frames=(3, 9))
    assert d.names == ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2"]
    expect = (take.xyz_stabilized[3:10, :4] @ axis_matrix("Z").T) / 10.0
    assert np.allclose(d.xyz, expect, equal_nan=True)
    sel = ExportParameters(selected_only=True)
    assert prepare_export(take, options=sel, selection=[4, 1]).names == ["Chin", "Brim_4"]
    with pytest.raises(ValueError, match="no points are selected"):
        prepare_export(take, options=sel)
    with pytest.raises(ValueError, match="outside"):
        prepare_export(take, frames=(5, 30))
    with pytest.raises(ValueError, match="repeat"):
        prepare_export(take, points=[1, 1])
    raw = make_take()
    raw.xyz_stabilized[:] = np.nan
    with pytest.raises(ValueError, match="not been stabilized"):
        prepare_export(raw, options=ExportParameters(use_stabilized=True))


def test_hold_gaps_by_hand():
    xyz = np.full((5, 3, 3), np.nan)
    xyz[1, 0] = 1.0
    xyz[3, 0] = 3.0
    xyz[:, 1] = np.arange(5.0)[:, None]
    valid = np.isfinite(xyz[..., 0])
    out = hold_gaps(xyz, valid)
    assert np.array_equal(out[:, 0, 0], [1.0, 1.0, 1.0, 3.0, 3.0])   # leading gap takes the first
    assert np.array_equal(out[:, 1, 0], np.arange(5.0))
    assert np.array_equal(out[:, 2], np.zeros((5, 3)))                 # never seen: origin
    assert np.isnan(xyz[0, 0, 0])                                       # input untouched


# ---------------------------------------------------------------------------------- CSV
def test_csv_3d_round_trip_and_independent_parse(take, tmp_path):
    path = tmp_path / "t.csv"
    export_take(take, path, options=ExportParameters(units="cm"))
    back = read_csv_3d(path)
    assert back.names == ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2", "Brim_4", "Brim_5"]
    assert np.array_equal(back.frames, FIRST + np.arange(30))
    assert np.allclose(back.times, back.frames / FPS, atol=1e-6)
    assert np.allclose(back.xyz, take.xyz / 10.0, atol=1e-7, equal_nan=True)
    rows = list(csv.reader(io.StringIO(path.read_text())))
    assert rows[0][:5] == ["frame", "time", "Nose_Tip:X", "Nose_Tip:Y", "Nose_Tip:Z"]
    assert len(rows) == 31 and all(len(r) == 2 + 18 for r in rows)
    assert rows[1 + 5][5:8] == ["", "", ""]                  # Chin's gap: empty cells
    assert float(rows[1][2]) == pytest.approx(take.xyz[0, 0, 0] / 10.0, abs=1e-7)


def test_csv_2d_tracks(take):
    text = csv_2d_text(take)
    rows = list(csv.DictReader(io.StringIO(text)))
    ok = np.isfinite(take.obs_xy[..., 0])
    assert len(rows) == ok.sum()
    cams = [int(r["camera"]) for r in rows]
    assert cams == sorted(cams) and 3 not in cams           # grouped by camera; camera 3 saw nothing
    r0 = rows[0]
    assert (r0["frame"], r0["point"], r0["camera"], r0["source"]) == (str(FIRST), "Nose_Tip", "0", "BLOB")
    assert float(r0["x"]) == pytest.approx(take.obs_xy[0, 0, 0, 0], abs=1e-4)
    assert float(r0["y"]) == pytest.approx(take.obs_xy[0, 0, 0, 1], abs=1e-4)
    tgt = [r for r in rows if r["source"] == "TARGET"]
    assert tgt and all(r["point"] == "Point_2" and r["camera"] == "1" and r["quality"] == "0.8750" for r in tgt)
    assert all(r["quality"] == "" for r in rows if r["source"] == "BLOB")
    only = list(csv.DictReader(io.StringIO(csv_2d_text(take, cameras=[1], points=[0]))))
    assert len(only) == ok[:, 0, 1].sum() and {r["point"] for r in only} == {"Nose_Tip"}


# ---------------------------------------------------------------------------------- TRC
def test_trc_round_trip(take, tmp_path):
    path = tmp_path / "t.trc"
    export_take(take, path, options=ExportParameters(up_axis="Z"))
    d = read_trc(path)
    assert d.labels == ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2", "Brim_4", "Brim_5"]
    assert (d.data_rate, d.units, d.declared_frames, d.declared_markers) == (60.0, "mm", 30, 6)
    assert d.orig_start_frame == FIRST + 1 and not d.truncated
    assert np.array_equal(d.frame_numbers, FIRST + 1 + np.arange(30))
    assert np.allclose(d.times, (FIRST + np.arange(30)) / FPS, atol=1e-6)
    assert np.allclose(d.xyz, take.xyz @ axis_matrix("Z").T, atol=1e-6, equal_nan=True)
    lines = path.read_text().splitlines()
    assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
    assert lines[3].split("\t")[2::3][:6] == d.labels
    assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"] and lines[5] == ""
    assert lines[6 + 5].split("\t")[5:8] == ["", "", ""]      # Chin's gap: blank fields
    export_take(take, path, units="m", missing="NaN")
    d = read_trc(path)
    assert d.units == "m" and np.allclose(d.xyz, take.xyz, atol=1e-6, equal_nan=True)
    assert "NaN" in path.read_text()


def test_real_trc_files_parse(real_data):
    walk = read_trc(real_data / "opensim-core" / "subject01_walk1.trc")
    assert (walk.n_frames, walk.n_points, walk.data_rate) == (151, 41, 60.0)
    assert "Top.Head" in walk.labels and np.isfinite(walk.xyz).all()
    assert walk.xyz[0, 0] == pytest.approx([617.247620, 1055.275020, 170.781980])
    assert walk.times[1] == pytest.approx(0.017)
    blanks = read_trc(real_data / "opensim-core" / "dataWithBlanksForMissingMarkers.trc")
    assert (blanks.n_frames, blanks.n_points, blanks.data_rate) == (464, 40, 250.0)
    gap = ~np.isfinite(blanks.xyz[..., 0])
    assert gap[0].all() and 0.05 < gap.mean() < 0.95        # heavy gaps, first rows empty
    nans = read_trc(real_data / "opensim-core" / "dataWithNaNsOfDifferentCases.trc")
    assert (nans.n_frames, nans.n_points) == (5, 14)
    missing = ~np.isfinite(nans.xyz[..., 0])
    assert missing[:, 8].all() and missing.sum() == 5          # "thigh": NaN, NAN, Nan, naN, nan
    assert nans.xyz[0, 7] == pytest.approx([169.582650, 61.839033, 231.459215])
    comma = read_trc(real_data / "pyomeca" / "markers.trc")
    assert comma.n_points == 51 and comma.declared_frames == 652 and comma.truncated
    assert 0 < comma.n_frames < 652 and comma.xyz[0, 0] == pytest.approx([733.7041, 80.9832, 191.8668])
    p2s = read_trc(next((real_data / "pose2sim-demo" / "pose-3d").glob("*.trc")))
    assert (p2s.n_frames, p2s.n_points, p2s.units) == (100, 21, "m")
    assert p2s.xyz[0, 0, 0] == pytest.approx(-0.06497214796810755 * 1000.0)


def test_trc_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.trc"
    bad.write_text("hello\n")
    with pytest.raises(TRCError, match="bad.trc: not a TRC file"):
        read_trc(bad)
    bad.write_text("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tNumMarkers\n60\t1\nFrame#\tTime\tA\n\t\tX1\tY1\tZ1\n\n"
                   "1\t0\t1\tzz\t3\n")
    with pytest.raises(TRCError, match=r"bad.trc: line 7: 'zz' is not a number"):
        read_trc(bad)
    with pytest.raises(TRCError, match="cannot read"):
        read_trc(tmp_path / "missing.trc")


# ---------------------------------------------------------------------------------- BVH
def parse_bvh(text: str) -> dict:
    """A small BVH parser (enough for the real files and ours): joints with their channels,
    frame count, frame time and the motion table."""
    tokens = text.split("\n")
    i = 0
    joints: list[tuple[str, list[str]]] = []
    depth = 0
    assert tokens[0].strip() == "HIERARCHY"
    i = 1
    while tokens[i].strip() != "MOTION":
        words = tokens[i].split()
        if words and words[0] in ("ROOT", "JOINT"):
            assert words[0] == "JOINT" or depth == 0, "ROOT inside a hierarchy"
            joints.append((" ".join(words[1:]), []))
        elif words and words[0] == "CHANNELS":
            assert int(words[1]) == len(words) - 2
            joints[-1][1].extend(words[2:])
        elif words and words[0] == "OFFSET":
            assert len(words) == 4 and all(np.isfinite(float(w)) for w in words[1:])
        elif words == ["{"]:
            depth += 1
        elif words == ["}"]:
            depth -= 1
        elif words:
            assert words in (["End", "Site"],), words
        i += 1
    assert depth == 0
    n_frames = int(tokens[i + 1].split(":")[1])
    frame_time = float(tokens[i + 2].split(":")[1])
    rows = [r.split() for r in tokens[i + 3:] if r.strip()]
    motion = np.array(rows, dtype=float)
    return {"joints": joints, "frames": n_frames, "frame_time": frame_time, "motion": motion}


def test_bvh_syntax_matches_the_real_files(take, real_data, tmp_path):
    for f in sorted((real_data / "bvh").glob("*.bvh")):
        b = parse_bvh(f.read_text())
        n_channels = sum(len(c) for _, c in b["joints"])
        assert b["motion"].shape == (b["frames"], n_channels), f.name
    path = tmp_path / "t.bvh"
    export_take(take, path, options=ExportParameters(units="cm"))
    b = parse_bvh(path.read_text())
    assert [j for j, _ in b["joints"]] == ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2", "Brim_4", "Brim_5"]
    assert all(c == ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]
               for _, c in b["joints"])
    assert b["frames"] == 30 and b["frame_time"] == pytest.approx(1 / 60, abs=1e-10)
    m = b["motion"].reshape(30, 6, 6)
    expect = hold_gaps(take.xyz / 10.0, np.isfinite(take.xyz[..., 0]))
    assert np.allclose(m[..., :3], expect, atol=1e-7) and not m[..., 3:].any()
    assert np.allclose(m[5:9, 1, :3], take.xyz[4, 1] / 10.0, atol=1e-7)    # the gap holds the last value


# ---------------------------------------------------------------------------------- BVA
def parse_bva(text: str) -> dict[str, dict]:
    out = {}
    blocks = re.split(r"(?m)^(?=Segment: )", text)
    for blk in filter(None, blocks):
        lines = blk.rstrip("\n").split("\n")
        name = lines[0].split(": ", 1)[1]
        n = int(lines[1].split(": ")[1])
        ft = float(lines[2].split(": ")[1])
        assert lines[3].split("\t") == ["XTRAN", "YTRAN", "ZTRAN", "XROT", "YROT", "ZROT", "XSCALE", "YSCALE",
                                        "ZSCALE"]
        units = lines[4].split("\t")
        rows = np.array([r.split("\t") for r in lines[5:]], dtype=float)
        assert rows.shape == (n, 9)
        out[name] = {"frame_time": ft, "units": units, "rows": rows}
    return out


def test_bva_matches_seed_003_layout(take, tmp_path):
    path = tmp_path / "t.bva"
    export_take(take, path)
    segs = parse_bva(path.read_text())
    assert list(segs) == ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2", "Brim_4", "Brim_5"]
    s = segs["Nose_Tip"]
    assert s["frame_time"] == pytest.approx(1 / 60, abs=1e-6)
    assert s["units"] == ["INCHES"] * 3 + ["DEGREES"] * 3 + ["INCHES"] * 3
    expect = hold_gaps(take.xyz, np.isfinite(take.xyz[..., 0])) / 25.4
    assert np.allclose(s["rows"][:, :3], expect[:, 0], atol=1e-6)
    assert np.array_equal(s["rows"][:, 3:], np.tile([0, 0, 0, 1, 1, 1], (30, 1)))
    mm = parse_bva(bva_text(take, units="mm", options=ExportParameters(up_axis="Z")))
    assert mm["Chin"]["units"][0] == "MILLIMETERS"
    assert np.allclose(mm["Chin"]["rows"][0, :3], take.xyz[0, 1] @ axis_matrix("Z").T, atol=1e-4)


def test_bva_2d_flips_image_y(take):
    segs = parse_bva(bva_text(take, camera=0, points=[0, 2]))
    xy = take.obs_xy[:, 0, 0].astype(float)
    rows = segs["Nose_Tip"]["rows"]
    assert segs["Nose_Tip"]["units"][:3] == ["PIXELS"] * 3
    assert np.allclose(rows[0, :3], [xy[0, 0], 720.0 - xy[0, 1], 0.0], atol=1e-4)
    assert np.allclose(rows[12:14, :2], [xy[11, 0], 720.0 - xy[11, 1]], atol=1e-4)   # gap holds
    with pytest.raises(ValueError, match="camera must be"):
        bva_text(take, camera=9)


# ---------------------------------------------------------------------------------- XCP
GUIDE_CAMERA_ATTRS = {"DEVICEID", "NAME", "PIXEL_ASPECT_RATIO", "SENSOR_SIZE", "SKEW"}
GUIDE_KEYFRAME_ATTRS = {"FRAME", "FOCAL_LENGTH", "IMAGE_ERROR", "ORIENTATION", "POSITION", "PRINCIPAL_POINT",
                        "VICON_RADIAL"}


def test_xcp_current_frame(take, tmp_path):
    path = tmp_path / "current.xcp"
    export_take(take, path)                           # the current frame: 7
    calib = load_calibration(path)
    assert calib.names == ["cam0", "cam1", "cam2", "cam3"]
    f = take.current_frame
    for c, cam in enumerate(calib.cameras):
        assert cam.n_keyframes == 1 and cam.frames[0] == 0
        assert cam.device_id == take.cameras[c].device_id
        assert cam.intrinsics == take.cameras[c].intrinsics
        assert np.allclose(cam.R[0], take.R[f, c], atol=1e-12) and np.allclose(cam.t[0], take.t[f, c], atol=1e-9)
    # IMAGE_ERROR: mean reprojection error of what the camera sees in that frame (0: exact projections)
    assert calib.cameras[0].image_error[0] == pytest.approx(0.0, abs=1e-3)
    assert np.isnan(calib.cameras[3].image_error[0])  # camera 3 observes nothing
    # The layout of the guide's example: <Cameras><Camera ...><KeyFrames><KeyFrame .../>
    root = etree.fromstring(path.read_bytes())
    assert root.tag == "Cameras" and root.get("VERSION") == "1.0"
    cam_el = root.findall("Camera")
    assert len(cam_el) == 4 and GUIDE_CAMERA_ATTRS <= set(cam_el[0].attrib)
    kf = cam_el[0].find("KeyFrames").findall("KeyFrame")
    assert len(kf) == 1 and set(kf[0].attrib) == GUIDE_KEYFRAME_ATTRS
    assert np.allclose([float(v) for v in kf[0].get("POSITION").split()], camera_centre(take.R[f, 0], take.t[f, 0]))
    export_take(take, path, frame=20)
    assert np.allclose(load_calibration(path).cameras[1].t[0], take.t[20, 1], atol=1e-9)


def test_xcp_moving_cameras_one_keyframe_per_frame(take, tmp_path):
    path = tmp_path / "all.xcp"
    export_take(take, path, all_frames=True)
    calib = load_calibration(path)
    assert calib.cameras[1].n_keyframes == take.n_frames          # it moves every frame
    assert np.array_equal(calib.cameras[1].frames, np.arange(take.n_frames))
    assert calib.cameras[0].n_keyframes == 1                      # static cameras need one
    R, t = calib.poses(take.n_frames)
    assert np.allclose(R, take.R, atol=1e-12) and np.allclose(t, take.t, atol=1e-9)


def test_xcp_refuses_unsolved_poses(take, tmp_path):
    take.R[7, 2] = np.nan
    with pytest.raises(ExportError, match=r"x.xcp: camera 2 \(cam2\) has no solved pose at frame 7"):
        export_take(take, tmp_path / "x.xcp")
    take.R[:, 2] = np.nan
    with pytest.raises(ExportError, match=r"camera 2 \(cam2\) has no solved pose in any frame"):
        export_take(take, tmp_path / "x.xcp", all_frames=True)


# ---------------------------------------------------------------------------- dispatcher
def test_every_format_is_written_atomically(take, tmp_path):
    for ext in EXPORT_FORMATS:
        export_take(take, tmp_path / f"out{ext.upper()}")
        assert (tmp_path / f"out{ext.upper()}").stat().st_size > 0
    export_take(take, tmp_path / "tracks.csv", kind="2d")
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []   # no temp files left


def test_dispatcher_errors_name_the_file(take, tmp_path):
    with pytest.raises(ExportError, match=r"out.obj: cannot export to '.obj'"):
        export_take(take, tmp_path / "out.obj")
    with pytest.raises(ExportError, match="does not exist"):
        export_take(take, tmp_path / "nowhere" / "out.fbx")
    with pytest.raises(ExportError, match=r"out.trc: option\(s\) camera do not apply to .trc"):
        export_take(take, tmp_path / "out.trc", camera=0)
    with pytest.raises(ExportError, match=r"out.csv: .*Selected Points Only"):
        export_take(take, tmp_path / "out.csv", options=ExportParameters(selected_only=True))
    with pytest.raises(ExportError, match=r"out.csv: CSV kind"):
        export_take(take, tmp_path / "out.csv", kind="4d")
    assert not any(tmp_path.iterdir())
    (tmp_path / "dir.trc").mkdir()
    with pytest.raises(ExportError, match=r"dir.trc: cannot write the file"):
        export_take(take, tmp_path / "dir.trc")
    assert [p.name for p in tmp_path.iterdir()] == ["dir.trc"]            # no temporary file left


def test_c3d_export_honours_the_options(take, tmp_path):
    path = tmp_path / "t.c3d"
    opts = ExportParameters(up_axis="Z", include_brim=False, use_stabilized=True)
    export_take(take, path, options=opts)
    d = read_c3d(path)
    assert d.labels == ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2"]
    assert np.allclose(d.xyz, take.xyz_stabilized[:, :4] @ axis_matrix("Z").T, atol=1e-3, equal_nan=True)
    assert d.first_frame == FIRST + 1


# ---------------------------------------------------------------------------- C3D import
def test_our_c3d_opens_as_the_same_take(take, tmp_path):
    path = tmp_path / "ours.c3d"
    export_c3d(take, path)
    back = take_from_c3d(path)
    assert back.n_cameras == 0
    assert back.metadata["no_video"] == "1"
    assert (back.n_frames, back.frame_rate, back.first_frame_number) == (30, pytest.approx(FPS), FIRST)
    # generated names come back unlabelled; C3D labels are unique, so the repeated label is suffixed
    assert back.points.labels == ["Nose_Tip", "Chin", "", "Nose_Tip_2", "", ""]
    assert np.array_equal(back.points.ids, take.points.ids)
    assert np.array_equal(back.points.kind, take.points.kind)
    assert np.array_equal(back.points.brim_index, take.points.brim_index)
    assert np.allclose(back.xyz, take.xyz, atol=1e-3, equal_nan=True)
    assert np.array_equal(back.recon, take.recon)                       # incl. the interpolated sample
    assert back.next_point_id == take.points.ids.max() + 1
    back.check()


def test_foreign_c3d_opens_as_a_take(real_data, tmp_path):
    src = real_data / "ezc3d" / "Vicon.c3d"
    d = read_c3d(src)
    markers = d.marker_indices()
    take = take_from_c3d(src)
    assert take.n_points == len(markers) and take.n_frames == d.n_frames
    assert take.points.labels == [d.labels[i] for i in markers]
    assert np.all(take.points.kind == PointKind.FACE)
    assert take.frame_rate == d.frame_rate and take.first_frame_number == d.first_frame - 1
    assert np.allclose(take.xyz, d.xyz[:, markers], equal_nan=True)
    valid = np.isfinite(take.xyz[..., 0])
    assert np.array_equal(take.recon == Recon.MULTI_VIEW, valid) and np.all(take.recon[~valid] == Recon.NONE)
    # carapost export DATA.c3d OUT.EXT: the C3D frame numbers survive a round trip
    out = tmp_path / "again.c3d"
    export_file(src, out)
    again = read_c3d(out)
    assert again.first_frame == d.first_frame and again.labels == take.points.labels
    assert np.allclose(again.xyz, take.xyz, atol=1e-3, equal_nan=True)
    export_file(src, tmp_path / "vicon.trc")
    assert read_trc(tmp_path / "vicon.trc").n_points == len(markers)


def test_c3d_import_errors(tmp_path):
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"\x00" * 600)
    with pytest.raises(ValueError, match="bad.c3d"):
        take_from_c3d(bad)
    with pytest.raises(ExportError, match=r"x.txt: cannot export from"):
        export_file(tmp_path / "x.txt", tmp_path / "y.fbx")


def test_paths_are_pathlike_or_str(take, tmp_path):
    export_take(take, str(tmp_path / "s.trc"))
    assert Path(tmp_path / "s.trc").exists()
