"""Exports: one entry point choosing the format by extension, and what every exporter shares.

``export_take(take, "out.fbx")`` writes ``.c3d .fbx .xcp .csv .trc .bvh .bva`` (formats in
``docs/formats/exports.md`` and ``docs/formats/fbx.md``); ``export_file("in.cara", "out.trc")``
loads a ``.cara`` project or any ``.c3d`` first (the ``carapost export`` command).

Every 3D exporter goes through :func:`prepare_export`, which applies the Export section of the
Properties pane (:class:`~carapost.model.params.ExportParameters`) the same way:

* **points**: all points; only the selected ones when *Selected Points Only* is on (the
  selection is UI state, so the caller passes it); brim points dropped when *Include Brim
  Points* is off; or an explicit ``points=`` list, used as given;
* **data**: ``take.xyz``, or ``take.xyz_stabilized`` when *Export Stabilized Data* is on;
* **axes**: the take's world frame is the brim frame (``X`` along the card, ``Y`` up, ``Z`` out
  of it, right-handed). *Up Axis* ``Y`` keeps it; ``Z`` rotates it by +90 degrees about ``X``:
  ``(x, y, z) -> (x, -z, y)`` (still right-handed, ``Y`` becomes depth);
* **units**: millimetres or centimetres (*Units*); some formats add their own (TRC metres,
  BVA inches);
* **time**: frame ``f`` of the take has the CaraPost frame number ``take.first_frame_number + f``
  and the time ``number / frame_rate`` seconds.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from carapost.model.params import ExportParameters
from carapost.model.take import PointKind, Take

__all__ = ["EXPORT_FORMATS", "ExportData", "ExportError", "UNIT_SCALE", "UNIT_NAMES", "axis_matrix",
           "to_export_space", "select_points", "frame_range", "prepare_export", "unique_names", "hold_gaps",
           "export_take", "export_xcp", "export_file", "load_for_export"]

#: Extensions :func:`export_take` writes.
EXPORT_FORMATS = (".c3d", ".fbx", ".xcp", ".csv", ".trc", ".bvh", ".bva")
#: Export units: factor from millimetres.
UNIT_SCALE = {"mm": 1.0, "cm": 0.1, "m": 0.001, "in": 1.0 / 25.4}
#: Long names of the units.
UNIT_NAMES = {"mm": "millimetres", "cm": "centimetres", "m": "metres", "in": "inches"}


class ExportError(ValueError):
    """An export cannot be written; the message names the file and the problem."""


@dataclass
class ExportData:
    """Points of a take ready to write, in export axes and units.

    Attributes
    ----------
    indices : int64 (K,)
        Point columns of the take, in export order.
    names : list of str (K,)
        Unique names (label, else ``Point_<id>`` / ``Brim_<id>``; repeats get ``_2``...).
    ids : int64 (K,)
        Point ids.
    kind : uint8 (K,)
        :class:`~carapost.model.take.PointKind`.
    frames : int64 (N,)
        Take frame indices ``a..b``.
    frame_numbers : int64 (N,)
        CaraPost frame numbers ``first_frame_number + frames``.
    times : float64 (N,)
        Seconds, ``frame_numbers / frame_rate``.
    xyz : float64 (N, K, 3)
        Positions in export axes and units; NaN in gaps.
    valid : bool (N, K)
        Finite samples.
    units : str
        ``"mm"``, ``"cm"``, ``"m"`` or ``"in"``.
    up_axis : str
        ``"Y"`` or ``"Z"``.
    frame_rate : float
        Hz.
    stabilized : bool
        Whether ``xyz`` comes from ``take.xyz_stabilized``.
    """

    indices: np.ndarray
    names: list[str]
    ids: np.ndarray
    kind: np.ndarray
    frames: np.ndarray
    frame_numbers: np.ndarray
    times: np.ndarray
    xyz: np.ndarray
    valid: np.ndarray
    units: str
    up_axis: str
    frame_rate: float
    stabilized: bool

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.indices.shape[0])


def axis_matrix(up_axis: str) -> np.ndarray:
    """Rotation (3, 3) from the take's world frame (Y up) to export axes with ``up_axis`` up."""
    if up_axis == "Y":
        return np.eye(3)
    if up_axis == "Z":
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    raise ValueError(f"up axis must be 'Y' or 'Z', got {up_axis!r}")


