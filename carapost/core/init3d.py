"""Initialize 3D: grow 3D points from seeds within each caddy, merge the caddies, bundle.

The reference guide's "3D initialization algorithm", on one frame:

1. Exclude the brim points and every unused detection in the brim's image regions (the
   convex hull of the projected brim dots, grown by ``brim_margin_px``).
2. For each camera caddy, starting from the seed points, look iteratively for new matched
   pairs of detections across the caddy's two views: pairs within the epipolar tolerance
   whose triangulated point lies within Max Allowed Depth of a point found so far, accepting
   only unambiguous candidates (:func:`carapost.core.grow.grow_pair`), until no more matches
   are found.
3. Merge the caddies' results: points within Max 3D Distance To Merge (seen in disjoint
   cameras, mutually nearest, consistent when triangulated together) are the same marker.
4. Attach detections of the other cameras that agree with a point, unambiguously.
5. Bundle-adjust poses and points (brim dots fixed when a brim is given), then attach again.

Additions that make the result trustworthy without hand-checking (``docs/initialize-3d.md``
gives the reasons and measurements):

* the seeds are bundled first (the guide's "Bundle Current Frame [Unconstrained]" after
  matching them), and the tolerances are measured on them (:class:`~.init3d_steps.Tolerances`):
  the epipolar tolerance is six times the seeds' RMS epipolar distance (at least 1 px, at most
  Max Allowed Symmetric Epipolar Distance);
* "unambiguous" uses the other cameras' support, the epipolar distance and the surface of the
  points found so far to tell a detection's partners apart (:mod:`carapost.core.grow`), and
  optional relaxed stages reach up to twice Max Allowed Depth on the known surface;
* a view is attached only if the point's joint triangulation stays consistent (largest error
  within the tolerance and a chi-square test on the added error), a detection claimed by a
  point it agrees with better is reassigned, and two-view points lying off the surface of
  the others are dropped (:mod:`carapost.core.init3d_steps`).

:func:`merge_detections` is Edit > Merge (M): detections selected in two or more cameras
become one 3D point.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..model.params import Initialize3DParameters
from .bundle import bundle_adjust
from .camera import Intrinsics, backproject, project
from .epipolar_match import (DetectionArrays, consistent_views, detection_arrays, gather_xy, in_front,
                             pair_candidates, triangulate_points)
from .grow import DEFAULT_STAGES, GUIDE_STAGES, GrowStage, grow_pair
from .init3d_steps import (PointSet, Tolerances, attach, drop_off_surface, enforce_residuals, measure_tolerances,
                           merge_points, resolve_conflicts)
from .triangulate import triangulate

__all__ = ["Init3DResult", "merge_detections", "initialize_3d", "DEFAULT_CADDIES", "check_cameras",
           "brim_observations", "brim_region_mask"]

DEFAULT_CADDIES: tuple[tuple[int, int], ...] = ((0, 1), (2, 3))
#: Stages for camera pairs that are not caddies (only candidates on the known surface).
CROSS_STAGES: tuple[GrowStage, ...] = (GrowStage(1.0, np.inf, True), GrowStage(1.0, 1.0, True))
#: Candidates more than this fraction of Max Allowed Depth further off the surface than the
#: best partner do not compete with it.
SURFACE_MARGIN = 0.5
#: Candidates are on the surface within this fraction of Max Allowed Depth (relaxed stages).
SURFACE_TOLERANCE = 0.5
#: Two-view points more than this fraction of Max Allowed Depth off the others' surface are dropped.
FINAL_SURFACE_TOLERANCE = 1.0
#: Partners within this fraction of the epipolar tolerance of the best are not told apart.
EPIPOLAR_MARGIN = 0.5


@dataclass(frozen=True)
class Init3DResult:
    """The points found by 3D initialization on one frame.

    ``P`` points (face markers; seeds first, in the order given), ``C`` cameras, ``B`` brim dots.

    Attributes
    ----------
    xyz : array (P, 3)
        Point positions, mm.
    det_index : int array (P, C)
        Attached detection per camera (index into that camera's detections), -1 for none.
    xy : array (P, C, 2)
        The attached detections' centres, raw px (NaN where none).
    from_seed : bool array (P,)
        The point is one of the seeds.
    caddy : int array (P,)
        Index (into ``caddies``) of the caddy whose growth found the point; -1 for seeds and
        for points found along another camera pair.
    pair : int array (P, 2)
        The two cameras whose match created the point ((-1, -1) for seeds).
    residuals : array (P, C)
        Reprojection error of each attached view, raw px (NaN where none).
    R, t : arrays (C, 3, 3), (C, 3)
        Camera poses used for the result (refined when bundled).
    brim_det_index : int array (B, C)
        Detection attached to each brim dot (-1 none); ``(0, C)`` without a brim.
    report : dict
        Counts per stage: ``seeds``, ``excluded`` and ``brim_observed`` (per camera),
        ``tolerances`` (``epipolar_px``, ``view_px``, ``noise_px`` measured on the seeds),
        ``grown`` / ``iterations`` / ``ambiguous`` (per camera pair, keyed ``"a-b"``;
        ``ambiguous`` counts detections left with partners that could not be told apart),
        ``merged``, ``merge_rejected``, ``attached`` (views), ``reassigned`` (views moved to
        the point they agree with better), ``detached`` (views), ``dropped`` and
        ``dropped_off_surface`` (points), ``seed_bundle`` and ``bundle`` (RMS per camera and
        costs, or None), ``points``; ``auto`` for :func:`~carapost.core.auto_init.auto_initialize`.
    """

    xyz: np.ndarray
    det_index: np.ndarray
    xy: np.ndarray
    from_seed: np.ndarray
    caddy: np.ndarray
    pair: np.ndarray
    residuals: np.ndarray
    R: np.ndarray
    t: np.ndarray
    brim_det_index: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return len(self.xyz)

    @property
    def n_views(self) -> np.ndarray:
        """Number of attached views per point, int (P,)."""
        return (self.det_index >= 0).sum(axis=1)


# --------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------


def check_cameras(intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                  n_cameras: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Validate poses ``R (C, 3, 3)``, ``t (C, 3)`` against the intrinsics; return float copies."""
    C = len(intrinsics) if n_cameras is None else n_cameras
    if len(intrinsics) != C:
        raise ValueError(f"{len(intrinsics)} intrinsics for {C} cameras")
    R = np.array(R, dtype=float)
    t = np.array(t, dtype=float)
    if R.shape != (C, 3, 3) or t.shape != (C, 3):
        raise ValueError(f"poses must have shapes ({C}, 3, 3) and ({C}, 3), got {R.shape} and {t.shape}")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise ValueError("camera poses must be finite (solve the brim first)")
    return R, t


def _check_caddies(caddies: Sequence[Sequence[int]], C: int) -> list[tuple[int, int]]:
    out = []
    for cad in caddies:
        if len(cad) != 2:
            raise ValueError(f"a caddy is a pair of cameras, got {tuple(cad)}")
        a, b = int(cad[0]), int(cad[1])
        if a == b:
            raise ValueError(f"caddy {tuple(cad)} names one camera twice")
        if not (0 <= a < C and 0 <= b < C):
            continue  # a caddy of cameras this take does not have (e.g. the default on 2 cameras)
        out.append((a, b))
    return out


def _check_seeds(seeds: Sequence[Mapping[int, int]], dets: Sequence[DetectionArrays]) -> np.ndarray:
    C = len(dets)
    out = np.full((len(seeds), C), -1, np.int64)
    owner: dict[tuple[int, int], int] = {}
    for s, seed in enumerate(seeds):
        if not isinstance(seed, Mapping):
            raise ValueError(f"seed {s}: expected a mapping camera -> detection index, got {type(seed).__name__}")
        for cam, det in seed.items():
            c, d = int(cam), int(det)
            if not 0 <= c < C:
                raise ValueError(f"seed {s}: camera {c} does not exist ({C} cameras)")
            if not 0 <= d < len(dets[c]):
                raise ValueError(f"seed {s}: camera {c} has no detection {d} ({len(dets[c])} detections)")
            if (c, d) in owner:
                raise ValueError(f"seeds {owner[(c, d)]} and {s} use the same detection {d} of camera {c}")
            owner[(c, d)] = s
            out[s, c] = d
        if (out[s] >= 0).sum() < 2:
            raise ValueError(f"seed {s} is matched in {(out[s] >= 0).sum()} camera(s); a seed needs at least 2")
    return out


# --------------------------------------------------------------------------------------
# Merge (M)
# --------------------------------------------------------------------------------------


def merge_detections(det_xy: Mapping[int, Any], intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                     *, max_residual: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Edit > Merge (M): detections selected in two or more cameras become one 3D point.

    Parameters
    ----------
    det_xy : mapping camera -> array (2,)
        The selected detections' centres, raw px, at most one per camera.
    intrinsics : C Intrinsics
    R, t : arrays (C, 3, 3), (C, 3)
        World-to-camera poses.
    max_residual : float
        Largest allowed reprojection error of any view, px (the tracking parameters' Max
        Allowed 2D Projection Error is a natural choice).

    Returns
    -------
    xyz : array (3,)
        The point, mm.
    residuals : array (C,)
        Reprojection error per camera, px (NaN for cameras without a selected detection).

    Raises
    ------
    ValueError
        Fewer than two cameras, an unknown camera, a point behind a camera, or a view whose
        reprojection error exceeds ``max_residual`` (the detections do not belong together).
    """
    C = len(intrinsics)
    R, t = check_cameras(intrinsics, R, t)
    xy = np.full((C, 2), np.nan)
    for cam, p in det_xy.items():
        c = int(cam)
        if not 0 <= c < C:
            raise ValueError(f"merge: camera {c} does not exist ({C} cameras)")
        v = np.asarray(p, dtype=float).ravel()
        if v.shape != (2,) or not np.isfinite(v).all():
            raise ValueError(f"merge: camera {c}: expected a finite (x, y), got {p!r}")
        xy[c] = v
    n = int(np.isfinite(xy).all(1).sum())
    if n < 2:
        raise ValueError(f"merge needs detections in at least 2 cameras, got {n}")
    tri = triangulate(xy[None], intrinsics, R, t)
    X = tri.xyz[0]
    res = tri.residuals[0]
    if not np.isfinite(X).all():
        raise ValueError("merge: the selected detections cannot be triangulated")
    cams = np.flatnonzero(np.isfinite(xy).all(1))
    behind = [int(c) for c in cams if not in_front(X, R[c], t[c])]
    if behind:
        raise ValueError(f"merge: the point would lie behind camera(s) {behind}; the detections do not match")
    worst = int(cams[np.nanargmax(res[cams])])
    if res[worst] > max_residual:
        raise ValueError(f"merge: the detections do not belong together: reprojection error {res[worst]:.2f} px "
                         f"in camera {worst} exceeds {max_residual:g} px")
    return X, res


# --------------------------------------------------------------------------------------
# Brim
# --------------------------------------------------------------------------------------


def brim_observations(brim_xyz: np.ndarray, dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics],
                      R: np.ndarray, t: np.ndarray, *, radius: float,
                      usable: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Detections of the brim dots: the one detection within ``radius`` px of each projection.

    Returns
    -------
    int array (B, C)
        Detection index per brim dot and camera, -1 where none (or where two detections lie
        within the radius, or two dots claim the same detection).
    """
    brim_xyz = np.asarray(brim_xyz, float).reshape(-1, 3)
    B, C = len(brim_xyz), len(dets)
    out = np.full((B, C), -1, np.int64)
    for c in range(C):
        free = np.flatnonzero(np.ones(len(dets[c]), bool) if usable is None else usable[c])
        if B == 0 or len(free) == 0:
            continue
        proj = project(brim_xyz, intrinsics[c], R[c], t[c])
        vis = np.flatnonzero(np.isfinite(proj).all(1) & in_front(brim_xyz, R[c], t[c]))
        if len(vis) == 0:
            continue
        k = min(2, len(free))
        d, j = cKDTree(dets[c].xy[free]).query(proj[vis], k=k)
        d = d.reshape(len(d), -1)
        j = j.reshape(len(j), -1)
        single = (d[:, 0] <= radius) & ((d[:, 1] > radius) if k == 2 else True)
        det = free[j[single, 0]]
        claims = np.bincount(det, minlength=len(dets[c]))
        keep = claims[det] == 1
        out[vis[single][keep], c] = det[keep]
    return out


def brim_region_mask(brim_xyz: np.ndarray, xy: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray,
                     *, margin: float) -> np.ndarray:
    """Which points ``xy (n, 2)`` lie in the brim's image region of one camera.

    The region is the convex hull of the projected brim dots (those in front of the camera),
    grown by ``margin`` px.

    Returns
    -------
    bool array (n,)
    """
    xy = np.asarray(xy, float).reshape(-1, 2)
    p = project(np.asarray(brim_xyz, float), intr, R, t)
    p = p[np.isfinite(p).all(1) & in_front(brim_xyz, R, t)]
    if len(p) < 3 or len(xy) == 0:
        return np.zeros(len(xy), bool)
    try:
        eq = ConvexHull(p).equations  # (k, 3): unit normal . x + offset <= 0 inside
    except QhullError:  # collinear projections: a segment, grown by the margin
        a, b = p[np.argmin(p @ (p[-1] - p[0]))], p[np.argmax(p @ (p[-1] - p[0]))]
        d = b - a
        s = np.clip(((xy - a) @ d) / max(d @ d, 1e-12), 0.0, 1.0)
        return np.linalg.norm(xy - (a + s[:, None] * d), axis=1) <= margin
    return (xy @ eq[:, :2].T + eq[:, 2]).max(axis=1) <= margin


# --------------------------------------------------------------------------------------
# Initialize 3D
# --------------------------------------------------------------------------------------


def _support(cand: Any, pair: tuple[int, int], dets: Sequence[DetectionArrays], usable: Sequence[np.ndarray],
             intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, tol: Tolerances) -> np.ndarray:
    """Number of other cameras holding a detection that agrees with each candidate pair, int (K,)."""
    det = np.full((len(cand), len(dets)), -1, np.int64)
    det[:, pair[0]] = cand.ia
    det[:, pair[1]] = cand.ib
    others = [c for c in range(len(dets)) if c not in pair]
    new = consistent_views(det, cand.xyz, dets, intrinsics, R, t, usable, others, search=tol.search, tol=tol.view,
                           max_increase=tol.max_increase)
    return (new >= 0).sum(axis=1)


class _Run:
    """State of one :func:`initialize_3d` call (the steps share the detections, poses, report)."""

    def __init__(self, dets: list[DetectionArrays], intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                 params: Initialize3DParameters, excluded: list[np.ndarray], brim: np.ndarray | None,
                 brim_det: np.ndarray, report: dict[str, Any]) -> None:
        self.dets, self.intr, self.R, self.t = dets, list(intrinsics), R, t
        self.params, self.excluded, self.brim, self.brim_det = params, excluded, brim, brim_det
        self.report = report
        self.trust_seeds = True
        self.pts = PointSet.empty(len(dets))
        self.tol = Tolerances(params.max_allowed_symmetric_epipolar_distance, 3.0, 0.1, np.inf)

    def triangulate(self) -> np.ndarray:
        return triangulate_points(self.pts.det, self.dets, self.intr, self.R, self.t)[0]

    def grow(self, pairs: Sequence[tuple[int, int]], caddy_ids: Sequence[int], anchors: np.ndarray,
             stages: Sequence[GrowStage]) -> None:
        """Step 2 along each camera pair (adds rows to the point set)."""
        n = [len(d) for d in self.dets]
        md = self.params.max_allowed_depth
        for (a, b), k in zip(pairs, caddy_ids):
            used = self.pts.used(n)
            usable = [~(used[c] | self.excluded[c]) for c in range(len(n))]
            cand = pair_candidates(a, b, self.dets, self.intr, self.R, self.t, max_epipolar=self.tol.epipolar,
                                   usable=usable)
            sup = _support(cand, (a, b), self.dets, usable, self.intr, self.R, self.t, self.tol)
            rays = backproject(self.dets[a].xy[cand.ia], self.intr[a], self.R[a], self.t[a])
            g = grow_pair(cand, n[a], n[b], anchors, max_depth=md, support=sup,
                          epipolar_margin=EPIPOLAR_MARGIN * self.tol.epipolar, rays=rays,
                          surface_margin=SURFACE_MARGIN * md, surface_tolerance=SURFACE_TOLERANCE * md,
                          stages=stages)
            det = np.full((len(g), len(n)), -1, np.int64)
            det[:, a] = g.ia
            det[:, b] = g.ib
            self.pts.add(det, seed=False, caddy=k, pair=(a, b))
            key = f"{a}-{b}"
            self.report["grown"][key] = self.report["grown"].get(key, 0) + len(g)
            self.report["iterations"][key] = int(g.iteration.max()) if len(g) else 0
            self.report["ambiguous"][key] = g.n_ambiguous

    def consolidate(self, xyz: np.ndarray) -> np.ndarray:
        """Steps 3-4: merge, attach, check; returns the points' positions."""
        rep, pts, tol = self.report, self.pts, self.tol
        args = (self.dets, self.intr, self.R, self.t)
        xyz, m, rj = merge_points(pts, xyz, *args, max_distance=self.params.max_3d_distance_to_merge, tol=tol)
        rep["merged"] += m
        rep["merge_rejected"] += rj
        rep["attached"] += attach(pts, xyz, self.dets, self.excluded, self.intr, self.R, self.t, tol)
        xyz, det, drop = enforce_residuals(pts, *args, max_residual=tol.view)
        protect = pts.seed if self.trust_seeds else np.zeros(len(pts), bool)
        moved, dropped = resolve_conflicts(pts, xyz, *args, tol, protect=protect)
        rep["reassigned"] += moved
        if moved:
            rep["attached"] += attach(pts, self.triangulate(), self.dets, self.excluded, self.intr, self.R, self.t,
                                      tol)
            xyz, det2, drop2 = enforce_residuals(pts, *args, max_residual=tol.view)
            det, drop = det + det2, drop + drop2 + dropped
        md = self.params.max_allowed_depth
        protect = pts.seed if self.trust_seeds else np.zeros(len(pts), bool)
        xyz, off = drop_off_surface(pts, xyz, *args, tolerance=FINAL_SURFACE_TOLERANCE * md, max_lateral=md,
                                    protect=protect, test_behind=pts.seed & ~protect)
        rep["detached"] += det
        rep["dropped"] += drop
        rep["dropped_off_surface"] += off
        return xyz

    def bundle(self, xyz: np.ndarray) -> dict[str, Any]:
        """Bundle-adjust poses and points (brim dots fixed); updates ``R``, ``t``."""
        obs = gather_xy(self.pts.det, self.dets)
        X = xyz
        fixed = np.zeros(len(xyz), bool)
        if self.brim is not None and len(self.brim):
            obs = np.concatenate([obs, gather_xy(self.brim_det, self.dets)])
            X = np.concatenate([xyz, self.brim])
            fixed = np.concatenate([fixed, np.ones(len(self.brim), bool)])
        res = bundle_adjust(obs[None], self.intr, self.R[None], self.t[None], X[None], fixed_points=fixed,
                            loss="huber", f_scale=1.0)
        self.R, self.t = res.R[0], res.t[0]
        return {"rms_per_camera": [float(v) for v in res.rms_per_camera], "initial_cost": res.initial_cost,
                "final_cost": res.final_cost, "success": res.success, "nfev": res.nfev}


def exclusions(dets: Sequence[DetectionArrays], exclude: Sequence[np.ndarray] | None) -> list[np.ndarray]:
    """Per camera, the detections the caller excluded (bool (n_c,)); checks the masks' shapes."""
    C = len(dets)
    n = [len(d) for d in dets]
    excluded = [np.zeros(k, bool) for k in n]
    if exclude is not None:
        if len(exclude) != C:
            raise ValueError(f"exclude has {len(exclude)} masks for {C} cameras")
        for c in range(C):
            m = np.asarray(exclude[c], bool).ravel()
            if m.shape != (n[c],):
                raise ValueError(f"exclude mask of camera {c} has {m.size} entries for {n[c]} detections")
            excluded[c] = m.copy()
    return excluded


def initialize_3d(detections: Sequence[Any], intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                  seeds: Sequence[Mapping[int, int]], params: Initialize3DParameters | None = None, *,
                  caddies: Sequence[Sequence[int]] = DEFAULT_CADDIES,
                  exclude: Sequence[np.ndarray] | None = None, brim_xyz: np.ndarray | None = None,
                  bundle: bool = True, relaxed: bool = True, cross_pairs: bool = False, attach_px: float = 3.0,
                  brim_margin_px: float = 15.0, trust_seeds: bool = True) -> Init3DResult:
    """Process > Initialize 3D on one frame.

    Parameters
    ----------
    detections : C per-camera detections
        Each a table with ``"x"``, ``"y"`` (and optionally ``"polarity"``; only detections of
        the same polarity are matched) or an array (n_c, 2), raw px.
    intrinsics : C Intrinsics
    R, t : arrays (C, 3, 3), (C, 3)
        World-to-camera poses of the frame (from the brim solve), mm.
    seeds : list of mapping camera -> detection index
        Hand-matched seed points (5-10, spread over the face), each matched in at least two
        cameras (preferably all, at least the two cameras of one caddy). They come first in
        the result, in this order.
    params : Initialize3DParameters, optional
        Max Allowed Depth, Max 3D Distance To Merge, Max Allowed Symmetric Epipolar Distance
        (defaults if omitted).
    caddies : sequence of camera pairs
        Default ``((0, 1), (2, 3))``; pairs naming cameras the take lacks are ignored.
    exclude : C bool arrays (n_c,), optional
        Detections never to match (e.g. the brim's).
    brim_xyz : array (B, 3), optional
        Brim dots, mm (world = brim frame). Their detections and every unused detection in the
        brim's image region are excluded, and the brim dots are held fixed in the bundle.
    bundle : bool
        Bundle-adjust the seeds before growing and all points at the end (poses refined).
    relaxed : bool
        After the guide's rule, also accept candidates up to 2 x Max Allowed Depth away that
        lie on the surface of the points found (markers spaced wider than Max Allowed Depth).
    cross_pairs : bool
        Also grow along camera pairs that are not caddies (markers no caddy sees in both
        cameras). Off by default: such pairs are built from the detections every other step
        left over, where a wrong pairing is most likely.
    attach_px : float
        Upper bound of the reprojection tolerance for attaching and merging views, px (the
        tolerance itself is measured on the seeds).
    brim_margin_px : float
        Growth of the brim's image region, px.
    trust_seeds : bool
        Seeds are never dropped nor lose a detection (hand-matched seeds). Off for seeds found
        automatically: they are checked like every other point (they still come first).

    Returns
    -------
    Init3DResult

    Raises
    ------
    ValueError
        Inconsistent shapes, unknown cameras or detections in the seeds, a detection used by two
        seeds, a seed matched in fewer than two cameras.
    """
    params = Initialize3DParameters() if params is None else params
    params.validate()
    C = len(detections)
    if C < 1:
        raise ValueError("initialize 3D needs at least one camera")
    dets = [detection_arrays(d, c) for c, d in enumerate(detections)]
    R, t = check_cameras(intrinsics, R, t, C)
    cads = _check_caddies(caddies, C)
    seed_det = _check_seeds(seeds, dets)
    if not attach_px > 0 or not brim_margin_px >= 0:
        raise ValueError("attach_px must be positive and brim_margin_px not negative")
    n = [len(d) for d in dets]
    report: dict[str, Any] = {"seeds": len(seed_det), "grown": {}, "iterations": {}, "ambiguous": {}, "merged": 0,
                              "merge_rejected": 0, "attached": 0, "detached": 0, "dropped": 0,
                              "dropped_off_surface": 0, "reassigned": 0, "bundle": None, "seed_bundle": None}

    # 1. exclusions: explicit, the brim's detections, the brim's image region (seeds are kept)
    excluded = exclusions(dets, exclude)
    seeds_ps = PointSet.empty(C)
    seeds_ps.add(seed_det, seed=True, caddy=-1, pair=(-1, -1))
    seed_used = seeds_ps.used(n)
    brim = None if brim_xyz is None else np.asarray(brim_xyz, float).reshape(-1, 3)
    brim_det = np.full((0 if brim is None else len(brim), C), -1, np.int64)
    if brim is not None:
        brim_det = brim_observations(brim, dets, intrinsics, R, t, radius=attach_px,
                                     usable=[~u for u in seed_used])
        for c in range(C):
            excluded[c][brim_det[brim_det[:, c] >= 0, c]] = True
            excluded[c] |= brim_region_mask(brim, dets[c].xy, intrinsics[c], R[c], t[c], margin=brim_margin_px)
    for c in range(C):
        excluded[c] &= ~seed_used[c]
    report["excluded"] = [int(e.sum()) for e in excluded]
    report["brim_observed"] = [int((brim_det[:, c] >= 0).sum()) for c in range(C)]

    run = _Run(dets, intrinsics, R, t, params, excluded, brim, brim_det, report)
    run.pts = seeds_ps
    run.trust_seeds = trust_seeds
    # the seeds, bundled first; the tolerances are measured on them
    if bundle and len(seed_det):
        report["seed_bundle"] = run.bundle(run.triangulate())
    tol = measure_tolerances(seed_det, dets, run.intr, run.R, run.t,
                             max_epipolar=params.max_allowed_symmetric_epipolar_distance, max_view=attach_px)
    run.tol = tol
    report["tolerances"] = {"epipolar_px": tol.epipolar, "view_px": tol.view, "noise_px": tol.noise}
    seed_xyz = run.triangulate()

    # 2. grow within each caddy from the seeds
    run.grow(cads, list(range(len(cads))), seed_xyz, DEFAULT_STAGES if relaxed else GUIDE_STAGES)
    # 3. merge the caddies, 4. attach other cameras (and check)
    xyz = run.consolidate(run.triangulate())
    if cross_pairs:
        others = [(a, b) for a in range(C) for b in range(a + 1, C) if (a, b) not in cads and (b, a) not in cads]
        if others and len(xyz):
            run.grow(others, [-1] * len(others), xyz, CROSS_STAGES)
            xyz = run.consolidate(run.triangulate())
    # 5. bundle, then attach with the refined poses
    if bundle and len(run.pts):
        report["bundle"] = run.bundle(xyz)
        xyz = run.consolidate(run.triangulate())
        if brim is not None:
            used = run.pts.used(n)
            run.brim_det = brim_observations(brim, dets, run.intr, run.R, run.t, radius=tol.view,
                                             usable=[~u for u in used])

    pts = run.pts
    xyz, res = triangulate_points(pts.det, dets, run.intr, run.R, run.t)
    report["points"] = len(pts)
    return Init3DResult(xyz=xyz, det_index=pts.det.copy(), xy=gather_xy(pts.det, dets), from_seed=pts.seed.copy(),
                        caddy=pts.caddy.copy(), pair=pts.pair.copy(), residuals=res, R=run.R, t=run.t,
                        brim_det_index=run.brim_det, report=report)
