"""The Process menu's gap filling, stabilization and alignment, as undoable operations.

* :func:`interpolate_gaps` — "Interpolate Gaps" (neighbour-driven prediction, or the learned face
  model of :mod:`carapost.core.face_model` with ``method="face_model"``);
* :func:`stabilize_manual` / :func:`stabilize_assisted` — "Stabilize Data [Manual]" /
  "[Assisted]" (results in ``xyz_stabilized``; the raw data are kept);
* :func:`align_data` — "Align Data" (a three-point coordinate frame);
* :func:`evaluate_fill` — the error of a gap-filling method, measured by hiding known samples
  and filling them again (no change to the take);
* :func:`face_model_for` — a face model learnt from the take or from a ROM take;
* :func:`blink_depths_for` — how far each marker closes in a blink, from a ROM take (for
  ``method="blink"``, :mod:`carapost.core.gapfill_blink`).

"Remove Interpolated 3D Points" is :func:`carapost.ops.points.remove_interpolated`.

Every operation leaves the take untouched and returns a :class:`ReportedChange`: a
:class:`~carapost.ops.change.Composite` whose ``report`` dict carries the numbers the guide
says are reported (stabilization error, points filled, ...).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from carapost.core.align import apply_frame, frame_from_points
from carapost.core.camera import backproject
from carapost.core.face_model import FaceModel, build_face_model, face_model_fill
from carapost.core.gapfill import constrain_to_rays, fill_gaps, hide_runs
from carapost.core.gapfill_blink import excursion_depths, fill_blink_gaps
from carapost.core.stabilize import StabilizeResult
from carapost.core.stabilize import stabilize_assisted as _assisted
from carapost.core.stabilize import stabilize_manual as _manual
from carapost.model.params import FILL_METHODS, GapFillingParameters, StabilizationParameters
from carapost.model.take import BrimModel, PointKind, Recon, Take

from .change import ArrayPatch, AttributeChange, Change, Composite

__all__ = [
    "ReportedChange",
    "FillEvaluation",
    "interpolate_gaps",
    "evaluate_fill",
    "face_model_for",
    "blink_depths_for",
    "upper_lid_columns",
    "stabilize_manual",
    "stabilize_assisted",
    "align_data",
    "METHODS",
]

#: Gap-filling methods of :func:`interpolate_gaps`.
METHODS = FILL_METHODS


@dataclass
class ReportedChange(Composite):
    """A :class:`Composite` change with a report of what the operation found."""

    report: dict[str, Any] = field(default_factory=dict)


@dataclass
class FillEvaluation:
    """Errors of a gap-filling method on hidden known samples (:func:`evaluate_fill`).

    Attributes
    ----------
    method : str
    hidden : bool array (F', P)
        The hidden samples, frames of the active range.
    errors : float64 array (N,)
        Distance between each refilled hidden sample and its known position, mm (NaN where
        the method left the sample unfilled).
    """

    method: str
    hidden: np.ndarray
    errors: np.ndarray

    @property
    def n_hidden(self) -> int:
        return int(self.hidden.sum())

    @property
    def n_filled(self) -> int:
        return int(np.isfinite(self.errors).sum())

    @property
    def median(self) -> float:
        e = self.errors[np.isfinite(self.errors)]
        return float(np.median(e)) if len(e) else float("nan")

    @property
    def p95(self) -> float:
        e = self.errors[np.isfinite(self.errors)]
        return float(np.percentile(e, 95)) if len(e) else float("nan")

    def summary(self) -> dict[str, float | int | str]:
        return {"method": self.method, "hidden": self.n_hidden, "filled": self.n_filled,
                "median_mm": self.median, "p95_mm": self.p95}


# ----------------------------------------------------------------------------- helpers
def _range(take: Take) -> np.ndarray:
    a, b = take.active_range
    if not (0 <= a <= b < take.n_frames):
        raise ValueError(f"the active range {a}..{b} is outside the take's {take.n_frames} frames")
    return np.arange(a, b + 1)


def _columns(take: Take, points: Sequence[int] | None) -> np.ndarray:
    if points is None or len(points) == 0:
        return np.arange(take.n_points)
    cols = np.unique(np.asarray(points, dtype=np.int64))
    if cols.min() < 0 or cols.max() >= take.n_points:
        raise ValueError(f"point indices must be within 0..{take.n_points - 1}")
    return cols


def _point_name(take: Take, col: int) -> str:
    return take.points.name(int(col))


def upper_lid_columns(take: Take) -> set[int]:
    """Columns whose label names an eyelid marker (contains "lid", any case) and not a lower
    one ("low"/"bot"/"inf"): the markers that may take the palpebral-fissure prior of
    :mod:`carapost.core.gapfill_lid` when no lower-lid marker lies on their closing path."""
    out = set()
    for j, lab in enumerate(take.points.labels):
        low = (lab or "").lower()
        if "lid" in low and not any(w in low for w in ("low", "bot", "inf")):
            out.add(j)
    return out


def _previously_filled(take: Take, frames: np.ndarray) -> np.ndarray:
    """Samples holding a position with fewer than two views behind it (F', P)."""
    xyz = take.xyz[frames]
    finite = np.isfinite(xyz).all(-1)
    recon = take.recon[frames]
    out = finite & np.isin(recon, [Recon.INTERPOLATED, Recon.SINGLE_SENSOR])
    if take.n_cameras:
        out |= finite & (take.n_views()[frames] <= 1)
    return out


def _single_rays(take: Take, frames: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays (origin, direction) ``(F', P, 3)`` of the samples in ``mask`` with exactly one 2D
    observation and a solved camera; NaN elsewhere."""
    Fr, P = mask.shape
    origin = np.full((Fr, P, 3), np.nan)
    direction = np.full((Fr, P, 3), np.nan)
    if not take.n_cameras or not mask.any():
        return origin, direction
    obs = take.obs_xy[frames].astype(float)                  # (F', P, C, 2)
    seen = np.isfinite(obs).all(-1)
    single = mask & (seen.sum(-1) == 1)
    if not single.any():
        return origin, direction
    for c, cam in enumerate(take.cameras):
        f, p = np.nonzero(single & seen[..., c])
        if not len(f):
            continue
        R, t = take.R[frames[f], c], take.t[frames[f], c]
        o, d = backproject(obs[f, p, c], cam.intrinsics, R, t)
        origin[f, p], direction[f, p] = o, d
    return origin, direction


def _fill_arrays(take: Take, frames: np.ndarray, fill: np.ndarray, known: np.ndarray, method: str,
                 params: GapFillingParameters, model: FaceModel | None, n_neighbours: int,
                 momentum_s: float, blink_depths: dict[int, float] | None = None,
                 blink_depth_model: str = "geometry") -> tuple[np.ndarray, np.ndarray]:
    """New positions (F', P, 3) and the filled mask for the samples in ``fill``."""
    if method not in METHODS:
        raise ValueError(f"unknown gap-filling method {method!r}; use one of {', '.join(METHODS)}")
    xyz = take.xyz[frames]
    fw, bw = params.use_forwards_prediction, params.use_backwards_prediction
    velocity_frames = max(0.0, momentum_s) * take.frame_rate
    out = xyz.copy()
    filled = np.zeros(fill.shape, bool)
    remaining = fill
    if method == "face_model":
        if model is None:
            model = build_face_model(np.where(known[..., None], xyz, np.nan))
        res = face_model_fill(xyz, fill, model, known=known, forwards=fw, backwards=bw)
        out[res.filled] = res.xyz[res.filled]
        filled |= res.filled
        remaining = fill & ~res.filled
    if remaining.any():
        res = fill_gaps(xyz, remaining, known=known & ~fill, forwards=fw, backwards=bw, n_neighbours=n_neighbours,
                        velocity_frames=velocity_frames)
        if method == "blink":
            res, _ = fill_blink_gaps(xyz, remaining, frame_rate=take.frame_rate, known=known & ~fill, base=res,
                                     n_neighbours=n_neighbours, depths=blink_depths,
                                     depth_model=blink_depth_model, lid_points=upper_lid_columns(take),
                                     lid_marker_offset_mm=params.lid_marker_offset,
                                     fissure_mm=params.palpebral_fissure)
        out[res.filled] = res.xyz[res.filled]
        filled |= res.filled
    return out, filled


# ----------------------------------------------------------------------------- gap filling
def interpolate_gaps(take: Take, points: Sequence[int] | None = None, *, method: str | None = None,
                     params: GapFillingParameters | None = None, face_model: FaceModel | None = None,
                     n_neighbours: int = 8, momentum_s: float = 0.0, rom: Take | None = None,
                     blink_depths: dict[int, float] | None = None,
                     blink_depth_model: str = "geometry") -> ReportedChange:
    """"Interpolate Gaps": fill the gaps of the selected points (all if none) in the active range.

    Parameters
    ----------
    take : Take
    points : point columns, optional
    method : {"neighbours", "face_model", "blink"}, optional
        Default: the Gap-Filling Parameters' *Method*. ``"neighbours"``: the guide's neighbour-driven forward/backward prediction
        (:func:`carapost.core.gapfill.fill_gaps`). ``"face_model"``: the learned face model
        (``face_model``, or one learnt from the active range's complete frames), with the
        neighbour method for the samples the model does not cover. ``"blink"``: the neighbour
        method, and for gaps a marker enters and leaves displaced from its neighbourhood (an
        eyelid in a blink) a fitted closing-and-reopening pulse
        (:func:`carapost.core.gapfill_blink.fill_blink_gaps`).
    params : GapFillingParameters, optional
        Default ``take.params.gapfill``: Overwrite Existing Filled Gaps (positions with fewer
        than two views behind them are recomputed), Use Forwards / Backwards Prediction,
        Allow Single Sensor Tracking Gap-Filling (a sample with exactly one 2D observation is
        moved onto that observation's ray: recon ``SINGLE_SENSOR``).
    face_model : FaceModel, optional
        For ``method="face_model"`` (see :func:`face_model_for`).
    n_neighbours : int
        Neighbours per prediction.
    momentum_s : float
        Time constant (seconds) of the continuation of a point's own motion into the gap
        (0: the guide's algorithm; see ``docs/gap-filling.md``).
    rom : Take, optional
        A range-of-motion take of the same actor and markers. ``method="blink"``: each marker's
        blink depth is measured in it (:func:`blink_depths_for`); ``method="face_model"`` (without
        ``face_model``): the model is learnt from it (:func:`face_model_for`).
    blink_depths : dict {point column: mm}, optional
        For ``method="blink"``: known depths instead (overrides ``rom``). Without either the
        depth comes from the eye's geometry (``blink_depth_model="geometry"``: the lower-lid
        marker the lid closes onto, or for a marker labelled as an upper lid without one the
        palpebral-fissure prior, :mod:`carapost.core.gapfill_lid`) or is fitted to the pulse
        (``"fit"``, which the take determines only loosely).
    blink_depth_model : {"geometry", "fit"}
        See ``blink_depths``.

    Returns
    -------
    ReportedChange
        Patches of ``xyz`` and ``recon``; ``report`` has ``filled``, ``single_sensor``,
        ``unfilled`` (gaps with no known sample on either side to predict from) and
        ``method``.

    Raises
    ------
    ValueError
        Unknown method, bad point indices, or both predictions disabled.
    """
    params = take.params.gapfill if params is None else params
    method = params.method if method is None else method
    if not (params.use_forwards_prediction or params.use_backwards_prediction):
        raise ValueError("Interpolate Gaps: enable Use Forwards Prediction or Use Backwards Prediction")
    frames = _range(take)
    cols = _columns(take, points)
    xyz = take.xyz[frames]
    finite = np.isfinite(xyz).all(-1)
    sel = np.zeros(take.n_points, bool)
    sel[cols] = True
    redo = _previously_filled(take, frames) if params.overwrite_existing_filled_gaps else np.zeros_like(finite)
    fill = (~finite | redo) & sel[None, :]
    known = finite & ~redo
    text = f"Interpolate Gaps ({method})"
    if not fill.any():
        return ReportedChange([], f"{text}: no gaps", report={"filled": 0, "single_sensor": 0, "unfilled": 0,
                                                               "method": method})
    if method == "blink" and blink_depths is None and rom is not None:
        blink_depths = blink_depths_for(take, rom)
    if method == "face_model" and face_model is None and rom is not None:
        face_model = face_model_for(take, rom=rom)
    new, filled = _fill_arrays(take, frames, fill, known, method, params, face_model, n_neighbours, momentum_s,
                               blink_depths, blink_depth_model)
    recon = take.recon[frames].copy()
    on_ray = np.zeros_like(filled)
    if params.allow_single_sensor_tracking_gap_filling and take.n_cameras:
        o, d = _single_rays(take, frames, filled)
        on_ray = filled & np.isfinite(o).all(-1) & np.isfinite(d).all(-1)
        new[on_ray] = constrain_to_rays(new[on_ray], o[on_ray], d[on_ray])
    recon[filled] = Recon.INTERPOLATED
    recon[on_ray] = Recon.SINGLE_SENSOR
    n_filled = int(filled.sum())
    report = {"filled": n_filled, "single_sensor": int(on_ray.sum()), "unfilled": int((fill & ~filled).sum()),
              "method": method}
    if not n_filled:
        return ReportedChange([], f"{text}: nothing could be filled", report=report)
    fr = np.flatnonzero(filled.any(1))
    pc = np.flatnonzero(filled.any(0))
    idx = (frames[fr][:, None], pc[None, :])
    sub = np.ix_(fr, pc)
    changes: list[Change] = [ArrayPatch.capture(take, "xyz", idx, new[sub]),
                             ArrayPatch.capture(take, "recon", idx, recon[sub])]
    return ReportedChange(changes, f"{text}: {n_filled} filled", report=report)


def _rom_pairs(take: Take, rom: Take, cols: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Columns of ``take`` and the matching columns of ``rom`` (by label; by column when
    neither take is labelled and both have as many points)."""
    labels = take.points.labels
    rom_index = {lab: i for i, lab in enumerate(rom.points.labels) if lab}
    pairs = [(j, rom_index[lab]) for j, lab in enumerate(labels) if lab and lab in rom_index]
    if not pairs and rom.n_points == take.n_points:
        pairs = [(j, j) for j in range(take.n_points)]
    if cols is not None:
        pairs = [(j, r) for j, r in pairs if j in set(cols.tolist())]
    if len(pairs) < 3:
        raise ValueError(f"the ROM take {rom.name!r} shares fewer than 3 labelled points with the take")
    return np.array([j for j, _ in pairs], np.int64), np.array([r for _, r in pairs], np.int64)


def blink_depths_for(take: Take, rom: Take, points: Sequence[int] | None = None) -> dict[int, float]:
    """Each marker's full excursion from its neighbourhood (an eyelid's blink depth), mm,
    measured on a range-of-motion take (:func:`carapost.core.gapfill_blink.excursion_depths`).

    Parameters
    ----------
    take : Take
    rom : Take
        Same actor and marker set; points matched by label.
    points : point columns of ``take``, optional
        Default all matched points.

    Returns
    -------
    dict {column of take: depth mm}
        Markers seen in fewer than 10 ROM frames are left out.

    Raises
    ------
    ValueError
        Fewer than 3 points in common.
    """
    cols = None if points is None else _columns(take, points)
    tk_cols, rom_cols = _rom_pairs(take, rom, cols)
    # the whole ROM is the neighbourhood: every matched point's depth against all of them
    depth = excursion_depths(rom.xyz, rom_cols)
    return {int(j): float(d) for j, d in zip(tk_cols, depth) if np.isfinite(d)}


def face_model_for(take: Take, *, rom: Take | None = None, points: Sequence[int] | None = None,
                   **options: Any) -> FaceModel:
    """A face model for ``take``: learnt from its active range, or from a ROM take.

    Parameters
    ----------
    take : Take
    rom : Take, optional
        A range-of-motion take of the same actor and marker set; its points are matched to
        the take's by label (unlabelled points are matched by column when both takes have the
        same number of points).
    points : point columns of ``take``, optional
        Markers the model should cover (default: chosen by
        :func:`~carapost.core.face_model.build_face_model`).
    **options
        Passed to :func:`~carapost.core.face_model.build_face_model`.

    Returns
    -------
    FaceModel
        ``points`` index the columns of ``take``.

    Raises
    ------
    ValueError
        No points in common with the ROM take, or too few complete frames.
    """
    cols = None if points is None else _columns(take, points)
    if rom is None:
        frames = _range(take)
        return build_face_model(take.xyz[frames], points=cols, **options)
    tk_cols, rom_cols = _rom_pairs(take, rom, cols)
    model = build_face_model(rom.xyz[:, rom_cols], **options)
    model.points = tk_cols[model.points]
    return model


def evaluate_fill(take: Take, method: str = "neighbours", *, hide_fraction: float = 0.05, min_len: int = 5,
                  max_len: int = 30, seed: int = 0, hide: np.ndarray | None = None,
                  points: Sequence[int] | None = None, params: GapFillingParameters | None = None,
                  face_model: FaceModel | None = None, n_neighbours: int = 8,
                  momentum_s: float = 0.0, rom: Take | None = None,
                  blink_depths: dict[int, float] | None = None, blink_depth_model: str = "geometry") -> FillEvaluation:
    """Measure a gap-filling method: hide known samples, fill them, compare.

    Parameters
    ----------
    take : Take
        Not modified.
    method : {"neighbours", "face_model", "blink"}
    hide_fraction, min_len, max_len, seed
        Gap-like runs to hide (:func:`carapost.core.gapfill.hide_runs`): ``hide_fraction`` of
        the known samples of the selected points in the active range, in runs of
        ``min_len..max_len`` frames with known samples on both sides.
    hide : bool array (F', P), optional
        Explicit samples to hide instead (frames of the active range), e.g. blink-like gaps
        of the eyelid markers; they must be known samples.
    points : point columns, optional
        Points whose samples may be hidden (default all).
    params, face_model, n_neighbours, momentum_s, rom, blink_depths, blink_depth_model
        As for :func:`interpolate_gaps`. A face model is learnt *after* hiding (so the hidden
        samples do not inform it) unless one is given.

    Returns
    -------
    FillEvaluation
    """
    params = take.params.gapfill if params is None else params
    frames = _range(take)
    cols = _columns(take, points)
    xyz = take.xyz[frames]
    finite = np.isfinite(xyz).all(-1)
    if hide is None:
        sel = np.zeros(take.n_points, bool)
        sel[cols] = True
        hidden = hide_runs(finite & sel[None, :], hide_fraction, min_len=min_len, max_len=max_len, seed=seed)
    else:
        hidden = np.asarray(hide, dtype=bool)
        if hidden.shape != finite.shape:
            raise ValueError(f"hide mask must have shape {finite.shape} (active range frames, points)")
        if (hidden & ~finite).any():
            raise ValueError("hide mask covers samples that have no position")
    known = finite & ~hidden
    if method == "blink" and blink_depths is None and rom is not None:
        blink_depths = blink_depths_for(take, rom)
    new, filled = _fill_arrays(take, frames, hidden, known, method, params, face_model, n_neighbours, momentum_s,
                               blink_depths, blink_depth_model)
    err = np.linalg.norm(new[hidden] - xyz[hidden], axis=-1)
    err[~filled[hidden]] = np.nan
    return FillEvaluation(method, hidden, err)


# ----------------------------------------------------------------------------- stabilization
def _stabilize_change(take: Take, frames: np.ndarray, res: StabilizeResult, text: str) -> ReportedChange:
    idx = (slice(int(frames[0]), int(frames[-1]) + 1),)
    report = {"error_mm": res.error, "base_error_mm": res.base_error, "inter_error_mm": res.inter_error,
              "iterations": res.iterations, "stable_points_per_frame": float(res.used.sum(1).mean())}
    patch = ArrayPatch.capture(take, "xyz_stabilized", idx, res.xyz)
    return ReportedChange([patch], f"{text}: stabilization error {res.error:.3f} mm", report=report)


def _base(take: Take, frames: np.ndarray, base_frame: int | None) -> int:
    b = take.current_frame if base_frame is None else int(base_frame)
    if not frames[0] <= b <= frames[-1]:
        raise ValueError(f"the base frame {b} is outside the active range {frames[0]}..{frames[-1]}")
    return b - int(frames[0])


def _check_gap_free(take: Take, frames: np.ndarray, cols: np.ndarray, what: str) -> None:
    if len(cols) < 3:
        raise ValueError(f"{what}: select at least three points (got {len(cols)})")
    miss = ~np.isfinite(take.xyz[frames][:, cols]).all(-1)
    if miss.any():
        f, j = np.argwhere(miss)[0]
        raise ValueError(f"{what}: point {_point_name(take, cols[j])} has a gap at frame {int(frames[f])}; "
                         f"select points that are gap-free over the active range")


def stabilize_manual(take: Take, points: Sequence[int], *, base_frame: int | None = None) -> ReportedChange:
    """"Stabilize Data [Manual]": map the selected points (>= 3, gap-free over the active
    range) of every frame onto the base frame (default the current frame).

    Returns
    -------
    ReportedChange
        Patch of ``xyz_stabilized`` over the active range; ``report["error_mm"]`` is the
        stabilization error (Base/Inter Frame Weighting of ``take.params.stabilization`` applied
        to the RMS base-frame and inter-frame errors of the selected points).
    """
    frames = _range(take)
    cols = np.unique(np.asarray(points, dtype=np.int64))
    _check_gap_free(take, frames, cols, "Stabilize Data [Manual]")
    sp = take.params.stabilization
    res = _manual(take.xyz[frames], cols, _base(take, frames, base_frame), base_weight=sp.base_frame_weighting,
                  inter_weight=sp.inter_frame_weighting)
    return _stabilize_change(take, frames, res, "Stabilize Data [Manual]")


def stabilize_assisted(take: Take, points: Sequence[int], *, base_frame: int | None = None,
                       params: StabilizationParameters | None = None) -> ReportedChange:
    """"Stabilize Data [Assisted]": the manual result refined over the most stable points.

    Parameters
    ----------
    take : Take
    points : point columns
        At least three points, gap-free over the active range.
    base_frame : int, optional
        Default the current frame.
    params : StabilizationParameters, optional
        Default ``take.params.stabilization`` (Use Brim Points, Base / Inter Frame
        Weighting, Stable Points Percent, Max Processing Iterations).

    Returns
    -------
    ReportedChange
        Patch of ``xyz_stabilized``; ``report`` has the stabilization error and its parts.
    """
    params = take.params.stabilization if params is None else params
    frames = _range(take)
    cols = np.unique(np.asarray(points, dtype=np.int64))
    _check_gap_free(take, frames, cols, "Stabilize Data [Assisted]")
    kinds = [PointKind.FACE] + ([PointKind.BRIM] if params.use_brim_points else [])
    cand = np.flatnonzero(np.isin(take.points.kind, kinds))
    res = _assisted(take.xyz[frames], cols, _base(take, frames, base_frame), candidates=cand,
                    base_weight=params.base_frame_weighting, inter_weight=params.inter_frame_weighting,
                    stable_fraction=params.stable_points_percent, max_iterations=params.max_processing_iterations)
    return _stabilize_change(take, frames, res, "Stabilize Data [Assisted]")


# ----------------------------------------------------------------------------- alignment
def align_data(take: Take, points: Sequence[int], *, frame: int | None = None, data: str = "auto") -> ReportedChange:
    """"Align Data": express the face data in the frame of three selected points.

    The frame (see :mod:`carapost.core.align`): origin at the first point, x axis towards the
    second, the third in the xy plane (positive y), ``z = x × y``; measured at ``frame``
    (default the current frame). Applied to every frame of the take.

    Parameters
    ----------
    take : Take
    points : three point columns, in order
    frame : int, optional
    data : {"auto", "stabilized", "raw"}
        ``"stabilized"``: the stabilized data are aligned (the raw data are untouched; as the
        guide notes, stabilizing again starts from the raw data and loses the alignment).
        ``"raw"``: the world frame itself changes: ``xyz``, ``xyz_stabilized``, the camera
        poses (so every projection is unchanged) and the brim model are re-expressed.
        ``"auto"``: ``"stabilized"`` if the take has stabilized data, else ``"raw"``.

    Returns
    -------
    ReportedChange
        ``report`` has the rotation ``A`` (rows: new axes in old coordinates), the
        ``origin`` and ``data``.

    Raises
    ------
    ValueError
        Not exactly three distinct points, a point without a position in the frame, or
        collinear points.
    """
    cols = [int(p) for p in points]
    if len(cols) != 3 or len(set(cols)) != 3:
        raise ValueError("Align Data: select exactly three different points")
    if min(cols) < 0 or max(cols) >= take.n_points:
        raise ValueError(f"point indices must be within 0..{take.n_points - 1}")
    f = take.current_frame if frame is None else int(frame)
    if not 0 <= f < take.n_frames:
        raise ValueError(f"frame {f} is outside the take")
    if data not in ("auto", "stabilized", "raw"):
        raise ValueError(f"data must be 'auto', 'stabilized' or 'raw', got {data!r}")
    has_stab = bool(np.isfinite(take.xyz_stabilized).any())
    if data == "auto":
        data = "stabilized" if has_stab else "raw"
    src = take.xyz_stabilized if data == "stabilized" else take.xyz
    P3 = src[f, cols]
    bad = [cols[i] for i in range(3) if not np.isfinite(P3[i]).all()]
    if bad:
        names = ", ".join(_point_name(take, c) for c in bad)
        raise ValueError(f"Align Data: {names} has no {'stabilized ' if data == 'stabilized' else ''}position "
                         f"in frame {f}")
    A, o = frame_from_points(*P3)
    everything = (slice(None),)
    changes: list[Change] = [ArrayPatch.capture(take, "xyz_stabilized", everything,
                                                apply_frame(take.xyz_stabilized, A, o))]
    if data == "raw":
        changes.append(ArrayPatch.capture(take, "xyz", everything, apply_frame(take.xyz, A, o)))
        # X = A^T X' + o, so R X + t = (R A^T) X' + (R o + t)
        changes.append(ArrayPatch.capture(take, "R", everything, take.R @ A.T))
        changes.append(ArrayPatch.capture(take, "t", everything, take.t + take.R @ o))
        if take.brim is not None:
            b = take.brim
            nb = BrimModel(b.name, apply_frame(b.xyz, A, o), b.radius.copy(), b.polarity.copy(), b.svg)
            changes.append(AttributeChange.capture(take, "brim", nb))
    names = ", ".join(_point_name(take, c) for c in cols)
    return ReportedChange(changes, f"Align Data ({data}) to {names}",
                          report={"A": A, "origin": o, "data": data, "frame": f})
