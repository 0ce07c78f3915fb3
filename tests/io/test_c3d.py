"""C3D export / import: round trips checked by ezc3d and py-c3d, and real third-party files."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from carapost.core.camera import Intrinsics
from carapost.io import c3d as c3d_module
from carapost.io import c3d_binary as cb
from carapost.io.c3d import RESIDUAL_SCALE, C3DError, export_c3d, info_c3d, read_c3d
from carapost.model.take import CameraInfo, PointKind, Recon, Take

ezc3d = pytest.importorskip("ezc3d")
pyc3d = pytest.importorskip("c3d")


# ----------------------------------------------------------------------------- synthetic take
def make_take(n_frames: int = 40, n_cameras: int = 4, seed: int = 0) -> Take:
    """5 face points (two share a label, two unlabelled) and 3 brim points, with gaps and every
    reconstruction type."""
    rng = np.random.default_rng(seed)
    cams = [CameraInfo(f"cam{i}", i, Intrinsics(1200.0, (640.0, 400.0))) for i in range(n_cameras)]
    take = Take.new(cams, n_frames, 59.94, name="synthetic take")
    take.add_points(5, labels=["Nose_Tip", "Chin_Center", "", "Nose_Tip", ""])
    take.add_points(3, kind=PointKind.BRIM, brim_index=np.array([0, 4, 11]))
    F, P = take.n_frames, take.n_points
    take.xyz = rng.normal(0.0, 120.0, (F, P, 3)) + np.array([0.0, 0.0, 600.0])
    take.recon[:] = Recon.MULTI_VIEW
    take.obs_xy[:, :, 0] = 1.0  # cameras 0 and 2 see everything by default
    take.obs_xy[:, :, 2] = 1.0
    # gaps
    take.xyz[5:9, 1] = np.nan
    take.recon[5:9, 1] = Recon.NONE
    take.xyz[0, 6] = np.nan
    take.recon[0, 6] = Recon.NONE
    take.xyz[-1, :] = np.nan
    take.recon[-1, :] = Recon.NONE
    # interpolated and single-sensor samples
    take.recon[10:14, 2] = Recon.INTERPOLATED
    take.obs_xy[10:14, 2] = np.nan
    take.recon[20:23, 3] = Recon.SINGLE_SENSOR
    take.obs_xy[20:23, 3] = np.nan
    take.obs_xy[20:23, 3, 1] = 2.0
    take.first_frame_number = 100
    return take


EXPECTED_LABELS = ["Nose_Tip", "Chin_Center", "Point_2", "Nose_Tip_2", "Point_4",
                   "Brim_5", "Brim_6", "Brim_7"]


def expected_fourth(take: Take) -> tuple[np.ndarray, np.ndarray]:
    """Residual (mm, -1 for gaps) and camera byte that the writer must produce."""
    valid = np.isfinite(take.xyz).all(-1)
    code = np.select([take.recon == Recon.SINGLE_SENSOR, take.recon == Recon.MULTI_VIEW], [1, 2], 0)
    seen = np.isfinite(take.obs_xy[..., :7, 0])
    mask = (seen.astype(int) << np.arange(seen.shape[-1])).sum(-1) * (code > 0)
    return np.where(valid, code * abs(RESIDUAL_SCALE), -1.0), np.where(valid, mask, 0)


def py_c3d_frames(path: Path) -> tuple[object, np.ndarray]:
    """py-c3d reader and its (F, P, 5) frames; any warning other than 'no analog data' fails."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message="No analog data found")
        with open(path, "rb") as fh:
            reader = pyc3d.Reader(fh)
            frames = np.stack([p.copy() for _, p, _ in reader.read_frames()])
    return reader, frames


@pytest.fixture
def take() -> Take:
    return make_take()


