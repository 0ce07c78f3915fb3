"""Marker trajectories as CSV in seed 002's layout (OptiTrack Motive's marker export).

Layout (comma separated)::

    line 1   free text; ``key,value`` pairs such as ``Length Units,Millimeters`` and
             ``Export Frame Rate,100`` are understood
    line 2   (anything, usually empty)
    line 3   (anything; written as ``,Type,Marker,Marker,...``)
    line 4   ``,Name,<m1>,<m1>,<m1>,<m2>,<m2>,<m2>,...``: marker names from the third column,
             each repeated for its x, y, z columns
    line 5   (anything; written as ``,ID,1,1,1,2,2,2,...``)
    line 6   (anything; written as ``,,Position,Position,...``)
    line 7   ``Frame,Time,X,Y,Z,X,Y,Z,...`` (the column titles)
    then     ``<frame>,<time>,x,y,z,...`` one line per frame; an empty cell is a missing value

Seed 002 describes "6 header lines" with the names on the 4th; its reader removes the 4th line
and then 6 more, i.e. 7 lines before the data, which is also what Motive writes. The reader
here takes the names from line 4 and the data from the first line after it whose first cell is
a frame number, so files with 6 or 7 header lines both read. A name given once per marker
(followed by two empty cells) is accepted too.

Coordinates are converted to millimetres: the unit comes from ``Length Units`` in line 1, else
from the ``units`` argument (default millimetres; seed 002's own files were in metres).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write_bytes

__all__ = ["MarkerCSV", "MarkerCSVError", "read_marker_csv", "write_marker_csv", "UNIT_TO_MM"]

#: Length units understood (``Length Units`` values and the ``units`` argument), to mm.
UNIT_TO_MM = {"mm": 1.0, "millimeters": 1.0, "millimetres": 1.0, "cm": 10.0, "centimeters": 10.0,
              "centimetres": 10.0, "m": 1000.0, "meters": 1000.0, "metres": 1000.0}


class MarkerCSVError(ValueError):
    """A marker CSV file that cannot be read or written; the message names the file."""


@dataclass
class MarkerCSV:
    """Marker trajectories read from a CSV file.

    Attributes
    ----------
    names : list of str (M,)
    xyz : float64 (F, M, 3)
        Millimetres; NaN where a value is missing.
    frames : int64 (F,)
        The file's frame numbers.
    times : float64 (F,)
        Seconds (NaN where the file has none).
    frame_rate : float
        From line 1 if given, else from the time column (0 if unknown).
    units : str
        The file's length unit as found (or assumed).
    first_line : str
        Line 1 as read (kept when writing a labelled copy).
    """

    names: list[str]
    xyz: np.ndarray
    frames: np.ndarray
    times: np.ndarray
    frame_rate: float
    units: str
    first_line: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.xyz.shape[0])


def _keyvals(line: str) -> dict[str, str]:
    cells = [c.strip() for c in line.split(",")]
    return {cells[i].lower(): cells[i + 1] for i in range(0, len(cells) - 1, 2) if cells[i]}


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def read_marker_csv(path: str | os.PathLike, *, units: str | None = None) -> MarkerCSV:
    """Read marker trajectories in seed 002's (Motive's) CSV layout.

    Parameters
    ----------
    path : path-like
    units : str, optional
        Length unit of the coordinates when line 1 does not say (``"mm"``, ``"cm"``, ``"m"``,
        ...); default millimetres.

    Returns
    -------
    MarkerCSV

    Raises
    ------
    MarkerCSVError
        Unreadable file, fewer than 5 lines, no marker names on line 4, a non-numeric value,
        an unknown unit, or no data line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise MarkerCSVError(f"{path}: cannot read the marker CSV ({e})") from e
    lines = text.splitlines()
    if len(lines) < 5:
        raise MarkerCSVError(f"{path}: a marker CSV needs header lines and data; found {len(lines)} lines")
    info = _keyvals(lines[0])
    unit = info.get("length units", units or "mm").strip().lower()
    if unit not in UNIT_TO_MM:
        raise MarkerCSVError(f"{path}: unknown length unit {unit!r} (expected one of {sorted(UNIT_TO_MM)})")
    cells = [c.strip() for c in lines[3].split(",")]
    raw = cells[2:]
    n_m = len(raw) // 3
    if n_m == 0:
        raise MarkerCSVError(f"{path}: line 4 holds no marker names (they start in the third column)")
    names = []
    for k in range(n_m):
        trio = [c for c in raw[3 * k:3 * k + 3] if c]
        if not trio:
            raise MarkerCSVError(f"{path}: line 4 has no name for marker {k + 1} (column {3 + 3 * k})")
        names.append(trio[0])
    start = next((i for i in range(4, len(lines)) if lines[i].split(",", 1)[0].strip().lstrip("-").isdigit()
                  and _is_number(lines[i].split(",", 1)[0])), None)
    if start is None:
        raise MarkerCSVError(f"{path}: no data line (a line starting with a frame number) after the header")
    width = 2 + 3 * n_m
    rows = []
    for i in range(start, len(lines)):
        ln = lines[i]
        if not ln.strip():
            continue
        c = [x.strip() for x in ln.split(",")]
        if len(c) < width:
            c += [""] * (width - len(c))
        rows.append(c[:width])
    arr = np.array(rows, dtype=object)
    arr[arr == ""] = "nan"
    try:
        num = arr.astype(np.float64)
    except ValueError as e:
        raise MarkerCSVError(f"{path}: a value is not a number ({e})") from e
    frames_f = num[:, 0]
    if not np.isfinite(frames_f).all():
        raise MarkerCSVError(f"{path}: every data line needs a frame number")
    xyz = num[:, 2:].reshape(len(num), n_m, 3) * UNIT_TO_MM[unit]
    xyz[~np.isfinite(xyz).all(-1)] = np.nan
    times = num[:, 1]
    rate = 0.0
    for key in ("export frame rate", "capture frame rate", "frame rate"):
        if key in info and _is_number(info[key]) and float(info[key]) > 0:
            rate = float(info[key])
            break
    if rate == 0.0 and np.isfinite(times).sum() > 1:
        dtm = np.diff(times[np.isfinite(times)])
        if (dtm > 0).any():
            rate = float(1.0 / np.median(dtm[dtm > 0]))
    return MarkerCSV(names, xyz, frames_f.astype(np.int64), times, rate, unit, lines[0])


