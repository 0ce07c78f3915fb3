"""Blob detections as CSV: ``frame,camera,x,y,major,minor,angle,polarity,score``.

One row per detection, a header row first, coordinates in raw pixels (the centre of the
top-left pixel is ``(0, 0)``), semi-axes in pixels, angle in radians, polarity ``1`` (white)
or ``-1`` (black), score the detector's probability 0..1. Floats are written with 9
significant digits, enough to read back every float32 exactly. Lines starting with ``#`` are
comments. Rows are sorted by frame, then camera, keeping each table's order.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from ..model.detections import DETECTION_FIELDS, Detections
from .atomic import atomic_write_text

__all__ = ["HEADER", "write_detections_csv", "read_detections_csv", "tables_from_detections",
           "detections_from_tables"]

HEADER: tuple[str, ...] = ("frame", "camera", "x", "y", "major", "minor", "angle", "polarity", "score")

Table = Mapping[str, np.ndarray]
Rows = Mapping[tuple[int, int], Table] | Iterable[tuple[int, int, Table]]


def _iter_tables(rows: Rows) -> list[tuple[int, int, Table]]:
    if isinstance(rows, Mapping):
        items = [(int(f), int(c), t) for (f, c), t in rows.items()]
    else:
        items = [(int(f), int(c), t) for f, c, t in rows]
    items.sort(key=lambda it: (it[0], it[1]))
    return items


def write_detections_csv(path: str | os.PathLike, rows: Rows) -> None:
    """Write detection tables to a CSV file atomically.

    Parameters
    ----------
    path : path-like
        Destination; written to a temporary file in the same folder, then renamed over it.
    rows : mapping or iterable
        ``{(frame, camera): table}`` or an iterable of ``(frame, camera, table)``, where a
        table is a dict of equal-length arrays with the fields of
        :data:`carapost.model.detections.DETECTION_FIELDS` (as returned by
        :func:`carapost.core.blobs.detect_blobs`).

    Raises
    ------
    ValueError
        If a table lacks a field or its arrays differ in length (the file is not touched).
    """
    path = Path(path)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(HEADER)
    for f, c, t in _iter_tables(rows):
        missing = [k for k in DETECTION_FIELDS if k not in t]
        if missing:
            raise ValueError(f"{path}: detections of frame {f}, camera {c} lack {', '.join(missing)}")
        cols = {k: np.asarray(t[k]) for k in DETECTION_FIELDS}
        n = len(cols["x"])
        if any(len(v) != n for v in cols.values()):
            raise ValueError(f"{path}: detections of frame {f}, camera {c} have fields of different lengths")
        xs = {k: cols[k].astype(np.float32) for k in ("x", "y", "major", "minor", "angle", "score")}
        pol = cols["polarity"].astype(np.int64)
        for i in range(n):
            w.writerow([f, c, *(f"{float(xs[k][i]):.9g}" for k in ("x", "y", "major", "minor", "angle")),
                        int(pol[i]), f"{float(xs['score'][i]):.9g}"])
    atomic_write_text(path, buf.getvalue())


def read_detections_csv(path: str | os.PathLike) -> dict[tuple[int, int], dict[str, np.ndarray]]:
    """Read a detections CSV.

    Returns
    -------
    dict
        ``{(frame, camera): table}`` with the dtypes of
        :data:`carapost.model.detections.DETECTION_FIELDS`, in file order within each table.

    Raises
    ------
    ValueError
        If the file is missing, has no or a wrong header, or a row is malformed (the message
        names the file and the line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{path}: no such detections file") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (UTF-8) CSV file") from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{path}: empty file, expected the header {','.join(HEADER)}")
    header = tuple(h.strip().lower() for h in next(csv.reader([lines[0][1]])))
    if header != HEADER:
        raise ValueError(f"{path}: line {lines[0][0]}: expected the header {','.join(HEADER)}, got {lines[0][1]!r}")
    acc: dict[tuple[int, int], list[list[float]]] = {}
    for (lineno, ln), row in zip(lines[1:], csv.reader([ln for _, ln in lines[1:]])):
        if len(row) != len(HEADER):
            raise ValueError(f"{path}: line {lineno}: expected {len(HEADER)} values, got {len(row)}")
        try:
            f, c = int(row[0]), int(row[1])
            vals = [float(v) for v in row[2:]]
        except ValueError:
            raise ValueError(f"{path}: line {lineno}: not a number in {ln!r}") from None
        if f < 0 or c < 0:
            raise ValueError(f"{path}: line {lineno}: negative frame or camera")
        if vals[5] not in (1.0, -1.0):
            raise ValueError(f"{path}: line {lineno}: polarity must be 1 or -1, got {row[7]!r}")
        if not all(np.isfinite(vals)):
            raise ValueError(f"{path}: line {lineno}: non-finite value")
        acc.setdefault((f, c), []).append(vals)
    out: dict[tuple[int, int], dict[str, np.ndarray]] = {}
    for key, vals in acc.items():
        a = np.asarray(vals, float)
        out[key] = {k: a[:, j].astype(dt) for j, (k, dt) in enumerate(DETECTION_FIELDS.items())}
    return out


def tables_from_detections(dets: Mapping[int, Detections] | list[Detections],
                           *, detected_only: bool = True) -> dict[tuple[int, int], dict[str, np.ndarray]]:
    """``{(frame, camera): table}`` from per-camera :class:`Detections` (camera -> detections)."""
    items = dets.items() if isinstance(dets, Mapping) else enumerate(dets)
    out = {}
    for cam, d in items:
        for f in range(d.n_frames):
            if detected_only and not d.detected[f] and d.count(f) == 0:
                continue
            out[(f, int(cam))] = {k: v.copy() for k, v in d.frame(f).items()}
    return out


def detections_from_tables(tables: Mapping[tuple[int, int], Table], n_frames: int,
                           n_cameras: int) -> list[Detections]:
    """Per-camera :class:`Detections` from ``{(frame, camera): table}``.

    Raises
    ------
    ValueError
        If a frame or camera is outside ``n_frames`` / ``n_cameras``.
    """
    per_cam: list[dict[int, Table]] = [{} for _ in range(n_cameras)]
    for (f, c), t in tables.items():
        if not (0 <= c < n_cameras):
            raise ValueError(f"camera {c} outside 0..{n_cameras - 1}")
        if not (0 <= f < n_frames):
            raise ValueError(f"frame {f} outside 0..{n_frames - 1}")
        per_cam[c][f] = t
    return [Detections.from_frames(n_frames, frames) for frames in per_cam]
