"""The .cara project file: exact round trip, atomic save, sources, versions, damaged files."""

from __future__ import annotations

import copy
import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from carapost.core.camera import Intrinsics
from carapost.io import cara, cara_schema, cara_write
from carapost.io.cara import CARA_VERSION, CaraError, LoadResult, load_take, relocate_source, save_take
from carapost.model.detections import DETECTION_FIELDS, Detections
from carapost.model.params import Parameters
from carapost.model.take import (POINT_ARRAYS, BrimModel, CameraInfo, Keyframes, ObsSource, PointKind,
                                 Recon, SourceRef, Take)

F, C = 600, 4  # 600 frames: the point arrays span three 256-frame chunks


# ----------------------------------------------------------------------------- helpers
def make_sources(folder: Path, n: int = C) -> list[Path]:
    """One fake ``.pico`` file per camera in ``folder/video``."""
    vid = folder / "video"
    vid.mkdir(parents=True, exist_ok=True)
    paths = []
    for c in range(n):
        p = vid / f"take_{c}.pico"
        p.write_bytes(b"pico" + bytes([c]))
        paths.append(p)
    return paths


def make_take(sources: list[Path] | None = None, seed: int = 1) -> Take:
    """A small take with every part filled in, NaN and -1 included."""
    rng = np.random.default_rng(seed)
    cams = []
    for c in range(C):
        intr = Intrinsics(900.0 + c, (320.5, 240.25), (640, 480), aspect=1.0 + 0.01 * c, skew=0.1 * c,
                          radial=(1e-7 * (c + 1), -2e-13, 3e-19 if c == 3 else 0.0),
                          distortion_centre=(321.0, 239.0) if c == 2 else None)
        src = None if sources is None else SourceRef(str(sources[c]), "", "pico")
        cams.append(CameraInfo(f"cam_{c}", c, intr, image_size=(640, 480), source=src, frame_offset=c - 1,
                               rotation=(0, 90, 180, 270)[c], device_id=f"dev-{c:03d}"))
    R = rng.standard_normal((F, C, 3, 3))
    t = rng.standard_normal((F, C, 3)) * 100
    R[5:9, 1] = np.nan  # unsolved frames of one camera
    t[5:9, 1] = np.nan
    take = Take.new(cams, F, 59.94, R=R, t=t, name="Ünïcode take")
    take.add_points(9, labels=["lip_l", "", "brow_r", "nose", "", "chin", "jaw_l", "jaw_r", "cheek"])
    take.add_points(4, kind=PointKind.BRIM, brim_index=np.array([0, 3, 5, 7]))
    take.remove_points([1])  # ids are no longer 0..P-1
    P = take.n_points
    take.xyz = rng.standard_normal((F, P, 3)) * 50
    take.xyz[rng.random((F, P)) < 0.05] = np.nan
    take.xyz[0, 0, 0] = -0.0
    take.recon = rng.integers(0, 4, (F, P)).astype(np.uint8)
    take.obs_xy = (rng.random((F, P, C, 2)) * 640).astype(np.float32)
    take.obs_xy[rng.random((F, P, C)) < 0.2] = np.nan
    take.obs_det = rng.integers(-1, 30, (F, P, C)).astype(np.int32)
    take.obs_src = rng.integers(0, 5, (F, P, C)).astype(np.uint8)
    take.obs_q = np.where(rng.random((F, P, C)) < 0.1, rng.random((F, P, C)), np.nan).astype(np.float32)
    take.xyz_stabilized = take.xyz + 1.5
    dets = []
    for c in range(C):
        frames = {int(f): {k: (rng.random(n) * 100).astype(dt) if k != "polarity" else
                           rng.choice([-1, 1], n).astype(np.int8) for k, dt in DETECTION_FIELDS.items()}
                  for f, n in zip(rng.choice(F, 40, replace=False), rng.integers(0, 30, 40))}
        d = Detections.from_frames(F, frames)
        d.detected[:3] = True  # detected, nothing found
        dets.append(d)
    take.detections = dets
    ids = take.points.ids
    take.keyframes = Keyframes(frame=np.array([3, 10, 10], np.int32), point_id=ids[[0, 2, 2]],
                               camera=np.array([0, 1, 3], np.int16),
                               xy=np.array([[1, 2], [3, 4], [np.nan, 6]], np.float32),
                               pattern=np.arange(12, dtype=np.float32).reshape(3, 4),
                               search=np.arange(12, 24, dtype=np.float32).reshape(3, 4))
    take.labels = ["lip_l", "brow_r", "nose", "chin", "jaw_l", "jaw_r", "cheek", "extra"]
    take.sticks = np.array([[ids[0], ids[2]], [ids[3], ids[4]]], np.int64)
    take.stick_colours = np.array([[255, 0, 0], [0, 255, 0]], np.uint8)
    take.brim = BrimModel("v2.0", rng.standard_normal((8, 3)), np.full(8, 2.5), np.array([1, -1] * 4, np.int8),
                          svg="<svg>" + "x" * 100_000 + "</svg>")
    take.params.tracking.set("Patch Match Threshold", 0.65)
    take.params.blobs.find_white_blobs = True
    take.params.export.units = "cm"
    take.params.tracker.n_frames = 25
    take.caddies = [(0, 1), (2, 3)]
    take.active_range = (10, 500)
    take.view_range = (0, 550)
    take.current_frame = 42
    take.start_timecode = "10:20:30:12"
    take.first_frame_number = 1001
    take.rom_path = "/somewhere/rom.cara"
    take.metadata = {"logger": "HMC-1", "description": "smile; ünïcode", "": "empty key"}
    take.check()
    return take


