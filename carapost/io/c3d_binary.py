"""Low-level C3D encoding and decoding: header, parameter section, point data block.

This module knows the byte layout of the C3D format (https://www.c3d.org, "The C3D File Format
User Guide") and nothing about takes. :mod:`carapost.io.c3d` builds on it.

* Blocks are 512 bytes; block numbers are 1-based.
* Processor types: 84 Intel (little-endian IEEE), 85 DEC (little-endian words, VAX F-floats),
  86 MIPS/SGI (big-endian IEEE). The type is the 4th byte of the parameter section.
* Point data: per frame ``P`` points of four words ``x, y, z, w`` (int16 scaled by POINT:SCALE
  when the scale is positive, float32 when it is negative), then the frame's analog words.
  The fourth word ``w`` holds ``camera_mask << 8 | residual_byte`` (as an integer value, also in
  float files); ``w < 0`` marks an invalid sample. The residual is ``residual_byte * |scale|``;
  a residual of 0 means "modelled / interpolated" (not measured by cameras).

Everything here works on ``bytes`` already in memory; no file I/O.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

__all__ = [
    "BLOCK", "INTEL", "DEC", "MIPS", "C3DError", "Header", "Parameter", "ParameterSection",
    "parse_header", "parse_parameters", "get", "joined_strings", "joined_numbers", "frame_range",
    "decode_points", "encode_c3d",
]

BLOCK = 512
KEY = 0x50
INTEL, DEC, MIPS = 84, 85, 86
_CHAR, _BYTE, _INT, _FLOAT = -1, 1, 2, 4


class C3DError(ValueError):
    """A C3D file that cannot be read or written; the message names the file."""


# ---------------------------------------------------------------------------------- numbers
def _dec_floats(buf: np.ndarray) -> np.ndarray:
    """DEC (VAX F-floating) 4-byte groups, uint8 array ``(..., 4*n)``, to float32 ``(..., n)``.

    A VAX F-float is stored as two little-endian 16-bit words, most significant word first, with
    an exponent bias of 128 and a hidden bit worth 0.5: swapping the words gives IEEE bits whose
    value is 4 times too large.
    """
    b = np.ascontiguousarray(buf, dtype=np.uint8).reshape(buf.shape[:-1] + (-1, 4))
    ieee = np.ascontiguousarray(b[..., [2, 3, 0, 1]]).view("<f4")[..., 0]
    return (ieee / np.float32(4.0)).astype(np.float32)


def _endian(processor: int) -> str:
    return ">" if processor == MIPS else "<"


def _floats(data: bytes | np.ndarray, processor: int) -> np.ndarray:
    arr = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
    if processor == DEC:
        return _dec_floats(arr)
    return np.ascontiguousarray(arr).view(_endian(processor) + "f4").astype(np.float32)


# ----------------------------------------------------------------------------------- header
@dataclass(frozen=True)
class Header:
    """The C3D header block (block 1) and the processor type.

    ``first_frame``/``last_frame`` are the 1-based frame numbers as stored (16 bits: files with more
    than 65535 frames store the true range in TRIAL:ACTUAL_START_FIELD / ACTUAL_END_FIELD).
    """

    param_block: int
    n_points: int
    analog_words: int  #: analog samples per 3D frame, all channels together
    first_frame: int
    last_frame: int
    max_gap: int
    scale: float
    data_block: int
    analog_per_frame: int  #: analog samples per channel per 3D frame
    frame_rate: float
    processor: int
    n_param_blocks: int


def parse_header(raw: bytes, name: str) -> Header:
    """Decode the header block; ``name`` (the file) is used in error messages.

    Raises
    ------
    C3DError
        If ``raw`` is too short, lacks the C3D key byte, or points outside itself.
    """
    if len(raw) < 2 * BLOCK:
        raise C3DError(f"{name}: not a C3D file (only {len(raw)} bytes)")
    if raw[1] != KEY:
        raise C3DError(f"{name}: not a C3D file (byte 2 is {raw[1]:#x}, expected 0x50)")
    pblock = raw[0]
    pstart = (pblock - 1) * BLOCK
    if pblock < 2 or pstart + 4 > len(raw):
        raise C3DError(f"{name}: the header points to parameter block {pblock}, outside the file")
    n_blocks, processor = raw[pstart + 2], raw[pstart + 3]
    if processor not in (INTEL, DEC, MIPS):
        raise C3DError(f"{name}: unknown processor type {processor} in the parameter section "
                       "(expected 84 Intel, 85 DEC or 86 MIPS)")
    e = _endian(processor)
    words = struct.unpack(e + "12H", raw[:24])
    scale, rate = _floats(raw[12:16], processor)[0], _floats(raw[20:24], processor)[0]
    return Header(param_block=pblock, n_points=words[1], analog_words=words[2], first_frame=words[3],
                  last_frame=words[4], max_gap=words[5], scale=float(scale), data_block=words[8],
                  analog_per_frame=words[9], frame_rate=float(rate), processor=processor,
                  n_param_blocks=n_blocks)


# ------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class Parameter:
    """One parameter: ``value`` is a list of strings (type -1) or a flat numpy array in file order
    (first dimension fastest), int8 / int16 / float32 for types 1 / 2 / 4."""

    type: int
    dims: tuple[int, ...]
    value: list[str] | np.ndarray
    description: str = ""

    def ints(self, *, unsigned: bool = False) -> np.ndarray:
        """The value as int64 (empty for text); ``unsigned`` reads 16-bit words as 0..65535 and
        bytes as 0..255. Floats are rounded, non-finite ones read as 0."""
        if self.type == _CHAR:
            return np.zeros(0, np.int64)
        v = np.asarray(self.value)
        if self.type == _FLOAT:
            f = np.nan_to_num(v.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
            return np.round(np.clip(f, -2.0 ** 62, 2.0 ** 62)).astype(np.int64)
        if unsigned:
            return v.astype(np.int64) & (0xFFFF if self.type == _INT else 0xFF)
        return v.astype(np.int64)

    def first_int(self, *, unsigned: bool = False) -> int | None:
        """The first value as an int, or None if there is none."""
        v = self.ints(unsigned=unsigned)
        return int(v[0]) if len(v) else None

    def strings(self) -> list[str]:
        if self.type == _CHAR:
            return list(self.value)  # type: ignore[arg-type]
        return [str(x) for x in np.asarray(self.value).ravel()]


#: group name -> parameter name -> Parameter
ParameterSection = dict[str, dict[str, Parameter]]


def _decode_text(b: bytes) -> str:
    b = b.rstrip(b" \x00")
    try:
        return b.decode("utf-8")
    except UnicodeDecodeError:
        return b.decode("latin-1")


def _param_value(data: bytes, ptype: int, dims: tuple[int, ...], processor: int) -> list[str] | np.ndarray:
    if ptype == _CHAR:
        if not dims:
            return [_decode_text(data)]
        width, count = dims[0], math.prod(dims[1:])
        if width == 0:
            return [""] * count if len(dims) > 1 and count else []
        return [_decode_text(data[i * width:(i + 1) * width]) for i in range(count)]
    if ptype == _BYTE:
        return np.frombuffer(data, np.int8).copy()
    if ptype == _INT:
        return np.frombuffer(data, _endian(processor) + "i2").astype(np.int16)
    return _floats(data, processor)


def _description(raw: bytes, q: int, rec_end: int, bad, pname: str) -> str:
    """The description at ``q`` (length byte, text); it must fit in its record."""
    if q >= rec_end:
        return ""
    dlen = raw[q]
    if q + 1 + dlen > rec_end:
        raise bad(f"the description of {pname!r} runs past its record")
    return _decode_text(raw[q + 1:q + 1 + dlen])


def parse_parameters(raw: bytes, header: Header, name: str) -> ParameterSection:
    """Walk the parameter section strictly.

    The section runs from the header's parameter block to the start of the data (or, if the data
    come first, for the number of blocks it declares). Every record, with its value and its
    description, must fit in it; the walk ends at a record with a zero name length or group id, at
    a zero offset, or at the section's end. Zero-sized values (e.g. a ``[0, 0]`` character array)
    are accepted.

    Raises
    ------
    C3DError
        If a record runs past the section (or into the data), has an unknown type or more than 7
        dimensions, a non-printable name, or a value or description larger than its record.
    """
    e = _endian(header.processor)
    start = (header.param_block - 1) * BLOCK
    data_start = (header.data_block - 1) * BLOCK
    if header.data_block > header.param_block:
        # The section ends where the data begin. Some writers (Motion Analysis) declare too few
        # parameter blocks; a declared count that overlaps the data is caught record by record.
        end = min(data_start, len(raw))
    else:
        end = min(start + max(header.n_param_blocks, 1) * BLOCK, len(raw))
    groups: dict[int, tuple[str, str]] = {}
    params: list[tuple[int, str, Parameter]] = []
    pos = start + 4

    def bad(msg: str) -> C3DError:
        return C3DError(f"{name}: corrupt parameter section at byte {pos}: {msg}")

    while pos + 2 <= end:
        nlen, gid = struct.unpack("bb", raw[pos:pos + 2])
        if nlen == 0 or gid == 0:
            break
        n = abs(nlen)
        offpos = pos + 2 + n
        if offpos + 2 > end:
            raise bad("record runs past the end of the parameter section")
        pname_b = raw[pos + 2:offpos]
        if not all(32 <= c < 127 for c in pname_b):
            raise bad(f"name {pname_b!r} is not printable ASCII")
        pname = pname_b.decode("ascii").upper()
        (offset,) = struct.unpack(e + "h", raw[offpos:offpos + 2])
        rec_end = end if offset == 0 else offpos + offset
        if offset < 0 or rec_end > end:
            raise bad(f"record {pname!r} has offset {offset}, pointing outside the parameter section")
        q = offpos + 2
        if gid < 0:
            desc = _description(raw, q, rec_end, bad, pname)
            groups[-gid] = (pname, desc)
        else:
            if q + 2 > rec_end:
                raise bad(f"parameter {pname!r} is shorter than its type and dimensions")
            ptype, ndims = struct.unpack("bB", raw[q:q + 2])
            if ptype not in (_CHAR, _BYTE, _INT, _FLOAT):
                raise bad(f"parameter {pname!r} has unknown type {ptype}")
            if ndims > 7:
                raise bad(f"parameter {pname!r} has {ndims} dimensions (at most 7)")
            dims = tuple(raw[q + 2:q + 2 + ndims])
            q += 2 + ndims
            size = abs(ptype) * math.prod(dims)
            if len(dims) != ndims or q + size > rec_end:
                raise bad(f"parameter {pname!r} ({ptype=}, {dims=}) does not fit in its record")
            value = _param_value(raw[q:q + size], ptype, dims, header.processor)
            q += size
            desc = _description(raw, q, rec_end, bad, pname)
            params.append((gid, pname, Parameter(ptype, dims, value, desc)))
        if offset == 0:
            break
        pos = rec_end
    out: ParameterSection = {gname: {} for gname, _ in groups.values()}
    for gid, pname, p in params:
        gname = groups.get(gid, (f"GROUP{gid}", ""))[0]
        out.setdefault(gname, {})[pname] = p
    return out


def get(params: ParameterSection, group: str, name: str) -> Parameter | None:
    return params.get(group, {}).get(name)


def joined_strings(params: ParameterSection, group: str, name: str) -> list[str]:
    """``NAME`` followed by ``NAME2``, ``NAME3``... (how C3D stores more than 255 entries)."""
    out: list[str] = []
    p, k = get(params, group, name), 2
    while p is not None:
        out.extend(p.strings())
        p, k = get(params, group, f"{name}{k}"), k + 1
    return out


def joined_numbers(params: ParameterSection, group: str, name: str) -> np.ndarray | None:
    """``NAME``, ``NAME2``... as one int64 array (see :meth:`Parameter.ints`); None if absent."""
    p = get(params, group, name)
    if p is None:
        return None
    parts, k = [p.ints()], 2
    while (p := get(params, group, f"{name}{k}")) is not None:
        parts.append(p.ints())
        k += 1
    return np.concatenate(parts)


def _u32(p: Parameter | None) -> int | None:
    if p is None or p.type != _INT or len(np.asarray(p.value)) < 2:
        return None
    lo, hi = (int(x) for x in p.ints(unsigned=True)[:2])
    return lo | (hi << 16)


def frame_range(header: Header, params: ParameterSection) -> tuple[int, int]:
    """``(first_frame, n_frames)`` from TRIAL:ACTUAL_*_FIELD, POINT:LONG_FRAMES, POINT:FRAMES or the
    header, in that order of preference (the header's 16-bit range is the least reliable)."""
    first = header.first_frame
    start = _u32(get(params, "TRIAL", "ACTUAL_START_FIELD"))
    stop = _u32(get(params, "TRIAL", "ACTUAL_END_FIELD"))
    if start is not None and stop is not None and stop >= start >= 1:
        return start, stop - start + 1
    long_frames = get(params, "POINT", "LONG_FRAMES")
    n = long_frames.first_int() if long_frames is not None and long_frames.type == _FLOAT else None
    if n is not None and n >= 1:
        return first, n
    frames = get(params, "POINT", "FRAMES")
    if frames is not None and len(np.asarray(frames.value)) >= 1:
        n = int(frames.ints(unsigned=True)[0])
        if n >= 1:
            return first, n
    return first, max(header.last_frame - header.first_frame + 1, 0)


# ------------------------------------------------------------------------------ point data
def decode_points(raw: bytes, *, n_points: int, n_frames: int, data_block: int, analog_words: int,
                  scale: float, processor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode the point data block.

    Returns
    -------
    xyz : float64 (F, P, 3)
        File units; NaN where the sample is invalid (negative fourth word or non-finite).
    residual : float64 (F, P)
        File units; NaN where invalid; 0 means modelled / interpolated.
    camera_mask : uint8 (F, P)
        Bit ``k`` set when camera ``k`` (0..6) saw the point.

    ``F`` is ``n_frames`` or fewer if the file is shorter than its parameters claim.
    """
    is_float = scale < 0
    wsize = 4 if is_float else 2
    fbytes = (4 * n_points + analog_words) * wsize
    offset = (data_block - 1) * BLOCK
    avail = max(len(raw) - offset, 0) // fbytes if fbytes else 0
    F, P = (min(n_frames, avail), n_points) if n_points else (n_frames, 0)
    if P == 0 or F == 0:
        return np.zeros((F, P, 3)), np.zeros((F, P)), np.zeros((F, P), np.uint8)
    with np.errstate(invalid="ignore", over="ignore"):  # garbage bytes may hold signalling NaNs
        return _decode_block(raw, F, P, fbytes, offset, wsize, is_float, scale, processor)


def _decode_block(raw: bytes, F: int, P: int, fbytes: int, offset: int, wsize: int, is_float: bool,
                  scale: float, processor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    block = np.frombuffer(raw, np.uint8, count=F * fbytes, offset=offset).reshape(F, fbytes)
    block = block[:, :4 * P * wsize]
    if is_float:
        vals = _floats(block, processor).reshape(F, P, 4)
        xyz = vals[..., :3].astype(np.float64)
        w = vals[..., 3].astype(np.float64)
        ok = np.isfinite(w) & (w >= 0) & (w < 2.0 ** 31)
        word = np.where(ok, np.trunc(np.where(ok, w, 0.0)), 0).astype(np.int64)
        invalid = ~ok
        res_scale = abs(scale)
    else:
        ints = np.ascontiguousarray(block).view(_endian(processor) + "i2").reshape(F, P, 4)
        xyz = ints[..., :3].astype(np.float64) * scale
        word = ints[..., 3].astype(np.int64)
        invalid = word < 0
        res_scale = abs(scale)
    invalid |= ~np.isfinite(xyz).all(axis=-1)
    residual = (word & 0xFF).astype(np.float64) * res_scale
    mask = ((word >> 8) & 0x7F).astype(np.uint8)
    xyz[invalid] = np.nan
    residual[invalid] = np.nan
    mask[invalid] = 0
    return xyz, residual, mask


# --------------------------------------------------------------------------------- writing
ParamValue = str | list[str] | int | float | np.ndarray


def _encode_value(group: str, pname: str, value: ParamValue) -> tuple[int, tuple[int, ...], bytes]:
    where = f"C3D parameter {group}:{pname}"
    if isinstance(value, str):
        b = value.encode("utf-8")
        if len(b) > 255:
            raise C3DError(f"{where}: text longer than 255 bytes")
        return _CHAR, (len(b),), b
    if isinstance(value, list):
        enc = [s.encode("utf-8") for s in value]
        width = max([1] + [len(b) for b in enc])
        if width > 255 or len(enc) > 255:
            raise C3DError(f"{where}: {len(enc)} strings of up to {width} bytes (limit 255 x 255)")
        return _CHAR, (width, len(enc)), b"".join(b.ljust(width, b" ") for b in enc)
    arr = np.asarray(value)
    scalar = arr.ndim == 0
    arr = arr.ravel()
    if len(arr) > 255:
        raise C3DError(f"{where}: {len(arr)} values (limit 255 per parameter)")
    dims = () if scalar else (len(arr),)
    if np.issubdtype(arr.dtype, np.integer) or arr.dtype == bool:
        if len(arr) and (arr.min() < -32768 or arr.max() > 32767):
            raise C3DError(f"{where}: value outside the 16-bit range")
        return _INT, dims, arr.astype("<i2").tobytes()
    return _FLOAT, dims, arr.astype("<f4").tobytes()


def _record(nlen_name: bytes, gid: int, body: bytes, desc: str, last: bool) -> bytes:
    d = desc.encode("utf-8")[:255]
    tail = body + bytes([len(d)]) + d
    offset = 0 if last else len(tail) + 2
    return struct.pack("bb", len(nlen_name), gid) + nlen_name + struct.pack("<h", offset) + tail


def _parameter_section(groups: list[tuple[str, str, list[tuple[str, ParamValue, str]]]]) -> bytes:
    """Intel parameter section (without padding) for ``[(group, description, [(name, value,
    description), ...]), ...]``: all group records first, then all parameters, then a terminator."""
    recs: list[bytes] = []
    for gi, (gname, gdesc, _) in enumerate(groups, start=1):
        recs.append(_record(gname.encode("ascii"), -gi, b"", gdesc, last=False))
    for gi, (gname, _, plist) in enumerate(groups, start=1):
        for pname, value, pdesc in plist:
            ptype, dims, data = _encode_value(gname, pname, value)
            body = struct.pack("bB", ptype, len(dims)) + bytes(dims) + data
            rec = _record(pname.encode("ascii"), gi, body, pdesc, last=False)
            if len(rec) > 32767:
                raise C3DError(f"C3D parameter {gname}:{pname} is too large ({len(rec)} bytes)")
            recs.append(rec)
    return b"".join(recs) + b"\x00\x00"


def _u16_word(v: int) -> int:
    """An unsigned 16-bit count stored in a signed int16 parameter."""
    v = min(max(int(v), 0), 0xFFFF)
    return v - 0x10000 if v > 0x7FFF else v


def encode_c3d(*, xyz: np.ndarray, fourth: np.ndarray, frame_rate: float, first_frame: int, scale: float,
               point_groups: dict[str, list[tuple[str, ParamValue, str]]],
               extra_groups: list[tuple[str, str, list[tuple[str, ParamValue, str]]]]) -> bytes:
    """A complete Intel/float C3D file.

    Parameters
    ----------
    xyz : float32 (F, P, 3)
        Coordinates as written (0 for invalid samples).
    fourth : float32 (F, P)
        The fourth word per sample (``mask << 8 | residual_byte``, or -1).
    frame_rate : float
    first_frame : int
        1-based number of the first frame (may exceed 16 bits: TRIAL stores 32 bits).
    scale : float
        POINT:SCALE, negative (float data); ``|scale|`` is the residual unit.
    point_groups : dict
        Extra POINT parameters (``LABELS``, ``DESCRIPTIONS``, ``UNITS``...) as ``[(name, value,
        description)]`` under key ``"POINT"``.
    extra_groups : list
        Further groups ``(name, description, [(param, value, description), ...])``.
    """
    F, P = xyz.shape[:2]
    if P > 65535:
        raise C3DError(f"C3D cannot hold {P} points (limit 65535)")
    if scale >= 0:
        raise ValueError("encode_c3d writes float data: scale must be negative")
    last_frame = first_frame + F - 1
    # The data start depends on the parameter size, which contains the data start: two passes.
    data_block = 3
    for _ in range(3):
        point = [("USED", _u16_word(P), "Number of points"),
                 ("FRAMES", _u16_word(F), "Number of frames"),
                 ("LONG_FRAMES", np.float32(F), "Number of frames (exact above 65535)"),
                 ("DATA_START", _u16_word(data_block), "First block of point data"),
                 ("SCALE", np.float32(scale), "Point scale (negative: float data)"),
                 ("RATE", np.float32(frame_rate), "Frame rate, Hz")] + point_groups.get("POINT", [])
        groups = [("POINT", "3D point parameters", point),
                  ("ANALOG", "Analog data parameters",
                   [("USED", 0, "Number of analog channels"), ("RATE", np.float32(0.0), "Analog rate, Hz")]),
                  ("TRIAL", "Trial parameters",
                   [("ACTUAL_START_FIELD", np.array([_u16_word(first_frame & 0xFFFF),
                                                     _u16_word(first_frame >> 16)]), "First frame"),
                    ("ACTUAL_END_FIELD", np.array([_u16_word(last_frame & 0xFFFF),
                                                   _u16_word(last_frame >> 16)]), "Last frame")])]
        groups += extra_groups
        section = b"\x01" + bytes([KEY]) + b"\x00" + bytes([INTEL]) + _parameter_section(groups)
        n_blocks = -(-len(section) // BLOCK)
        if n_blocks > 255:
            raise C3DError("C3D parameter section would exceed 255 blocks")
        if 2 + n_blocks == data_block:
            break
        data_block = 2 + n_blocks
    section = bytearray(section.ljust(n_blocks * BLOCK, b"\x00"))
    section[2] = n_blocks
    header = bytearray(BLOCK)
    struct.pack_into("<BBHHHHHfHHf", header, 0, 2, KEY, P, 0, min(max(first_frame, 1), 0xFFFF),
                     min(max(last_frame, 1), 0xFFFF), 0, scale, data_block, 0, frame_rate)
    body = np.empty((F, P, 4), "<f4")
    body[..., :3] = xyz
    body[..., 3] = fourth
    # No padding after the last frame: readers that take the frame count from the file size when
    # it exceeds 16 bits (ezc3d) would see the padding as extra frames.
    return bytes(header) + bytes(section) + body.tobytes()
