"""Ordinary video files and image folders as frame-exact, random-access camera sources.

Video (AVI, MP4, MOV, MKV, ...) is read with PyAV (FFmpeg). On open the whole stream is
demuxed *and decoded once* (no colour conversion) to build an index: the presentation
timestamp (PTS) of every frame that actually decodes, in display order, and the PTS of every
keyframe packet. The frame count is therefore the number of decodable frames, never the
container's claim. Frame ``i`` is then read by seeking to the last keyframe at or before
``pts[i]`` and decoding forward until the frame whose PTS is ``pts[i]`` comes out; reads that
move forward within reach continue decoding without seeking. This gives the same pixels as a
sequential decode (tested on real H.264 and VP9 files). Streams without usable timestamps fall
back to counting frames from the start. ``verify=False`` builds the index from the demuxed
packets alone (fast for long videos). See ``docs/formats/pico.md`` ("Sources").

Image folders (png/jpg/tif/bmp) are sorted naturally (``img_10`` after ``img_9``).

Colour input is converted to 8-bit grayscale: FFmpeg's ``gray`` conversion (full-range luma)
for video, OpenCV's ``IMREAD_GRAYSCALE`` for images.
"""

from __future__ import annotations

import bisect
import logging
import math
import os
import re
import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from carapost.io.pico import PicoMetadata, _check_index

