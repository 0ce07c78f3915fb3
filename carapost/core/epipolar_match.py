"""Matching detections between cameras: epipolar candidates and consistent extra views.

Building blocks of 3D initialization (:mod:`carapost.core.init3d`,
:mod:`carapost.core.auto_init`), on numpy arrays of raw-pixel detection centres:

* :func:`detection_arrays` normalises a camera's detections (a table with ``x``, ``y`` and
  optionally ``polarity``, or an ``(n, 2)`` array).
* :func:`pair_candidates` lists the detection pairs of two cameras within a symmetric
  epipolar distance, triangulated (one vectorised distance table per camera pair).
* :func:`consistent_views` finds, for points seen in some cameras, the one detection of
  another camera that agrees with them (projection nearby *and* a consistent joint
  triangulation); :func:`attach_views` attaches such detections unambiguously.

A point's views are rows of an ``int (P, C)`` array of detection indices (-1 = none).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .camera import Intrinsics, project, symmetric_epipolar_distance
from .triangulate import triangulate

__all__ = ["DetectionArrays", "detection_arrays", "PairCandidates", "pair_candidates", "consistent_views",
           "attach_views", "triangulate_points", "gather_xy", "in_front"]


@dataclass(frozen=True)
class DetectionArrays:
    """One camera's detections as arrays.

    Attributes
    ----------
    xy : float64 (n, 2)
        Centres, raw px.
    polarity : int8 (n,) or None
        +1 white, -1 black (``None`` when the input carried no polarity).
    """

    xy: np.ndarray
    polarity: np.ndarray | None

    def __len__(self) -> int:
        return len(self.xy)


def detection_arrays(det: object, camera: int = 0) -> DetectionArrays:
    """Normalise one camera's detections.

    Parameters
    ----------
    det : mapping with ``"x"``, ``"y"`` (and optionally ``"polarity"``) arrays (n,), or array (n, 2)
        Raw-pixel detection centres.
    camera : int
        Camera index, for error messages.

    Returns
    -------
    DetectionArrays

    Raises
    ------
    ValueError
        Wrong shapes or non-finite coordinates.
    """
    pol = None
    if isinstance(det, Mapping):
        if "x" not in det or "y" not in det:
            raise ValueError(f"camera {camera}: detections need 'x' and 'y' arrays")
        x = np.asarray(det["x"], dtype=float).ravel()
        y = np.asarray(det["y"], dtype=float).ravel()
        if x.shape != y.shape:
            raise ValueError(f"camera {camera}: 'x' and 'y' have different lengths ({len(x)}, {len(y)})")
        xy = np.stack([x, y], axis=1)
        if "polarity" in det and det["polarity"] is not None:
            pol = np.asarray(det["polarity"]).astype(np.int8).ravel()
            if pol.shape != x.shape:
                raise ValueError(f"camera {camera}: 'polarity' has {len(pol)} entries for {len(x)} detections")
    else:
        xy = np.asarray(det, dtype=float)
        if xy.size == 0:
            xy = xy.reshape(0, 2)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"camera {camera}: detections must be an (n, 2) array, got shape {xy.shape}")
        xy = xy.copy()
    if not np.isfinite(xy).all():
        raise ValueError(f"camera {camera}: detection coordinates must be finite")
    return DetectionArrays(xy=xy, polarity=pol)


def in_front(xyz: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Whether points ``xyz (..., 3)`` are in front of the camera ``R (3, 3)``, ``t (3,)``."""
    return (np.asarray(xyz) @ np.asarray(R)[2] + np.asarray(t)[2]) > 0