def test_round_trip_read_c3d(tmp_path: Path, take: Take) -> None:
    path = tmp_path / "take.c3d"
    export_c3d(take, path)
    d = read_c3d(path)
    assert d.backend == "carapost"
    assert d.labels == EXPECTED_LABELS
    assert d.xyz.shape == take.xyz.shape
    gaps = ~np.isfinite(take.xyz).all(-1)
    np.testing.assert_array_equal(np.isnan(d.xyz).any(-1), gaps)
    np.testing.assert_array_equal(np.isnan(d.xyz).all(-1), gaps)
    np.testing.assert_array_equal(d.xyz[~gaps], take.xyz.astype(np.float32)[~gaps])  # float32 exactly
    np.testing.assert_array_equal(d.recon, take.recon)
    np.testing.assert_array_equal(d.point_ids, take.points.ids)
    np.testing.assert_array_equal(d.kind, take.points.kind)
    np.testing.assert_array_equal(d.brim_index, take.points.brim_index)
    res, mask = expected_fourth(take)
    np.testing.assert_allclose(d.residual[~gaps], res[~gaps], atol=1e-6)
    np.testing.assert_array_equal(d.camera_mask, mask)
    assert d.frame_rate == np.float32(59.94)
    assert d.first_frame == 101 and d.first_frame_number == 100
    assert d.units == "mm" and d.scale_to_mm == 1.0
    assert d.stabilized is False
    assert d.descriptions[0] == "CaraPost face point, id 0"
    assert d.descriptions[7] == "CaraPost brim point, id 7, brim dot 11"
    assert d.gap_fraction() == pytest.approx(gaps.mean())


def test_round_trip_ezc3d(tmp_path: Path, take: Take) -> None:
    path = tmp_path / "take.c3d"
    export_c3d(take, path)
    c = ezc3d.c3d(str(path))
    pts = c["data"]["points"]  # (4, P, F)
    xyz = pts[:3].transpose(2, 1, 0)
    gaps = ~np.isfinite(take.xyz).all(-1)
    np.testing.assert_array_equal(np.isnan(xyz).any(-1), gaps)
    np.testing.assert_array_equal(xyz[~gaps], take.xyz.astype(np.float32)[~gaps])
    assert c["parameters"]["POINT"]["LABELS"]["value"] == EXPECTED_LABELS
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(59.94, abs=1e-5)
    assert c["header"]["points"]["first_frame"] == 100  # ezc3d counts from 0
    assert c["header"]["points"]["last_frame"] == 100 + take.n_frames - 1
    assert c["parameters"]["CARAPOST"]["KIND"]["value"].tolist() == [0] * 5 + [1] * 3
    assert list(c["parameters"]["CARAPOST"]["RECON_NAMES"]["value"]) == [
        "NONE", "INTERPOLATED", "SINGLE_SENSOR", "MULTI_VIEW"]


def test_round_trip_py_c3d(tmp_path: Path, take: Take) -> None:
    path = tmp_path / "take.c3d"
    export_c3d(take, path)
    reader, frames = py_c3d_frames(path)  # also: no header/parameter inconsistency warnings
    assert [s.strip() for s in reader.point_labels] == EXPECTED_LABELS
    assert reader.first_frame == 101 and reader.last_frame == 100 + take.n_frames
    assert reader.point_rate == pytest.approx(59.94, abs=1e-5)
    assert reader.get("POINT:UNITS").string_value.strip() == "mm"
    assert frames.shape == (take.n_frames, take.n_points, 5)
    gaps = ~np.isfinite(take.xyz).all(-1)
    res, mask = expected_fourth(take)
    np.testing.assert_array_equal(frames[..., 3] < 0, gaps)  # residual -1 marks gaps
    np.testing.assert_array_equal(frames[~gaps][:, :3], take.xyz.astype(np.float32)[~gaps])
    np.testing.assert_array_equal(frames[gaps][:, :3], 0.0)  # the spec's zero coordinates
    np.testing.assert_allclose(frames[..., 3][~gaps], res[~gaps], atol=1e-6)
    np.testing.assert_array_equal(frames[..., 4][~gaps], mask[~gaps])
    np.testing.assert_allclose(np.unique(frames[..., 3][~gaps]), [0.0, 0.01, 0.02], atol=1e-6)


