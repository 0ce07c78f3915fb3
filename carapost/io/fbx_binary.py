"""Binary FBX node records: the low-level writer under :mod:`carapost.io.fbx`.

A binary FBX file (layout in ``docs/formats/fbx.md``) is a header, a tree of *node records* and
a footer. A node has a name, a list of typed *properties* and a list of child nodes. This module
knows nothing about scenes: :mod:`carapost.io.fbx` builds the tree, :func:`encode_fbx` turns it
into bytes.

Property types (one type-code byte, then the value, little-endian):

====  ====================  ===============================================================
code  constructor           value
====  ====================  ===============================================================
C     :func:`p_bool`        bool, 1 byte
Y     :func:`p_int16`       int16
I     :func:`p_int32`       int32
L     :func:`p_int64`       int64
F     :func:`p_float32`     float32
D     :func:`p_float64`     float64
S     :func:`p_string`      uint32 length + UTF-8 bytes (no terminator); ``"\\x00\\x01"`` joins
                            an object's name and class (``"Nose\\x00\\x01Model"``)
R     :func:`p_raw`         uint32 length + bytes
f d   :func:`p_array`       float32 / float64 array: uint32 count, uint32 encoding (0 raw,
i l   :func:`p_array`       int32 / int64 array      1 zlib), uint32 byte length, then the data
b     :func:`p_array`       bool array (1 byte each)
====  ====================  ===============================================================

Node record, version < 7500 (7.5 and later widen the first three fields to uint64)::

    uint32 end_offset        absolute file offset just past this record
    uint32 num_properties
    uint32 property_list_len bytes of the property list
    uint8  name_len
    char   name[name_len]
    property list
    child records, then a null record (13 zero bytes; 25 from 7.5)

The null record follows the children when there are any; like the FBX SDK, a childless node
also gets one when it has no properties, or is an ``AnimationStack`` / ``AnimationLayer``,
unless it is the last of its siblings. The top-level list ends with a null record.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Prop", "FbxNode", "p_bool", "p_int16", "p_int32", "p_int64", "p_float32", "p_float64",
           "p_string", "p_raw", "p_array", "encode_fbx",
           "HEADER_MAGIC", "FILE_ID", "CREATION_TIME", "FOOTER_ID", "FOOTER_MAGIC",
           "SUPPORTED_VERSIONS", "KTIME_PER_SECOND"]

#: The first 23 bytes of every binary FBX file (then the uint32 version).
HEADER_MAGIC = b"Kaydara FBX Binary  \x00\x1a\x00"
#: FBX time unit: ticks per second (``KTime``).
KTIME_PER_SECOND = 46186158000
#: Versions this writer produces: 7.4 (32-bit offsets) and 7.5 (64-bit offsets).
SUPPORTED_VERSIONS = (7400, 7500)
#: ``FileId``, ``CreationTime`` and the footer id are checked against each other by the FBX SDK.
#: These three values form a consistent set (the one Blender's exporter writes, so the SDK and
#: every reader accept them); the real creation date goes in ``CreationTimeStamp``.
FILE_ID = bytes.fromhex("28b32aebb624ccc2bfc8b02aa92bfcf1")
CREATION_TIME = "1970-01-01 10:00:00:000"
FOOTER_ID = bytes.fromhex("fabcab09d0c8d466b176fb831cf7267e")
#: The last 16 bytes of every binary FBX file.
FOOTER_MAGIC = bytes.fromhex("f85a8c6adef5d97eece90ce3758f290b")

_ALWAYS_SENTINEL = {"AnimationStack", "AnimationLayer"}
_ARRAY_CODES = {np.dtype(np.float32): b"f", np.dtype(np.float64): b"d", np.dtype(np.int32): b"i",
                np.dtype(np.int64): b"l", np.dtype(np.bool_): b"b"}
#: Arrays larger than this many bytes are zlib-compressed (as the FBX SDK does).
_COMPRESS_ABOVE = 128


@dataclass(frozen=True)
class Prop:
    """One encoded property: its type code and its little-endian payload."""

    code: bytes
    payload: bytes

    def __len__(self) -> int:
        return 1 + len(self.payload)


def p_bool(v: bool) -> Prop:
    """bool property."""
    return Prop(b"C", b"\x01" if v else b"\x00")


def p_int16(v: int) -> Prop:
    """int16 property."""
    return Prop(b"Y", struct.pack("<h", int(v)))


def p_int32(v: int) -> Prop:
    """int32 property."""
    return Prop(b"I", struct.pack("<i", int(v)))


def p_int64(v: int) -> Prop:
    """int64 property."""
    return Prop(b"L", struct.pack("<q", int(v)))


def p_float32(v: float) -> Prop:
    """float32 property."""
    return Prop(b"F", struct.pack("<f", float(v)))


def p_float64(v: float) -> Prop:
    """float64 property."""
    return Prop(b"D", struct.pack("<d", float(v)))


def p_string(v: str | bytes) -> Prop:
    """String property (UTF-8)."""
    b = v.encode("utf-8") if isinstance(v, str) else bytes(v)
    return Prop(b"S", struct.pack("<I", len(b)) + b)


def p_raw(v: bytes) -> Prop:
    """Raw bytes property."""
    return Prop(b"R", struct.pack("<I", len(v)) + bytes(v))


def p_array(values: Any, dtype: Any) -> Prop:
    """Array property of ``dtype`` (float32, float64, int32, int64 or bool).

    Arrays over 128 bytes are zlib-compressed (encoding 1), smaller ones stored raw.
    """
    dt = np.dtype(dtype)
    code = _ARRAY_CODES.get(dt)
    if code is None:
        raise ValueError(f"FBX arrays hold float32, float64, int32, int64 or bool, not {dt}")
    arr = np.ascontiguousarray(np.asarray(values).reshape(-1), dtype=dt.newbyteorder("<"))
    raw = arr.tobytes()
    encoding = 0
    if len(raw) > _COMPRESS_ABOVE:
        raw, encoding = zlib.compress(raw, 1), 1  # level 1: 3x faster than 6, same size here
    return Prop(code, struct.pack("<III", arr.size, encoding, len(raw)) + raw)


@dataclass
class FbxNode:
    """A node record: name, properties, children.

    Build with ``FbxNode("Version", [p_int32(232)])``; add children with :meth:`add`.
    """

    name: str
    props: list[Prop] = field(default_factory=list)
    children: list["FbxNode"] = field(default_factory=list)

    def add(self, name: str, *props: Prop) -> "FbxNode":
        """Append a child node and return it."""
        child = FbxNode(name, list(props))
        self.children.append(child)
        return child

    def find(self, name: str) -> "FbxNode | None":
        """First child called ``name``."""
        return next((c for c in self.children if c.name == name), None)


def _encode_nodes(nodes: list[FbxNode], offset: int, wide: bool, out: list[bytes]) -> int:
    """Append the records of sibling ``nodes`` starting at file ``offset``; return the end."""
    for k, node in enumerate(nodes):
        offset = _encode_node(node, offset, wide, k == len(nodes) - 1, out)
    return offset


def _encode_node(node: FbxNode, offset: int, wide: bool, is_last: bool, out: list[bytes]) -> int:
    name = node.name.encode("utf-8")
    if len(name) > 255:
        raise ValueError(f"FBX node name longer than 255 bytes: {node.name[:40]!r}...")
    head_fmt = "<QQQ" if wide else "<III"
    sentinel = b"\x00" * (25 if wide else 13)
    props = b"".join(p.code + p.payload for p in node.props)
    head_at = len(out)
    out.append(b"")  # placeholder for the header, filled once the end offset is known
    out.append(props)
    pos = offset + struct.calcsize(head_fmt) + 1 + len(name) + len(props)
    if node.children:
        pos = _encode_nodes(node.children, pos, wide, out)
        out.append(sentinel)
        pos += len(sentinel)
    elif (not node.props or node.name in _ALWAYS_SENTINEL) and not is_last:
        out.append(sentinel)
        pos += len(sentinel)
    limit = 2 ** 64 if wide else 2 ** 32
    if pos >= limit:
        raise ValueError("the FBX data exceed 4 GiB: write version 7500 (64-bit offsets)")
    out[head_at] = struct.pack(head_fmt, pos, len(node.props), len(props)) + bytes([len(name)]) + name
    return pos


def encode_fbx(nodes: list[FbxNode], version: int = 7400) -> bytes:
    """A complete binary FBX file holding the top-level ``nodes``.

    Parameters
    ----------
    nodes : list of FbxNode
        Top-level records in file order (``FBXHeaderExtension``, ``FileId``, ...).
    version : {7400, 7500}
        7400 writes 32-bit record offsets, 7500 64-bit ones.

    Returns
    -------
    bytes
        Header, records, top-level null record, footer.
    """
    if version not in SUPPORTED_VERSIONS:
        raise ValueError(f"FBX version must be one of {SUPPORTED_VERSIONS}, got {version}")
    wide = version >= 7500
    out: list[bytes] = [HEADER_MAGIC + struct.pack("<I", version)]
    end = _encode_nodes(nodes, len(out[0]), wide, out)
    out.append(b"\x00" * (25 if wide else 13))
    end += 25 if wide else 13
    # Footer: id, 4 zero bytes, zero padding to a 16-byte boundary (a full 16 if already
    # aligned), the version, 120 zero bytes, the magic.
    end += len(FOOTER_ID) + 4
    pad = (-end) % 16 or 16
    out.append(FOOTER_ID + b"\x00" * 4 + b"\x00" * pad + struct.pack("<I", version) + b"\x00" * 120
               + FOOTER_MAGIC)
    return b"".join(out)
