"""CSV exports: 3D trajectories and 2D tracks (``docs/formats/exports.md``).

* :func:`export_csv_3d`: one row per frame: ``frame,time`` then ``x,y,z`` of each point; one
  header row ``frame,time,<name>:X,<name>:Y,<name>:Z,...``. ``frame`` is the CaraPost frame
  number, ``time`` seconds (``frame / rate``); coordinates in the Export section's axes and
  units (6 decimals in mm, 7 in cm); gaps are empty cells.
* :func:`export_csv_2d`: one row per 2D observation: ``frame,point,camera,x,y,source,quality``,
  grouped by camera, then frame, then point. ``x, y`` are raw (distorted) pixels with the
  centre of the top-left pixel at (0, 0); ``source`` is ``BLOB``, ``PATCH``, ``TARGET`` or
  ``KEYFRAME``; ``quality`` the target-track match score (empty when none).
* :func:`read_csv_3d` reads a 3D file back.

Both writers are atomic and quote names with ``csv`` rules when needed.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carapost.model.params import ExportParameters
from carapost.model.take import ObsSource, Take

from .atomic import atomic_write_bytes
from .export import frame_range, prepare_export, select_points, unique_names

__all__ = ["export_csv_3d", "export_csv_2d", "read_csv_3d", "CSV3D", "csv_3d_text", "csv_2d_text"]

_DECIMALS = {"mm": 6, "cm": 7, "m": 9, "in": 8}


def _header_line(fields: list[str]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(fields)
    return buf.getvalue()


def csv_3d_text(take: Take, *, options: ExportParameters | None = None,
                selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
                points: np.ndarray | list[int] | None = None) -> str:
    """The 3D trajectory CSV of a take (see :func:`export_csv_3d`)."""
    data = prepare_export(take, options=options, selection=selection, points=points, frames=frames)
    header = ["frame", "time"] + [f"{n}:{a}" for n in data.names for a in "XYZ"]
    dec = _DECIMALS[data.units]
    fmt = ",".join(["%d", "%.6f"] + [f"%.{dec}f"] * (3 * data.n_points)) + "\n"
    table = np.concatenate([data.frame_numbers[:, None].astype(float), data.times[:, None],
                            data.xyz.reshape(data.n_frames, -1)], axis=1)
    # Python's %-formatting writes NaN as "nan"; no other field holds letters.
    rows = "".join(fmt % tuple(row) for row in table.tolist()).replace("nan", "")
    return _header_line(header) + rows


def export_csv_3d(take: Take, path: str | os.PathLike, *, options: ExportParameters | None = None,
                  selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
                  points: np.ndarray | list[int] | None = None) -> None:
    """Write 3D trajectories as CSV, atomically.

    Parameters
    ----------
    take : Take
    path : path-like
    options : ExportParameters, optional
        Units, up axis, raw / stabilized, selected only, brim (default ``take.params.export``).
    selection, frames, points
        As :func:`carapost.io.export.prepare_export`.

    Raises
    ------
    ValueError
        Nothing to export, bad range or selection (the message names the file).
    """
    path = Path(path)
    try:
        text = csv_3d_text(take, options=options, selection=selection, frames=frames, points=points)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    atomic_write_bytes(path, text.encode("utf-8"))


def csv_2d_text(take: Take, *, options: ExportParameters | None = None,
                selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
                points: np.ndarray | list[int] | None = None, cameras: list[int] | None = None) -> str:
    """The 2D track CSV of a take (see :func:`export_csv_2d`)."""
    idx = select_points(take, options=options, selection=selection, points=points)
    fr = frame_range(take, frames)
    cams = list(range(take.n_cameras)) if cameras is None else [int(c) for c in cameras]
    if any(not 0 <= c < take.n_cameras for c in cams):
        raise ValueError(f"cameras must be in 0..{take.n_cameras - 1}, got {cameras}")
    names = unique_names([take.points.name(int(i)) for i in idx])
    xy = take.obs_xy[fr[0]:fr[-1] + 1][:, idx][:, :, cams]           # (N, K, C', 2)
    src = take.obs_src[fr[0]:fr[-1] + 1][:, idx][:, :, cams]
    q = take.obs_q[fr[0]:fr[-1] + 1][:, idx][:, :, cams]
    ok = np.isfinite(xy).all(-1)
    c_i, n_i, k_i = np.nonzero(ok.transpose(2, 0, 1))                 # camera, frame, point order
    numbers = (int(take.first_frame_number) + fr)[n_i]
    xs = xy[n_i, k_i, c_i, 0].astype(float)
    ys = xy[n_i, k_i, c_i, 1].astype(float)
    qs = q[n_i, k_i, c_i].astype(float)
    ss = src[n_i, k_i, c_i]
    src_names = np.full(256, "NONE", dtype=object)
    for member in ObsSource:
        src_names[int(member)] = member.name
    quoted = np.array([_header_line([n]).rstrip("\n") for n in names], dtype=object)
    cam_ids = np.array([take.cameras[c].channel for c in cams], dtype=np.int64)
    qtext = [("" if q != q else f"{q:.4f}") for q in qs.tolist()]  # q != q: NaN
    lines = [f"{n},{p},{c},{x:.4f},{y:.4f},{s},{qq}\n" for n, p, c, x, y, s, qq in
             zip(numbers.tolist(), quoted[k_i].tolist(), cam_ids[c_i].tolist(), xs.tolist(), ys.tolist(),
                 src_names[ss].tolist(), qtext)]
    return "frame,point,camera,x,y,source,quality\n" + "".join(lines)


def export_csv_2d(take: Take, path: str | os.PathLike, *, options: ExportParameters | None = None,
                  selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
                  points: np.ndarray | list[int] | None = None, cameras: list[int] | None = None) -> None:
    """Write 2D tracks (every observation of every point in every camera) as CSV, atomically.

    Parameters
    ----------
    take : Take
    path : path-like
    options : ExportParameters, optional
        Only the point options apply (selected only, brim); pixels are not converted.
    selection, frames, points
        As :func:`carapost.io.export.prepare_export`.
    cameras : list of int, optional
        Camera indices to write (default: all); the ``camera`` column holds their channel.

    Raises
    ------
    ValueError
        Nothing to export, bad range, selection or camera (the message names the file).
    """
    path = Path(path)
    try:
        text = csv_2d_text(take, options=options, selection=selection, frames=frames, points=points,
                           cameras=cameras)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    atomic_write_bytes(path, text.encode("utf-8"))


@dataclass
class CSV3D:
    """A 3D trajectory CSV read back: ``names (P,)``, ``frames (N,)``, ``times (N,)``,
    ``xyz (N, P, 3)`` (file units, NaN gaps)."""

    names: list[str]
    frames: np.ndarray
    times: np.ndarray
    xyz: np.ndarray


def read_csv_3d(path: str | os.PathLike) -> CSV3D:
    """Read a file written by :func:`export_csv_3d`.

    Raises
    ------
    ValueError
        Not such a file (the message names it and the line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ValueError(f"{path}: cannot read the file ({e.strerror or e})") from None
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or rows[0][:2] != ["frame", "time"] or (len(rows[0]) - 2) % 3:
        raise ValueError(f"{path}: not a CaraPost 3D CSV (expected a header 'frame,time,<name>:X,...')")
    cols = rows[0][2:]
    names = [c.rsplit(":", 1)[0] for c in cols[::3]]
    body = [r for r in rows[1:] if any(s.strip() for s in r)]
    table = np.full((len(body), len(rows[0])), np.nan)
    for i, r in enumerate(body):
        if len(r) != len(rows[0]):
            raise ValueError(f"{path}: line {i + 2} has {len(r)} fields, expected {len(rows[0])}")
        try:
            table[i] = [float(s) if s.strip() else np.nan for s in r]
        except ValueError:
            raise ValueError(f"{path}: line {i + 2}: a field is not a number") from None
    return CSV3D(names=names, frames=table[:, 0].astype(np.int64), times=table[:, 1],
                 xyz=table[:, 2:].reshape(len(body), len(names), 3))
