"""Automatic labelling of marker trajectories: the array contract and the entry point.

The labelling functions work on *unlabelled per-frame point clouds*:

``points`` : float (F, N, 3), mm
    The points of each frame, in any order (the order may change from frame to frame); NaN
    rows are empty slots.
``hints`` : int (F, N)
    What the user (or a file) says about individual points: the marker index of point
    ``points[f, j]``, or -1 when unknown. A labelled reference frame, the seed method's
    "fallback frames", "frame mappings" and "fully labelled markers" are all hints.
``labels`` (the result) : int32 (F, N)
    The marker index of each point, -1 for points left unlabelled (spurious points, or
    points that could not be identified).

:func:`trajectories_from_labels` turns a result into labelled trajectories ``(F, M, 3)``;
:func:`points_from_trajectories` does the reverse (and can shuffle, to hide the labels).

Two methods (:func:`label_points` dispatches):

* ``"assignment"`` (default, :mod:`carapost.core.label_assign`): unambiguous frame-to-frame
  links build tracklets (:mod:`carapost.core.label_tracks`); every tracklet start is resolved
  by a global (Hungarian) assignment against motion-model and neighbourhood-shape predictions
  of the unoccupied markers (:mod:`carapost.core.label_engine`).
* ``"nearest"`` (:mod:`carapost.core.label_nn`): seed 002's per-frame nearest-neighbour method
  with all its options (thresholds, bounding box, skeleton extrapolation, hand heuristics).

Swap detection and repair on labelled trajectories is :mod:`carapost.core.swaps`; marker-set
templates and "Label From Template" are :mod:`carapost.core.template`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "LabelResult",
    "ProgressFn",
    "check_points",
    "check_hints",
    "points_from_trajectories",
    "trajectories_from_labels",
    "hints_from_frame",
    "skeleton_from_sticks",
    "label_accuracy",
    "label_points",
]

#: Progress callback: ``progress(done, total)``; returning ``False`` cancels (where supported).
ProgressFn = Callable[[int, int], object]


@dataclass
class LabelResult:
    """Output of a labelling method.

    Attributes
    ----------
    labels : int32 (F, N)
        Marker index of every point, -1 where unlabelled (always -1 for empty slots).
    report : dict
        Method-specific counts (JSON-serialisable): unlabelled points, events, relabels...
    """

    labels: np.ndarray
    report: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------ checks
def check_points(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate ``points`` (F, N, 3); returns it as float64 and its validity mask (F, N).

    A point is valid when its three coordinates are finite; a partly finite row is empty.

    Raises
    ------
    ValueError
        Wrong shape.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points must have shape (frames, points, 3), got {pts.shape}")
    valid = np.isfinite(pts).all(-1)
    return pts, valid


def check_hints(hints: np.ndarray | None, shape: tuple[int, int], n_markers: int,
                valid: np.ndarray) -> np.ndarray:
    """Validate ``hints`` against the points' ``(F, N)`` shape; returns int32 (F, N).

    Hints on empty slots are dropped. ``None`` gives all -1.

    Raises
    ------
    ValueError
        Wrong shape, labels outside ``-1 .. n_markers - 1``, or a marker hinted on two points
        of the same frame.
    """
    if hints is None:
        return np.full(shape, -1, np.int32)
    h = np.asarray(hints)
    if h.shape != shape:
        raise ValueError(f"hints must have the points' shape {shape}, got {h.shape}")
    if h.size and not np.issubdtype(h.dtype, np.integer):
        raise ValueError("hints must be integer marker indices (-1 = unknown)")
    h = np.where(valid, h, -1).astype(np.int32)
    if h.size and (h.min() < -1 or h.max() >= n_markers):
        raise ValueError(f"hints must be -1 or marker indices 0..{n_markers - 1}")
    _check_unique(h, "hints")
    return h


def _check_unique(labels: np.ndarray, what: str) -> None:
    F = labels.shape[0]
    f, j = np.nonzero(labels >= 0)
    if len(f) == 0:
        return
    key = f.astype(np.int64) * (int(labels.max()) + 1) + labels[f, j]
    u, c = np.unique(key, return_counts=True)
    if (c > 1).any():
        bad = u[c > 1][0]
        m = int(labels.max()) + 1
        raise ValueError(f"{what}: marker {int(bad % m)} is given to two points in frame {int(bad // m)} "
                         f"(of {F})")


# ------------------------------------------------------------------- conversions
def points_from_trajectories(xyz: np.ndarray, extra: np.ndarray | None = None, *, shuffle: bool = True,
                             seed: int | np.random.Generator | None = 0) -> tuple[np.ndarray, np.ndarray]:
    """Unlabelled point clouds from labelled trajectories (hides the labels).

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, NaN for gaps.
    extra : float (F, S, 3), optional
        Unlabelled extra points (spurious), NaN padded.
    shuffle : bool
        Shuffle the points of each frame independently (else markers first, in order).
    seed : int or Generator or None

    Returns
    -------
    points : float64 (F, N, 3)
        ``N = M + S``; the valid points of each frame first, NaN after them.
    truth : int32 (F, N)
        The marker index of each point, -1 for extra points and empty slots.
    """
    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"xyz must have shape (frames, markers, 3), got {xyz.shape}")
    F, M, _ = xyz.shape
    if extra is None:
        extra = np.zeros((F, 0, 3))
    extra = np.asarray(extra, np.float64)
    if extra.ndim != 3 or extra.shape[0] != F or extra.shape[2] != 3:
        raise ValueError(f"extra must have shape ({F}, S, 3), got {extra.shape}")
    allp = np.concatenate([xyz, extra], axis=1)
    lab = np.concatenate([np.broadcast_to(np.arange(M, dtype=np.int32), (F, M)),
                          np.full((F, extra.shape[1]), -1, np.int32)], axis=1)
    valid = np.isfinite(allp).all(-1)
    N = allp.shape[1]
    key = np.where(valid, 0.0, 2.0)
    if shuffle:
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        key = key + rng.random((F, N))
    else:
        key = key + np.arange(N) / (N + 1.0)
    order = np.argsort(key, axis=1, kind="stable")
    pts = np.take_along_axis(allp, order[..., None], axis=1)
    truth = np.take_along_axis(lab, order, axis=1)
    ok = np.take_along_axis(valid, order, axis=1)
    pts[~ok] = np.nan
    truth = np.where(ok, truth, -1).astype(np.int32)
    return pts, truth


def trajectories_from_labels(points: np.ndarray, labels: np.ndarray, n_markers: int) -> np.ndarray:
    """Labelled trajectories from labelled point clouds.

    Parameters
    ----------
    points : float (F, N, 3)
    labels : int (F, N)
        Marker index per point, -1 unlabelled.
    n_markers : int

    Returns
    -------
    float64 (F, M, 3)
        NaN where a marker has no point.

    Raises
    ------
    ValueError
        Shapes disagree, a label is out of range, or a marker labels two points of a frame.
    """
    pts, valid = check_points(points)
    lab = np.asarray(labels)
    if lab.shape != pts.shape[:2]:
        raise ValueError(f"labels must have shape {pts.shape[:2]}, got {lab.shape}")
    lab = np.where(valid, lab, -1)
    if lab.size and (lab.min() < -1 or lab.max() >= n_markers):
        raise ValueError(f"labels must be -1 or 0..{n_markers - 1}")
    _check_unique(lab, "labels")
    F = pts.shape[0]
    out = np.full((F, n_markers, 3), np.nan)
    f, j = np.nonzero(lab >= 0)
    out[f, lab[f, j]] = pts[f, j]
    return out


def hints_from_frame(labels_at_frame: np.ndarray, frame: int, n_frames: int) -> np.ndarray:
    """Hints (F, N) that label only one frame: ``labels_at_frame`` (N,) at ``frame``."""
    lab = np.asarray(labels_at_frame, np.int32).ravel()
    if not 0 <= frame < n_frames:
        raise ValueError(f"frame {frame} is outside 0..{n_frames - 1}")
    h = np.full((n_frames, lab.size), -1, np.int32)
    h[frame] = lab
    return h


def skeleton_from_sticks(sticks: np.ndarray, n_markers: int) -> np.ndarray:
    """A seed-002 skeleton (at most one parent and one child per marker) from sticks.

    Parameters
    ----------
    sticks : int (S, 2)
        Marker index pairs ``(a, b)``; ``a`` is taken as the parent of ``b``. A marker keeps its
        first parent and its first child; further sticks at it are ignored.
    n_markers : int

    Returns
    -------
    int64 (M, 2)
        ``[:, 0]`` parent, ``[:, 1]`` child, -1 where none.
    """
    s = np.asarray(sticks, np.int64).reshape(-1, 2)
    if s.size and (s.min() < 0 or s.max() >= n_markers):
        raise ValueError(f"sticks must join markers 0..{n_markers - 1}")
    sk = np.full((n_markers, 2), -1, np.int64)
    for a, b in s:
        if a == b:
            continue
        if sk[b, 0] < 0 and sk[a, 1] < 0:
            sk[b, 0] = a
            sk[a, 1] = b
    return sk


def label_accuracy(labels: np.ndarray, truth: np.ndarray) -> dict:
    """Share of valid samples labelled correctly.

    Parameters
    ----------
    labels, truth : int (F, N)
        Result and ground truth (-1 = spurious / unlabelled). Empty slots must be -1 in both.

    Returns
    -------
    dict
        ``accuracy`` (correct / marker samples), ``wrong`` (a marker sample given another
        marker), ``missed`` (a marker sample left unlabelled), ``spurious_labelled`` (a
        spurious point given a marker), ``marker_samples``.
    """
    lab = np.asarray(labels)
    tru = np.asarray(truth)
    if lab.shape != tru.shape:
        raise ValueError(f"labels {lab.shape} and truth {tru.shape} differ in shape")
    is_m = tru >= 0
    n = int(is_m.sum())
    correct = int((is_m & (lab == tru)).sum())
    wrong = int((is_m & (lab >= 0) & (lab != tru)).sum())
    missed = int((is_m & (lab < 0)).sum())
    spur = int((~is_m & (lab >= 0)).sum())
    return {"accuracy": correct / n if n else 1.0, "wrong": wrong, "missed": missed,
            "spurious_labelled": spur, "marker_samples": n}


# ------------------------------------------------------------------------- dispatch
def label_points(points: np.ndarray, hints: np.ndarray | None, n_markers: int, *, method: str = "assignment",
                 names: Sequence[str] | None = None, template: np.ndarray | None = None,
                 progress: ProgressFn | None = None, **options: object) -> LabelResult:
    """Label unlabelled point clouds with either method.

    Parameters
    ----------
    points : float (F, N, 3)
    hints : int (F, N) or None
        Known labels (at least one labelled frame, unless ``template`` is given).
    n_markers : int
    method : {"assignment", "nearest"}
    names : sequence of str, optional
        Marker names (the nearest method's hand heuristics need them).
    template : float (M, 3), optional
        Neutral marker positions (assignment method: reference when no hints, and predictions
        of markers not yet seen).
    progress : callable, optional
    **options
        Passed to :func:`~carapost.core.label_assign.label_assignment` or
        :func:`~carapost.core.label_nn.label_nearest`.

    Returns
    -------
    LabelResult
    """
    if method == "assignment":
        from .label_assign import label_assignment
        return label_assignment(points, hints, n_markers, template=template, progress=progress,
                                **options)  # type: ignore[arg-type]
    if method == "nearest":
        from .label_nn import label_nearest
        return label_nearest(points, hints, n_markers, names=names, progress=progress,
                             **options)  # type: ignore[arg-type]
    raise ValueError(f"unknown labelling method {method!r} (expected 'assignment' or 'nearest')")