def to_export_space(xyz: np.ndarray, *, up_axis: str = "Y", units: str = "mm") -> np.ndarray:
    """World positions ``(..., 3)`` in mm to export axes and units (NaN propagates)."""
    if units not in UNIT_SCALE:
        raise ValueError(f"units must be one of {', '.join(UNIT_SCALE)}, got {units!r}")
    Q = axis_matrix(up_axis) * UNIT_SCALE[units]
    return np.asarray(xyz, dtype=float) @ Q.T


def unique_names(names: list[str]) -> list[str]:
    """Later repeats of a name get ``_2``, ``_3``... (the first suffix not already used)."""
    used = set(names)
    seen: set[str] = set()
    out = []
    for n in names:
        if n in seen:
            k = 2
            while f"{n}_{k}" in used:
                k += 1
            n = f"{n}_{k}"
            used.add(n)
        seen.add(n)
        out.append(n)
    return out


def _options(take: Take, options: ExportParameters | None) -> ExportParameters:
    return take.params.export if options is None else options


def select_points(take: Take, *, options: ExportParameters | None = None,
                  selection: np.ndarray | list[int] | None = None,
                  points: np.ndarray | list[int] | None = None) -> np.ndarray:
    """Point columns to export (int64 (K,)), following the Export section.

    Parameters
    ----------
    take : Take
    options : ExportParameters, optional
        Default ``take.params.export``.
    selection : int array, optional
        The selected point columns, used when *Selected Points Only* is on.
    points : int array, optional
        Explicit columns, in order; overrides ``options`` and ``selection``.

    Raises
    ------
    ValueError
        Indices out of range or repeated; *Selected Points Only* without a selection; no point
        left to export.
    """
    opts = _options(take, options)
    P = take.n_points
    if points is not None:
        idx = _indices(points, P, "points")
    else:
        idx = np.arange(P, dtype=np.int64)
        if opts.selected_only:
            if selection is None or len(selection) == 0:
                raise ValueError("Selected Points Only is on but no points are selected")
            sel = _indices(selection, P, "selection")
            idx = np.sort(sel)
        if not opts.include_brim:
            idx = idx[take.points.kind[idx] != PointKind.BRIM]
    if idx.size == 0:
        raise ValueError("no points to export" + ("" if opts.include_brim else
                                                  " (Include Brim Points is off)"))
    return idx


def _indices(values: Any, P: int, what: str) -> np.ndarray:
    idx = np.asarray(values).ravel()
    if idx.size and not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"{what} must be integer point columns")
    idx = idx.astype(np.int64)
    if idx.size and (idx.min() < 0 or idx.max() >= P):
        raise ValueError(f"{what}: point columns must be in 0..{P - 1}")
    if len(np.unique(idx)) != len(idx):
        raise ValueError(f"{what}: point columns repeat")
    return idx


def frame_range(take: Take, frames: tuple[int, int] | None) -> np.ndarray:
    """Take frame indices (int64 (N,)) of an inclusive range (default: the whole take)."""
    F = take.n_frames
    a, b = (0, F - 1) if frames is None else (int(frames[0]), int(frames[1]))
    if not 0 <= a <= b < F:
        raise ValueError(f"frame range {frames} is outside 0..{F - 1}")
    return np.arange(a, b + 1, dtype=np.int64)