def write_marker_csv(path: str | os.PathLike, names: Sequence[str], xyz: np.ndarray, *,
                     frame_rate: float = 0.0, frames: np.ndarray | None = None,
                     times: np.ndarray | None = None, first_line: str | None = None,
                     units: str = "mm", decimals: int = 6) -> None:
    """Write marker trajectories in seed 002's layout, atomically.

    Parameters
    ----------
    path : path-like
        Destination; its folder must exist.
    names : sequence of str (M,)
        Marker names (no commas).
    xyz : float (F, M, 3)
        Millimetres; NaN is written as empty cells.
    frame_rate : float
        Hz (written in line 1; also makes the times when ``times`` is not given).
    frames : int (F,), optional
        Frame numbers (default 0, 1, 2, ...).
    times : float (F,), optional
        Seconds.
    first_line : str, optional
        Line 1 (e.g. the source file's); default a CaraPost line with the frame rate and unit.
    units : str
        Unit to write the coordinates in (``"mm"`` or ``"m"`` ...).
    decimals : int
        Digits after the decimal point.

    Raises
    ------
    MarkerCSVError
        Bad shapes, a name containing a comma, an unknown unit, or the folder is missing.
    """
    path = Path(path)
    x = np.asarray(xyz, np.float64)
    M = len(names)
    if x.ndim != 3 or x.shape[1:] != (M, 3):
        raise MarkerCSVError(f"{path}: xyz must have shape (frames, {M}, 3), got {x.shape}")
    if any("," in n or "\n" in n for n in names):
        raise MarkerCSVError(f"{path}: marker names cannot contain commas or line breaks")
    u = units.lower()
    if u not in UNIT_TO_MM:
        raise MarkerCSVError(f"{path}: unknown length unit {units!r}")
    if not path.parent.is_dir():
        raise MarkerCSVError(f"{path}: cannot write, the folder {path.parent} does not exist")
    F = x.shape[0]
    fr = np.arange(F) if frames is None else np.asarray(frames, np.int64)
    if times is None:
        tm = fr / frame_rate if frame_rate > 0 else np.full(F, np.nan)
    else:
        tm = np.asarray(times, np.float64)
    if fr.shape != (F,) or tm.shape != (F,):
        raise MarkerCSVError(f"{path}: frames and times must have {F} entries")
    unit_word = {"mm": "Millimeters", "cm": "Centimeters", "m": "Meters"}.get(u, units)
    head = first_line if first_line is not None else (
        f"Format Version,1.23,Exported By,CaraPost,Export Frame Rate,{frame_rate:g},Length Units,{unit_word}")
    lines = [head.rstrip("\r\n"), "",
             ",Type," + ",".join(["Marker"] * (3 * M)),
             ",Name," + ",".join(n for n in names for _ in range(3)),
             ",ID," + ",".join(str(k + 1) for k in range(M) for _ in range(3)),
             ",," + ",".join(["Position"] * (3 * M)),
             "Frame,Time (Seconds)," + ",".join(["X", "Y", "Z"] * M)]
    flat = (x / UNIT_TO_MM[u]).reshape(F, 3 * M)
    cells = np.char.mod(f"%.{int(decimals)}f", np.where(np.isfinite(flat), flat, 0.0)).astype(object)
    cells[~np.isfinite(flat)] = ""
    tcol = np.char.mod("%.6f", np.where(np.isfinite(tm), tm, 0.0)).astype(object)
    tcol[~np.isfinite(tm)] = ""
    for f in range(F):
        lines.append(f"{fr[f]},{tcol[f]}," + ",".join(cells[f]))
    data = ("\n".join(lines) + "\n").encode("utf-8")
    atomic_write_bytes(path, data)
