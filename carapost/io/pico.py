"""The ``.pico`` container: one camera's 8-bit grayscale frames plus capture metadata.

The byte layout is specified in ``docs/formats/pico.md``; in short (all integers little-endian)::

    file header   MAGIC(8) major:u16 minor:u16 flags:u32 json_len:u32 json_crc:u32  + JSON
    frame record  "PFRM" frame:u32 length:u32 crc:u32 codec:u8 pad:3 head_crc:u32  + payload
    ...           (one record per frame, in frame order)
    index         "PIDX" n:u32  n x (record_offset:u64 length:u32 crc:u32)  entries_crc:u32
    footer meta   "PMET" json_len:u32 json_crc:u32  + JSON
    trailer       "PEND" major:u32 index_offset:u64 meta_offset:u64 n:u32 trailer_crc:u32

Random access reads one record with a single ``os.pread`` through the index. A file without a
valid trailer/index (capture interrupted, file truncated) is re-scanned record by record; every
intact frame stays readable and the problem is reported in :attr:`PicoReader.warnings`.
"""

from __future__ import annotations

import logging
import mmap
import operator
import os
import secrets
import struct
import threading
import zlib
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from carapost.io.pico_meta import (
    PICO_VERSION,
    PicoMetadata,
    meta_from_json,
    meta_to_json,
)

__all__ = [
    "PICO_VERSION",
    "PicoError",
    "PicoMetadata",
    "PicoWriter",
    "PicoReader",
    "take_files",
    "take_name",
    "find_calibration",
    "CALIBRATION_EXTENSIONS",
    "channel_of",
    "update_metadata",
]

log = logging.getLogger(__name__)

MAGIC = b"\x89PICO\r\n\x1a"
_FILE_HEAD = struct.Struct("<8sHHIII")          # magic, major, minor, flags, json_len, json_crc
_REC_HEAD = struct.Struct("<4sIIIB3xI")          # magic, frame, length, crc, codec, head_crc
_REC_HEAD_CRC_SPAN = _REC_HEAD.size - 4
_IDX_HEAD = struct.Struct("<4sI")
_META_HEAD = struct.Struct("<4sII")
_TRAILER = struct.Struct("<4sIQQII")            # magic, major, index_off, meta_off, n, crc
_INDEX_DTYPE = np.dtype([("offset", "<u8"), ("length", "<u4"), ("crc", "<u4")])
REC_MAGIC, IDX_MAGIC, META_MAGIC, END_MAGIC = b"PFRM", b"PIDX", b"PMET", b"PEND"

CODEC_JPEG = 1
CODEC_ZLIB_SUB = 2     # lossless: horizontal difference filter (PNG "Sub") + zlib level 1
_CODEC_NAMES = {"jpeg": CODEC_JPEG, "lossless": CODEC_ZLIB_SUB}

_MISSING = np.uint64(np.iinfo(np.uint64).max)   # index offset of a frame that was not recovered


class PicoError(ValueError):
    """A ``.pico`` file is not a pico file, is damaged, or a frame in it is corrupt."""


# ------------------------------------------------------------------------------------------
# codecs
# ------------------------------------------------------------------------------------------
def _encode(frame: np.ndarray, codec: int, quality: int) -> bytes:
    if codec == CODEC_JPEG:
        ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("OpenCV failed to JPEG-encode a frame")
        return buf.tobytes()
    diff = np.empty_like(frame)
    diff[:, 0] = frame[:, 0]
    np.subtract(frame[:, 1:], frame[:, :-1], out=diff[:, 1:])   # uint8 wraps: exact inverse by cumsum
    return zlib.compress(diff.tobytes(), 1)


def _decode(payload: memoryview | bytes, codec: int, shape: tuple[int, int]) -> np.ndarray | None:
    if codec == CODEC_JPEG:
        return cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_GRAYSCALE)
    if codec == CODEC_ZLIB_SUB:
        raw = zlib.decompress(payload, bufsize=max(shape[0] * shape[1], 1))
        if len(raw) != shape[0] * shape[1]:
            return None
        return np.cumsum(np.frombuffer(raw, np.uint8).reshape(shape), axis=1, dtype=np.uint8)
    return None


