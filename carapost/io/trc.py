"""TRC marker trajectories (OpenSim, Mokka, Pose2Sim): write and read.

A TRC file is text, tab-separated (some writers use commas)::

    PathFileType  4  (X/Y/Z)  take.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    60  60  151  41  mm  60  1  151
    Frame#  Time  Nose_Tip        Chin ...           (a name every third column)
                  X1  Y1  Z1  X2  Y2  Z2 ...
                                                     (a blank line)
    1  0.000000  617.247620  1055.275020  170.781980 ...

:func:`export_trc` writes the take's points (Export section: points, raw / stabilized, up axis;
units mm or cm, or ``units="m"``). ``Frame#`` is the CaraPost frame number + 1 (TRC, like C3D,
counts from 1), ``Time`` is ``frame number / rate`` seconds. Gaps are blank fields (what
OpenSim and Mokka read as missing), or ``missing="NaN"``.

:func:`read_trc` reads any TRC: tab or comma separated, missing samples as blank fields or any
case of ``NaN``, header frame counts that disagree with the rows present (truncated files are
read as far as they go, and say so).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carapost.model.params import ExportParameters
from carapost.model.take import Take

from .atomic import atomic_write_bytes
from .export import prepare_export

__all__ = ["TRCData", "TRCError", "export_trc", "trc_text", "read_trc"]

_TO_MM = {"mm": 1.0, "millimeters": 1.0, "millimetres": 1.0, "cm": 10.0, "m": 1000.0, "meters": 1000.0,
          "metres": 1000.0, "in": 25.4, "inches": 25.4}
_DECIMALS = {"mm": 6, "cm": 7, "m": 9}


class TRCError(ValueError):
    """A TRC file cannot be read; the message names the file and, where it applies, the line."""


def _rate(v: float) -> str:
    return format(float(v), ".10g")


def _clean(name: str) -> str:
    return "_".join(name.split()) or "_"


def trc_text(take: Take, *, options: ExportParameters | None = None,
             selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
             points: np.ndarray | list[int] | None = None, units: str | None = None,
             missing: str = "", file_name: str = "take.trc") -> str:
    """The TRC text of a take (see :func:`export_trc`)."""
    if units is not None and units not in _DECIMALS:
        raise ValueError(f"TRC units must be mm, cm or m, got {units!r}")
    if "\t" in missing or "\n" in missing:
        raise ValueError("the missing-value text cannot hold tabs or line breaks")
    data = prepare_export(take, options=options, selection=selection, points=points, frames=frames, units=units)
    if data.units not in _DECIMALS:
        raise ValueError(f"TRC units must be mm, cm or m, got {data.units!r}")
    N, K = data.n_frames, data.n_points
    rate = _rate(data.frame_rate)
    first = int(data.frame_numbers[0]) + 1
    lines = [f"PathFileType\t4\t(X/Y/Z)\t{file_name}",
             "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
             f"{rate}\t{rate}\t{N}\t{K}\t{data.units}\t{rate}\t{first}\t{N}",
             "Frame#\tTime\t" + "\t".join(f"{_clean(n)}\t\t" for n in data.names),
             "\t\t" + "\t".join(f"X{k + 1}\tY{k + 1}\tZ{k + 1}" for k in range(K)),
             ""]
    dec = _DECIMALS[data.units]
    fmt = "\t".join(["%d", "%.6f"] + [f"%.{dec}f"] * (3 * K)) + "\n"
    table = np.concatenate([(data.frame_numbers + 1)[:, None].astype(float), data.times[:, None],
                            data.xyz.reshape(N, -1)], axis=1)
    body = "".join(fmt % tuple(row) for row in table.tolist()).replace("nan", missing)
    return "\n".join(lines) + "\n" + body


def export_trc(take: Take, path: str | os.PathLike, *, options: ExportParameters | None = None,
               selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
               points: np.ndarray | list[int] | None = None, units: str | None = None,
               missing: str = "") -> None:
    """Write a take's points as a TRC file, atomically.

    Parameters
    ----------
    take : Take
    path : path-like
    options : ExportParameters, optional
        Points, raw / stabilized data, up axis, units (default ``take.params.export``).
    selection, frames, points
        As :func:`carapost.io.export.prepare_export`.
    units : {"mm", "cm", "m"}, optional
        Overrides the options' units (OpenSim models work in metres).
    missing : str
        Text of a missing coordinate: "" (blank field, default) or e.g. ``"NaN"``.

    Raises
    ------
    ValueError
        Nothing to export, bad range, selection or units (the message names the file).
    """
    path = Path(path)
    try:
        text = trc_text(take, options=options, selection=selection, frames=frames, points=points, units=units,
                        missing=missing, file_name=path.name)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    atomic_write_bytes(path, text.encode("utf-8"))


@dataclass
class TRCData:
    """A TRC file's trajectories.

    Attributes
    ----------
    path : str
    labels : list of str (P,)
    frame_numbers : int64 (N,)
        The ``Frame#`` column (TRC counts from 1).
    times : float64 (N,)
        Seconds.
    xyz : float64 (N, P, 3)
        Positions in millimetres (converted from the file's units); NaN where missing.
    data_rate, camera_rate : float
        Hz.
    units : str
        As written in the file.
    scale_to_mm : float
    declared_frames, declared_markers : int
        ``NumFrames`` / ``NumMarkers`` of the header.
    orig_start_frame : int
        ``OrigDataStartFrame`` (1 if absent).
    truncated : bool
        Fewer data rows than ``NumFrames``.
    """

    path: str
    labels: list[str]
    frame_numbers: np.ndarray
    times: np.ndarray
    xyz: np.ndarray
    data_rate: float
    camera_rate: float
    units: str
    scale_to_mm: float
    declared_frames: int
    declared_markers: int
    orig_start_frame: int
    truncated: bool

    @property
    def n_frames(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[1])


def _number(tok: str, path: Path, line: int) -> float:
    s = tok.strip()
    if not s:
        return np.nan
    try:
        return float(s)
    except ValueError:
        raise TRCError(f"{path}: line {line}: {s!r} is not a number") from None


def read_trc(path: str | os.PathLike) -> TRCData:
    """Read a TRC file.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    TRCData
        Positions in millimetres, NaN for blank or NaN fields (any letter case).

    Raises
    ------
    TRCError
        The file is missing or unreadable, is not a TRC file (no ``PathFileType`` line, no
        header), or holds a field that is not a number.
    """
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8", errors="replace")
    except OSError as e:
        raise TRCError(f"{path}: cannot read the file ({e.strerror or e})") from None
    lines = text.splitlines()
    if not lines or not lines[0].lstrip("\ufeff").startswith("PathFileType"):
        raise TRCError(f"{path}: not a TRC file (the first line does not start with PathFileType)")
    delim = "\t" if "\t" in lines[0] else ","
    if len(lines) < 5:
        raise TRCError(f"{path}: the TRC header is incomplete ({len(lines)} lines, expected at least 5)")
    keys = [k.strip() for k in lines[1].split(delim)]
    vals = [v.strip() for v in lines[2].split(delim)]
    head = {k: v for k, v in zip(keys, vals) if k}
    if "DataRate" not in head or "NumMarkers" not in head:
        raise TRCError(f"{path}: line 2 should name DataRate ... NumMarkers, got {lines[1][:80]!r}")

    def num(key: str, default: float) -> float:
        try:
            return float(head[key]) if head.get(key) else default
        except ValueError:
            raise TRCError(f"{path}: line 3: {key} {head[key]!r} is not a number") from None

    rate = num("DataRate", 0.0)
    declared_frames = int(num("NumFrames", 0))
    declared_markers = int(num("NumMarkers", 0))
    names = [n.strip() for n in lines[3].split(delim)[2:]]
    labels = [n for n in names if n]
    P = len(labels) if labels else declared_markers
    rows = []
    for i, line in enumerate(lines[5:], start=6):
        fields = line.split(delim)
        if not any(f.strip() for f in fields):
            continue
        values = fields[2:2 + 3 * P]
        values += [""] * (3 * P - len(values))
        frame = _number(fields[0], path, i)
        time = _number(fields[1], path, i) if len(fields) > 1 else np.nan
        rows.append([frame, time] + [_number(v, path, i) for v in values])
    table = np.array(rows, dtype=float).reshape(len(rows), 2 + 3 * P)
    units = head.get("Units", "")
    to_mm = _TO_MM.get(units.lower(), 1.0)
    xyz = table[:, 2:].reshape(len(rows), P, 3) * to_mm
    invalid = ~np.isfinite(xyz).all(-1)
    xyz[invalid] = np.nan
    frames = np.where(np.isfinite(table[:, 0]), table[:, 0], 0).astype(np.int64)
    labels += [f"Marker{k + 1}" for k in range(len(labels), P)]
    return TRCData(path=str(path), labels=labels, frame_numbers=frames, times=table[:, 1], xyz=xyz,
                   data_rate=rate, camera_rate=num("CameraRate", rate), units=units, scale_to_mm=to_mm,
                   declared_frames=declared_frames, declared_markers=declared_markers,
                   orig_start_frame=int(num("OrigDataStartFrame", 1)),
                   truncated=len(rows) < declared_frames)

