"""The common source interface: open_source, OffsetSource, FrameCache, and conversion to .pico."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from carapost.io.convert import convert_to_pico
from carapost.io.pico import PicoError, PicoMetadata, PicoReader, PicoWriter, take_files
from carapost.io.sources import FrameCache, FrameSource, OffsetSource, SourceError, open_source
from carapost.io.video import VideoSource

W, H = 48, 32


def frame(k: int, w: int = W, h: int = H) -> np.ndarray:
    """A frame whose pixels are all distinct functions of (k, x, y)."""
    yy, xx = np.mgrid[0:h, 0:w]
    return ((xx * 3 + yy * 7 + k * 11) % 251).astype(np.uint8)


class CountingSource:
    """A FrameSource in memory that counts its reads (optionally slow, optionally broken)."""

    kind = "images"

    def __init__(self, n: int = 20, delay: float = 0.0, broken: tuple[int, ...] = ()) -> None:
        self.path = Path("/virtual/counting")
        self.n_frames, self.width, self.height, self.frame_rate = n, W, H, 30.0
        self.meta = PicoMetadata(camera_name="counting", width=W, height=H, rotation=90)
        self.warnings: list[str] = []
        self.reads: list[int] = []
        self.delay, self.broken = delay, broken
        self._lock = threading.Lock()

    def read(self, index: int) -> np.ndarray:
        if not 0 <= index < self.n_frames:
            raise IndexError(index)
        with self._lock:
            self.reads.append(index)
        if self.delay:
            time.sleep(self.delay)
        if index in self.broken:
            raise PicoError(f"{self.path}: frame {index} is corrupt (CRC mismatch)")
        return frame(index)

    def close(self) -> None:
        pass


def make_pico(path: Path, n: int = 6, **kw) -> Path:
    with PicoWriter(path, PicoMetadata(camera_name=path.stem), codec="lossless", **kw) as w:
        for k in range(n):
            w.write(frame(k))
    return path


# -- open_source --------------------------------------------------------------------------------
def test_open_source_dispatches_by_kind(tmp_path: Path) -> None:
    pico = make_pico(tmp_path / "T_0.pico")
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(3):
        cv2.imwrite(str(folder / f"f{k}.png"), frame(k))
    for path, kind, n in ((pico, "pico", 6), (folder, "images", 3)):
        src = open_source(path)
        try:
            assert isinstance(src, FrameSource) and src.kind == kind and src.n_frames == n
            assert (src.width, src.height) == (W, H) and src.meta.width == W
            np.testing.assert_array_equal(src.read(1), frame(1))
            with pytest.raises(IndexError):
                src.read(n)
        finally:
            src.close()
    assert isinstance(OffsetSource(CountingSource()), FrameSource)


def test_open_source_video(real_data: Path) -> None:
    path = real_data / "pose2sim-demo" / "videos" / "cam02.mp4"
    if not path.exists():
        pytest.skip("pose2sim demo videos not present")
    with open_source(path) as src:                         # type: ignore[attr-defined]
        assert isinstance(src, VideoSource) and src.kind == "video" and src.n_frames == 100


def test_open_source_errors_name_the_file(tmp_path: Path) -> None:
    (tmp_path / "calib.xcp").write_text("<Cameras/>")
    cv2.imwrite(str(tmp_path / "one.png"), frame(0))
    with pytest.raises(SourceError, match=r"calib\.xcp: unsupported file type '\.xcp'"):
        open_source(tmp_path / "calib.xcp")
    with pytest.raises(SourceError, match=r"one\.png: a single image"):
        open_source(tmp_path / "one.png")
    with pytest.raises(SourceError, match=r"nothing\.mp4: no such file"):
        open_source(tmp_path / "nothing.mp4")
    (tmp_path / "bad_0.pico").write_text("garbage")
    with pytest.raises(ValueError, match=r"bad_0\.pico: not a \.pico file"):
        open_source(tmp_path / "bad_0.pico")


# -- OffsetSource -------------------------------------------------------------------------------
def test_offset_maps_take_frames_to_source_frames() -> None:
    src = CountingSource(n=10)
    view = OffsetSource(src, offset=3)
    assert view.rotation == 90                                # from the source metadata
    assert view.n_frames == 10 and view.valid(0) is True and view.valid(7) is False
    np.testing.assert_array_equal(view.read(2), frame(5))
    black = view.read(8)                                      # source frame 11 does not exist
    assert black.shape == (H, W) and not black.any()
    np.testing.assert_array_equal(view.valid(np.arange(10)), np.arange(10) < 7)
    view.increment_offset()                                   # "Increment Image Sequence Offset"
    assert view.offset == 4 and view.source_frame(2) == 6
    np.testing.assert_array_equal(view.read(2), frame(6))
    view.offset = -2
    assert not view.read(1).any() and not view.valid(1)
    np.testing.assert_array_equal(view.read(2), frame(0))
    with pytest.raises(IndexError):
        view.read(10)
    with pytest.raises(ValueError, match="offset"):
        view.offset = 1.5                                     # type: ignore[assignment]
    assert 11 not in src.reads and -1 not in src.reads        # black frames never hit the source


@pytest.mark.parametrize("rotation", [0, 90, 180, 270])
def test_rotation_only_affects_display(rotation: int) -> None:
    view = OffsetSource(CountingSource(), rotation=rotation)
    raw, disp = view.read(4), view.read_display(4)
    np.testing.assert_array_equal(raw, frame(4))              # detections' pixels: un-rotated
    np.testing.assert_array_equal(disp, np.rot90(raw, k=-rotation // 90))
    assert disp.shape[::-1] == view.display_size
    if rotation == 90:                                        # clockwise: top-left goes top-right
        assert disp[0, -1] == raw[0, 0]
    ys, xs = np.mgrid[0:H, 0:W]
    xy = np.stack([xs.ravel(), ys.ravel()], -1)
    uv = view.image_to_display(xy).astype(int)
    np.testing.assert_array_equal(disp[uv[:, 1], uv[:, 0]], raw[xy[:, 1], xy[:, 0]])
    pts = np.array([[0.25, 3.5], [40.0, 1.0]])
    np.testing.assert_allclose(view.display_to_image(view.image_to_display(pts)), pts)


def test_rotate_clockwise_and_validation() -> None:
    view = OffsetSource(CountingSource(), rotation=0)
    view.rotate_clockwise()
    view.rotate_clockwise()
    view.rotate_clockwise(-3)
    assert view.rotation == 270
    with pytest.raises(ValueError, match="rotation"):
        view.rotation = 45


# -- FrameCache ---------------------------------------------------------------------------------
def test_cache_hits_and_read_only_frames() -> None:
    src = CountingSource()
    with FrameCache(src) as cache:
        a = cache.get(3)
        b = cache.get(3)
        assert a is b and src.reads == [3] and (cache.hits, cache.misses) == (1, 1)
        np.testing.assert_array_equal(a, frame(3))
        with pytest.raises(ValueError):
            a[0, 0] = 1                                       # shared frames are read-only
        assert 3 in cache and 4 not in cache


def test_cache_is_bounded_in_bytes_lru() -> None:
    src = CountingSource()
    with FrameCache(src, max_bytes=3 * W * H) as cache:
        for k in (0, 1, 2, 0, 3):                             # 0 is used again: 1 is the oldest
            cache.get(k)
        assert len(cache) == 3 and cache.nbytes == 3 * W * H
        assert 1 not in cache and all(k in cache for k in (0, 2, 3))


def test_prefetch_decodes_ahead_in_background() -> None:
    src = CountingSource(n=40, delay=0.002)
    with FrameCache(src) as cache:
        cache.prefetch(range(10, 30))
        assert cache.wait(timeout=10)
        assert sorted(src.reads) == list(range(10, 30))
        for k in range(10, 30):
            np.testing.assert_array_equal(cache.get(k), frame(k))
        assert src.reads.count(15) == 1 and cache.hits == 20
        cache.prefetch([5, 6, 99, -1])                        # out-of-range frames are ignored
        assert cache.wait(timeout=10) and 5 in cache and 6 in cache


def test_prefetch_is_replaced_and_bounded() -> None:
    src = CountingSource(n=200, delay=0.003)
    with FrameCache(src, max_bytes=10 * W * H) as cache:
        cache.prefetch(range(0, 200))                         # more than fits: only 10 queued
        cache.prefetch(range(100, 200))                       # the newest request wins
        assert cache.wait(timeout=10)
        assert len(src.reads) <= 12 and all(k in cache for k in range(100, 110))


def test_prefetch_survives_broken_frames_and_get_reports_them() -> None:
    src = CountingSource(broken=(2,))
    with FrameCache(src) as cache:
        cache.prefetch([1, 2, 3])
        assert cache.wait(timeout=10) and 1 in cache and 3 in cache and 2 not in cache
        with pytest.raises(PicoError, match="frame 2"):
            cache.get(2)


def test_concurrent_get_and_prefetch_decode_once() -> None:
    src = CountingSource(n=30, delay=0.005)
    with FrameCache(src) as cache:
        cache.prefetch(range(30))
        got = [cache.get(k) for k in range(30)]
        assert cache.wait(timeout=10)
    for k, img in enumerate(got):
        np.testing.assert_array_equal(img, frame(k))
    assert sorted(src.reads) == list(range(30))               # never decoded twice


def test_closed_cache_stops_its_thread() -> None:
    cache = FrameCache(CountingSource())
    cache.prefetch([1])
    cache.wait(timeout=10)
    thread = cache._thread
    cache.close()
    assert thread is not None and not thread.is_alive() and len(cache) == 0
    with pytest.raises(ValueError, match="closed"):
        cache.prefetch([2])


# -- conversion ---------------------------------------------------------------------------------
def test_convert_real_mp4_to_pico(real_data: Path, tmp_path: Path) -> None:
    mp4 = real_data / "pose2sim-demo" / "videos" / "cam02.mp4"
    if not mp4.exists():
        pytest.skip("pose2sim demo videos not present")
    calls: list[tuple[int, int]] = []
    out = convert_to_pico([mp4], tmp_path, "DEMO", max_frames=20, progress=lambda d, t: calls.append((d, t)),
                          metadata={"logger_name": "lab", "start_timecode": "01:00:00:00"})
    assert out == [tmp_path / "DEMO_0.pico"] and calls[-1] == (20, 20) and len(calls) == 20
    with PicoReader(out[0]) as r, VideoSource(mp4) as v:
        assert (r.n_frames, r.width, r.height, r.frame_rate) == (20, 1080, 1920, 60.0)
        m = r.meta
        assert (m.camera_name, m.channel, m.logger_name, m.start_timecode) == ("cam02", 0, "lab", "01:00:00:00")
        assert m.extra["source_kind"] == "video" and m.extra["source_path"].endswith("cam02.mp4")
        for i in (0, 7, 19):
            a, b = r.read(i).astype(np.float64), v.read(i)
            psnr = 10 * np.log10(255**2 / np.mean((a - b) ** 2))
            assert psnr > 40.0


def folder_source(path: Path, n: int, shift: int = 0) -> Path:
    path.mkdir()
    for k in range(n):
        cv2.imwrite(str(path / f"img_{k}.png"), frame(k + shift))
    return path


def test_convert_with_offsets_lossless(tmp_path: Path) -> None:
    a = folder_source(tmp_path / "a", 10)
    b = folder_source(tmp_path / "b", 12)
    out = convert_to_pico([a, b], tmp_path / "out", "TAKE", codec="lossless", frame_offsets=[0, 3])
    assert [p.name for p in out] == ["TAKE_0.pico", "TAKE_1.pico"]
    assert take_files(out[1]) == out
    with PicoReader(out[0]) as r0, PicoReader(out[1]) as r1:
        assert r0.n_frames == r1.n_frames == 9                # min(10 - 0, 12 - 3)
        assert r1.meta.channel == 1 and r1.meta.extra["source_offset"] == 3
        for f in range(9):
            np.testing.assert_array_equal(r0.read(f), frame(f))
            np.testing.assert_array_equal(r1.read(f), frame(f + 3))
    out = convert_to_pico([a, b], tmp_path / "neg", "N", codec="lossless", frame_offsets=[0, -2], max_frames=5)
    with PicoReader(out[1]) as r1:
        assert r1.n_frames == 5 and not r1.read(1).any()     # black before the source starts
        np.testing.assert_array_equal(r1.read(2), frame(0))


def test_convert_cancel_keeps_finished_files_only(tmp_path: Path) -> None:
    srcs = [folder_source(tmp_path / f"s{c}", 8) for c in range(3)]
    done: list[int] = []
    out = convert_to_pico(srcs, tmp_path / "out", "TAKE", progress=lambda d, t: done.append(d),
                          cancel=lambda: len(done) >= 11)    # stops inside the second camera
    assert out == [tmp_path / "out" / "TAKE_0.pico"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["TAKE_0.pico"]   # no .part left
    with PicoReader(out[0]) as r:
        assert r.n_frames == 8 and r.warnings == []


def test_convert_errors(tmp_path: Path) -> None:
    a = folder_source(tmp_path / "a", 4)
    with pytest.raises(ValueError, match="no sources"):
        convert_to_pico([], tmp_path, "T")
    with pytest.raises(ValueError, match="2 frame offsets for 1 sources"):
        convert_to_pico([a], tmp_path, "T", frame_offsets=[0, 1])
    with pytest.raises(ValueError, match="share no frames"):
        convert_to_pico([a], tmp_path, "T", frame_offsets=[4])
    with pytest.raises(ValueError, match="invalid take name"):
        convert_to_pico([a], tmp_path, "a/b")
    with pytest.raises(ValueError, match="cannot set channel"):
        convert_to_pico([a], tmp_path, "T", metadata={"channel": 3})
    with pytest.raises(ValueError, match=r"missing\.avi"):
        convert_to_pico([a, tmp_path / "missing.avi"], tmp_path, "T")
    assert not list(tmp_path.glob("T_*"))