__all__ = ["VIDEO_EXTENSIONS", "IMAGE_EXTENSIONS", "VideoError", "VideoSource",
           "ImageFolderSource", "natural_key", "image_files"]

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = frozenset({".avi", ".mp4", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm", ".wmv"})
IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp"})


class VideoError(ValueError):
    """A video file or image folder cannot be used as a camera source."""


def natural_key(name: str) -> list[Any]:
    """Sort key that orders digit runs numerically: ``img_9`` < ``img_10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _display_rotation_cw(ccw_degrees: float) -> int:
    """FFmpeg's display-matrix angle (counter-clockwise) as our clockwise 0/90/180/270."""
    return int(round(-ccw_degrees / 90.0)) % 4 * 90


# ------------------------------------------------------------------------------------------
# video
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _VideoIndex:
    pts: tuple[int, ...]          # presentation time stamps in display order (empty if unusable)
    key_pts: tuple[int, ...]      # sorted PTS of keyframe packets
    n_frames: int
    width: int
    height: int
    frame_rate: float
    rotation: int
    codec: str
    warnings: tuple[str, ...]
    verified: bool                # frame list from decoding (True) or from packets (False)


_INDEX_CACHE: OrderedDict[tuple[str, int, int, bool], _VideoIndex] = OrderedDict()
_INDEX_CACHE_SIZE = 64
_INDEX_CACHE_LOCK = threading.Lock()


def _import_av() -> Any:
    try:
        import av
    except ImportError:                                   # pragma: no cover
        raise VideoError("reading video files needs PyAV: pip install av") from None
    return av


class VideoSource:
    """A video file as a frame-exact random-access source (kind ``"video"``).

    Parameters
    ----------
    path : str or Path
        The video file.
    verify : bool
        True (default): decode the whole stream once on open, so the frame list is exactly the
        frames that decode. False: list frames from the demuxed packets only (one frame per
        packet; much faster to open a long video, but a frame that fails to decode is only
        found when it is read).

    Attributes
    ----------
    n_frames : int
        Number of frames that decode (verified by decoding the whole stream once on open,
        unless ``verify=False``); never the container header's claim.
    width, height : int
        Image size in pixels.
    frame_rate : float
        Frames per second (container's average rate; from the timestamps if absent).
    meta : PicoMetadata
        Synthesised: camera name = file stem, rotation from the display matrix.
    warnings : list of str
        Problems met while indexing (undecodable packets, missing timestamps).

    Notes
    -----
    ``read`` is thread-safe (calls are serialised on one decoder); for parallel decoding open
    one source per thread. The index is cached in memory per (path, size, mtime), so reopening
    the same file is cheap.
    """

    kind = "video"

    def __init__(self, path: str | os.PathLike, *, verify: bool = True) -> None:
        self.path = Path(path)
        self._av = _import_av()
        if not self.path.is_file():
            raise VideoError(f"{self.path}: no such video file")
        self._lock = threading.RLock()
        self._container: Any = None
        self._frames: Iterator[Any] | None = None
        self._last_pts: int | None = None      # PTS of the last frame returned (None: decoder not positioned)
        self._last_index = -2                  # its frame index
        self._ordinal = -1                     # counting mode: ordinal of last decoded frame
        st = self.path.stat()
        file_id = (str(self.path.resolve()), st.st_size, st.st_mtime_ns)
        key = (*file_id, verify)
        with _INDEX_CACHE_LOCK:
            idx = _INDEX_CACHE.get((*file_id, True)) or _INDEX_CACHE.get(key)   # verified serves both
            if idx is not None:
                _INDEX_CACHE.move_to_end((*file_id, idx.verified))
        if idx is None:
            idx = self._build_index(verify)
            with _INDEX_CACHE_LOCK:
                _INDEX_CACHE[key] = idx
                while len(_INDEX_CACHE) > _INDEX_CACHE_SIZE:
                    _INDEX_CACHE.popitem(last=False)
        self._idx = idx
        self.n_frames, self.width, self.height = idx.n_frames, idx.width, idx.height
        self.frame_rate = idx.frame_rate
        self.warnings = list(idx.warnings)
        for w in self.warnings:
            log.warning("%s: %s", self.path, w)
        self.meta = PicoMetadata(camera_name=self.path.stem, frame_rate=self.frame_rate,
                                 width=self.width, height=self.height, rotation=idx.rotation,
                                 extra={"source_path": str(self.path), "source_kind": "video",
                                        "source_codec": idx.codec})

    # -- index -------------------------------------------------------------------------------
    def _open_container(self) -> tuple[Any, Any]:
        av = self._av
        try:
            container = av.open(str(self.path), mode="r")
        except (av.FFmpegError, OSError, UnicodeDecodeError) as exc:
            raise VideoError(f"{self.path}: not a readable video file ({exc})") from None
        if not container.streams.video:
            container.close()
            raise VideoError(f"{self.path}: the file has no video stream")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        return container, stream

    def _decoded(self, container: Any, stream: Any, warn: list[str] | None) -> Iterator[Any]:
        """Decoded frames of ``stream`` from the container's current position."""
        av = self._av
        for packet in container.demux(stream):
            try:
                frames = packet.decode()
            except av.FFmpegError as exc:
                if warn is not None:
                    warn.append(f"undecodable packet at pts {packet.pts} skipped ({exc})")
                continue
            yield from frames

    def _build_index(self, verify: bool) -> _VideoIndex:
        av = self._av
        container, stream = self._open_container()
        warn: list[str] = []
        pts: list[int | None] = []
        key_pts: list[int] = []
        width = height = 0
        rotation = 0
        try:
            for packet in container.demux(stream):
                if packet.is_keyframe and packet.pts is not None:
                    key_pts.append(packet.pts)
                if not verify:
                    if packet.size:
                        pts.append(packet.pts)                 # one frame per packet, unverified
                    if width:
                        continue                               # size known: no more decoding
                try:
                    frames = packet.decode()
                except av.FFmpegError as exc:
                    warn.append(f"undecodable packet at pts {packet.pts} skipped ({exc})")
                    continue
                for fr in frames:
                    if not width:
                        width, height = fr.width, fr.height
                        rotation = _display_rotation_cw(fr.rotation)
                    if verify:
                        pts.append(fr.pts)
            if not verify:
                pts.sort(key=lambda p: -1 if p is None else p)  # display order
            codec = stream.codec_context.name
            rate = stream.average_rate or stream.guessed_rate
            time_base = stream.time_base
        except av.FFmpegError as exc:
            raise VideoError(f"{self.path}: cannot decode the video ({exc})") from None
        finally:
            container.close()
        if not pts or not width:
            raise VideoError(f"{self.path}: no decodable video frames")
        known = [p for p in pts if p is not None]
        exact = len(known) == len(pts) and all(b > a for a, b in zip(known, known[1:]))
        if not exact:
            warn.append("frame timestamps are missing or not increasing: random access decodes "
                        "from the start of the file (slow)")
        if rate:
            frame_rate = float(rate)
        elif exact and len(known) > 1 and time_base:
            frame_rate = float((len(known) - 1) / ((known[-1] - known[0]) * Fraction(time_base)))
        else:
            frame_rate = 0.0
        if not (math.isfinite(frame_rate) and frame_rate > 0):
            warn.append("frame rate unknown; assuming 60 fps")
            frame_rate = 60.0
        return _VideoIndex(pts=tuple(known) if exact else (), key_pts=tuple(sorted(set(key_pts))),
                           n_frames=len(pts), width=width, height=height, frame_rate=frame_rate,
                           rotation=rotation, codec=codec, warnings=tuple(warn), verified=verify)

    # -- reading -----------------------------------------------------------------------------
    def _drop_decoder(self) -> None:
        if self._frames is not None:
            self._frames.close()                                   # type: ignore[attr-defined]
            self._frames = None
        self._last_pts = None

    def _restart(self, seek_pts: int | None) -> None:
        """(Re)position the decoder at the keyframe at or before ``seek_pts`` (None = start)."""
        self._drop_decoder()
        if seek_pts is None and self._container is not None:   # from the start: a fresh demuxer
            self._container.close()
            self._container = None
        if self._container is None:
            self._container, self._stream = self._open_container()
        if seek_pts is not None:
            self._container.seek(seek_pts, stream=self._stream, backward=True, any_frame=False)
        self._frames = self._decoded(self._container, self._stream, None)
        self._last_pts = None
        self._ordinal = -1

    def _gray(self, frame: Any) -> np.ndarray:
        img = frame.to_ndarray(format="gray")
        if img.shape != (self.height, self.width):
            raise VideoError(f"{self.path}: frame size changed mid-stream "
                             f"({img.shape[1]}x{img.shape[0]}, expected {self.width}x{self.height})")
        return np.ascontiguousarray(img)

    def read(self, index: int) -> np.ndarray:
        """Decode frame ``index`` (0-based, display order).

        Returns
        -------
        ndarray, shape (height, width), uint8

        Raises
        ------
        IndexError
            ``index`` outside ``0 .. n_frames-1``.
        VideoError
            The frame could not be reached by decoding.
        """
        i = _check_index(index, self.n_frames, self.path)
        with self._lock:
            if self._idx.pts:
                return self._read_by_pts(i)
            return self._read_by_count(i)

    def _read_by_pts(self, i: int) -> np.ndarray:
        target = self._idx.pts[i]
        keys = self._idx.key_pts
        k = bisect.bisect_right(keys, target) - 1          # last keyframe at or before the target
        last = self._last_pts
        # (seek?, keyframe pts or None = from the start). Continue decoding when no keyframe lies
        # between the last frame returned and the target. Seeking goes to the keyframe at or before
        # the target; a demuxer that seeks by DTS can land one keyframe too late, so retry one
        # keyframe earlier, then from the very start.
        plan: list[tuple[bool, int | None]] = []
        if (self._frames is not None and last is not None and last < target
                and (k < 0 or keys[k] <= last or i == self._last_index + 1)):
            plan.append((False, None))
        plan += [(True, keys[j]) for j in (k, k - 1) if j >= 0] + [(True, None)]
        for seek, start in plan:
            if seek:
                try:
                    self._restart(start)
                except self._av.FFmpegError:
                    continue
            assert self._frames is not None
            for fr in self._frames:
                if fr.pts is None:
                    continue
                if fr.pts == target:
                    self._last_pts, self._last_index = fr.pts, i
                    return self._gray(fr)
                if fr.pts > target:
                    break
            self._last_pts = None                           # overshot or ran out: start earlier
        self._drop_decoder()
        raise VideoError(f"{self.path}: frame {i} (pts {target}) could not be decoded")

    def _read_by_count(self, i: int) -> np.ndarray:
        if self._frames is None or self._ordinal >= i:
            self._restart(None)
        assert self._frames is not None
        for fr in self._frames:
            self._ordinal += 1
            if self._ordinal == i:
                return self._gray(fr)
        self._drop_decoder()
        raise VideoError(f"{self.path}: frame {i} could not be decoded")

    def close(self) -> None:
        with self._lock:
            self._drop_decoder()
            if self._container is not None:
                self._container.close()
                self._container = None

    def __enter__(self) -> "VideoSource":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return f"VideoSource({str(self.path)!r}, n_frames={self.n_frames}, {self.width}x{self.height})"


# ------------------------------------------------------------------------------------------
# image folders
# ------------------------------------------------------------------------------------------
def image_files(folder: str | os.PathLike) -> list[Path]:
    """Image files (png/jpg/jpeg/tif/tiff/bmp) directly in ``folder``, naturally sorted."""
    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file()]
    return sorted(files, key=lambda p: (natural_key(p.name), p.name))


def _imread_gray(path: Path) -> np.ndarray | None:
    try:
        buf = np.fromfile(path, np.uint8)               # works with non-ASCII paths on Windows
    except OSError:
        return None
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if buf.size else None


class ImageFolderSource:
    """A folder of still images as a camera source (kind ``"images"``).

    Parameters
    ----------
    path : str or Path
        The folder; its png/jpg/tif/bmp files in natural order are the frames.
    frame_rate : float
        Frames per second to report (images carry none).

    Notes
    -----
    The frame count is the number of image files; the first image is decoded on open for the
    size, and every frame is checked on read (a file that does not decode, or has another size,
    raises :class:`VideoError` naming it). Thread-safe.
    """

    kind = "images"

    def __init__(self, path: str | os.PathLike, *, frame_rate: float = 60.0) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise VideoError(f"{self.path}: not a folder")
        self.files = image_files(self.path)
        if not self.files:
            raise VideoError(f"{self.path}: the folder contains no png/jpg/tif/bmp images")
        first = _imread_gray(self.files[0])
        if first is None:
            raise VideoError(f"{self.files[0]}: not a readable image")
        self.height, self.width = first.shape
        self.n_frames = len(self.files)
        self.frame_rate = float(frame_rate)
        self.warnings: list[str] = []
        self.meta = PicoMetadata(camera_name=self.path.name, frame_rate=self.frame_rate,
                                 width=self.width, height=self.height,
                                 extra={"source_path": str(self.path), "source_kind": "images"})

    def read(self, index: int) -> np.ndarray:
        """Decode frame ``index``: (height, width) uint8. IndexError outside the range."""
        i = _check_index(index, self.n_frames, self.path)
        f = self.files[i]
        img = _imread_gray(f)
        if img is None:
            raise VideoError(f"{f}: not a readable image (frame {i})")
        if img.shape != (self.height, self.width):
            raise VideoError(f"{f}: image is {img.shape[1]}x{img.shape[0]}, but the folder's first "
                             f"image is {self.width}x{self.height} (frame {i})")
        return img

    def close(self) -> None:
        return None

    def __enter__(self) -> "ImageFolderSource":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return f"ImageFolderSource({str(self.path)!r}, n_frames={self.n_frames}, {self.width}x{self.height})"