def bits(a: np.ndarray) -> tuple:
    a = np.ascontiguousarray(a)
    return a.dtype.str, a.shape, a.tobytes()


def assert_takes_identical(a: Take, b: Take) -> None:
    """Every field equal; every array bit-identical (dtype, shape, bytes: NaN payloads too)."""
    for f in dataclasses.fields(Take):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            assert bits(va) == bits(vb), f.name
        elif f.name == "detections":
            assert len(va) == len(vb)
            for da, db in zip(va, vb):
                for k in ["frame_ptr", "detected", *DETECTION_FIELDS]:
                    assert bits(getattr(da, k)) == bits(getattr(db, k)), f"detections.{k}"
        elif f.name in ("points", "keyframes", "brim") and va is not None:
            assert vb is not None
            for g in dataclasses.fields(va):
                x, y = getattr(va, g.name), getattr(vb, g.name)
                if isinstance(x, np.ndarray):
                    assert bits(x) == bits(y), f"{f.name}.{g.name}"
                else:
                    assert x == y, f"{f.name}.{g.name}"
        elif f.name == "params":
            assert va.to_dict() == vb.to_dict()
            assert {k: {n: type(v) for n, v in s.items()} for k, s in va.to_dict().items()} == \
                   {k: {n: type(v) for n, v in s.items()} for k, s in vb.to_dict().items()}
        else:
            assert va == vb, f.name
            assert type(va) is type(vb), f.name


@pytest.fixture
def take_and_dir(tmp_path):
    folder = tmp_path / "session"
    sources = make_sources(folder)
    return make_take(sources), folder


# -------------------------------------------------------------------------- round trip
def test_round_trip_is_exact(take_and_dir):
    take, folder = take_and_dir
    before = copy.deepcopy(take)
    path = folder / "take.cara"
    save_take(take, path)
    assert_takes_identical(take, before)  # saving does not modify the take
    res = load_take(path)
    assert isinstance(res, LoadResult)
    assert res.missing_sources == [] and res.messages == []
    # relative paths were filled in on save
    assert [c.source.relpath for c in res.take.cameras] == [f"video/take_{c}.pico" for c in range(C)]
    for c, cam in enumerate(take.cameras):
        cam.source.relpath = f"video/take_{c}.pico"
    assert_takes_identical(res.take, take)
    assert np.signbit(res.take.xyz[0, 0, 0])  # -0.0 kept
    assert res.take.params.tracking.patch_match_threshold == 0.65
    assert res.take.params.export.units == "cm"
    assert res.take.detections[0].detected[:3].all()
    assert res.take.cameras[2].intrinsics.distortion_centre == (321.0, 239.0)
    assert res.take.cameras[0].intrinsics.distortion_centre is None


def test_file_layout(take_and_dir):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "carapost.cara"
        assert (f.attrs["version_major"], f.attrs["version_minor"]) == CARA_VERSION == (1, 0)
        assert f.attrs["writer"].startswith("carapost ")
        for name in POINT_ARRAYS:
            ds = f[f"tracks/{name}"]
            assert ds.chunks is not None and ds.chunks[0] == 256, name
            assert ds.compression is not None or ds.id.get_create_plist().get_nfilters() > 0, name
        src = f["cameras/1/source"].attrs
        assert src["path"] == str((folder / "video" / "take_1.pico").resolve())
        assert src["relpath"] == "video/take_1.pico"
        assert src["kind"] == "pico"
        assert "distortion_centre" not in f["cameras/0"].attrs
        assert f["params/tracking"].attrs["patch_match_threshold"] == 0.65