def triangulate_points(det_index: np.ndarray, dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics],
                       R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate points from their attached detections.

    Parameters
    ----------
    det_index : int array (P, C)
        Detection index per camera, -1 for none.
    dets : C DetectionArrays
    intrinsics : C Intrinsics
    R, t : arrays (C, 3, 3), (C, 3)

    Returns
    -------
    xyz : array (P, 3)
        mm; NaN for points with fewer than two views.
    residuals : array (P, C)
        Reprojection error per attached view, raw px (NaN where none).
    """
    xy = gather_xy(det_index, dets)
    if len(xy) == 0:
        return np.empty((0, 3)), np.empty((0, len(dets)))
    tri = triangulate(xy, intrinsics, R, t)
    return tri.xyz, tri.residuals


def gather_xy(det_index: np.ndarray, dets: Sequence[DetectionArrays]) -> np.ndarray:
    """Detection centres ``(P, C, 2)`` of ``det_index (P, C)`` (NaN where -1)."""
    P, C = det_index.shape
    out = np.full((P, C, 2), np.nan)
    for c in range(C):
        has = det_index[:, c] >= 0
        out[has, c] = dets[c].xy[det_index[has, c]]
    return out


@dataclass(frozen=True)
class PairCandidates:
    """Candidate matches between two cameras.

    Attributes
    ----------
    ia, ib : int arrays (K,)
        Detection indices in camera ``a`` and ``b``.
    epipolar : array (K,)
        Symmetric epipolar distance, px.
    xyz : array (K, 3)
        Triangulated point of each pair, mm.
    residual : array (K,)
        Largest reprojection error of the two views, raw px.
    """

    ia: np.ndarray
    ib: np.ndarray
    epipolar: np.ndarray
    xyz: np.ndarray
    residual: np.ndarray

    def __len__(self) -> int:
        return len(self.ia)

    def subset(self, keep: np.ndarray) -> "PairCandidates":
        return PairCandidates(self.ia[keep], self.ib[keep], self.epipolar[keep], self.xyz[keep],
                              self.residual[keep])


def pair_candidates(a: int, b: int, dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics],
                    R: np.ndarray, t: np.ndarray, *, max_epipolar: float,
                    usable: Sequence[np.ndarray] | None = None) -> PairCandidates:
    """All pairs of usable detections of cameras ``a`` and ``b`` within ``max_epipolar``.

    The pairs also need the same polarity (when both cameras carry one), a triangulated point
    in front of both cameras and a reprojection error of at most ``max_epipolar`` in each view.

    Parameters
    ----------
    a, b : int
        Camera indices.
    dets : C DetectionArrays
    intrinsics : C Intrinsics
    R, t : arrays (C, 3, 3), (C, 3)
        World-to-camera poses.
    max_epipolar : float
        Max Allowed Symmetric Epipolar Distance, px.
    usable : C bool arrays (n_c,), optional
        Detections that may be matched (default all).

    Returns
    -------
    PairCandidates
    """
    ua = np.ones(len(dets[a]), bool) if usable is None else np.asarray(usable[a], bool)
    ub = np.ones(len(dets[b]), bool) if usable is None else np.asarray(usable[b], bool)
    ia_all = np.flatnonzero(ua)
    ib_all = np.flatnonzero(ub)
    empty = PairCandidates(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
                           np.zeros(0))
    if len(ia_all) == 0 or len(ib_all) == 0:
        return empty
    xa = dets[a].xy[ia_all]
    xb = dets[b].xy[ib_all]
    D = symmetric_epipolar_distance(xa[:, None], xb[None], intrinsics[a], R[a], t[a], intrinsics[b], R[b], t[b])
    ok = D <= max_epipolar
    pa, pb = dets[a].polarity, dets[b].polarity
    if pa is not None and pb is not None:
        ok &= pa[ia_all][:, None] == pb[ib_all][None, :]
    ka, kb = np.nonzero(ok)
    if len(ka) == 0:
        return empty
    ia, ib = ia_all[ka], ib_all[kb]
    xy = np.stack([dets[a].xy[ia], dets[b].xy[ib]], axis=1)
    tri = triangulate(xy, [intrinsics[a], intrinsics[b]], R[[a, b]], t[[a, b]])
    res = np.max(tri.residuals, axis=1)
    good = np.isfinite(tri.xyz).all(1) & (res <= max_epipolar)
    good &= in_front(tri.xyz, R[a], t[a]) & in_front(tri.xyz, R[b], t[b])
    return PairCandidates(ia[good], ib[good], D[ka, kb][good], tri.xyz[good], res[good])


#: Competition radii of :func:`grow_pair`'s stages, in units of Max Allowed Depth.
GROW_SCHEDULE: tuple[float, ...] = (np.inf, 4.0, 2.0, 1.0)


def consistent_views(det_index: np.ndarray, xyz: np.ndarray, dets: Sequence[DetectionArrays],
                     intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, usable: Sequence[np.ndarray],
                     cameras: Sequence[int], *, search: float, tol: float, max_increase: float = np.inf,
                     k: int = 3) -> np.ndarray:
    """For each point and camera, the one usable detection that agrees with the point's views.

    A detection *agrees* when it lies within ``search`` px of the point's projection and the
    point's views plus that detection triangulate with every reprojection error within ``tol``
    px. (A point seen by two close cameras has an uncertain depth, so its projection into a
    distant camera may miss the detection by more than the measurement noise; the joint
    triangulation is the fair test.)

    Parameters
    ----------
    det_index : int array (P, C)
        The points' current views (-1 none); only cameras where a point has none are searched.
    xyz : array (P, 3)
        The points, mm (NaN rows are skipped).
    usable : C bool arrays (n_c,)
        Detections that may be proposed.
    cameras : sequence of int
        Cameras to search.
    search, tol : float
        px.
    max_increase : float
        Largest increase of the sum of squared reprojection errors (px^2) caused by adding
        the detection: a chi-square test with two degrees of freedom (e.g. ``13.8 sigma^2``
        for a 0.1 % false rejection rate at detection noise ``sigma``).
    k : int
        Nearest detections examined per point and camera.

    Returns
    -------
    int array (P, C)
        The agreeing detection where exactly one agrees, else -1.
    """
    P, C = det_index.shape
    out = np.full((P, C), -1, np.int64)
    ok = np.isfinite(xyz).all(1)
    rows, cams, cand = [], [], []
    for c in cameras:
        free = np.flatnonzero(usable[c])
        want = np.flatnonzero(ok & (det_index[:, c] < 0))
        if len(free) == 0 or len(want) == 0:
            continue
        proj = project(xyz[want], intrinsics[c], R[c], t[c])
        vis = np.isfinite(proj).all(1) & in_front(xyz[want], R[c], t[c])
        want, proj = want[vis], proj[vis]
        if len(want) == 0:
            continue
        kk = min(k, len(free))
        d, j = cKDTree(dets[c].xy[free]).query(proj, k=kk, distance_upper_bound=search)
        d = d.reshape(len(d), -1)
        j = j.reshape(len(j), -1)
        hit = np.isfinite(d)
        r, q = np.nonzero(hit)
        rows.append(want[r])
        cams.append(np.full(len(r), c, np.int64))
        cand.append(free[j[r, q]])
    if not rows:
        return out
    rows_a = np.concatenate(rows)
    cams_a = np.concatenate(cams)
    cand_a = np.concatenate(cand)
    if len(rows_a) == 0:
        return out
    trial = det_index[rows_a].copy()
    trial[np.arange(len(rows_a)), cams_a] = cand_a
    X, res = triangulate_points(trial, dets, intrinsics, R, t)
    good = np.isfinite(X).all(1) & ~(np.nan_to_num(res, nan=0.0) > tol).any(axis=1)
    if np.isfinite(max_increase):
        base_rows, inv = np.unique(rows_a, return_inverse=True)
        _, res0 = triangulate_points(det_index[base_rows], dets, intrinsics, R, t)
        ssr0 = np.nansum(res0 ** 2, axis=1)
        ssr = np.nansum(np.nan_to_num(res, nan=0.0) ** 2, axis=1)
        good &= ssr - ssr0[inv] <= max_increase
    key = rows_a * C + cams_a
    n_good = np.bincount(key[good], minlength=P * C)
    single = good & (n_good[key] == 1)
    out[rows_a[single], cams_a[single]] = cand_a[single]
    return out


def attach_views(xyz: np.ndarray, det_index: np.ndarray, dets: Sequence[DetectionArrays],
                 intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, usable: Sequence[np.ndarray],
                 *, search: float, tol: float, max_increase: float = np.inf,
                 cameras: Sequence[int] | None = None) -> np.ndarray:
    """Attach detections that agree with a point unambiguously (:func:`consistent_views`).

    A detection proposed for two points is attached to neither.

    Returns
    -------
    int array (P, C)
        The new attachments (``det_index`` is not modified).
    """
    C = det_index.shape[1]
    prop = consistent_views(det_index, xyz, dets, intrinsics, R, t, usable,
                            range(C) if cameras is None else cameras, search=search, tol=tol,
                            max_increase=max_increase)
    out = det_index.copy()
    for c in range(C):
        p = np.flatnonzero(prop[:, c] >= 0)
        j = prop[p, c]
        claims = np.bincount(j, minlength=len(dets[c]))
        keep = claims[j] == 1
        out[p[keep], c] = j[keep]
    return out