def test_export_selection_range_stabilized(tmp_path: Path, take: Take) -> None:
    take.xyz_stabilized = take.xyz[..., ::-1] * 0.5
    path = tmp_path / "sel.c3d"
    export_c3d(take, path, points=[6, 0, 3], frames=(4, 21), stabilized=True)
    d = read_c3d(path)
    want = take.xyz_stabilized[4:22][:, [6, 0, 3]]
    assert d.xyz.shape == (18, 3, 3)
    np.testing.assert_array_equal(np.isnan(d.xyz), np.isnan(want))
    np.testing.assert_allclose(d.xyz, want.astype(np.float32), equal_nan=True, rtol=0, atol=0)
    assert d.labels == ["Brim_6", "Nose_Tip", "Nose_Tip_2"]
    np.testing.assert_array_equal(d.recon, take.recon[4:22][:, [6, 0, 3]])
    assert d.first_frame == 100 + 4 + 1 and d.first_frame_number == 104
    assert d.stabilized is True
    np.testing.assert_array_equal(d.point_ids, [6, 0, 3])


def test_many_points_and_frames(tmp_path: Path) -> None:
    """More than 255 points (LABELS2...) and more than 65535 frames (TRIAL fields)."""
    cams = [CameraInfo("cam0", 0, Intrinsics(1000.0, (320.0, 240.0)))]
    take = Take.new(cams, 3, 30.0)
    take.add_points(300)
    take.xyz = np.arange(3 * 300 * 3, dtype=float).reshape(3, 300, 3)
    take.recon[:] = Recon.MULTI_VIEW
    path = tmp_path / "many.c3d"
    export_c3d(take, path)
    d = read_c3d(path)
    assert d.labels == [f"Point_{i}" for i in range(300)]
    np.testing.assert_array_equal(d.xyz, take.xyz)
    c = ezc3d.c3d(str(path))
    labels = c["parameters"]["POINT"]["LABELS"]["value"] + c["parameters"]["POINT"]["LABELS2"]["value"]
    assert labels == d.labels and c["data"]["points"].shape == (4, 300, 3)
    reader, frames = py_c3d_frames(path)
    assert reader.point_used == 300 and frames.shape == (3, 300, 5)

    long = Take.new(cams, 70000, 60.0)
    long.add_points(1)
    long.xyz[:, 0, :] = np.arange(70000)[:, None]
    long.recon[:] = Recon.MULTI_VIEW
    export_c3d(long, path)
    d = read_c3d(path)
    assert d.n_frames == 70000 and d.first_frame == 1
    np.testing.assert_array_equal(d.xyz[:, 0, 2], np.arange(70000))
    assert ezc3d.c3d(str(path))["data"]["points"].shape == (4, 1, 70000)


def test_export_errors(tmp_path: Path, take: Take) -> None:
    path = tmp_path / "out.c3d"
    path.write_bytes(b"keep me")
    with pytest.raises(ValueError, match="frame range"):
        export_c3d(take, path, frames=(5, take.n_frames))
    with pytest.raises(ValueError, match="0..7"):
        export_c3d(take, path, points=[8])
    with pytest.raises(ValueError, match="repeat"):
        export_c3d(take, path, points=[1, 1])
    with pytest.raises(ValueError, match="no points"):
        export_c3d(take, path, points=[])
    with pytest.raises(ValueError, match="not been stabilized"):
        export_c3d(take, path, stabilized=True)
    with pytest.raises(C3DError, match="does not exist"):
        export_c3d(take, tmp_path / "missing" / "x.c3d")
    assert path.read_bytes() == b"keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.c3d"]  # no temporary files left


def test_read_errors(tmp_path: Path) -> None:
    with pytest.raises(C3DError, match="nope.c3d"):
        read_c3d(tmp_path / "nope.c3d")
    txt = tmp_path / "notes.c3d"
    txt.write_text("hello " * 300)
    with pytest.raises(C3DError, match="notes.c3d: not a C3D file"):
        read_c3d(txt)
    short = tmp_path / "short.c3d"
    short.write_bytes(b"\x02\x50" + bytes(100))
    with pytest.raises(C3DError, match="short.c3d"):
        read_c3d(short)