def test_round_trip_minimal_take(tmp_path):
    cam = CameraInfo("only", 0, Intrinsics(500.0, (10.0, 10.0)))
    take = Take.new([cam], 1, 30.0)
    save_take(take, tmp_path / "m.cara")
    res = load_take(tmp_path / "m.cara")
    assert_takes_identical(res.take, take)
    assert res.take.caddies == [] and res.take.brim is None and res.take.cameras[0].source is None


def test_round_trip_without_blosc_uses_lzf(take_and_dir, monkeypatch):
    take, folder = take_and_dir
    monkeypatch.setattr(cara_schema, "blosc_available", lambda: False)
    save_take(take, folder / "lzf.cara")
    with h5py.File(folder / "lzf.cara", "r") as f:
        assert f["tracks/obs_xy"].compression == "lzf" and f["tracks/obs_xy"].shuffle
    back = load_take(folder / "lzf.cara").take
    assert bits(back.obs_xy) == bits(take.obs_xy)
    assert bits(back.xyz) == bits(take.xyz)


def test_save_refuses_inconsistent_take(tmp_path):
    take = make_take()
    take.recon = take.recon[:, :3]
    with pytest.raises(CaraError, match=r"bad\.cara.*recon"):
        save_take(take, tmp_path / "bad.cara")
    assert list(tmp_path.iterdir()) == []


def test_save_into_missing_folder(tmp_path):
    with pytest.raises(CaraError, match="does not exist"):
        save_take(make_take(), tmp_path / "nope" / "x.cara")


# ---------------------------------------------------------------------------- atomicity
def test_failure_mid_save_leaves_old_file(take_and_dir, monkeypatch):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)
    old = path.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(cara_write, "_write_detections", boom)  # after the take and tracks are written
    other = make_take(seed=2)
    with pytest.raises(RuntimeError, match="disk on fire"):
        save_take(other, path)
    assert path.read_bytes() == old
    assert sorted(p.name for p in folder.iterdir()) == ["take.cara", "video"]
    monkeypatch.undo()
    assert_takes_identical(load_take(path).take, load_take(path).take)


def test_failure_at_replace_is_a_cara_error(take_and_dir, monkeypatch):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)
    old = path.read_bytes()

    def no_replace(src, dst):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(cara.os, "replace", no_replace)
    with pytest.raises(CaraError, match=r"take\.cara: cannot save: Permission denied"):
        save_take(take, path)
    assert path.read_bytes() == old
    assert sorted(p.name for p in folder.iterdir()) == ["take.cara", "video"]


def test_save_keeps_existing_file_mode(take_and_dir):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)
    os.chmod(path, 0o640)
    save_take(take, path)
    assert path.stat().st_mode & 0o777 == 0o640


# ------------------------------------------------------------------------------ sources
def test_moved_folder_finds_sources_by_relative_path(take_and_dir, tmp_path):
    take, folder = take_and_dir
    save_take(take, folder / "take.cara")
    moved = tmp_path / "elsewhere" / "session_moved"
    moved.parent.mkdir()
    shutil.move(str(folder), str(moved))
    res = load_take(moved / "take.cara")
    assert res.missing_sources == []
    for c, cam in enumerate(res.take.cameras):
        assert Path(cam.source.path) == (moved / "video" / f"take_{c}.pico").resolve()
        assert Path(cam.source.path).read_bytes() == b"pico" + bytes([c])
    assert len(res.messages) == C and all("found at" in m for m in res.messages)


def test_relative_path_is_tried_before_absolute(take_and_dir, tmp_path):
    take, folder = take_and_dir
    save_take(take, folder / "take.cara")
    copied = tmp_path / "copy"
    shutil.copytree(folder, copied)  # the originals still exist at the absolute paths
    res = load_take(copied / "take.cara")
    assert [Path(c.source.path).parent for c in res.take.cameras] == [(copied / "video").resolve()] * C


def test_sources_in_the_cara_folder_are_found_by_name(take_and_dir, tmp_path):
    take, folder = take_and_dir
    save_take(take, folder / "take.cara")
    flat = tmp_path / "flat"
    flat.mkdir()
    shutil.move(str(folder / "take.cara"), str(flat / "take.cara"))
    for c in range(C):
        shutil.move(str(folder / "video" / f"take_{c}.pico"), str(flat / f"take_{c}.pico"))
    res = load_take(flat / "take.cara")
    assert res.missing_sources == []
    assert [Path(c.source.path) for c in res.take.cameras] == [(flat / f"take_{c}.pico").resolve()
                                                               for c in range(C)]
    assert [c.source.relpath for c in res.take.cameras] == [f"take_{c}.pico" for c in range(C)]


