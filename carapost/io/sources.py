"""The common camera-source interface: ``.pico`` files, video files and image folders.

- :class:`FrameSource` is the protocol every source follows (``PicoReader``, ``VideoSource``,
  ``ImageFolderSource`` and :class:`OffsetSource`).
- :func:`open_source` picks the reader by extension (or folder).
- :class:`OffsetSource` applies a camera's frame offset ("Increment Image Sequence Offset")
  and its display rotation.
- :class:`FrameCache` keeps decoded frames (LRU, bounded in bytes) and decodes ahead in a
  background thread for scrubbing.

Pixel coordinates follow the project convention: ``(x, y)`` = (column, row) with the centre
of the top-left pixel at ``(0, 0)``. Detections always refer to the un-rotated image.
"""

from __future__ import annotations

import itertools
import logging
import operator
import os
import threading
from collections import OrderedDict, deque
from collections.abc import Iterable
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from carapost.io.pico import PicoMetadata, PicoReader, _check_index
from carapost.io.video import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, ImageFolderSource, VideoSource

__all__ = ["SourceError", "FrameSource", "open_source", "OffsetSource", "FrameCache",
           "SUPPORTED_EXTENSIONS"]

log = logging.getLogger(__name__)

SUPPORTED_EXTENSIONS = frozenset({".pico"}) | VIDEO_EXTENSIONS


class SourceError(ValueError):
    """A path cannot be opened as a camera source."""