def test_written_parameter_section_is_strictly_valid(tmp_path: Path, take: Take) -> None:
    path = tmp_path / "take.c3d"
    export_c3d(take, path)
    raw = path.read_bytes()
    h = cb.parse_header(raw, str(path))
    assert len(raw) == (h.data_block - 1) * 512 + take.n_frames * take.n_points * 16  # no padding
    params = cb.parse_parameters(raw, h, str(path))
    assert h.processor == cb.INTEL and h.scale == np.float32(RESIDUAL_SCALE)
    assert h.data_block == int(params["POINT"]["DATA_START"].ints()[0]) == 2 + h.n_param_blocks
    assert cb.frame_range(h, params) == (101, take.n_frames)
    assert params["MANUFACTURER"]["SOFTWARE"].strings() == ["carapost"]


# --------------------------------------------------------------------------------- real files
# (relative path, points, frames, rate, units, gap fraction) from SOURCES.md, and which library
# readers can open the file ("e" ezc3d, "p" py-c3d).
REAL = [
    ("ezc3d/Vicon.c3d", 51, 580, 100.0, "mm", 0.010, "ep"),
    ("ezc3d/Qualisys.c3d", 55, 340, 200.0, "mm", 0.0, "ep"),
    ("ezc3d/Optotrak.c3d", 54, 29, 30.0, "mm", 0.038, "ep"),
    ("opensim-core/walking2.c3d", 44, 1249, 250.0, "mm", 0.50, "ep"),
    ("kineticstoolkit/kinematics_basket_sprint.c3d", 26, 3678, 120.0, "m", 0.388, "ep"),
    ("kineticstoolkit/kinematics_racing_static.c3d", 41, 700, 69.9, "m", 0.205, "e"),
    ("kineticstoolkit/kinematics_tennis_serve.c3d", 39, 1092, 50.0, "m", 0.0, "ep"),
    ("c3d.org-samples/sample_00/Motion_Analysis_Corporation/Walk1.c3d", 49, 151, 60.0, "mm", 0.163, "ep"),
    ("c3d.org-samples/sample_00/Vicon_Motion_Systems/pyCGM2_lower_limb_CGM24_Walking01.c3d", 171, 493, 100.0,
     "mm", 0.125, "ep"),
    ("c3d.org-samples/sample_01/Eb015pi.c3d", 26, 450, 50.0, "mm", 0.019, "ep"),
    ("c3d.org-samples/sample_01/Eb015sr.c3d", 26, 450, 50.0, "mm", 0.019, "p"),
    ("c3d.org-samples/sample_03/gait-raw.c3d", 27, 142, 50.0, "mm", 0.545, "ep"),
    ("c3d.org-samples/sample_04/sub_labels.c3d", 114, 333, 60.0, "mm", 0.52, "ep"),
    ("c3d.org-samples/sample_13/Dance.c3d", 40, 499, 65.05, "mm", 0.0, "p"),
    ("c3d.org-samples/sample_29/Facial-Sing.c3d", 38, 3000, 100.0, "mm", 0.033, ""),
    ("c3d.org-samples/sample_32/vicon_zerowire.c3d", 55, 306, 100.0, "mm", 0.277, "ep"),
    ("c3d.org-samples/sample_33/bigparlove.c3d", 205, 323, 200.0, "mm", 0.017, "e"),
]