def test_missing_sources_are_listed_and_load_succeeds(take_and_dir):
    take, folder = take_and_dir
    save_take(take, folder / "take.cara")
    saved = [c.source.path for c in take.cameras]
    (folder / "video" / "take_0.pico").unlink()
    (folder / "video" / "take_2.pico").unlink()
    res = load_take(folder / "take.cara")
    assert res.missing_sources == [0, 2]
    assert sum("not found" in m for m in res.messages) == 2
    assert res.take.cameras[0].source.path == str(Path(saved[0]).resolve())  # kept as saved
    assert res.take.cameras[0].source.relpath == "video/take_0.pico"
    assert bits(res.take.xyz) == bits(take.xyz)


def test_relocate_source(take_and_dir, tmp_path):
    take, folder = take_and_dir
    new = tmp_path / "new" / "cam1.mov"
    new.parent.mkdir()
    new.write_bytes(b"video")
    before = take.cameras[1]
    relocate_source(take, 1, new, cara_path=tmp_path / "take.cara")
    src = take.cameras[1].source
    assert (src.path, src.relpath, src.kind) == (str(new), "new/cam1.mov", "video")
    assert before.source.kind == "pico"  # the old CameraInfo object was not modified
    relocate_source(take, 2, new.parent)
    assert take.cameras[2].source.kind == "images" and take.cameras[2].source.relpath == ""
    with pytest.raises(ValueError, match="no camera 7"):
        relocate_source(take, 7, new)
    with pytest.raises(ValueError, match="no such file"):
        relocate_source(take, 0, tmp_path / "missing.pico")
    save_take(take, folder / "take.cara")
    res = load_take(folder / "take.cara")
    assert res.take.cameras[1].source.path == str(new) and res.missing_sources == []


# ----------------------------------------------------------------------------- versions
def _edit(path: Path, fn) -> None:
    with h5py.File(path, "r+") as f:
        fn(f)


def test_newer_major_version_is_refused(take_and_dir):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)
    _edit(path, lambda f: (f.attrs.__setitem__("version_major", 2), f.attrs.__setitem__("version_minor", 0)))
    with pytest.raises(CaraError) as e:
        load_take(path)
    assert str(path) in str(e.value)
    assert "written by a newer CaraPost (format 2.0); this version reads up to 1.x" in str(e.value)


def test_newer_minor_version_loads_with_a_message(take_and_dir):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)

    def newer(f):
        f.attrs["version_minor"] = 7
        f["tracks"].create_dataset("future_thing", data=np.zeros((F, 3)))
        f.create_group("future_group").attrs["x"] = 1
        f["take"].attrs["future_attr"] = "?"
    _edit(path, newer)
    res = load_take(path)
    assert len(res.messages) == 1 and "format 1.7" in res.messages[0] and "newer" in res.messages[0]
    assert bits(res.take.obs_xy) == bits(take.obs_xy)


def test_migrates_version_0_9(take_and_dir):
    take, folder = take_and_dir
    path = folder / "old.cara"
    save_take(take, path)

    def to_0_9(f):  # 0.9 stored obs_xy as float64 and had neither obs_q nor xyz_stabilized
        f.attrs["version_major"], f.attrs["version_minor"] = 0, 9
        obs = f["tracks/obs_xy"][()]
        del f["tracks/obs_xy"], f["tracks/obs_q"], f["tracks/xyz_stabilized"]
        f["tracks"].create_dataset("obs_xy", data=obs.astype(np.float64), chunks=(256,) + obs.shape[1:],
                                   compression="gzip")
    _edit(path, to_0_9)
    with h5py.File(path, "r") as f:
        assert f["tracks/obs_xy"].dtype == np.float64 and "obs_q" not in f["tracks"]
    res = load_take(path)
    assert len(res.messages) == 1
    msg = res.messages[0]
    assert "migrated from format 0.9 to 1.0" in msg and "float32" in msg and "stabilized" in msg
    back = res.take
    assert bits(back.obs_xy) == bits(take.obs_xy)  # float32 -> float64 -> float32 is exact
    assert back.obs_q.dtype == np.float32 and np.isnan(back.obs_q).all()
    assert back.xyz_stabilized.shape == take.xyz.shape and np.isnan(back.xyz_stabilized).all()
    assert bits(back.xyz) == bits(take.xyz)
    # saving writes the current version
    save_take(back, path)
    with h5py.File(path, "r") as f:
        assert (f.attrs["version_major"], f.attrs["version_minor"]) == (1, 0)
        assert f["tracks/obs_xy"].dtype == np.float32


