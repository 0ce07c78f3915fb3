"""The .pico container: round trips, metadata, damage recovery, atomic writes, take files."""

from __future__ import annotations

import logging
import os
import struct
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from carapost.io.pico import (
    PicoError,
    PicoMetadata,
    PicoReader,
    PicoWriter,
    channel_of,
    take_files,
    update_metadata,
)
from carapost.model.params import BlobParameters

REC_HEAD = 24   # bytes of a frame record header (docs/formats/pico.md)


def face_frames(n: int, h: int = 360, w: int = 640, seed: int = 0) -> list[np.ndarray]:
    """Realistic content: shaded face oval, skin texture, dark painted dots, motion, noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    face = np.exp(-(((xx - w / 2) / (0.32 * w)) ** 2 + ((yy - h / 2) / (0.45 * h)) ** 2) ** 2)
    tex = cv2.resize(rng.normal(0, 1, (h // 16, w // 16)).astype(np.float32), (w, h),
                     interpolation=cv2.INTER_CUBIC)
    base = 40 + 150 * face + 12 * tex + 6 * cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 1.5)
    for x, y in np.c_[rng.uniform(0.25, 0.75, 60) * w, rng.uniform(0.2, 0.85, 60) * h]:
        cv2.circle(base, (int(x * 16), int(y * 16)), 4 * 16, 25.0, -1, cv2.LINE_AA, 4)
    out = []
    for k in range(n):
        m = np.float32([[1, 0, 3 * np.sin(k / 3)], [0, 1, 2 * np.cos(k / 5)]])
        img = cv2.warpAffine(base, m, (w, h), borderMode=cv2.BORDER_REFLECT)
        img += rng.normal(0, 2.0, (h, w)).astype(np.float32)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def write(path: Path, frames: list[np.ndarray], meta: PicoMetadata | None = None, **kw) -> Path:
    with PicoWriter(path, meta or PicoMetadata(), **kw) as w:
        for f in frames:
            w.write(f)
    return path


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    return face_frames(12)


@pytest.fixture
def jpeg_file(tmp_path: Path, frames: list[np.ndarray]) -> Path:
    return write(tmp_path / "TAKE_0.pico", frames, codec="jpeg", quality=92)


# -- round trips ------------------------------------------------------------------------------
def test_jpeg_round_trip_psnr_above_40db(jpeg_file: Path, frames: list[np.ndarray]) -> None:
    with PicoReader(jpeg_file) as r:
        assert (r.n_frames, r.width, r.height, r.codec, r.warnings) == (12, 640, 360, "jpeg", [])
        for i, f in enumerate(frames):
            img = r.read(i)
            assert img.shape == (360, 640) and img.dtype == np.uint8
            assert psnr(img, f) > 40.0


def test_lossless_round_trip_is_exact(tmp_path: Path, frames: list[np.ndarray]) -> None:
    rng = np.random.default_rng(3)
    odd = [rng.integers(0, 256, (37, 53), dtype=np.uint8), np.zeros((37, 53), np.uint8),
           np.full((37, 53), 255, np.uint8), np.tile(np.arange(53, dtype=np.uint8) * 5, (37, 1))]
    for name, seq in (("A_0.pico", frames[:4]), ("B_0.pico", odd)):
        p = write(tmp_path / name, seq, codec="lossless")
        with PicoReader(p) as r:
            assert r.codec == "lossless" and r.n_frames == len(seq)
            for i, f in enumerate(seq):
                np.testing.assert_array_equal(r.read(i), f)


def test_jpeg_quality_changes_size(tmp_path: Path, frames: list[np.ndarray]) -> None:
    lo = write(tmp_path / "L_0.pico", frames[:3], quality=50).stat().st_size
    hi = write(tmp_path / "H_0.pico", frames[:3], quality=95).stat().st_size
    assert lo < 0.7 * hi


def test_random_access_is_order_independent(jpeg_file: Path) -> None:
    with PicoReader(jpeg_file) as r:
        seq = [r.read(i) for i in range(r.n_frames)]
    order = np.random.default_rng(7).permutation(np.repeat(np.arange(12), 2))
    with PicoReader(jpeg_file) as r:
        for i in order:
            np.testing.assert_array_equal(r.read(i), seq[i])
        np.testing.assert_array_equal(r.read(np.int64(5)), seq[5])


def test_concurrent_reads_match(jpeg_file: Path) -> None:
    with PicoReader(jpeg_file) as r:
        seq = [r.read(i) for i in range(r.n_frames)]
        idx = list(range(12)) * 4
        with ThreadPoolExecutor(4) as ex:
            got = list(ex.map(r.read, idx))
    for i, img in zip(idx, got):
        np.testing.assert_array_equal(img, seq[i])


def test_index_out_of_range(jpeg_file: Path) -> None:
    with PicoReader(jpeg_file) as r:
        for bad in (-1, 12, 100):
            with pytest.raises(IndexError, match="out of range 0..11"):
                r.read(bad)
        with pytest.raises(TypeError):
            r.read(1.5)  # type: ignore[arg-type]


def test_zero_frame_file(tmp_path: Path) -> None:
    p = write(tmp_path / "E_0.pico", [], PicoMetadata(camera_name="empty"))
    with PicoReader(p) as r:
        assert r.n_frames == 0 and r.warnings == [] and r.meta.camera_name == "empty"


# -- metadata -------------------------------------------------------------------------------
def full_meta() -> PicoMetadata:
    return PicoMetadata(logger_name="Logger-7", logger_description="Stage B, helmet 2 — café",
                        logger_id="5f3a-99", camera_name="Cam left upper", channel=3,
                        frame_rate=59.94, start_timecode="10:21:33;17", width=640, height=360,
                        rotation=270, blob_parameters=BlobParameters(black_threshold=0.55).to_dict(),
                        extra={"operator": "J. Doe", "gains": [1.5, 2.0], "nested": {"a": None}})


def test_metadata_round_trip(tmp_path: Path, frames: list[np.ndarray]) -> None:
    meta = full_meta()
    p = write(tmp_path / "M_3.pico", frames[:2], meta)
    with PicoReader(p) as r:
        assert r.meta == meta
        assert r.meta.format_version == "1.0" and r.version == (1, 0)
        assert BlobParameters.from_dict(r.meta.blob_parameters).black_threshold == 0.55
        assert r.frame_rate == pytest.approx(59.94)


def test_writer_does_not_mutate_meta_and_fills_size(tmp_path: Path, frames: list[np.ndarray]) -> None:
    meta = PicoMetadata(camera_name="x")
    p = write(tmp_path / "S_0.pico", frames[:1], meta)
    assert (meta.width, meta.height) == (0, 0)
    with PicoReader(p) as r:
        assert (r.meta.width, r.meta.height) == (640, 360)


def test_unknown_metadata_keys_survive_in_extra() -> None:
    d = full_meta().to_dict()
    d["added_in_v1_3"] = 42
    m = PicoMetadata.from_dict(d)
    assert m.extra["added_in_v1_3"] == 42 and m.extra["operator"] == "J. Doe"


@pytest.mark.parametrize("kw, msg", [
    ({"rotation": 45}, "rotation"), ({"start_timecode": "1:2:3:4"}, "start_timecode"),
    ({"frame_rate": 0}, "frame_rate"), ({"frame_rate": float("nan")}, "frame_rate"),
    ({"channel": -1}, "channel"), ({"extra": []}, "extra"), ({"camera_name": 3}, "camera_name"),
])
def test_metadata_validation(kw: dict, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        PicoMetadata(**kw)


def test_non_json_extra_is_rejected_at_open(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not JSON-serialisable"):
        PicoWriter(tmp_path / "J_0.pico", PicoMetadata(extra={"f": object()}))
    assert list(tmp_path.iterdir()) == []


def test_update_metadata_in_place(tmp_path: Path, frames: list[np.ndarray]) -> None:
    p = write(tmp_path / "U_0.pico", frames[:3], PicoMetadata(camera_name="before"))
    with PicoReader(p) as r:
        before = [r.read(i) for i in range(3)]
        new = r.meta.copy()
    new.camera_name, new.rotation = "after", 90
    new.blob_parameters = {"black_threshold": 0.3}
    update_metadata(p, new)
    update_metadata(p, new)                       # idempotent, file does not grow
    size = p.stat().st_size
    update_metadata(p, new)
    assert p.stat().st_size == size
    with PicoReader(p) as r:
        assert r.warnings == [] and r.meta.camera_name == "after" and r.meta.rotation == 90
        for i in range(3):
            np.testing.assert_array_equal(r.read(i), before[i])
    bad = new.copy()
    bad.width = 10
    with pytest.raises(ValueError, match="does not match"):
        update_metadata(p, bad)


# -- damage ------------------------------------------------------------------------------------
def test_truncated_file_recovers_intact_frames(jpeg_file: Path, tmp_path: Path, caplog) -> None:
    with PicoReader(jpeg_file) as r:
        ref = [r.read(i) for i in range(r.n_frames)]
        ends = r._index["offset"] + REC_HEAD + r._index["length"]
    data = jpeg_file.read_bytes()
    cut = int(len(data) * 0.7)
    expected = int((ends <= cut).sum())
    assert 0 < expected < 12
    bad = tmp_path / "CUT_0.pico"
    bad.write_bytes(data[:cut])
    with caplog.at_level(logging.WARNING, logger="carapost.io.pico"):
        r = PicoReader(bad)
    with r:
        assert r.n_frames == expected and not r.has_index
        assert r.warnings and any("recovered" in w for w in r.warnings)
        assert any("CUT_0.pico" in rec.getMessage() for rec in caplog.records)
        assert r.meta.camera_name == "" and (r.width, r.height) == (640, 360)   # header metadata
        for i in range(expected):
            np.testing.assert_array_equal(r.read(i), ref[i])
        with pytest.raises(IndexError):
            r.read(expected)


def test_file_cut_inside_header_or_trailer(jpeg_file: Path, tmp_path: Path) -> None:
    data = jpeg_file.read_bytes()
    p = tmp_path / "T_0.pico"
    p.write_bytes(data[:-5])                           # trailer damaged, all frames intact
    with PicoReader(p) as r:
        assert r.n_frames == 12 and r.warnings
    p.write_bytes(data[:30])                           # inside the header JSON
    with pytest.raises(PicoError, match="metadata are damaged"):
        PicoReader(p)


def flip_byte(path: Path, offset: int) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        b = f.read(1)
        f.seek(offset)
        f.write(bytes([b[0] ^ 0x5A]))


def test_flipped_byte_in_frame_raises_for_that_frame_only(jpeg_file: Path) -> None:
    k = 6
    with PicoReader(jpeg_file) as r:
        ref = [r.read(i) for i in range(r.n_frames)]
        off, length = int(r._index["offset"][k]), int(r._index["length"][k])
    flip_byte(jpeg_file, off + REC_HEAD + length // 2)
    with PicoReader(jpeg_file) as r:
        assert r.warnings == []                        # opening is O(1): damage is found on read
        with pytest.raises(PicoError, match=rf"TAKE_0\.pico: frame {k} is corrupt"):
            r.read(k)
        for i in range(12):
            if i != k:
                np.testing.assert_array_equal(r.read(i), ref[i])
        assert r.verify() == [k]


def test_damage_without_index_is_reported_by_rescan(jpeg_file: Path, tmp_path: Path) -> None:
    with PicoReader(jpeg_file) as r:
        ref = [r.read(i) for i in range(r.n_frames)]
        idx = r._index.copy()
    data = bytearray(jpeg_file.read_bytes()[: int(idx["offset"][10])])   # frames 0..9, no index
    data[int(idx["offset"][3]) + REC_HEAD + 100] ^= 0xFF                  # payload of frame 3
    data[int(idx["offset"][7]) + 2] ^= 0xFF                               # record header of frame 7
    p = tmp_path / "D_0.pico"
    p.write_bytes(bytes(data))
    with PicoReader(p) as r:
        assert r.n_frames == 10
        text = " ".join(r.warnings)
        assert "corrupt frame(s): 3" in text and "1 frame(s) missing" in text
        with pytest.raises(PicoError, match="frame 3 is corrupt"):
            r.read(3)
        with pytest.raises(PicoError, match="frame 7 is missing"):
            r.read(7)
        for i in (0, 1, 2, 4, 5, 6, 8, 9):
            np.testing.assert_array_equal(r.read(i), ref[i])


def test_damaged_index_falls_back_to_rescan(jpeg_file: Path) -> None:
    with PicoReader(jpeg_file) as r:
        ref = r.read(11)
    size = jpeg_file.stat().st_size
    index_off = struct.unpack("<Q", jpeg_file.read_bytes()[size - 24: size - 16])[0]
    flip_byte(jpeg_file, index_off + 8 + 3)
    with PicoReader(jpeg_file) as r:
        assert r.n_frames == 12 and "frame index is damaged" in r.warnings[0]
        np.testing.assert_array_equal(r.read(11), ref)


def test_not_a_pico_file(tmp_path: Path) -> None:
    txt = tmp_path / "notes_0.pico"
    txt.write_text("hello, this is not video\n" * 10)
    with pytest.raises(PicoError, match=r"notes_0\.pico: not a \.pico file"):
        PicoReader(txt)
    empty = tmp_path / "empty_0.pico"
    empty.write_bytes(b"")
    with pytest.raises(PicoError, match="not a .pico file"):
        PicoReader(empty)
    with pytest.raises(PicoError, match="cannot open"):
        PicoReader(tmp_path / "missing_0.pico")
    assert issubclass(PicoError, ValueError)


def test_newer_major_version_is_rejected(jpeg_file: Path) -> None:
    with open(jpeg_file, "r+b") as f:
        f.seek(8)
        f.write(struct.pack("<H", 2))
    with pytest.raises(PicoError, match="version 2.0 is newer"):
        PicoReader(jpeg_file)


# -- writer --------------------------------------------------------------------------------
def test_writer_is_atomic(tmp_path: Path, frames: list[np.ndarray]) -> None:
    target = tmp_path / "A_0.pico"
    w = PicoWriter(target, PicoMetadata())
    w.write(frames[0])
    assert not target.exists()                           # only a hidden temporary so far
    w.close()
    assert sorted(os.listdir(tmp_path)) == ["A_0.pico"]
    ref = tmp_path.parent / f"{tmp_path.name}_perm_ref"
    ref.write_bytes(b"")                                # same permissions as any new file (umask)
    assert target.stat().st_mode & 0o777 == ref.stat().st_mode & 0o777
    ref.unlink()

    with pytest.raises(RuntimeError):
        with PicoWriter(target, PicoMetadata()) as w:    # replacing: old file survives a failure
            w.write(frames[1])
            raise RuntimeError("capture crashed")
    assert sorted(os.listdir(tmp_path)) == ["A_0.pico"]
    with PicoReader(target) as r:
        assert r.n_frames == 1

    w = PicoWriter(tmp_path / "B_0.pico", PicoMetadata())
    w.write(frames[0])
    w.abort()
    assert sorted(os.listdir(tmp_path)) == ["A_0.pico"]


@pytest.mark.parametrize("bad", [np.zeros((360, 640), np.uint16), np.zeros((360, 640, 3), np.uint8),
                                 np.zeros((100, 640), np.uint8), np.zeros((0, 0), np.uint8)])
def test_writer_rejects_bad_frames(tmp_path: Path, frames: list[np.ndarray], bad: np.ndarray) -> None:
    with PicoWriter(tmp_path / "W_0.pico", PicoMetadata()) as w:
        w.write(frames[0])
        with pytest.raises(ValueError, match=r"W_0\.pico"):
            w.write(bad)


@pytest.mark.parametrize("kw", [{"codec": "h264"}, {"quality": 0}, {"quality": 101}, {"quality": 9.5}])
def test_writer_rejects_bad_options(tmp_path: Path, kw: dict) -> None:
    with pytest.raises(ValueError, match=r"X_0\.pico"):
        PicoWriter(tmp_path / "X_0.pico", PicoMetadata(), **kw)
    with pytest.raises(ValueError, match="does not exist"):
        PicoWriter(tmp_path / "nope" / "X_0.pico", PicoMetadata())


# -- take files ------------------------------------------------------------------------------
def test_take_files_sorted_numerically(tmp_path: Path, frames: list[np.ndarray]) -> None:
    for name in ("TAKE_0.pico", "TAKE_1.pico", "TAKE_10.pico", "TAKE_2.pico", "OTHER_0.pico",
                 "TAKE_x.pico", "TAKE_1.txt", "MY_TAKE_3.pico"):
        (tmp_path / name).write_bytes(b"")
    got = [p.name for p in take_files(tmp_path / "TAKE_2.pico")]
    assert got == ["TAKE_0.pico", "TAKE_1.pico", "TAKE_2.pico", "TAKE_10.pico"]
    assert [p.name for p in take_files(tmp_path / "MY_TAKE_3.pico")] == ["MY_TAKE_3.pico"]
    assert channel_of("a/b/ROM_Day2_12.pico") == ("ROM_Day2", 12)
    with pytest.raises(ValueError, match="_<channel number>"):
        take_files(tmp_path / "TAKE.pico")