@runtime_checkable
class FrameSource(Protocol):
    """One camera's frames, random access by 0-based frame index.

    Attributes
    ----------
    path : Path
    kind : str
        ``"pico"``, ``"video"`` or ``"images"``.
    n_frames, width, height : int
    frame_rate : float
        Frames per second.
    meta : PicoMetadata
        Capture metadata (synthesised for non-pico sources).
    warnings : list of str
        Problems found while opening (damaged file, missing timestamps, ...).
    """

    path: Path
    kind: str
    n_frames: int
    width: int
    height: int
    frame_rate: float
    meta: PicoMetadata
    warnings: list[str]

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as (height, width) uint8; IndexError outside 0..n_frames-1."""
        ...

    def close(self) -> None:
        ...


def open_source(path: str | os.PathLike, *, frame_rate: float | None = None) -> FrameSource:
    """Open a ``.pico`` file, a video file or an image folder as a :class:`FrameSource`.

    Parameters
    ----------
    path : str or Path
        ``*.pico``; ``*.avi/.mp4/.mov/.mkv/...``; or a folder of png/jpg/tif/bmp images.
    frame_rate : float, optional
        Frame rate of an image folder (default 60); ignored for other sources.

    Raises
    ------
    SourceError (ValueError)
        The path does not exist or is of an unsupported type. Reader errors (``PicoError``,
        ``VideoError``) are ValueErrors too and name the file.
    """
    p = Path(path)
    if p.is_dir():
        return ImageFolderSource(p, frame_rate=60.0 if frame_rate is None else frame_rate)
    if not p.exists():
        raise SourceError(f"{p}: no such file or folder")
    ext = p.suffix.lower()
    if ext == ".pico":
        return PicoReader(p)
    if ext in VIDEO_EXTENSIONS:
        return VideoSource(p)
    if ext in IMAGE_EXTENSIONS:
        raise SourceError(f"{p}: a single image is not a camera source; open the folder that "
                          f"holds the image sequence")
    raise SourceError(f"{p}: unsupported file type {ext or '(no extension)'!r}; expected .pico, "
                      f"{', '.join(sorted(VIDEO_EXTENSIONS))} or a folder of images")


# ------------------------------------------------------------------------------------------
# offset and rotation
# ------------------------------------------------------------------------------------------
class OffsetSource:
    """A source seen through a per-camera frame offset and a display rotation.

    Take frame ``f`` shows source frame ``f + offset``; take frames whose source frame does not
    exist read as black and are reported by :meth:`valid`. :meth:`read` returns the un-rotated
    image (the one detections refer to); only :meth:`read_display` applies ``rotation``.

    Parameters
    ----------
    source : FrameSource
    offset : int
        Source frame shown at take frame 0 ("Increment Image Sequence Offset" adds 1).
    rotation : {0, 90, 180, 270}, optional
        Display rotation, degrees clockwise; default: the source metadata's rotation.
    n_frames : int, optional
        Length of the take (default: the source's frame count).
    """

    def __init__(self, source: FrameSource, offset: int = 0, rotation: int | None = None,
                 n_frames: int | None = None) -> None:
        self.source = source
        self.offset = offset
        self.rotation = source.meta.rotation if rotation is None else rotation
        n = source.n_frames if n_frames is None else n_frames
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"{source.path}: take length must be a whole number >= 0, got {n!r}")
        self.n_frames = int(n)

    # -- forwarded attributes --------------------------------------------------------------
    @property
    def path(self) -> Path:
        return self.source.path

    @property
    def kind(self) -> str:
        return self.source.kind

    @property
    def width(self) -> int:
        return self.source.width

    @property
    def height(self) -> int:
        return self.source.height

    @property
    def frame_rate(self) -> float:
        return self.source.frame_rate

    @property
    def meta(self) -> PicoMetadata:
        return self.source.meta

    @property
    def warnings(self) -> list[str]:
        return self.source.warnings

    # -- offset ----------------------------------------------------------------------------
    @property
    def offset(self) -> int:
        return self._offset

    @offset.setter
    def offset(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{self.source.path}: frame offset must be a whole number, got {value!r}")
        self._offset = int(value)

    def increment_offset(self, step: int = 1) -> None:
        """"Increment Image Sequence Offset": the view moves ``step`` frames forward."""
        self.offset = self._offset + int(step)

    def source_frame(self, frame: int | np.ndarray) -> int | np.ndarray:
        """Source frame index shown at take frame(s) ``frame`` (may be out of the source)."""
        return frame + self._offset

    def valid(self, frame: int | np.ndarray) -> bool | np.ndarray:
        """True where take frame(s) ``frame`` show a real source frame (vectorised)."""
        s = np.asarray(frame) + self._offset
        ok = (s >= 0) & (s < self.source.n_frames)
        return bool(ok) if ok.ndim == 0 else ok

    # -- rotation --------------------------------------------------------------------------
    @property
    def rotation(self) -> int:
        return self._rotation

    @rotation.setter
    def rotation(self, value: int) -> None:
        if isinstance(value, bool) or value not in (0, 90, 180, 270):
            raise ValueError(f"{self.source.path}: rotation must be 0, 90, 180 or 270, got {value!r}")
        self._rotation = int(value)

    def rotate_clockwise(self, quarter_turns: int = 1) -> None:
        """Rotate the display by ``quarter_turns`` x 90 degrees clockwise (negative: anticlockwise)."""
        self.rotation = (self._rotation + 90 * int(quarter_turns)) % 360

    @property
    def display_size(self) -> tuple[int, int]:
        """(width, height) of the rotated display image."""
        return (self.height, self.width) if self._rotation in (90, 270) else (self.width, self.height)

    def image_to_display(self, xy: np.ndarray) -> np.ndarray:
        """Map image pixel coordinates (..., 2) to display coordinates (same shape, float64)."""
        xy = np.asarray(xy, dtype=np.float64)
        x, y = xy[..., 0], xy[..., 1]
        w1, h1 = self.width - 1, self.height - 1
        r = self._rotation
        out = (np.stack([x, y], -1) if r == 0 else np.stack([h1 - y, x], -1) if r == 90 else
               np.stack([w1 - x, h1 - y], -1) if r == 180 else np.stack([y, w1 - x], -1))
        return out

    def display_to_image(self, xy: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`image_to_display`."""
        xy = np.asarray(xy, dtype=np.float64)
        u, v = xy[..., 0], xy[..., 1]
        w1, h1 = self.width - 1, self.height - 1
        r = self._rotation
        return (np.stack([u, v], -1) if r == 0 else np.stack([v, h1 - u], -1) if r == 90 else
                np.stack([w1 - u, h1 - v], -1) if r == 180 else np.stack([w1 - v, u], -1))

    # -- reading ---------------------------------------------------------------------------
    def read(self, index: int) -> np.ndarray:
        """Take frame ``index``: (height, width) uint8, black where :meth:`valid` is False.

        Raises
        ------
        IndexError
            ``index`` outside the take, ``0 .. n_frames-1``.
        """
        f = _check_index(index, self.n_frames, self.path)
        s = f + self._offset
        if not 0 <= s < self.source.n_frames:
            return np.zeros((self.height, self.width), np.uint8)
        return self.source.read(s)

    def read_display(self, index: int) -> np.ndarray:
        """Take frame ``index`` rotated for display: (H, W) or (W, H) uint8, C-contiguous."""
        img = self.read(index)
        if self._rotation == 0:
            return img
        return np.ascontiguousarray(np.rot90(img, k=-(self._rotation // 90)))

    def close(self) -> None:
        self.source.close()

    def __repr__(self) -> str:
        return f"OffsetSource({self.source!r}, offset={self._offset}, rotation={self._rotation})"


# ------------------------------------------------------------------------------------------
# cache
# ------------------------------------------------------------------------------------------
class FrameCache:
    """LRU cache of one source's decoded frames, bounded in bytes, with background prefetch.

    Cached frames are returned read-only (they are shared). Decoding happens outside the
    cache's lock; a frame being decoded by the prefetch thread is waited for, not decoded
    twice.

    Parameters
    ----------
    source : FrameSource
    max_bytes : int
        Upper bound of the cached pixel data (the newest frame is always kept).
    """

    def __init__(self, source: FrameSource, *, max_bytes: int = 512 * 2**20) -> None:
        if max_bytes <= 0:
            raise ValueError(f"{source.path}: cache size must be > 0 bytes, got {max_bytes!r}")
        self.source = source
        self.max_bytes = int(max_bytes)
        self._frames: OrderedDict[int, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._inflight: dict[int, threading.Event] = {}
        self._queue: deque[int] = deque()
        self._thread: threading.Thread | None = None
        self._busy = False
        self._stop = False
        self.hits = self.misses = 0

    @property
    def nbytes(self) -> int:
        """Bytes of pixel data currently cached."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, frame: object) -> bool:
        with self._lock:
            return frame in self._frames

    def get(self, frame: int) -> np.ndarray:
        """Frame ``frame`` of the source (cached, read-only); errors as the source's ``read``."""
        frame = operator.index(frame)
        with self._lock:
            img = self._frames.get(frame)
            if img is not None:
                self._frames.move_to_end(frame)
                self.hits += 1
                return img
            self.misses += 1
        return self._load(frame)

    def _load(self, frame: int) -> np.ndarray:
        with self._lock:
            while True:
                img = self._frames.get(frame)
                if img is not None:
                    return img
                ev = self._inflight.get(frame)
                if ev is None:
                    ev = self._inflight[frame] = threading.Event()
                    break
                self._lock.release()
                try:
                    ev.wait()
                finally:
                    self._lock.acquire()
        try:
            img = self.source.read(frame)
            if not img.flags.owndata:             # never freeze (or keep alive) someone else's buffer
                img = img.copy()
            img.setflags(write=False)
            with self._lock:
                self._put(frame, img)
            return img
        finally:
            with self._lock:
                self._inflight.pop(frame, None)
            ev.set()

    def _put(self, frame: int, img: np.ndarray) -> None:
        if frame in self._frames:
            self._bytes -= self._frames.pop(frame).nbytes
        self._frames[frame] = img
        self._bytes += img.nbytes
        while self._bytes > self.max_bytes and len(self._frames) > 1:
            _, old = self._frames.popitem(last=False)
            self._bytes -= old.nbytes

    def prefetch(self, frames: Iterable[int]) -> None:
        """Decode ``frames`` ahead, in order, in a background thread.

        Replaces any pending request (the newest scrub position wins). Only as many frames as
        fit in ``max_bytes`` are queued; frames outside the source are ignored.
        """
        per_frame = max(1, self.source.width * self.source.height)
        room = max(1, self.max_bytes // per_frame)
        n = self.source.n_frames
        todo = list(itertools.islice((int(f) for f in frames if 0 <= int(f) < n), room))
        with self._lock:
            if self._stop:
                raise ValueError(f"{self.source.path}: frame cache is closed")
            self._queue.clear()
            self._queue.extend(todo)
            if self._thread is None:
                self._thread = threading.Thread(target=self._worker, name="carapost-prefetch",
                                                daemon=True)
                self._thread.start()
            self._wake.notify_all()

    def _worker(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._stop:
                    self._busy = False
                    self._wake.notify_all()
                    self._wake.wait()
                if self._stop:
                    self._busy = False
                    self._wake.notify_all()
                    return
                frame = self._queue.popleft()
                self._busy = True
                if frame in self._frames:
                    continue
            try:
                self._load(frame)
            except Exception as exc:          # a damaged frame must not kill the prefetcher
                log.warning("%s: prefetch of frame %d failed: %s", self.source.path, frame, exc)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the prefetch queue is drained; False on timeout."""
        with self._lock:
            return self._wake.wait_for(lambda: not self._queue and not self._busy, timeout)

    def clear(self) -> None:
        """Drop every cached frame and any pending prefetch."""
        with self._lock:
            self._queue.clear()
            self._frames.clear()
            self._bytes = 0

    def close(self) -> None:
        """Stop the prefetch thread and drop the cache (the source stays open)."""
        with self._lock:
            self._stop = True
            self._queue.clear()
            self._wake.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout=10)
        self.clear()

    def __enter__(self) -> "FrameCache":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
