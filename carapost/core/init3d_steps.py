"""The steps of Initialize 3D after growing: merging, attaching, checking (used by :mod:`.init3d`).

Points under construction live in a :class:`PointSet` (views as an ``int (P, C)`` array of
detection indices). Every step here is vectorised over points and returns counts for the
report. The :class:`Tolerances` are measured from the seeds (see :func:`measure_tolerances`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .camera import Intrinsics, backproject, symmetric_epipolar_distance
from .epipolar_match import DetectionArrays, attach_views, consistent_views, gather_xy, triangulate_points
from .grow import surface_offset

__all__ = ["PointSet", "Tolerances", "measure_tolerances", "merge_points", "attach", "enforce_residuals",
           "resolve_conflicts", "drop_off_surface"]

#: Effective epipolar tolerance = this many times the seeds' RMS epipolar distance ...
EPIPOLAR_RMS_FACTOR = 6.0
#: ... but at least this many px (the blob detector's centre errors have a tail to ~1 px).
EPIPOLAR_FLOOR_PX = 1.0
#: Chi-square quantile (2 degrees of freedom, 0.1 % false rejection) for adding a view.
CHI2_ADD_VIEW = 13.8
#: Smallest detection noise assumed, px.
NOISE_FLOOR_PX = 0.1
#: Detections within this many tolerances of a projection are examined.
SEARCH_FACTOR = 3.0


@dataclass
class PointSet:
    """Points under construction.

    Attributes
    ----------
    det : int array (P, C)
        Views (detection index per camera, -1 none).
    seed : bool array (P,)
    caddy : int array (P,)
        Caddy index that found the point (-1: seed or another camera pair).
    pair : int array (P, 2)
        Cameras of the match that created the point ((-1, -1) for seeds).
    """

    det: np.ndarray
    seed: np.ndarray
    caddy: np.ndarray
    pair: np.ndarray

    @classmethod
    def empty(cls, C: int) -> "PointSet":
        return cls(np.full((0, C), -1, np.int64), np.zeros(0, bool), np.zeros(0, np.int64),
                   np.full((0, 2), -1, np.int64))

    def __len__(self) -> int:
        return len(self.det)

    def add(self, det: np.ndarray, *, seed: bool, caddy: int, pair: tuple[int, int]) -> None:
        n = len(det)
        self.det = np.concatenate([self.det, np.asarray(det, np.int64).reshape(n, self.det.shape[1])])
        self.seed = np.concatenate([self.seed, np.full(n, seed)])
        self.caddy = np.concatenate([self.caddy, np.full(n, caddy, np.int64)])
        self.pair = np.concatenate([self.pair, np.tile(np.asarray(pair, np.int64), (n, 1))])

    def keep(self, mask: np.ndarray) -> None:
        self.det, self.seed, self.caddy, self.pair = (self.det[mask], self.seed[mask], self.caddy[mask],
                                                      self.pair[mask])

    def n_views(self) -> np.ndarray:
        return (self.det >= 0).sum(axis=1)

    def used(self, n_dets: Sequence[int]) -> list[np.ndarray]:
        """Per camera: bool (n_c,), detections attached to a point."""
        out = []
        for c, n in enumerate(n_dets):
            u = np.zeros(n, bool)
            d = self.det[:, c]
            u[d[d >= 0]] = True
            out.append(u)
        return out

    def owner(self, n_dets: Sequence[int]) -> list[np.ndarray]:
        """Per camera: int (n_c,), the point holding each detection (-1 none)."""
        out = []
        for c, n in enumerate(n_dets):
            o = np.full(n, -1, np.int64)
            d = self.det[:, c]
            o[d[d >= 0]] = np.flatnonzero(d >= 0)
            out.append(o)
        return out


@dataclass(frozen=True)
class Tolerances:
    """Matching tolerances measured on the seeds.

    Attributes
    ----------
    epipolar : float
        Symmetric epipolar distance accepted for a candidate pair, px (at most the Max
        Allowed Symmetric Epipolar Distance).
    view : float
        Largest reprojection error of any view of a point, px.
    noise : float
        Detection noise estimated from the seeds' reprojection errors, px.
    max_increase : float
        Largest increase of a point's sum of squared reprojection errors when a view is
        added, px^2 (chi-square test).
    """

    epipolar: float
    view: float
    noise: float
    max_increase: float

    @property
    def search(self) -> float:
        return SEARCH_FACTOR * self.view


def measure_tolerances(seed_det: np.ndarray, dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics],
                       R: np.ndarray, t: np.ndarray, *, max_epipolar: float, max_view: float) -> Tolerances:
    """Tolerances from the seeds' epipolar distances and reprojection errors.

    The epipolar tolerance is :data:`EPIPOLAR_RMS_FACTOR` times the RMS symmetric epipolar
    distance of every camera pair of every seed (at least :data:`EPIPOLAR_FLOOR_PX`, at most
    ``max_epipolar``): with an accurate calibration it is far tighter than the guide's 5 px
    default, which removes most wrong candidates; with a poor one it widens up to the user's
    limit. Without seeds the user's limits are used as they are.
    """
    xy = gather_xy(seed_det, dets)
    C = seed_det.shape[1]
    d = []
    for a in range(C):
        for b in range(a + 1, C):
            both = (seed_det[:, a] >= 0) & (seed_det[:, b] >= 0)
            if both.any():
                d.append(symmetric_epipolar_distance(xy[both, a], xy[both, b], intrinsics[a], R[a], t[a],
                                                     intrinsics[b], R[b], t[b]))
    if d:
        rms = float(np.sqrt(np.mean(np.concatenate(d) ** 2)))
        epi = float(min(max_epipolar, max(EPIPOLAR_FLOOR_PX, EPIPOLAR_RMS_FACTOR * rms)))
    else:
        epi = float(max_epipolar)
    noise = NOISE_FLOOR_PX
    if len(seed_det):
        _, res = triangulate_points(seed_det, dets, intrinsics, R, t)
        r = res[np.isfinite(res)]
        dof = 2 * len(r) - 3 * len(seed_det)
        if dof > 0:
            noise = max(NOISE_FLOOR_PX, float(np.sqrt(np.sum(r ** 2) / dof)))
    view = float(min(max_view, epi))
    return Tolerances(epipolar=epi, view=view, noise=noise, max_increase=CHI2_ADD_VIEW * noise ** 2)


def merge_points(pts: PointSet, xyz: np.ndarray, dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics],
                 R: np.ndarray, t: np.ndarray, *, max_distance: float, tol: Tolerances) -> tuple[np.ndarray, int, int]:
    """Step 3: merge points seen in disjoint cameras lying within ``max_distance`` mm (``pts`` in place).

    A pair merges when each is the other's nearest mergeable point and the union of their views
    triangulates with every reprojection error within ``tol.view``. The lower row survives
    (seeds come first). Returns the new ``xyz`` and the (merged, rejected) counts.
    """
    xyz = xyz.copy()
    merged = rejected = 0
    for _ in range(8):  # several caddies may each contribute a copy
        idx = np.flatnonzero(np.isfinite(xyz).all(1))
        if len(idx) < 2:
            break
        pairs = cKDTree(xyz[idx]).query_pairs(max_distance, output_type="ndarray")
        if len(pairs) == 0:
            break
        i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
        has = pts.det >= 0
        disjoint = ~(has[i] & has[j]).any(axis=1)
        i, j = i[disjoint], j[disjoint]
        if len(i) == 0:
            break
        d = np.linalg.norm(xyz[i] - xyz[j], axis=1)
        best = np.full(len(xyz), np.inf)
        np.minimum.at(best, i, d)
        np.minimum.at(best, j, d)
        mutual = (d == best[i]) & (d == best[j])
        i, j = i[mutual], j[mutual]
        # exact ties could pair a point twice: keep points that appear once
        count = np.bincount(np.concatenate([i, j]), minlength=len(xyz))
        once = (count[i] == 1) & (count[j] == 1)
        lo, hi = np.minimum(i, j)[once], np.maximum(i, j)[once]
        if len(lo) == 0:
            break
        union = np.where(pts.det[lo] >= 0, pts.det[lo], pts.det[hi])
        X, res = triangulate_points(union, dets, intrinsics, R, t)
        good = np.isfinite(X).all(1) & ~(np.nan_to_num(res, nan=0.0) > tol.view).any(axis=1)
        rejected += int((~good).sum())
        if not good.any():
            break
        lo, hi, union = lo[good], hi[good], union[good]
        pts.det[lo] = union
        pts.seed[lo] |= pts.seed[hi]
        xyz[lo] = X[good]
        alive = np.ones(len(xyz), bool)
        alive[hi] = False
        pts.keep(alive)
        xyz = xyz[alive]
        merged += len(lo)
    return xyz, merged, rejected


def attach(pts: PointSet, xyz: np.ndarray, dets: Sequence[DetectionArrays], excluded: Sequence[np.ndarray],
           intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, tol: Tolerances) -> int:
    """Step 4: attach free detections of other cameras that agree with a point (in place); returns the count."""
    used = pts.used([len(d) for d in dets])
    usable = [~(used[c] | excluded[c]) for c in range(len(dets))]
    new = attach_views(xyz, pts.det, dets, intrinsics, R, t, usable, search=tol.search, tol=tol.view,
                       max_increase=tol.max_increase)
    n = int((new != pts.det).sum())
    pts.det = new
    return n


def enforce_residuals(pts: PointSet, dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics],
                      R: np.ndarray, t: np.ndarray, *, max_residual: float) -> tuple[np.ndarray, int, int]:
    """Detach the worst view of points with a reprojection error above ``max_residual``, repeatedly;
    drop non-seed points left with fewer than two views (in place). Returns (xyz, detached, dropped)."""
    detached = dropped = 0
    C = pts.det.shape[1]
    xyz, res = triangulate_points(pts.det, dets, intrinsics, R, t)
    for _ in range(C):
        r = np.where(np.isfinite(res), res, -1.0)
        worst = np.argmax(r, axis=1) if len(r) else np.zeros(0, np.int64)
        bad = r[np.arange(len(r)), worst] > max_residual
        nv = pts.n_views()
        drop = ((bad & (nv <= 2)) | ~np.isfinite(xyz).all(1)) & ~pts.seed
        detach = bad & (nv > 2)
        if not (drop.any() or detach.any()):
            break
        pts.det[np.flatnonzero(detach), worst[detach]] = -1
        detached += int(detach.sum())
        dropped += int(drop.sum())
        pts.keep(~drop)
        xyz, res = triangulate_points(pts.det, dets, intrinsics, R, t)
        if not detach.any():
            break
    return xyz, detached, dropped


def resolve_conflicts(pts: PointSet, xyz: np.ndarray, dets: Sequence[DetectionArrays],
                      intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                      tol: Tolerances, protect: np.ndarray | None = None) -> tuple[int, int]:
    """Give a detection to the point it agrees with best (in place).

    A point ``P`` with no view in camera ``c`` that agrees (:func:`consistent_views`) with a
    detection already attached to another point ``Q`` has the stronger claim when ``P`` would
    then have more views than ``Q``: a wrong two-view match (a detection paired with clutter
    or with a detection of another marker) is contradicted by the views of the true point.
    ``Q`` loses the detection unless protected (default: the seeds); unprotected points left
    with fewer than two views are dropped. Returns (reassigned detections, dropped points).
    """
    P, C = pts.det.shape
    if P < 2:
        return 0, 0
    n = [len(d) for d in dets]
    owner = pts.owner(n)
    everything = [np.ones(k, bool) for k in n]
    prop = consistent_views(pts.det, xyz, dets, intrinsics, R, t, everything, range(C), search=tol.search,
                            tol=tol.view, max_increase=tol.max_increase)
    p, c = np.nonzero(prop >= 0)
    j = prop[p, c]
    start = np.concatenate([[0], np.cumsum(n)])
    q = np.concatenate(owner)[start[c] + j] if len(p) else np.zeros(0, np.int64)
    nv = pts.n_views()
    ok = (q >= 0) & (q != p)
    p, c, j, q = p[ok], c[ok], j[ok], q[ok]
    protect = pts.seed if protect is None else protect
    ok = (nv[p] + 1 > nv[q]) & ~protect[q]
    p, c, j, q = p[ok], c[ok], j[ok], q[ok]
    # one claim per detection; a point losing a detection does not claim in the same round
    key = c * (1 + max(n)) + j
    uniq, cnt = np.unique(key, return_counts=True)
    ok = np.isin(key, uniq[cnt == 1]) & ~np.isin(p, q)
    p, c, j, q = p[ok], c[ok], j[ok], q[ok]
    if len(p) == 0:
        return 0, 0
    pts.det[q, c] = -1
    pts.det[p, c] = j
    drop = (pts.n_views() < 2) & ~protect
    pts.keep(~drop)
    return len(p), int(drop.sum())


#: A two-view point more than this fraction of the surface tolerance *behind* the surface of
#: the other points is dropped (the skin would hide it); in front, the whole tolerance. Points
#: with more views are tested only for lying behind, by the whole tolerance (the plane through
#: the neighbours of a concave spot such as the philtrum lies well in front of it).
BEHIND_FRACTION = 0.5


def drop_off_surface(pts: PointSet, xyz: np.ndarray, dets: Sequence[DetectionArrays],
                     intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, *, tolerance: float,
                     max_lateral: float, protect: np.ndarray | None = None,
                     test_behind: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Drop points lying off the surface of the other points (in place).

    A wrong two-view match lies in front of or behind the skin along its rays; a point seen in
    more cameras can still be a phantom behind the skin (mirror-image markers of a symmetric
    face paired across the caddies). Two-view points are tested both ways; points marked in
    ``test_behind`` (default none) whatever their views, for lying behind. The offset is
    measured against the other points
    (:func:`~carapost.core.grow.surface_offset`); points found beyond the tolerance are
    measured again without each other (one wrong point bends its neighbours' surface) before
    they are dropped. ``protect`` (default: the seeds) marks points never dropped.
    Returns (xyz, dropped).
    """
    protect = pts.seed if protect is None else protect
    nv_all = pts.n_views()
    behind_only = np.zeros(len(pts), bool) if test_behind is None else test_behind & (nv_all > 2)
    cand = np.flatnonzero(((nv_all == 2) | behind_only) & ~protect & np.isfinite(xyz).all(1))
    two = nv_all[cand] == 2
    if len(cand) == 0 or len(xyz) < 4:
        return xyz, 0
    cam = np.argmax(pts.det[cand] >= 0, axis=1)
    ray_o = np.empty((len(cand), 3))
    ray_d = np.empty((len(cand), 3))
    for c in np.unique(cam):
        sel = cam == c
        ray_o[sel], ray_d[sel] = backproject(dets[c].xy[pts.det[cand[sel], c]], intrinsics[c], R[c], t[c])
    fin = np.isfinite(xyz).all(1)
    row = np.cumsum(fin) - 1  # each point's row among the finite ones
    off = surface_offset(xyz[cand], ray_o, ray_d, xyz[fin], max_lateral=max_lateral, exclude=row[cand])

    behind = np.where(two, BEHIND_FRACTION, 1.0) * tolerance

    def outside(o: np.ndarray) -> np.ndarray:
        o = np.nan_to_num(o, nan=0.0)
        return (o > behind) | (two & (o < -tolerance))

    bad = outside(off)
    if bad.any():
        ref = fin.copy()
        ref[cand[bad]] = False
        sus = np.flatnonzero(bad)
        off[sus] = surface_offset(xyz[cand[sus]], ray_o[sus], ray_d[sus], xyz[ref], max_lateral=max_lateral)
        bad = outside(off)
    if not bad.any():
        return xyz, 0
    keep = np.ones(len(xyz), bool)
    keep[cand[bad]] = False
    pts.keep(keep)
    return xyz[keep], int(bad.sum())