# ------------------------------------------------------------------------------------------
# writer
# ------------------------------------------------------------------------------------------
class PicoWriter:
    """Write one camera's frames to a ``.pico`` file.

    The data goes to a temporary file in the destination folder, which :meth:`close` completes
    (index, footer metadata, trailer, fsync) and renames onto ``path``; :meth:`abort` (or leaving
    a ``with`` block through an exception) deletes it instead.

    Parameters
    ----------
    path : str or Path
        Destination file, conventionally ``NAME_<channel>.pico``.
    meta : PicoMetadata
        Capture metadata (copied, never modified). ``width``/``height`` of 0 are taken from the
        first frame; non-zero values must match every frame.
    codec : {"jpeg", "lossless"}
        Per-frame coding. ``"lossless"`` is a horizontal-difference filter + zlib (level 1),
        measured faster to decode than PNG on camera images.
    quality : int
        JPEG quality 1..100.
    """

    def __init__(self, path: str | os.PathLike, meta: PicoMetadata, *, codec: str = "jpeg",
                 quality: int = 92) -> None:
        self.path = Path(path)
        if codec not in _CODEC_NAMES:
            raise ValueError(f"{self.path}: codec must be 'jpeg' or 'lossless', got {codec!r}")
        if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not 1 <= quality <= 100:
            raise ValueError(f"{self.path}: JPEG quality must be a whole number 1..100, got {quality!r}")
        if not isinstance(meta, PicoMetadata):
            raise ValueError(f"{self.path}: meta must be a PicoMetadata, got {type(meta).__name__}")
        if not self.path.parent.is_dir():
            raise ValueError(f"{self.path}: folder {self.path.parent} does not exist")
        self.meta = meta.copy()
        self.meta.format_version = f"{PICO_VERSION[0]}.{PICO_VERSION[1]}"
        self.codec, self.quality = codec, int(quality)
        self._codec_id = _CODEC_NAMES[codec]
        meta_to_json(self.path, self.meta, codec, self.quality)        # fail early on bad extra keys
        # a hidden temporary beside the target (same file system, so os.replace is atomic);
        # opened with "xb" rather than mkstemp so that it gets the normal (umask) permissions
        self._tmp = self.path.with_name(f".{self.path.name}.{secrets.token_hex(4)}.part")
        try:
            self._f = open(self._tmp, "xb")
        except OSError as exc:
            raise ValueError(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        self._pos = 0
        self._header_written = False
        self._offsets: list[int] = []
        self._lengths: list[int] = []
        self._crcs: list[int] = []
        self._done = False

    @property
    def n_frames(self) -> int:
        """Frames written so far."""
        return len(self._offsets)

    def __enter__(self) -> "PicoWriter":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None,
                 tb: TracebackType | None) -> None:
        if et is None:
            self.close()
        else:
            self.abort()

    def _emit(self, data: bytes) -> None:
        self._f.write(data)
        self._pos += len(data)

    def _write_header(self) -> None:
        js = meta_to_json(self.path, self.meta, self.codec, self.quality)
        self._emit(_FILE_HEAD.pack(MAGIC, *PICO_VERSION, 0, len(js), zlib.crc32(js)) + js)
        self._header_written = True

    def write(self, frame: np.ndarray) -> None:
        """Append one frame.

        Parameters
        ----------
        frame : ndarray, shape (H, W), uint8
            Grayscale image; H and W must match the metadata (or the first frame).
        """
        if self._done:
            raise ValueError(f"{self.path}: writer is closed")
        frame = np.asarray(frame)
        if frame.ndim != 2 or frame.dtype != np.uint8 or frame.size == 0:
            raise ValueError(f"{self.path}: a frame must be a non-empty (H, W) uint8 array, "
                             f"got shape {frame.shape} dtype {frame.dtype}")
        h, w = frame.shape
        if not self._header_written:
            if self.meta.width == 0 and self.meta.height == 0:
                self.meta.width, self.meta.height = w, h
            self._write_header()
        if (h, w) != (self.meta.height, self.meta.width):
            raise ValueError(f"{self.path}: frame {self.n_frames} is {w}x{h} but the take is "
                             f"{self.meta.width}x{self.meta.height}")
        self._write_payload(_encode(np.ascontiguousarray(frame), self._codec_id, self.quality),
                            self._codec_id)

    def _write_payload(self, payload: bytes, codec_id: int) -> None:
        crc = zlib.crc32(payload)
        head = _REC_HEAD.pack(REC_MAGIC, self.n_frames, len(payload), crc, codec_id, 0)
        head = head[:_REC_HEAD_CRC_SPAN] + struct.pack("<I", zlib.crc32(head[:_REC_HEAD_CRC_SPAN]))
        self._offsets.append(self._pos)
        self._lengths.append(len(payload))
        self._crcs.append(crc)
        self._emit(head)
        self._emit(payload)

    def close(self) -> None:
        """Write index, footer metadata and trailer, then atomically move the file into place."""
        if self._done:
            return
        try:
            if not self._header_written:
                self._write_header()
            idx = np.empty(self.n_frames, _INDEX_DTYPE)
            idx["offset"], idx["length"], idx["crc"] = self._offsets, self._lengths, self._crcs
            index_off = self._pos
            head = _IDX_HEAD.pack(IDX_MAGIC, self.n_frames)
            body = idx.tobytes()
            self._emit(head + body + struct.pack("<I", zlib.crc32(body, zlib.crc32(head))))
            meta_off = self._pos
            js = meta_to_json(self.path, self.meta, self.codec, self.quality)
            self._emit(_META_HEAD.pack(META_MAGIC, len(js), zlib.crc32(js)) + js)
            self._emit(_trailer(index_off, meta_off, self.n_frames))
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()
            os.replace(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._done = True

    def abort(self) -> None:
        """Discard everything written; no file is left behind."""
        self._done = True
        try:
            self._f.close()
        finally:
            self._tmp.unlink(missing_ok=True)


def _trailer(index_off: int, meta_off: int, n: int) -> bytes:
    body = _TRAILER.pack(END_MAGIC, PICO_VERSION[0], index_off, meta_off, n, 0)[:-4]
    return body + struct.pack("<I", zlib.crc32(body))


# ------------------------------------------------------------------------------------------
# reader
# ------------------------------------------------------------------------------------------
class PicoReader:
    """Random-access reader of a ``.pico`` file; also a ``FrameSource`` (kind ``"pico"``).

    Opening is O(1) when the file has its index. A file without a valid index (truncated or
    never closed) is re-scanned: every intact frame is readable, frames after the damage are
    dropped or reported, and the reasons are in :attr:`warnings` (also logged). Reading is
    thread-safe (one ``os.pread`` per frame).

    Raises
    ------
    PicoError
        Not a pico file, a newer major version, or unreadable metadata.
    """

    kind = "pico"

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.warnings: list[str] = []
        try:
            self._fh = open(self.path, "rb")
        except OSError as exc:
            raise PicoError(f"{self.path}: cannot open: {exc.strerror or exc}") from None
        self._lock = threading.Lock()
        self._index_offset: int | None = None        # set when opened through the index
        self._meta_offset: int | None = None
        try:
            self._size = os.fstat(self._fh.fileno()).st_size
            self._open()
        except BaseException:
            self._fh.close()
            raise

    # -- opening ---------------------------------------------------------------------------
    def _pread(self, n: int, off: int) -> bytes:
        if hasattr(os, "pread"):
            return os.pread(self._fh.fileno(), n, off)
        with self._lock:                                     # pragma: no cover (Windows)
            self._fh.seek(off)
            return self._fh.read(n)

    def _warn(self, msg: str) -> None:
        self.warnings.append(msg)
        log.warning("%s: %s", self.path, msg)

    def _open(self) -> None:
        head = self._pread(_FILE_HEAD.size, 0)
        if len(head) < _FILE_HEAD.size or head[:8] != MAGIC:
            raise PicoError(f"{self.path}: not a .pico file (bad magic bytes)")
        _, major, minor, _flags, jlen, jcrc = _FILE_HEAD.unpack(head)
        self.version = (major, minor)
        if major > PICO_VERSION[0]:
            raise PicoError(f"{self.path}: .pico format version {major}.{minor} is newer than this "
                            f"program supports ({PICO_VERSION[0]}.x); please update CaraPost")
        self._data_start = _FILE_HEAD.size + jlen
        header_meta = None
        raw = self._pread(jlen, _FILE_HEAD.size)
        if len(raw) == jlen and zlib.crc32(raw) == jcrc:
            try:
                header_meta = meta_from_json(raw)
            except ValueError as exc:
                self._warn(f"header metadata unreadable ({exc})")
        else:
            self._warn("header metadata is damaged (CRC mismatch or truncated)")
        footer_meta = self._open_index()
        if footer_meta is None:
            self._rescan()
        chosen = footer_meta or header_meta
        if chosen is None:
            raise PicoError(f"{self.path}: both the header and the footer metadata are damaged")
        self.meta, doc = chosen
        self.codec = str(doc.get("codec", "jpeg"))
        self.quality = int(doc.get("quality", 0))
        self.width, self.height = self.meta.width, self.meta.height
        self.frame_rate = self.meta.frame_rate
        self.n_frames = len(self._index)

    def _open_index(self) -> tuple[PicoMetadata, dict[str, Any]] | None:
        """Load the index via the trailer; ``None`` (with a warning) when that is impossible."""
        if self._size < self._data_start + _TRAILER.size:
            self._warn("file has no index (truncated or not closed); re-scanning frames")
            return None
        raw = self._pread(_TRAILER.size, self._size - _TRAILER.size)
        magic, _major, index_off, meta_off, n, crc = _TRAILER.unpack(raw)
        why = None
        if magic != END_MAGIC or zlib.crc32(raw[:-4]) != crc:
            why = "file has no valid trailer (truncated or not closed)"
        elif not (self._data_start <= index_off < meta_off < self._size):
            why = "trailer points outside the file"
        else:
            ih = self._pread(_IDX_HEAD.size + n * _INDEX_DTYPE.itemsize + 4, index_off)
            body = ih[_IDX_HEAD.size:-4]
            ok = (len(body) == n * _INDEX_DTYPE.itemsize and ih[:4] == IDX_MAGIC
                  and _IDX_HEAD.unpack(ih[:_IDX_HEAD.size])[1] == n
                  and struct.unpack("<I", ih[-4:])[0] == zlib.crc32(ih[:-4]))
            if not ok:
                why = "frame index is damaged"
            else:
                index = np.frombuffer(body, _INDEX_DTYPE).copy()
                end = index["offset"] + _REC_HEAD.size + index["length"].astype(np.uint64)
                if n and (index["offset"].min() < self._data_start or end.max() > index_off):
                    why = "frame index points outside the frame data"
                else:
                    mh = self._pread(_META_HEAD.size, meta_off)
                    mmagic, mlen, mcrc = _META_HEAD.unpack(mh)
                    mraw = self._pread(mlen, meta_off + _META_HEAD.size)
                    if mmagic != META_MAGIC or len(mraw) != mlen or zlib.crc32(mraw) != mcrc:
                        why = "footer metadata is damaged"
                    else:
                        try:
                            meta = meta_from_json(mraw)
                        except ValueError as exc:
                            why = f"footer metadata unreadable ({exc})"
                        else:
                            self._index = index
                            self._index_offset = index_off
                            self._meta_offset = meta_off
                            return meta
        self._warn(f"{why}; re-scanning frames")
        return None

    def _rescan(self) -> None:
        """Rebuild the index by walking the frame records (resynchronising on damage)."""
        found: dict[int, tuple[int, int, int]] = {}
        bad_payload: list[int] = []
        skipped = 0
        with mmap.mmap(self._fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:   # size >= header
            pos, size = self._data_start, self._size
            while pos + _REC_HEAD.size <= size:
                head = mm[pos:pos + _REC_HEAD.size]
                magic, frame, length, crc, _codec, hcrc = _REC_HEAD.unpack(head)
                if magic != REC_MAGIC or zlib.crc32(head[:_REC_HEAD_CRC_SPAN]) != hcrc:
                    if magic == IDX_MAGIC or magic == META_MAGIC:
                        break
                    nxt = mm.find(REC_MAGIC, pos + 1)
                    if nxt < 0:
                        break
                    skipped += nxt - pos
                    pos = nxt
                    continue
                end = pos + _REC_HEAD.size + length
                if end > size:
                    self._warn(f"frame {frame} is cut off by the end of the file; dropped")
                    break
                if zlib.crc32(mm[pos + _REC_HEAD.size:end]) != crc:
                    bad_payload.append(frame)
                found[frame] = (pos, length, crc)
                pos = end
        n = max(found) + 1 if found else 0
        index = np.zeros(n, _INDEX_DTYPE)
        index["offset"] = _MISSING
        for frame, (off, length, crc) in found.items():
            index[frame] = (off, length, crc)
        self._index = index
        self._index_offset = self._meta_offset = None
        missing = int((index["offset"] == _MISSING).sum())
        msg = f"recovered {n - missing - len(bad_payload)} intact frame(s) of {n}"
        if bad_payload:
            msg += f"; corrupt frame(s): {_ranges(sorted(bad_payload))}"
        if missing:
            msg += f"; {missing} frame(s) missing"
        if skipped:
            msg += f"; skipped {skipped} damaged byte(s)"
        self._warn(msg)

    # -- reading ---------------------------------------------------------------------------
    def read(self, index: int) -> np.ndarray:
        """Decode frame ``index`` (0-based).

        Returns
        -------
        ndarray, shape (height, width), uint8

        Raises
        ------
        IndexError
            ``index`` outside ``0 .. n_frames-1``.
        PicoError
            The frame's record is damaged (CRC mismatch) or missing from a recovered file.
        """
        i = _check_index(index, self.n_frames, self.path)
        off, length, crc = self._index[i]
        if off == _MISSING:
            raise PicoError(f"{self.path}: frame {i} is missing (file damaged)")
        rec = self._pread(_REC_HEAD.size + int(length), int(off))
        if len(rec) != _REC_HEAD.size + length:
            raise PicoError(f"{self.path}: frame {i} is cut off by the end of the file")
        magic, frame, rlen, rcrc, codec, hcrc = _REC_HEAD.unpack_from(rec)
        payload = memoryview(rec)[_REC_HEAD.size:]
        if (magic != REC_MAGIC or frame != i or rlen != length or rcrc != crc
                or zlib.crc32(rec[:_REC_HEAD_CRC_SPAN]) != hcrc or zlib.crc32(payload) != crc):
            raise PicoError(f"{self.path}: frame {i} is corrupt (CRC mismatch)")
        try:
            img = _decode(payload, codec, (self.height, self.width))
        except zlib.error:
            img = None
        if img is None or img.shape != (self.height, self.width):
            raise PicoError(f"{self.path}: frame {i} cannot be decoded (codec {codec})")
        return img

    def verify(self) -> list[int]:
        """Check every frame's CRC without decoding; returns the indices of bad frames."""
        bad = []
        for i, (off, length, crc) in enumerate(self._index):
            if off == _MISSING:
                bad.append(i)
                continue
            rec = self._pread(_REC_HEAD.size + int(length), int(off))
            if len(rec) != _REC_HEAD.size + length or zlib.crc32(memoryview(rec)[_REC_HEAD.size:]) != crc:
                bad.append(i)
        return bad

    @property
    def has_index(self) -> bool:
        """True when the file was opened through its index (not recovered by a re-scan)."""
        return self._meta_offset is not None

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> "PicoReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return (f"PicoReader({str(self.path)!r}, n_frames={self.n_frames}, "
                f"{self.width}x{self.height}, codec={self.codec!r})")


def _check_index(index: int, n: int, path: Path) -> int:
    try:
        i = operator.index(index)
    except TypeError:
        raise TypeError(f"{path}: frame index must be an integer, got {index!r}") from None
    if not 0 <= i < n:
        raise IndexError(f"{path}: frame {i} out of range 0..{n - 1}")
    return i


def _ranges(v: list[int]) -> str:
    out, start = [], None
    for k, x in enumerate(v):
        if start is None:
            start = x
        if k == len(v) - 1 or v[k + 1] != x + 1:
            out.append(str(start) if start == x else f"{start}-{x}")
            start = None
    return ", ".join(out)


# ------------------------------------------------------------------------------------------
# files of a take, metadata update
# ------------------------------------------------------------------------------------------
def channel_of(path: str | os.PathLike) -> tuple[str, int]:
    """``("TAKE", 3)`` for ``.../TAKE_3.pico``; ValueError when the name has no ``_<number>``."""
    p = Path(path)
    prefix, sep, num = p.stem.rpartition("_")
    if not sep or not num.isdigit() or not prefix:
        raise ValueError(f"{p}: a .pico file name must end in _<channel number>, e.g. TAKE_0.pico")
    return prefix, int(num)


#: Calibration files looked for next to a take's ``.pico`` files, in this order.
CALIBRATION_EXTENSIONS = (".xcp", ".toml", ".qca")


def take_name(path: str | os.PathLike) -> str:
    """The take a camera file belongs to: ``NAME`` for ``NAME_0.pico`` (the stem otherwise)."""
    stem = Path(path).stem
    return stem.rsplit("_", 1)[0] if "_" in stem else stem


def find_calibration(any_take_file: str | os.PathLike) -> Path | None:
    """The calibration named after a take next to its files (``NAME.xcp``, else ``.toml``, else
    ``.qca`` for ``NAME_0.pico``), or None. The GUI's import, the API and batch jobs use this rule."""
    p = Path(any_take_file)
    for ext in CALIBRATION_EXTENSIONS:
        cand = p.parent / f"{take_name(p)}{ext}"
        if cand.is_file():
            return cand
    return None


def take_files(any_pico_path: str | os.PathLike) -> list[Path]:
    """All ``NAME_<n>.pico`` files of the take that ``any_pico_path`` belongs to.

    Returns
    -------
    list of Path
        Sorted by channel number numerically (``_10`` after ``_9``).
    """
    p = Path(any_pico_path)
    prefix, _ = channel_of(p)
    folder = p.parent
    if not folder.is_dir():
        raise ValueError(f"{p}: folder {folder} does not exist")
    found = []
    for q in folder.iterdir():
        if q.suffix.lower() != ".pico" or not q.is_file():
            continue
        try:
            qp, ch = channel_of(q)
        except ValueError:
            continue
        if qp == prefix:
            found.append((ch, q.name, q))
    if not found:
        raise ValueError(f"{p}: no {prefix}_<n>.pico files found in {folder}")
    return [q for _, _, q in sorted(found)]


def update_metadata(path: str | os.PathLike, meta: PicoMetadata) -> None:
    """Replace the footer metadata of a closed, intact ``.pico`` file in place.

    Frame data and the index are not touched: the file is truncated after the index and the new
    metadata and trailer are appended, then fsynced. Should that be interrupted, the file still
    opens (through a re-scan, with the header metadata) and loses no frame.

    Raises
    ------
    PicoError
        The file has no valid index (re-write it with a new :class:`PicoWriter` first).
    """
    p = Path(path)
    with PicoReader(p) as r:
        index_off, meta_off, n = r._index_offset, r._meta_offset, r.n_frames
        if index_off is None or meta_off is None:
            raise PicoError(f"{p}: cannot update metadata of a damaged file (no valid index)")
        codec, quality, old = r.codec, r.quality, r.meta
    new = meta.copy()
    if (new.width, new.height) != (old.width, old.height):
        raise ValueError(f"{p}: metadata image size {new.width}x{new.height} does not match the "
                         f"frames ({old.width}x{old.height})")
    js = meta_to_json(p, new, codec, quality)
    with open(p, "r+b") as f:
        f.truncate(meta_off)
        f.seek(meta_off)
        f.write(_META_HEAD.pack(META_MAGIC, len(js), zlib.crc32(js)) + js)
        f.write(_trailer(index_off, meta_off, n))
        f.flush()
        os.fsync(f.fileno())