@pytest.mark.parametrize("rel,P,F,rate,units,gap,libs", REAL, ids=[r[0].split("/")[-1] for r in REAL])
def test_real_files(real_data: Path, rel, P, F, rate, units, gap, libs) -> None:
    d = read_c3d(real_data / rel)
    assert (d.n_points, d.n_frames) == (P, F)
    assert len(d.labels) == P and all(d.labels)
    assert d.frame_rate == pytest.approx(rate, abs=0.01)
    assert d.units == units
    assert d.gap_fraction() == pytest.approx(gap, abs=0.005)
    assert d.backend == "carapost"
    assert d.recon is None  # not written by CaraPost
    valid = np.isfinite(d.xyz).all(-1)
    np.testing.assert_array_equal(np.isfinite(d.residual), valid)
    # Plausible lab coordinates in millimetres (metre files converted).
    assert 100 < np.nanmax(np.abs(d.xyz)) < 1e5


def test_real_metres_converted(real_data: Path) -> None:
    path = real_data / "kineticstoolkit/kinematics_tennis_serve.c3d"
    d = read_c3d(path)
    raw = ezc3d.c3d(str(path))["data"]["points"][:3].transpose(2, 1, 0)
    assert d.scale_to_mm == 1000.0
    np.testing.assert_allclose(d.xyz, raw * 1000.0, rtol=1e-12, equal_nan=True)


def test_real_big_endian_equals_intel(real_data: Path) -> None:
    """Eb015sr (SGI float, read by py-c3d) holds the same data as Eb015pi (Intel int16)."""
    a = read_c3d(real_data / "c3d.org-samples/sample_01/Eb015pi.c3d")
    b = read_c3d(real_data / "c3d.org-samples/sample_01/Eb015sr.c3d")
    assert a.labels == b.labels
    np.testing.assert_array_equal(np.isnan(a.xyz), np.isnan(b.xyz))
    np.testing.assert_allclose(a.xyz, b.xyz, atol=0.05, equal_nan=True)  # int16 x 1/12 mm quantum


@pytest.mark.parametrize("rel,libs", [(r[0], r[6]) for r in REAL], ids=[r[0].split("/")[-1] for r in REAL])
def test_real_own_decoder_matches_libraries(real_data: Path, rel: str, libs: str) -> None:
    """CaraPost's decoder gives ezc3d's coordinates bit for bit (Intel float, Intel int, DEC) and
    py-c3d's to its float32 arithmetic; files a library refuses are the ones SOURCES.md lists."""
    path = real_data / rel
    own = read_c3d(path).xyz
    for lib in ("ezc3d", "py-c3d"):
        if lib[0] not in libs:
            with pytest.raises(C3DError, match=lib):
                _library_xyz(path, lib)
            continue
        other = _library_xyz(path, lib) * read_c3d(path).scale_to_mm
        np.testing.assert_array_equal(np.isnan(other), np.isnan(own), err_msg=f"{rel} {lib}")
        if lib == "ezc3d":
            np.testing.assert_array_equal(other, own, err_msg=rel)
        else:
            np.testing.assert_allclose(other, own, rtol=1e-6, atol=2e-4, equal_nan=True, err_msg=rel)


def _library_xyz(path: Path, lib: str) -> np.ndarray:
    """Coordinates (file units) from ezc3d in process (trusted files only) or py-c3d."""
    if lib == "py-c3d":
        return c3d_module._xyz_pyc3d(path)
    try:
        return ezc3d.c3d(str(path))["data"]["points"][:3].transpose(2, 1, 0)
    except Exception as e:  # noqa: BLE001
        raise C3DError(f"ezc3d: {e}") from e


def test_reader_option_ezc3d_and_py_c3d(real_data: Path) -> None:
    """``reader=`` runs the libraries (ezc3d in a child process) and gives the same data."""
    path = real_data / "c3d.org-samples/sample_03/gait-raw.c3d"  # DEC integer
    own = read_c3d(path)
    via_ezc3d = read_c3d(path, reader="ezc3d")
    via_pyc3d = read_c3d(path, reader="py-c3d")
    assert (via_ezc3d.backend, via_pyc3d.backend) == ("ezc3d", "py-c3d")
    np.testing.assert_array_equal(via_ezc3d.xyz, own.xyz)
    np.testing.assert_allclose(via_pyc3d.xyz, own.xyz, atol=2e-4, equal_nan=True)
    np.testing.assert_array_equal(via_ezc3d.residual, own.residual)
    with pytest.raises(C3DError, match=r"Facial-Sing\.c3d: ezc3d failed"):
        read_c3d(real_data / "c3d.org-samples/sample_29/Facial-Sing.c3d", reader="ezc3d")
    with pytest.raises(ValueError, match="unknown C3D reader"):
        read_c3d(path, reader="btk")