def prepare_export(take: Take, *, options: ExportParameters | None = None,
                   selection: np.ndarray | list[int] | None = None,
                   points: np.ndarray | list[int] | None = None,
                   frames: tuple[int, int] | None = None, units: str | None = None,
                   up_axis: str | None = None) -> ExportData:
    """Select, convert and name the points to export.

    Parameters
    ----------
    take : Take
    options : ExportParameters, optional
        The Export section (default ``take.params.export``).
    selection, points
        See :func:`select_points`.
    frames : (int, int), optional
        Inclusive range of take frame indices (default: all).
    units, up_axis : str, optional
        Override the options' units (any of :data:`UNIT_SCALE`) or up axis.

    Raises
    ------
    ValueError
        Bad selection or range, or stabilized data requested from an unstabilized take.
    """
    opts = _options(take, options)
    idx = select_points(take, options=opts, selection=selection, points=points)
    fr = frame_range(take, frames)
    units = opts.units if units is None else units
    up = opts.up_axis if up_axis is None else up_axis
    src = take.xyz_stabilized if opts.use_stabilized else take.xyz
    if opts.use_stabilized and not np.isfinite(src).any():
        raise ValueError("Export Stabilized Data is on but the take has not been stabilized")
    xyz = to_export_space(src[fr[0]:fr[-1] + 1][:, idx], up_axis=up, units=units)
    valid = np.isfinite(xyz).all(-1)
    xyz[~valid] = np.nan
    pts = take.points
    names = unique_names([pts.name(int(i)).strip() or _generated(take, int(i)) for i in idx])
    numbers = int(take.first_frame_number) + fr
    return ExportData(indices=idx, names=names, ids=pts.ids[idx].astype(np.int64), kind=pts.kind[idx].copy(),
                      frames=fr, frame_numbers=numbers, times=numbers / float(take.frame_rate), xyz=xyz,
                      valid=valid, units=units, up_axis=up, frame_rate=float(take.frame_rate),
                      stabilized=bool(opts.use_stabilized))


def _generated(take: Take, i: int) -> str:
    prefix = "Brim" if take.points.kind[i] == PointKind.BRIM else "Point"
    return f"{prefix}_{int(take.points.ids[i])}"


