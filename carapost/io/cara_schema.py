"""The ``.cara`` schema: version, error type, dataset layout policy (chunks and compression).

The full layout is documented in ``docs/formats/cara.md``; :mod:`carapost.io.cara_write`
writes it and :mod:`carapost.io.cara_read` reads it. This module holds what both share.

Compression
-----------
Big per-frame arrays are chunked along frames (:data:`FRAME_CHUNK` frames per chunk) and
detection arrays along detections (:data:`DETECTION_CHUNK`). They are compressed with Blosc
(LZ4 codec, bit-shuffle, level 5; HDF5 filter 32001, registered by the ``hdf5plugin``
package), chosen by measurement (``benchmarks/bench_cara.py``): on a 10,000-frame take it
saves about 5x faster than gzip level 1 with shuffle and about 4x faster than LZF, with a
file about the size of gzip's. When ``hdf5plugin`` is not installed, files are written with
the built-in LZF filter plus shuffle instead (slower, readable by any h5py); reading a Blosc
file then fails with a :class:`CaraError` that says which package is missing.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import h5py
import numpy as np

_hdf5plugin: ModuleType | None
try:  # registers the Blosc filter with HDF5
    import hdf5plugin as _hdf5plugin
except ImportError:  # pragma: no cover - exercised only without the optional package
    _hdf5plugin = None

__all__ = [
    "FORMAT",
    "CARA_VERSION",
    "FRAME_CHUNK",
    "DETECTION_CHUNK",
    "SMALL_BYTES",
    "MAX_CHUNK_BYTES",
    "CaraError",
    "blosc_available",
    "compression_kwargs",
    "dataset_kwargs",
    "STR_DTYPE",
]

#: Value of the root attribute ``format``.
FORMAT = "carapost.cara"
#: The schema version this code writes, ``(major, minor)``. A newer major version is refused;
#: a newer minor version is read, ignoring what this version does not know.
CARA_VERSION: tuple[int, int] = (1, 0)

#: Frames per chunk of the per-frame arrays (``R``, ``t`` and the point arrays).
FRAME_CHUNK = 256
#: Detections per chunk of the per-detection arrays.
DETECTION_CHUNK = 65_536
#: Arrays other than per-frame ones smaller than this are stored contiguous, uncompressed.
SMALL_BYTES = 64 * 1024
#: Upper bound on one chunk's size; fewer frames per chunk are used for very wide arrays.
MAX_CHUNK_BYTES = 16 * 1024 * 1024

#: Variable-length UTF-8 strings.
STR_DTYPE = h5py.string_dtype("utf-8")

#: HDF5 registered filter id of Blosc.
BLOSC_FILTER_ID = 32001


class CaraError(ValueError):
    """A ``.cara`` file cannot be read or written; the message names the file and the problem."""


def blosc_available() -> bool:
    """Whether the Blosc HDF5 filter (from ``hdf5plugin``) can be used."""
    return _hdf5plugin is not None and bool(h5py.h5z.filter_avail(BLOSC_FILTER_ID))


def compression_kwargs() -> dict[str, Any]:
    """``create_dataset`` keyword arguments of the compression used for big arrays."""
    if blosc_available():
        assert _hdf5plugin is not None
        blosc = _hdf5plugin.Blosc
        return dict(blosc(cname="lz4", clevel=5, shuffle=blosc.BITSHUFFLE))
    return {"compression": "lzf", "shuffle": True}


def dataset_kwargs(arr: np.ndarray, *, per_frame: bool) -> dict[str, Any]:
    """Storage options of one array: contiguous if small, else chunked and compressed.

    Parameters
    ----------
    arr : ndarray
        The array to store.
    per_frame : bool
        True if the first axis is frames: always chunked (:data:`FRAME_CHUNK` frames) and
        compressed unless empty. False for other arrays (per detection, per point, ...):
        contiguous if smaller than :data:`SMALL_BYTES`, else chunks of
        :data:`DETECTION_CHUNK` rows.

    Returns
    -------
    dict
        Keyword arguments for ``h5py.Group.create_dataset``.
    """
    if arr.size == 0 or arr.ndim == 0 or (not per_frame and arr.nbytes < SMALL_BYTES):
        return {}
    row_bytes = max(1, arr[:1].nbytes)
    if per_frame:
        rows = max(1, min(FRAME_CHUNK, MAX_CHUNK_BYTES // row_bytes))
    else:
        rows = max(1, min(DETECTION_CHUNK, MAX_CHUNK_BYTES // row_bytes))
    chunks = (min(arr.shape[0], rows),) + arr.shape[1:]
    return {"chunks": chunks, "fletcher32": True, **compression_kwargs()}