def test_ezc3d_crash_is_contained(tmp_path: Path, take: Take, monkeypatch: pytest.MonkeyPatch) -> None:
    """A segmentation fault in the ezc3d child process becomes a C3DError, not a dead process.
    (Fuzzing found real ezc3d 1.7.2 crashes on files with one corrupted parameter byte; a forced
    crash keeps this test independent of which ones a future ezc3d fixes.)"""
    path = tmp_path / "take.c3d"
    export_c3d(take, path)
    monkeypatch.setattr(c3d_module, "_EZC3D_SCRIPT", "import ctypes; ctypes.string_at(0)")
    with pytest.raises(C3DError, match=r"take\.c3d: ezc3d crashed \(signal 11\)"):
        read_c3d(path, reader="ezc3d")


def test_damaged_files_raise_c3d_error_only(tmp_path: Path, take: Take) -> None:
    """Random byte damage in the header / parameters / data: a C3DError or a result, never
    another exception or a warning (fuzzing; the suite runs with warnings as errors)."""
    path = tmp_path / "take.c3d"
    export_c3d(take, path)
    src = path.read_bytes()
    rng = np.random.default_rng(7)
    outcomes = {"ok": 0, "error": 0}
    for _ in range(300):
        b = bytearray(src)
        for _ in range(rng.integers(1, 6)):
            b[rng.integers(0, 4 * 512)] = rng.integers(0, 256)
        if rng.random() < 0.2:
            b = b[:rng.integers(0, len(b))]
        path.write_bytes(bytes(b))
        try:
            read_c3d(path)
            outcomes["ok"] += 1
        except C3DError:
            outcomes["error"] += 1
    assert outcomes["ok"] > 50 and outcomes["error"] > 50


def test_real_vicon_matches_nexus_csv(real_data: Path) -> None:
    """ezc3d/Vicon.c3d and pyomeca/markers.csv are the same capture (Nexus CSV export)."""
    d = read_c3d(real_data / "ezc3d/Vicon.c3d")
    lines = (real_data / "pyomeca/markers.csv").read_text().splitlines()
    names = [s for s in lines[2].split(",") if s]
    rows = [ln.split(",") for ln in lines[5:] if ln.strip()]
    csv = np.array([[float(v) if v else np.nan for v in r[2:2 + 3 * len(names)]] for r in rows])
    csv = csv.reshape(len(rows), len(names), 3)
    assert names == d.labels and csv.shape == d.xyz.shape
    np.testing.assert_array_equal(np.isnan(csv), np.isnan(d.xyz))
    np.testing.assert_allclose(d.xyz, csv, rtol=5e-6, atol=1e-4, equal_nan=True)  # CSV: 6 digits


def test_real_facial_sing(real_data: Path) -> None:
    """The non-standard parameter section defeats ezc3d and py-c3d; CaraPost's decoder reads it."""
    d = read_c3d(real_data / "c3d.org-samples/sample_29/Facial-Sing.c3d")
    assert d.labels[:6] == [f"root-{i}" for i in range(1, 7)]
    assert "Unlabeled1" in d.labels and "section14-3" in d.labels
    valid = np.isfinite(d.xyz).all(-1)
    assert int((~valid).any(axis=0).sum()) == 7  # markers with gaps
    assert valid[:, d.labels.index("Unlabeled1")].mean() == pytest.approx(0.012, abs=0.001)
    assert valid[:, d.labels.index("section5-1")].mean() == pytest.approx(0.915, abs=0.001)
    face = d.xyz[:, [i for i, lab in enumerate(d.labels) if lab.startswith("section")]]
    extent = np.nanmax(face, axis=(0, 1)) - np.nanmin(face, axis=(0, 1))
    assert 150 < np.sort(extent)[-1] < 300  # a face, in mm: about 170 x 230 mm