def hold_gaps(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill gaps for formats without missing values: each gap holds the last valid sample
    (leading gaps the first one); points never valid are 0. ``xyz (N, K, 3)``, ``valid (N, K)``."""
    N, K = valid.shape
    if N == 0:
        return xyz.copy()
    rows = np.where(valid, np.arange(N)[:, None], -1)
    last = np.maximum.accumulate(rows, axis=0)
    first = np.where(valid.any(0), np.argmax(valid, axis=0), 0)
    src = np.where(last < 0, first[None, :], last)
    out = np.take_along_axis(xyz, src[:, :, None], axis=0)
    out[:, ~valid.any(0)] = 0.0
    return out


# ------------------------------------------------------------------------------ dispatch
def export_take(take: Take, path: str | os.PathLike, *, options: ExportParameters | None = None,
                selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
                **kwargs: Any) -> None:
    """Write ``take`` to ``path``, choosing the format by extension.

    Parameters
    ----------
    take : Take
    path : path-like
        ``.c3d .fbx .xcp .csv .trc .bvh .bva`` (case-insensitive); written atomically.
    options : ExportParameters, optional
        The Export section (default ``take.params.export``); XCP ignores it.
    selection : int array, optional
        Selected point columns (for *Selected Points Only*).
    frames : (int, int), optional
        Inclusive range of take frame indices (default: all frames; XCP: see ``frame``).
    **kwargs
        Format options: FBX ``version`` (7400 / 7500); XCP ``frame`` (default
        ``take.current_frame``) and ``all_frames`` (moving cameras: one keyframe per frame);
        CSV ``kind`` (``"3d"`` trajectories / ``"2d"`` tracks) and ``cameras``; TRC
        ``units`` (adds ``"m"``) and ``missing``; BVA ``units`` (``"in"`` default, ``"mm"``)
        and ``camera`` (2D tracks of one camera, image ``y`` flipped); ``points`` (explicit
        columns) for every 3D format.

    Raises
    ------
    ExportError
        Unknown extension or option, or the data cannot be exported (the message names the
        file); the folder is missing.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in EXPORT_FORMATS:
        raise ExportError(f"{path}: cannot export to '{path.suffix or path.name}': "
                          f"use one of {', '.join(EXPORT_FORMATS)}")
    if not path.parent.is_dir():
        raise ExportError(f"{path}: cannot write, the folder {path.parent} does not exist")
    allowed = {".c3d": {"points"}, ".fbx": {"points", "version", "timestamp"}, ".xcp": {"frame", "all_frames"},
               ".csv": {"points", "kind", "cameras"}, ".trc": {"points", "units", "missing"},
               ".bvh": {"points"}, ".bva": {"points", "units", "camera"}}[ext]
    unknown = sorted(set(kwargs) - allowed)
    if unknown:
        raise ExportError(f"{path}: option(s) {', '.join(unknown)} do not apply to {ext} "
                          f"(allowed: {', '.join(sorted(allowed)) or 'none'})")
    try:
        _dispatch(take, path, ext, options, selection, frames, kwargs)
    except ExportError:
        raise
    except ValueError as e:
        msg = str(e)
        raise ExportError(msg if str(path) in msg or path.name in msg else f"{path}: {msg}") from None
    except OSError as e:
        raise ExportError(f"{path}: cannot write the file ({e.strerror or e})") from None


def _dispatch(take: Take, path: Path, ext: str, options: ExportParameters | None, selection: Any,
              frames: tuple[int, int] | None, kw: dict[str, Any]) -> None:
    common = dict(options=options, selection=selection, frames=frames)
    if ext == ".fbx":
        from .fbx import export_fbx
        export_fbx(take, path, **common, **kw)
    elif ext == ".csv":
        from .csv_export import export_csv_2d, export_csv_3d
        kind = kw.pop("kind", "3d")
        if kind == "3d":
            if "cameras" in kw:
                raise ValueError("option cameras applies to 2D track CSV (kind='2d') only")
            export_csv_3d(take, path, **common, **kw)
        elif kind == "2d":
            export_csv_2d(take, path, **common, **kw)
        else:
            raise ValueError(f"CSV kind must be '3d' or '2d', got {kind!r}")
    elif ext == ".trc":
        from .trc import export_trc
        export_trc(take, path, **common, **kw)
    elif ext == ".bvh":
        from .bvh import export_bvh
        export_bvh(take, path, **common, **kw)
    elif ext == ".bva":
        from .bva import export_bva
        export_bva(take, path, **common, **kw)
    elif ext == ".xcp":
        export_xcp(take, path, **kw)
    else:  # .c3d
        _export_c3d(take, path, options=options, selection=selection, frames=frames, **kw)


def _export_c3d(take: Take, path: Path, *, options: ExportParameters | None, selection: Any,
                frames: tuple[int, int] | None, points: Any = None) -> None:
    """C3D through :func:`carapost.io.c3d.export_c3d`, honouring the points, data and up-axis
    options (C3D stays in millimetres: readers convert POINT:UNITS themselves)."""
    from .c3d import export_c3d
    opts = _options(take, options)
    idx = select_points(take, options=opts, selection=selection, points=points)
    if opts.up_axis != "Y":
        Q = axis_matrix(opts.up_axis)
        name = "xyz_stabilized" if opts.use_stabilized else "xyz"
        take = replace(take, **{name: getattr(take, name) @ Q.T})
    export_c3d(take, path, points=idx, stabilized=opts.use_stabilized, frames=frames)


# ----------------------------------------------------------------------------------- XCP
def export_xcp(take: Take, path: str | os.PathLike, *, frame: int | None = None,
               all_frames: bool = False) -> None:
    """Export XCP [Current Frame]: every camera's intrinsics and its pose at ``frame``.

    Parameters
    ----------
    take : Take
    path : path-like
        Destination ``.xcp`` (written atomically by :func:`carapost.io.xcp.write_xcp`).
    frame : int, optional
        Take frame index (default ``take.current_frame``). Its poses become a single
        ``<KeyFrame FRAME="0">`` per camera: valid for every frame, so another take of the same
        session can use the file. ``IMAGE_ERROR`` is the camera's mean reprojection error
        (pixels) over the points it observes in that frame (omitted when it observes none).
    all_frames : bool
        Moving cameras: keyframes encode every frame's pose (a new ``<KeyFrame>`` wherever the
        pose changes, i.e. one per frame when the rig flexes every frame; unsolved frames keep
        the previous pose). ``frame`` is then ignored.

    Raises
    ------
    ValueError
        A camera has no solved pose at ``frame`` (or at any frame with ``all_frames``), or the
        frame is outside the take. The message names the file and the camera.
    """
    from carapost.core.camera import project
    from .calibration import Calibration, CalibrationError, CameraCalibration
    from .xcp import write_xcp

    path = Path(path)
    f = int(take.current_frame if frame is None else frame)
    if not 0 <= f < take.n_frames:
        raise ValueError(f"{path}: frame {f} is outside the take (0..{take.n_frames - 1})")
    cams = []
    for c, cam in enumerate(take.cameras):
        R, t = take.R[f, c], take.t[f, c]
        where = f"camera {c} ({cam.name or 'unnamed'})"
        if not all_frames and not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise ValueError(f"{path}: {where} has no solved pose at frame {f}")
        intr = cam.intrinsics
        if not any(intr.sensor_size) and any(cam.image_size):
            intr = intr.with_(sensor_size=tuple(int(v) for v in cam.image_size))
        err = np.nan
        if not all_frames:
            obs = take.obs_xy[f, :, c].astype(float)
            ok = np.isfinite(obs).all(-1) & np.isfinite(take.xyz[f]).all(-1)
            if ok.any():
                err = float(np.nanmean(np.linalg.norm(project(take.xyz[f, ok], intr, R, t) - obs[ok], axis=-1)))
        R0, t0 = (R, t) if not all_frames else (np.eye(3), np.zeros(3))
        cams.append(CameraCalibration(name=cam.name, device_id=cam.device_id, user_id="", intrinsics=intr,
                                      frames=np.array([0]), R=R0[None], t=t0[None], image_error=np.array([err])))
    calib = Calibration(cameras=cams)
    if all_frames:
        try:
            calib = calib.with_poses(take.R, take.t)
        except ValueError as e:
            bad = [c for c in range(take.n_cameras)
                   if not (np.isfinite(take.R[:, c]).all((1, 2)) & np.isfinite(take.t[:, c]).all(1)).any()]
            who = f"camera {bad[0]} ({take.cameras[bad[0]].name or 'unnamed'})" if bad else "a camera"
            raise ValueError(f"{path}: {who} has no solved pose in any frame ({e})") from None
    try:
        write_xcp(path, calib)
    except CalibrationError as e:
        raise ValueError(str(e)) from None


def load_for_export(path: str | os.PathLike) -> Take:
    """The take in a ``.cara`` project or a ``.c3d`` file (opened as a take without video)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".cara":
        from .cara import load_take
        return load_take(path).take
    if ext == ".c3d":
        from .c3d_take import take_from_c3d
        return take_from_c3d(path)
    raise ExportError(f"{path}: cannot export from '{path.suffix or path.name}': use a .cara or .c3d file")


def export_file(src: str | os.PathLike, dst: str | os.PathLike, *, options: ExportParameters | None = None,
                frames: tuple[int, int] | None = None, **kwargs: Any) -> Take:
    """``carapost export SRC DST``: load ``src`` (``.cara`` / ``.c3d``), write ``dst``; returns the take."""
    take = load_for_export(src)
    export_take(take, dst, options=options, frames=frames, **kwargs)
    return take
