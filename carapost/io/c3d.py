"""C3D export and import (the format spec is ``docs/formats/c3d.md``).

* :func:`export_c3d` writes a take's points (all or a selection, raw or stabilized, a frame range)
  as an Intel / float C3D file in millimetres, atomically. Gaps are invalid samples (fourth word
  -1, coordinates 0). The reconstruction type (:class:`~carapost.model.take.Recon`) travels in the
  residual word as the C3D spec allows: residual 0 = interpolated (the spec's "modelled" value),
  residual byte 1 / 2 = single-sensor / multi-view, camera-mask bits = the cameras (channels 0..6)
  with an observation. A ``CARAPOST`` parameter group keeps point ids, kinds (face / brim), brim
  dot indices, the frame numbering and the coding version; POINT:DESCRIPTIONS names the kind too.
* :func:`read_c3d` reads any C3D file into :class:`C3DData` (coordinates in mm whatever the file's
  units). The header and parameter section are parsed by CaraPost's own strict parser
  (:mod:`carapost.io.c3d_binary`), which rejects structurally corrupt files with a
  :class:`C3DError`; the point block is decoded by CaraPost's vectorised decoder (Intel, DEC and
  MIPS; integer and float), which gives ezc3d's coordinates bit for bit on every real test file
  ezc3d can open, and also reads the files ezc3d and py-c3d refuse (big-endian, a zero-sized
  POINT:DESCRIPTIONS, Motion Analysis ANALOG:OFFSET). ``reader="ezc3d"`` / ``"py-c3d"`` use those
  libraries for the coordinates instead (ezc3d in a child process: it can segfault on damaged
  files). Residuals and camera masks are always decoded by CaraPost: ezc3d 1.7.2 swaps the two
  bytes of the residual word (mask and residual) relative to the spec and py-c3d.
* :func:`info_c3d` summarises a file for ``carapost info``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carapost import __version__
from carapost.model.take import PointKind, Recon, Take

from . import c3d_binary as cb
from .atomic import atomic_write_bytes
from .export import unique_names
from .c3d_binary import C3DError, ParameterSection

__all__ = ["C3DError", "C3DData", "export_c3d", "read_c3d", "info_c3d", "FORMAT_VERSION",
           "RESIDUAL_SCALE"]

#: Version of the CARAPOST parameter group written by :func:`export_c3d`.
FORMAT_VERSION = 1
#: POINT:SCALE written by :func:`export_c3d`: float data, residual unit 0.01 mm.
RESIDUAL_SCALE = -0.01
_RECON_CODE = {Recon.INTERPOLATED: 0, Recon.SINGLE_SENSOR: 1, Recon.MULTI_VIEW: 2}
_UNIT_TO_MM = {"mm": 1.0, "millimeters": 1.0, "millimetres": 1.0, "cm": 10.0, "dm": 100.0, "m": 1000.0,
               "meters": 1000.0, "metres": 1000.0, "in": 25.4, "inch": 25.4, "inches": 25.4, "ft": 304.8}
_NON_MARKER = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")


@dataclass
class C3DData:
    """The point data of a C3D file.

    Attributes
    ----------
    path : str
    labels : list of str
        One per point (POINT:LABELS, LABELS2...; stripped; ``pointN`` (1-based) where missing).
    descriptions : list of str
        One per point ("" where missing).
    xyz : float64 (F, P, 3)
        Positions in millimetres; NaN where the sample is invalid.
    residual : float64 (F, P)
        Residuals in millimetres; NaN where invalid; 0 means modelled / interpolated.
    camera_mask : uint8 (F, P)
        Bit ``k`` set when camera ``k`` (0..6) contributed; 0 where invalid.
    frame_rate : float
        Hz.
    first_frame : int
        Number of the first frame as stored in the file (C3D numbers frames from 1).
    units : str
        POINT:UNITS as found in the file ("" if absent: millimetres are assumed).
    scale_to_mm : float
        Factor applied to the file's coordinates and residuals.
    recon : uint8 (F, P) or None
        :class:`~carapost.model.take.Recon` of each sample, for files written by CaraPost.
    point_ids, kind, brim_index : int64 / uint8 / int32 (P,) or None
        CaraPost point ids, :class:`~carapost.model.take.PointKind`, brim dot index (-1 for face).
    first_frame_number : int or None
        CaraPost (0-based) frame number of the first frame, for files written by CaraPost.
    stabilized : bool or None
        Whether the file holds stabilized positions (CaraPost files).
    parameters : dict
        Every parameter, ``parameters[group][name]`` -> :class:`~carapost.io.c3d_binary.Parameter`.
    backend : str
        Which reader decoded the coordinates: ``"carapost"``, ``"ezc3d"`` or ``"py-c3d"``.
    """

    path: str
    labels: list[str]
    descriptions: list[str]
    xyz: np.ndarray
    residual: np.ndarray
    camera_mask: np.ndarray
    frame_rate: float
    first_frame: int
    units: str
    scale_to_mm: float
    recon: np.ndarray | None = None
    point_ids: np.ndarray | None = None
    kind: np.ndarray | None = None
    brim_index: np.ndarray | None = None
    first_frame_number: int | None = None
    stabilized: bool | None = None
    parameters: ParameterSection = field(default_factory=dict)
    backend: str = "carapost"

    @property
    def n_frames(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[1])

    def gap_fraction(self) -> float:
        """Share of point x frame samples that are invalid (0 for an empty file)."""
        valid = np.isfinite(self.xyz).all(-1)
        return float(1.0 - valid.mean()) if valid.size else 0.0

    def marker_indices(self) -> np.ndarray:
        """Points that are markers, i.e. not listed in POINT:ANGLES / FORCES / MOMENTS / POWERS /
        SCALARS / REACTIONS (model outputs written by Vicon Nexus and others)."""
        other: set[str] = set()
        for name in _NON_MARKER:
            other.update(s.strip() for s in cb.joined_strings(self.parameters, "POINT", name))
        other.discard("")
        return np.array([i for i, lab in enumerate(self.labels) if lab not in other], np.int64)


# ------------------------------------------------------------------------------------ export
def export_c3d(take: Take, path: str | os.PathLike, *, points: np.ndarray | list[int] | None = None,
               stabilized: bool = False, frames: tuple[int, int] | None = None) -> None:
    """Write points of ``take`` to a C3D file, atomically.

    Parameters
    ----------
    take : Take
    path : path-like
        Destination ``.c3d``; its folder must exist. Replaced atomically.
    points : int array (K,), optional
        Column indices of the points to write, in that order (default: all points).
    stabilized : bool
        Write ``take.xyz_stabilized`` instead of ``take.xyz``.
    frames : (int, int), optional
        Inclusive range of 0-based frame indices (default: the whole take).

    Notes
    -----
    Labels are :meth:`PointTable.name` (the label, else ``Point_<id>`` / ``Brim_<id>``), stripped;
    a name that repeats an earlier one gets ``_2``, ``_3``... (the first unused). The C3D first
    frame is ``take.first_frame_number + frames[0] + 1``: C3D numbers frames from 1, CaraPost from
    0. A finite position whose recon is NONE is written as interpolated.

    Raises
    ------
    ValueError
        Bad selection or range, nothing to write, or a stabilized export of an unstabilized take.
    C3DError
        The data do not fit the format (e.g. more than 65535 points); the folder is missing.
    """
    path = Path(path)
    F, P = take.n_frames, take.n_points
    a, b = (0, F - 1) if frames is None else (int(frames[0]), int(frames[1]))
    if not 0 <= a <= b < F:
        raise ValueError(f"frame range {frames} is outside 0..{F - 1}")
    idx = np.arange(P) if points is None else np.asarray(points).ravel()
    if idx.size and not np.issubdtype(idx.dtype, np.integer):
        raise ValueError("points must be integer column indices")
    idx = idx.astype(np.int64)
    if idx.size == 0:
        raise ValueError(f"no points to export to {path.name}")
    if idx.min() < 0 or idx.max() >= P:
        raise ValueError(f"point indices must be in 0..{P - 1}")
    if len(np.unique(idx)) != len(idx):
        raise ValueError("point indices repeat")
    src = take.xyz_stabilized if stabilized else take.xyz
    if stabilized and not np.isfinite(src).any():
        raise ValueError("the take has not been stabilized: no stabilized positions to export")
    if not path.parent.is_dir():
        raise C3DError(f"{path}: cannot write, the folder {path.parent} does not exist")

    xyz = src[a:b + 1][:, idx]
    valid = np.isfinite(xyz).all(axis=-1)
    recon = take.recon[a:b + 1][:, idx]
    code = np.zeros(recon.shape, np.int64)
    for r, c in _RECON_CODE.items():
        code[recon == r] = c
    n_mask = min(take.n_cameras, 7)
    seen = np.isfinite(take.obs_xy[a:b + 1][:, idx][:, :, :n_mask, 0])
    mask = (seen.astype(np.int64) << np.arange(n_mask)).sum(axis=-1)
    mask[code == 0] = 0
    fourth = np.where(valid, mask * 256 + code, -1).astype(np.float32)
    xyz32 = np.where(valid[..., None], xyz, 0.0).astype(np.float32)

    pts = take.points
    labels = unique_names([pts.name(int(i)).strip() or _generated_name(pts, int(i)) for i in idx])
    kind = pts.kind[idx].astype(np.int64)
    ids = pts.ids[idx].astype(np.int64)
    brim = pts.brim_index[idx].astype(np.int64)
    desc = [_description(int(k), int(i), int(bi)) for k, i, bi in zip(kind, ids, brim)]
    first_number = int(take.first_frame_number) + a
    c3d_first = max(first_number + 1, 1)

    point_params = (_chunked("LABELS", labels, "Point labels")
                    + _chunked("DESCRIPTIONS", desc, "Point descriptions")
                    + [("UNITS", "mm", "Units of the point coordinates")])
    ids_value = ids if ids.max() <= 32767 and ids.min() >= -32768 else ids.astype(np.float32)
    cara = ([("FORMAT_VERSION", FORMAT_VERSION, "Version of this group's layout"),
             ("RECON_CODING", "RESIDUAL_BYTE", "Recon in the residual word, see RECON_NAMES"),
             ("RECON_NAMES", ["NONE", "INTERPOLATED", "SINGLE_SENSOR", "MULTI_VIEW"],
              "invalid=NONE; residual byte 0,1,2 = INTERPOLATED, SINGLE_SENSOR, MULTI_VIEW"),
             ("STABILIZED", int(bool(stabilized)), "1 if stabilized positions"),
             ("FIRST_FRAME_NUMBER", _u32_words(first_number), "CaraPost frame number of frame 1 (lo, hi)"),
             ("FIRST_INDEX", _u32_words(a), "Take frame index of frame 1 (lo, hi)")]
            + _chunked("POINT_IDS", ids_value, "CaraPost point ids")
            + _chunked("KIND", kind, "0 face, 1 brim")
            + _chunked("BRIM_INDEX", brim, "Brim dot index, -1 for face points"))
    if take.name.strip():
        cara.append(("TAKE_NAME", take.name.strip()[:255], "Take name"))
    groups = [("MANUFACTURER", "Writer", [("COMPANY", "CaraPost for Python", ""),
                                           ("SOFTWARE", "carapost", ""),
                                           ("VERSION_LABEL", str(__version__), "")]),
              ("CARAPOST", "CaraPost take data", cara)]
    data = cb.encode_c3d(xyz=xyz32, fourth=fourth, frame_rate=float(take.frame_rate), first_frame=c3d_first,
                         scale=RESIDUAL_SCALE, point_groups={"POINT": point_params}, extra_groups=groups)
    atomic_write_bytes(path, data)


def _generated_name(pts, i: int) -> str:  # a label made only of spaces
    prefix = "Brim" if pts.kind[i] == PointKind.BRIM else "Point"
    return f"{prefix}_{int(pts.ids[i])}"


def _description(kind: int, pid: int, brim_index: int) -> str:
    if kind == PointKind.BRIM:
        return f"CaraPost brim point, id {pid}, brim dot {brim_index}"
    return f"CaraPost face point, id {pid}"


def _u32_words(v: int) -> np.ndarray:
    v = min(max(int(v), 0), 0xFFFFFFFF)
    lo, hi = v & 0xFFFF, v >> 16
    return np.array([lo - 0x10000 if lo > 0x7FFF else lo, hi - 0x10000 if hi > 0x7FFF else hi], np.int64)


def _chunked(name: str, values, desc: str) -> list[tuple[str, object, str]]:
    """``NAME``, ``NAME2``, ``NAME3``... holding at most 255 entries each."""
    out = []
    for k, s in enumerate(range(0, len(values), 255)):
        chunk = values[s:s + 255]
        value = list(chunk) if isinstance(values, list) else chunk
        out.append((name if k == 0 else f"{name}{k + 1}", value, desc))
    return out


# -------------------------------------------------------------------------------------- read
def read_c3d(path: str | os.PathLike, *, reader: str = "carapost") -> C3DData:
    """Read the 3D points of a C3D file.

    Parameters
    ----------
    path : path-like
    reader : {"carapost", "ezc3d", "py-c3d"}
        Who decodes the coordinates. The header and parameters are always parsed (strictly) by
        CaraPost first, and residuals / camera masks are always decoded by CaraPost (ezc3d 1.7.2
        misreads them). ``"carapost"`` (default): CaraPost's vectorised decoder (Intel, DEC, MIPS;
        integer and float). ``"ezc3d"``: ezc3d, run in a separate process because it can crash
        (segmentation fault) on damaged files. ``"py-c3d"``: the ``c3d`` package (pure Python).
        All three agree on the real test files (see ``tests/io/test_c3d.py``).

    Returns
    -------
    C3DData
        Coordinates and residuals converted to millimetres (POINT:UNITS m, cm, in... are scaled).

    Raises
    ------
    C3DError
        The file is missing, unreadable, not a C3D file, or its parameter section is corrupt; or the
        requested library reader failed on it.
    """
    if reader not in ("carapost", "ezc3d", "py-c3d"):
        raise ValueError(f"unknown C3D reader {reader!r} (expected 'carapost', 'ezc3d' or 'py-c3d')")
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise C3DError(f"{path}: cannot read the file ({e.strerror or e})") from e
    name = str(path)
    header = cb.parse_header(raw, name)
    params = cb.parse_parameters(raw, header, name)
    n_points = _n_points(header, params)
    first, n_frames = cb.frame_range(header, params)
    scale = _point_scale(header, params)
    data_block = header.data_block or _int_param(params, "POINT", "DATA_START", 0)
    if data_block < 2:
        raise C3DError(f"{name}: no point data block (data start {data_block})")
    xyz, residual, mask = cb.decode_points(raw, n_points=n_points, n_frames=n_frames, data_block=data_block,
                                           analog_words=header.analog_words, scale=scale,
                                           processor=header.processor)
    if reader != "carapost":
        lib = (_xyz_ezc3d if reader == "ezc3d" else _xyz_pyc3d)(path)
        if lib.shape != xyz.shape:
            raise C3DError(f"{name}: {reader} read {lib.shape[:2]} frames x points, the parameters say "
                           f"{xyz.shape[:2]}")
        xyz = lib
    invalid = ~np.isfinite(xyz).all(-1) | ~np.isfinite(residual)
    xyz[invalid] = np.nan
    residual[invalid] = np.nan
    mask[invalid] = 0

    units = _units(params)
    to_mm = _UNIT_TO_MM.get(units.lower(), 1.0)
    labels = [s.strip() for s in cb.joined_strings(params, "POINT", "LABELS")][:n_points]
    labels += [f"point{i + 1}" for i in range(len(labels), n_points)]
    labels = [lab or f"point{i + 1}" for i, lab in enumerate(labels)]
    descs = [s.strip() for s in cb.joined_strings(params, "POINT", "DESCRIPTIONS")][:n_points]
    descs += [""] * (n_points - len(descs))
    out = C3DData(path=name, labels=labels, descriptions=descs, xyz=xyz * to_mm, residual=residual * to_mm,
                  camera_mask=mask, frame_rate=_frame_rate(header, params), first_frame=int(first),
                  units=units, scale_to_mm=to_mm, parameters=params, backend=reader)
    _carapost_fields(out, params, abs(scale))
    return out


def info_c3d(path: str | os.PathLike) -> dict:
    """A summary of a C3D file for ``carapost info`` (JSON-serialisable)."""
    d = read_c3d(path)
    return {"path": d.path, "points": d.n_points, "frames": d.n_frames, "frame_rate": d.frame_rate,
            "first_frame": d.first_frame,
            "duration_s": d.n_frames / d.frame_rate if d.frame_rate > 0 else None,
            "units": d.units or "mm (assumed)", "gap_fraction": round(d.gap_fraction(), 6),
            "points_with_gaps": int((~np.isfinite(d.xyz[..., 0])).any(axis=0).sum()),
            "labels_sample": d.labels[:10], "written_by_carapost": d.recon is not None,
            "reader": d.backend}


def _int_param(params: ParameterSection, group: str, name: str, default: int) -> int:
    p = cb.get(params, group, name)
    v = p.first_int(unsigned=True) if p is not None else None
    return default if v is None else v


def _n_points(header: cb.Header, params: ParameterSection) -> int:
    return _int_param(params, "POINT", "USED", header.n_points)


def _point_scale(header: cb.Header, params: ParameterSection) -> float:
    p = cb.get(params, "POINT", "SCALE")
    for v in ([] if p is None or p.type != 4 else list(np.asarray(p.value)[:1])) + [header.scale]:
        if np.isfinite(v) and v != 0:
            return float(v)
    return -1.0


def _frame_rate(header: cb.Header, params: ParameterSection) -> float:
    p = cb.get(params, "POINT", "RATE")
    for v in ([] if p is None or p.type != 4 else list(np.asarray(p.value)[:1])) + [header.frame_rate]:
        if np.isfinite(v) and v > 0:
            return float(v)
    return 0.0


def _units(params: ParameterSection) -> str:
    p = cb.get(params, "POINT", "UNITS")
    if p is None:
        return ""
    s = p.strings()
    return s[0].strip() if s else ""


def _carapost_fields(out: C3DData, params: ParameterSection, res_unit: float) -> None:
    ver = cb.get(params, "CARAPOST", "FORMAT_VERSION")
    if ver is None or ver.first_int() != FORMAT_VERSION:
        return
    P = out.n_points
    ids, kind, brim = (cb.joined_numbers(params, "CARAPOST", n) for n in ("POINT_IDS", "KIND", "BRIM_INDEX"))
    if ids is not None and len(ids) == P:
        out.point_ids = ids
    if kind is not None and len(kind) == P:
        out.kind = kind.astype(np.uint8)
    if brim is not None and len(brim) == P:
        out.brim_index = brim.astype(np.int32)
    st = cb.get(params, "CARAPOST", "STABILIZED")
    out.stabilized = bool(st.first_int()) if st is not None and st.first_int() is not None else None
    ffn = cb.get(params, "CARAPOST", "FIRST_FRAME_NUMBER")
    if ffn is not None and len(ffn.ints()) == 2:
        lo, hi = ffn.ints(unsigned=True)
        out.first_frame_number = int(lo | (hi << 16))
    coding = cb.get(params, "CARAPOST", "RECON_CODING")
    unit = res_unit * out.scale_to_mm
    scheme = coding.strings()[0].strip() if coding is not None and coding.strings() else ""
    if scheme == "RESIDUAL_BYTE" and unit > 0:
        valid = np.isfinite(out.residual)
        byte = np.zeros(out.residual.shape, np.int64)
        byte[valid] = np.round(out.residual[valid] / unit).astype(np.int64)
        recon = np.full(byte.shape, Recon.NONE, np.uint8)
        recon[valid] = Recon.MULTI_VIEW
        recon[valid & (byte == 0)] = Recon.INTERPOLATED
        recon[valid & (byte == 1)] = Recon.SINGLE_SENSOR
        out.recon = recon


# ------------------------------------------------------------------------- library readers
_EZC3D_SCRIPT = """
import sys
import numpy as np
import ezc3d
pts = np.asarray(ezc3d.c3d(sys.argv[1])["data"]["points"], np.float64)
np.save(sys.argv[2], pts)
"""


def _xyz_ezc3d(path: Path) -> np.ndarray:
    """Coordinates (F, P, 3) in file units, NaN invalid, read by ezc3d in a child process.

    ezc3d is C++: a damaged file can crash it (a segmentation fault was found by fuzzing files that
    pass :func:`~carapost.io.c3d_binary.parse_parameters`, and with ``ignore_bad_formatting`` on
    c3d.org's sample 18), which would take the application down with it. The child process needs
    ``sys.executable`` to be a Python interpreter with ezc3d installed.
    """
    with tempfile.TemporaryDirectory(prefix="carapost-c3d-") as tmp:
        out = Path(tmp) / "points.npy"
        try:
            proc = subprocess.run([sys.executable, "-c", _EZC3D_SCRIPT, str(path), str(out)],
                                  capture_output=True, timeout=300, check=False)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise C3DError(f"{path}: ezc3d could not be run ({e})") from e
        if proc.returncode != 0 or not out.exists():
            how = (f"crashed (signal {-proc.returncode})" if proc.returncode < 0 else
                   "failed: " + (proc.stderr.decode("utf-8", "replace").strip().splitlines() or ["?"])[-1])
            raise C3DError(f"{path}: ezc3d {how}")
        pts = np.load(out)
    if pts.ndim != 3 or pts.shape[0] < 3:
        raise C3DError(f"{path}: ezc3d returned points of shape {pts.shape}")
    return np.ascontiguousarray(pts[:3].transpose(2, 1, 0))


def _xyz_pyc3d(path: Path) -> np.ndarray:
    """As :func:`_xyz_ezc3d` with py-c3d (the optional ``c3d`` package; pure Python, in process)."""
    try:
        import c3d as pyc3d
    except ImportError as e:
        raise C3DError(f"{path}: the py-c3d reader is not installed (pip install c3d)") from e
    try:
        with warnings.catch_warnings(), open(path, "rb") as fh:
            warnings.simplefilter("ignore")
            frames = [pts[:, :4].copy() for _, pts, _ in pyc3d.Reader(fh).read_frames(copy=False)]
    except Exception as e:  # noqa: BLE001 - py-c3d raises assorted errors on files it dislikes
        raise C3DError(f"{path}: py-c3d failed: {type(e).__name__}: {e}") from e
    if not frames:
        raise C3DError(f"{path}: py-c3d read no frames")
    arr = np.stack(frames).astype(np.float64)
    xyz = arr[..., :3]
    xyz[arr[..., 3] < 0] = np.nan
    return xyz