def test_real_bad_parameter_section(real_data: Path) -> None:
    path = real_data / "c3d.org-samples/sample_18/bad_parameter_section.c3d"
    with pytest.raises(C3DError, match=r"bad_parameter_section\.c3d.*corrupt parameter section"):
        read_c3d(path)
    with pytest.raises(ValueError):
        info_c3d(path)


def test_real_facial_round_trip(real_data: Path, tmp_path: Path) -> None:
    """Real facial trajectories through a Take and back: identical, gaps where they were."""
    d = read_c3d(real_data / "c3d.org-samples/sample_29/Facial-Sing.c3d")
    cams = [CameraInfo("cam0", 0, Intrinsics(1000.0, (320.0, 240.0)))]
    take = Take.new(cams, d.n_frames, d.frame_rate)
    take.add_points(d.n_points, labels=d.labels)
    take.xyz = d.xyz.copy()
    valid = np.isfinite(d.xyz).all(-1)
    take.recon[valid] = Recon.MULTI_VIEW
    export_c3d(take, tmp_path / "face.c3d")
    e = read_c3d(tmp_path / "face.c3d")
    assert e.labels == d.labels and e.frame_rate == d.frame_rate
    np.testing.assert_array_equal(e.xyz, d.xyz)  # the source is float32 already
    np.testing.assert_array_equal(e.recon, take.recon)


def test_info(real_data: Path) -> None:
    info = info_c3d(real_data / "c3d.org-samples/sample_29/Facial-Sing.c3d")
    assert info["points"] == 38 and info["frames"] == 3000 and info["frame_rate"] == 100.0
    assert info["duration_s"] == pytest.approx(30.0)
    assert info["units"] == "mm" and info["points_with_gaps"] == 7
    assert info["gap_fraction"] == pytest.approx(0.033, abs=0.001)
    assert info["labels_sample"][0] == "root-1" and len(info["labels_sample"]) == 10
    assert info["written_by_carapost"] is False and info["reader"] == "carapost"


def test_marker_indices_skip_model_outputs(real_data: Path) -> None:
    d = read_c3d(real_data / "c3d.org-samples/sample_00/Vicon_Motion_Systems/"
                 "pyCGM2_lower_limb_CGM24_Walking01.c3d")
    markers = d.marker_indices()
    assert 0 < len(markers) < d.n_points
    angles = {s.strip() for s in cb.joined_strings(d.parameters, "POINT", "ANGLES")}
    assert angles and not angles & {d.labels[i] for i in markers}


def test_real_residuals_follow_the_spec(real_data: Path) -> None:
    """Residual and camera byte as py-c3d decodes them (spec: high byte mask, low byte residual)."""
    for rel in ("ezc3d/Qualisys.c3d", "ezc3d/Optotrak.c3d", "c3d.org-samples/sample_01/Eb015pi.c3d"):
        d = read_c3d(real_data / rel)
        with warnings.catch_warnings(), open(real_data / rel, "rb") as fh:
            warnings.simplefilter("ignore")  # third-party files: py-c3d's consistency warnings
            frames = np.stack([p.copy() for _, p, _ in pyc3d.Reader(fh).read_frames()])
        valid = frames[..., 3] >= 0
        np.testing.assert_array_equal(np.isfinite(d.residual), valid, err_msg=rel)
        np.testing.assert_allclose(d.residual[valid], frames[..., 3][valid], rtol=1e-6, err_msg=rel)
        np.testing.assert_array_equal(d.camera_mask[valid], frames[..., 4][valid], err_msg=rel)
    q = read_c3d(real_data / "ezc3d/Qualisys.c3d")
    assert 1.0 < np.nanmedian(q.residual) < 3.0  # plausible residuals in mm
