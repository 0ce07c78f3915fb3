"""Growing matches between two cameras from existing 3D points (step 2 of Initialize 3D).

The reference guide: "starting with the seed-points you specified, look iteratively for new
matched 2D points across the two camera views, until no more matches are found. At each
iteration, use the epipolar constraint ... to find any unambiguous candidate matches which
lie within a specified distance of the current 3D points" (Max Allowed Depth).

:func:`grow_pair` implements that rule and makes "unambiguous" precise. A detection often
has several partners on its epipolar line; the candidates are told apart, in order, by

1. **support**: the number of other cameras holding a detection that agrees with the
   candidate (a true point seen by three or four cameras is confirmed by them);
2. **epipolar distance**: candidates more than ``epipolar_margin`` px worse than the best
   drop out;
3. **surface**: candidates lying more than ``surface_margin`` mm further off the local
   surface of the existing points than the best drop out (:func:`surface_offset`: a wrong
   pairing lands in front of or behind the skin, along the ray of its detection).

A candidate is accepted when it is the one left for both of its detections. The search runs
in :class:`GrowStage` stages: first every epipolar candidate competes (so that a wrong pair
near the seeds is not taken while the true partner is still far from every found point), then
the guide's rule (competitors within Max Allowed Depth), then optionally relaxed stages that
reach a little further (up to twice Max Allowed Depth — what the guide's troubleshooting
suggests for widely spaced markers) but accept only candidates lying on the known surface.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .epipolar_match import PairCandidates

__all__ = ["GrowStage", "GUIDE_STAGES", "DEFAULT_STAGES", "GrowResult", "grow_pair", "surface_offset"]


@dataclass(frozen=True)
class GrowStage:
    """One stage of :func:`grow_pair`.

    Attributes
    ----------
    depth : float
        A candidate is plausible within ``depth * max_depth`` of an existing point (candidates
        with support from other cameras: within ``2 * depth * max_depth``).
    compete : float
        Candidates within ``compete * max_depth`` of an existing point compete (``inf``: every
        unused epipolar candidate).
    on_surface : bool
        Plausible only when the candidate's surface offset is known and within the surface
        tolerance (or it has support).
    """

    depth: float = 1.0
    compete: float = 1.0
    on_surface: bool = False


#: The guide's rule, preceded by a stage where every epipolar candidate competes.
GUIDE_STAGES: tuple[GrowStage, ...] = (GrowStage(1.0, np.inf), GrowStage(1.0, 1.0))
#: The guide's stages, then relaxed stages reaching 1.5 and 2 times Max Allowed Depth.
DEFAULT_STAGES: tuple[GrowStage, ...] = GUIDE_STAGES + (GrowStage(1.5, np.inf, True), GrowStage(2.0, np.inf, True))

#: Candidates confirmed by another camera may lie this many times further from existing points.
SUPPORTED_REACH = 2.0


@dataclass(frozen=True)
class GrowResult:
    """Matches found by :func:`grow_pair`.

    Attributes
    ----------
    ia, ib : int arrays (N,)
        Matched detection indices in cameras ``a`` and ``b``, in the order found.
    xyz : array (N, 3)
        Their triangulated points, mm.
    iteration : int array (N,)
        Iteration (from 1) at which each match was accepted.
    n_ambiguous : int
        Detections left unmatched although they had a plausible partner (two or more
        partners that could not be told apart).
    """

    ia: np.ndarray
    ib: np.ndarray
    xyz: np.ndarray
    iteration: np.ndarray
    n_ambiguous: int

    def __len__(self) -> int:
        return len(self.ia)


def surface_offset(xyz: np.ndarray, ray_o: np.ndarray, ray_d: np.ndarray, points: np.ndarray, *,
                   max_lateral: float, k: int = 6, exclude: np.ndarray | None = None) -> np.ndarray:
    """Signed distance along a ray from a candidate point to the local surface of existing points.

    The surface near the ray is the least-squares plane through the (at most ``k``) existing
    points nearest to the ray, within ``max_lateral`` mm of it. A candidate match lies on the
    ray of its detection; the true one lies on the skin, a wrong one in front of or behind it.

    Parameters
    ----------
    xyz : array (N, 3)
        Candidate points, mm.
    ray_o, ray_d : arrays (N, 3)
        The ray of each candidate (origin, unit direction).
    points : array (M, 3)
        Existing points, mm (finite).
    max_lateral : float
        Largest distance of a neighbour from the ray, mm.
    k : int
        Number of neighbours.
    exclude : int array (N,), optional
        Index of a point (of ``points``) to leave out for each candidate (-1 none): the
        candidate itself when an existing point is tested against the others.

    Returns
    -------
    array (N,)
        Depth of the candidate minus depth of the surface along the ray, mm (negative: in
        front of the surface); NaN where fewer than three neighbours span a plane or the ray
        grazes it.
    """
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    N = len(xyz)
    out = np.full(N, np.nan)
    points = np.asarray(points, float).reshape(-1, 3)
    if N == 0 or len(points) < 3:
        return out
    k = min(k, len(points))
    v = points[None, :, :] - ray_o[:, None, :]                       # (N, M, 3)
    s = np.einsum("nmi,ni->nm", v, ray_d)
    lat = np.linalg.norm(v - s[..., None] * ray_d[:, None, :], axis=-1)
    if exclude is not None:
        ex = np.asarray(exclude)
        has = ex >= 0
        lat[np.flatnonzero(has), ex[has]] = np.inf
    idx = np.argpartition(lat, k - 1, axis=1)[:, :k]
    L = np.take_along_axis(lat, idx, axis=1)
    w = (L <= max_lateral).astype(float)
    n = w.sum(axis=1)
    Q = points[idx]                                                   # (N, k, 3)
    c = np.einsum("nk,nki->ni", w, Q) / np.maximum(n, 1)[:, None]
    D = (Q - c[:, None, :]) * w[..., None]
    ev, evec = np.linalg.eigh(np.einsum("nki,nkj->nij", D, D))
    normal = evec[:, :, 0]
    den = np.einsum("ni,ni->n", normal, ray_d)
    ok = (n >= 3) & (ev[:, 1] > 1e-2 * np.maximum(ev[:, 2], 1e-12)) & (np.abs(den) > 0.2)
    s_hat = np.einsum("ni,ni->n", normal, c - ray_o) / np.where(ok, den, 1.0)
    s_x = np.einsum("ni,ni->n", xyz - ray_o, ray_d)
    out[ok] = (s_x - s_hat)[ok]
    return out


def grow_pair(cand: PairCandidates, n_a: int, n_b: int, anchors: np.ndarray, *, max_depth: float,
              support: np.ndarray | None = None, epipolar_margin: float = np.inf,
              rays: tuple[np.ndarray, np.ndarray] | None = None, surface_margin: float = np.inf,
              surface_tolerance: float = np.inf, stages: Sequence[GrowStage] = GUIDE_STAGES,
              max_iterations: int = 1000) -> GrowResult:
    """Grow matches between two cameras from existing 3D points.

    Parameters
    ----------
    cand : PairCandidates
        From :func:`~carapost.core.epipolar_match.pair_candidates` (usable detections only).
    n_a, n_b : int
        Number of detections in each camera.
    anchors : array (K, 3)
        Existing 3D points (the seeds), mm.
    max_depth : float
        Max Allowed Depth, mm.
    support : int array (len(cand),), optional
        Other cameras confirming each candidate (default none).
    epipolar_margin : float
        px (``inf``, the default: candidates with equal support are told apart only when one
        is alone — the guide's rule).
    rays : (origin (len(cand), 3), direction (len(cand), 3)), optional
        Each candidate's ray in camera ``a``; enables the surface tests.
    surface_margin : float
        mm, for telling candidates apart by their surface offsets.
    surface_tolerance : float
        mm: largest surface offset of a plausible candidate in ``on_surface`` stages; in other
        stages candidates further than twice this off a known surface are implausible.
    stages : sequence of GrowStage
        Default: the guide's rule (:data:`GUIDE_STAGES`).

    Returns
    -------
    GrowResult
    """
    anchors = np.asarray(anchors, dtype=float).reshape(-1, 3)
    anchors = anchors[np.isfinite(anchors).all(1)]
    K = len(cand)
    sup = np.zeros(K, np.int64) if support is None else np.asarray(support, np.int64)
    used_a = np.zeros(n_a, bool)
    used_b = np.zeros(n_b, bool)
    when = np.zeros(K, np.int64)  # iteration of acceptance, 0 = not accepted
    dist = np.full(K, np.inf)     # distance of each candidate to the nearest point so far
    off = np.full(K, np.nan)      # surface offset, mm
    new, pts = anchors, anchors
    it = 0
    use_surface = rays is not None
    for stage in stages:
        while K and it < max_iterations:
            alive = ~used_a[cand.ia] & ~used_b[cand.ib]
            if len(new):
                dist = np.minimum(dist, cKDTree(new).query(cand.xyz, k=1)[0])
                if use_surface:
                    sel = np.flatnonzero(alive)
                    off[sel] = surface_offset(cand.xyz[sel], rays[0][sel], rays[1][sel], pts, max_lateral=max_depth)
                new = new[:0]
            reach = stage.depth * max_depth
            plausible = alive & ((dist <= reach) | ((sup > 0) & (dist <= SUPPORTED_REACH * reach)))
            if use_surface and np.isfinite(surface_tolerance):
                a_off = np.abs(off)
                if stage.on_surface:
                    plausible &= (a_off <= surface_tolerance) | (sup > 0)
                else:
                    plausible &= ~(a_off > 2 * surface_tolerance) | (sup > 0)
            if not plausible.any():
                break
            compete = alive & (dist <= stage.compete * max_depth)
            acc = (plausible
                   & _winner(cand.ia, sup, cand.epipolar, off, compete, n_a, epipolar_margin, surface_margin)
                   & _winner(cand.ib, sup, cand.epipolar, off, compete, n_b, epipolar_margin, surface_margin))
            if not acc.any():
                break
            it += 1
            when[acc] = it
            used_a[cand.ia[acc]] = True
            used_b[cand.ib[acc]] = True
            new = cand.xyz[acc]
            pts = np.concatenate([pts, new])
    alive = ~used_a[cand.ia] & ~used_b[cand.ib]
    left = alive & (dist <= max_depth)
    n_amb = int(len(np.unique(cand.ia[left])) + len(np.unique(cand.ib[left])))
    sel = np.flatnonzero(when > 0)
    sel = sel[np.argsort(when[sel], kind="stable")]
    return GrowResult(cand.ia[sel], cand.ib[sel], cand.xyz[sel], when[sel], n_amb)


def _winner(det: np.ndarray, support: np.ndarray, epi: np.ndarray, off: np.ndarray, compete: np.ndarray,
            n: int, epi_margin: float, surf_margin: float) -> np.ndarray:
    """Candidates that are the clear choice for their detection ``det`` among the competing ones.

    Most support first; then within ``epi_margin`` px of the smallest epipolar distance; then
    (where known) within ``surf_margin`` mm of the smallest surface offset. The choice is clear
    when a single candidate is left.
    """
    best = np.full(n, -1, np.int64)
    np.maximum.at(best, det[compete], support[compete])
    top = compete & (support == best[det])
    emin = np.full(n, np.inf)
    np.minimum.at(emin, det[top], epi[top])
    top &= epi <= emin[det] + epi_margin
    if np.isfinite(surf_margin):
        a = np.abs(off)
        known = top & np.isfinite(a)
        omin = np.full(n, np.inf)
        np.minimum.at(omin, det[known], a[known])
        top &= ~(np.isfinite(a) & (a > omin[det] + surf_margin))
    n_top = np.bincount(det[top], minlength=n)
    return top & (n_top[det] == 1)