def test_too_old_version_is_refused(take_and_dir):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)
    _edit(path, lambda f: (f.attrs.__setitem__("version_major", 0), f.attrs.__setitem__("version_minor", 5)))
    with pytest.raises(CaraError, match=r"take\.cara: format 0\.5 is too old .* from format 0\.9 on"):
        load_take(path)


# ------------------------------------------------------------------------ damaged files
@pytest.fixture
def saved(take_and_dir):
    take, folder = take_and_dir
    path = folder / "take.cara"
    save_take(take, path)
    return path


def _raises_naming(path: Path, match: str) -> str:
    with pytest.raises(CaraError, match=match) as e:
        load_take(path)
    assert str(path) in str(e.value)
    return str(e.value)


def test_missing_file(tmp_path):
    _raises_naming(tmp_path / "none.cara", "no such file")


def test_not_hdf5(tmp_path):
    p = tmp_path / "text.cara"
    p.write_text("hello, this is not HDF5\n" * 100)
    _raises_naming(p, "not an HDF5 file")


def test_truncated_file(saved, tmp_path):
    p = tmp_path / "half.cara"
    data = saved.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    _raises_naming(p, "truncated or damaged")


def test_hdf5_that_is_not_a_cara_file(tmp_path):
    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f["x"] = np.arange(3)
    _raises_naming(p, r"not a CaraPost project \(\.cara\) file: no 'format' attribute")


@pytest.mark.parametrize("dataset", ["tracks/xyz", "points/ids", "detections/2/x", "poses/R", "labels"])
def test_missing_dataset(saved, dataset):
    _edit(saved, lambda f: f.__delitem__(dataset))
    _raises_naming(saved, f"dataset '/{dataset}' is missing")


def test_missing_attribute(saved):
    _edit(saved, lambda f: f["take"].attrs.__delitem__("n_frames"))
    _raises_naming(saved, "attribute 'n_frames' of '/take' is missing")


def test_wrong_shape(saved):
    def shrink(f):
        recon = f["tracks/recon"][()]
        del f["tracks/recon"]
        f["tracks/recon"] = recon[:, :2]
    _edit(saved, shrink)
    _raises_naming(saved, r"inconsistent take: recon has shape \(600, 2\)")


def test_inconsistent_detections(saved):
    def bad(f):
        ptr = f["detections/1/frame_ptr"][()]
        ptr[-1] += 5
        f["detections/1/frame_ptr"][...] = ptr
    _edit(saved, bad)
    _raises_naming(saved, "camera 1's detection frame pointers")


def test_bad_parameter_value(saved):
    _edit(saved, lambda f: f["params/tracking"].attrs.__setitem__("patch_match_threshold", 7.0))
    _raises_naming(saved, "bad parameter.*Patch Match Threshold")


def test_unknown_parameters_are_ignored(saved):
    _edit(saved, lambda f: (f["params/tracking"].attrs.__setitem__("new_knob", 3),
                            f["params"].create_group("new_section").attrs.__setitem__("a", 1)))
    back = load_take(saved).take
    assert back.params.tracking.patch_match_threshold == 0.65
    assert back.params.to_dict().keys() == Parameters().to_dict().keys()


def test_corrupted_chunk_is_detected(saved):
    with h5py.File(saved, "r") as f:
        ds = f["tracks/xyz"]
        assert ds.fletcher32
        info = ds.id.get_chunk_info(1)
    with open(saved, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(b"\x00\xff" * 16)
    _raises_naming(saved, r"cannot read '/tracks/xyz': the file is truncated or damaged")


def test_blosc_file_without_hdf5plugin_names_the_package(saved):
    code = ("import sys; sys.modules['hdf5plugin'] = None\n"
            "from carapost.io.cara import load_take, CaraError\n"
            "try:\n    load_take(sys.argv[1])\nexcept CaraError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code, str(saved)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert str(saved) in out.stdout and "needs the 'hdf5plugin' package" in out.stdout


def test_take_without_cameras_roundtrips(tmp_path):
    """Marker data opened from a C3D file has no cameras; it still saves and loads."""
    import numpy as np

    from carapost.io.cara import load_take, save_take
    from carapost.model.take import Take

    take = Take.new([], 5, 100.0, name="markers")
    take.add_points(3, labels=["a", "b", ""])
    take.xyz[:] = np.arange(45, dtype=float).reshape(5, 3, 3)
    save_take(take, tmp_path / "m.cara")
    back = load_take(tmp_path / "m.cara").take
    assert back.n_cameras == 0 and back.points.labels == ["a", "b", ""]
    np.testing.assert_array_equal(back.xyz, take.xyz)
