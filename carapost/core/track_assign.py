"""Assigning a frame's detections to points: the matching rules of the tracker's rounds.

* :func:`match_points` — candidates near the predicted projections (gated by distance,
  polarity, blob size and, with images, patch appearance), chosen by the neighbours' vote or
  as the unambiguous nearest, each detection given to one point.
* :func:`complete_anchors` — points confirmed in some cameras are looked for in the others,
  next to where their 3D position projects.
* :func:`occluded` — a point hidden behind another in a camera is not matched there.
* :func:`elastic_radius`, :func:`inside` — search radii and the image frame.

Shapes: ``C`` cameras, ``T`` points; camera-first arrays ``(C, T, ...)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from .track_cameras import CameraSet
from .track_match import FrameDetections, greedy_assign, neighbour_support, query_candidates
from .track_patches import Appearance
from .track_reject import GATE, prune_views

if TYPE_CHECKING:  # pragma: no cover
    from .track_step import StepContext

__all__ = ["match_points", "complete_anchors", "reclaim", "occluded", "elastic_radius", "inside"]

#: An unsupported (non-elastic) match must be this much nearer than the runner-up: d2 > 2 d1 + 1 px.
AMBIGUITY_RATIO = 2.0
#: Projections closer than this (px) with depths differing by more than OCCLUSION_DEPTH_MM:
#: the farther point is hidden by the nearer one in that camera.
OCCLUSION_PX = 6.0
OCCLUSION_DEPTH_MM = 2.0
#: A candidate the neighbours support (weighted fraction agreeing on the displacement) at
#: least this much, and this much more than the runner-up, is taken.
MIN_SUPPORT = 0.5
SUPPORT_MARGIN = 0.25
#: Candidates per projection considered by the vote.
VOTE_CANDIDATES = 5
#: Search radius around an anchor's projection in a camera it was not matched in, px.
COMPLETE_PX = 3.0
#: A detection this many times nearer another point's expected projection is left to it.
OWNER_FACTOR = 0.5
#: Smallest elastic search radius, px.
MIN_RADIUS_PX = 2.0
#: A point placed by three views or more reclaims, in another camera, a detection this near
#: its projection from a point holding it with only two views, px (see :func:`reclaim`).
RECLAIM_PX = 1.0
#: Views that make a point's position trustworthy enough to reclaim detections.
RECLAIM_VIEWS = 3


def match_points(ctx: "StepContext", dets: FrameDetections, pc: np.ndarray, active: np.ndarray, radius: np.ndarray,
           claimed: np.ndarray, cols: np.ndarray, app: Appearance | None, *, ratio: np.ndarray | None,
           penalty: np.ndarray | None, vote: np.ndarray | None = None,
           owners: np.ndarray | None = None, hidden_by_claimed: np.ndarray | None = None) -> np.ndarray:
    """Match projections ``pc (C, n, 2)`` of points ``cols (n,)`` to detections; returns gids (C, n).

    ``ratio`` (n,) marks points that may only take an unambiguous nearest detection; points
    marked in ``vote`` (n,) (``cols`` must then be every point) take the candidate their
    neighbours' displacements support instead, when they have queried neighbours
    (:func:`~.track_match.neighbour_support`). With ``owners (C, n, 2)`` — where every point
    (``cols`` must then be every point) is expected in each camera, NaN if nowhere — a
    detection much nearer another point's expected projection than the query's is left to
    that point (:data:`OWNER_FACTOR`), even if that point is not looking for it now. Points
    marked in ``hidden_by_claimed`` (n,) (which must also be marked in ``ratio``) count
    detections already claimed by other points as rivals too: a re-acquired point whose
    projection falls on another point's detection is hidden behind it, and the nearest free
    detection (a stray one) is not its.
    """
    C, n = active.shape
    out = np.full((C, n), -1, np.int64)
    forbid = np.full((C, n), -2, np.int64)
    claimed = claimed.copy()
    todo = active.copy()
    p = ctx.params
    for _ in range(3):
        cand = query_candidates(dets, pc, todo, radius, claimed=claimed, polarity=ctx.polarity[cols],
                                size=ctx.size[:, cols], size_threshold=p.blob_size_difference_threshold,
                                forbid=forbid, k=VOTE_CANDIDATES if vote is not None else 4)
        cost = cand.dist
        tq = cand.query % n
        if owners is not None and len(tq):
            cost = _leave_to_owners(dets, cand, owners, cost, tq)
        voted = np.zeros(len(tq), bool)
        if vote is not None and len(tq):
            sup = neighbour_support(dets, cand, pc, ctx.graph.index, ctx.nbw, rows=vote[tq])
            voted = np.isfinite(sup).all(1) & vote[tq]
            sv = np.where(np.isfinite(sup), sup, -1.0) - 1e-6 * np.where(np.isfinite(cost), cost, 1e6)
            order = np.argsort(-sv, axis=1)
            rows = np.arange(len(tq))
            b1, b2 = order[:, 0], order[:, 1] if sv.shape[1] > 1 else order[:, 0]
            s1 = np.where(np.isfinite(sup[rows, b1]), sup[rows, b1], 0.0)
            s2 = np.where(np.isfinite(sup[rows, b2]) & (b2 != b1), sup[rows, b2], 0.0)
            clear = (s1 >= MIN_SUPPORT) & (s1 - s2 >= SUPPORT_MARGIN) & np.isfinite(cost[rows, b1])
            vcost = np.full_like(cost, np.inf)
            vcost[rows, b1] = (1.0 - s1) * 100.0 + cost[rows, b1]
            # a clear vote decides; an unclear one (neighbours hidden or ambiguous themselves)
            # leaves the unambiguous-nearest rule below -- unless the point is placed by clear
            # votes in other cameras (then it waits for its elastic prediction)
            cost = np.where((voted & clear)[:, None], vcost, cost)
            placed = np.zeros(n, bool)
            placed[tq[voted & clear]] = True
            cost = np.where((voted & ~clear & placed[tq])[:, None], np.inf, cost)
            voted &= clear
        if ratio is not None:
            best = cost.min(axis=1)
            amb = ratio[tq] & ~voted & ~((best <= cand.nearest + 1e-9) & (cand.second > AMBIGUITY_RATIO * best + 1.0))
            if hidden_by_claimed is not None and cand.taken is not None:
                amb |= hidden_by_claimed[tq] & ~(cand.taken > AMBIGUITY_RATIO * best + 1.0)
            cost = np.where(amb[:, None], np.inf, cost)
        if penalty is not None:
            cost = cost + penalty[tq][:, None]
        a = greedy_assign(cand.query, cand.det, cost, len(dets))
        got = a >= 0
        q, g = cand.query[got], a[got]
        cq, tq2 = np.divmod(q, n)
        if app is not None and len(q):
            ok = app.check(cq, cols[tq2], g)
            forbid[cq[~ok], tq2[~ok]] = g[~ok]
            q, g, cq, tq2 = q[ok], g[ok], cq[ok], tq2[ok]
            retry = ~ok
        else:
            retry = np.zeros(0, bool)
        out[cq, tq2] = g
        claimed[g] = True
        if not np.any(retry):
            break
        todo = np.zeros_like(todo)
        bq = cand.query[got][retry]
        todo.reshape(-1)[bq] = True
    return out


def _leave_to_owners(dets: FrameDetections, cand, owners: np.ndarray, cost: np.ndarray,
                     tq: np.ndarray) -> np.ndarray:
    """Forbid candidates (cost inf) lying much nearer another point's expected projection."""
    C, n = owners.shape[:2]
    ok = np.isfinite(owners).all(-1)
    flat = np.flatnonzero(ok.ravel())
    if len(flat) == 0:
        return cost
    valid = np.isfinite(cost) & (cand.det >= 0)
    if not np.any(valid):
        return cost
    key = owners.reshape(-1, 2)[flat].copy()
    key[:, 0] += (flat // n) * 1.0e6
    tree = cKDTree(key, balanced_tree=False, compact_nodes=False)
    # each candidate detection once; only owners nearer than OWNER_FACTOR * cost matter
    dv = cand.det[valid]
    mark = np.zeros(len(dets) + 1, bool)
    mark[dv] = True
    g = np.flatnonzero(mark)
    pos = np.empty(len(mark), np.int64)
    pos[g] = np.arange(len(g))
    inv = pos[dv]
    q = dets.pc[g].copy()
    q[:, 0] += dets.cam[g] * 1.0e6
    cv = cost[valid]
    d, j = tree.query(q, k=1, distance_upper_bound=OWNER_FACTOR * float(cv.max()) + 1e-9)
    found = j < len(flat)
    who = np.where(found, flat[np.minimum(j, len(flat) - 1)] % n, -1)
    d, who = d[inv], who[inv]
    other = (who >= 0) & (who != np.broadcast_to(tq[:, None], cost.shape)[valid]) & (d < OWNER_FACTOR * cv)
    out = cost.copy()
    out.reshape(-1)[np.flatnonzero(valid.ravel())[other]] = np.inf
    return out


def inside(pc: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Projections ``(C, n, 2)`` inside their camera's image (unknown sizes: anything finite)."""
    W, H = size[:, 0:1], size[:, 1:2]
    ok = np.isfinite(pc).all(-1)
    known = W > 0
    with np.errstate(invalid="ignore"):
        inside = (pc[..., 0] >= -0.5) & (pc[..., 1] >= -0.5) & (pc[..., 0] <= W - 0.5) & (pc[..., 1] <= H - 0.5)
    return ok & (inside | ~known)


def complete_anchors(ctx: "StepContext", dets: FrameDetections, pts: np.ndarray, Xa: np.ndarray, tent: np.ndarray,
              claimed: np.ndarray, R: np.ndarray, t: np.ndarray, app: Appearance | None, anchor_px: float,
              keep_all: bool, X_all: np.ndarray, occluders: np.ndarray, hidden: np.ndarray | None = None) -> None:
    """Match anchors in their missing cameras near their projection (updates ``tent``,
    ``claimed`` and ``Xa`` in place). A view is added only if it is unambiguous within
    :data:`COMPLETE_PX`, no other point (``occluders`` at ``X_all``) is in front of it there
    (or ``hidden (C, T)`` says so, when already known), and the point's views still agree
    (leave-one-out) with it."""
    cams = ctx.cams
    T = len(pts)
    uvp = cams.project_uv(np.where(pts[:, None], Xa, np.nan), R, t)
    pc = cams.to_pixels(uvp)
    miss = pts[None, :] & (tent < 0) & inside(pc, ctx.image_size) & ctx.cam_ok[:, None]
    if not np.any(miss):
        return
    Xo = np.where(pts[:, None], Xa, np.where(occluders[:, None], X_all, np.nan))
    po = cams.to_pixels(cams.project_uv(Xo, R, t))
    if hidden is None:
        hidden = occluded(Xo, pts, occluders | pts, po, R, t)
    miss &= ~hidden
    g = match_points(ctx, dets, pc, miss, np.full(T, COMPLETE_PX), claimed, np.arange(T), app,
                     ratio=np.ones(T, bool), penalty=None, owners=po)
    got = np.flatnonzero((g >= 0).any(0))
    if len(got) == 0:
        return
    both = np.where(g[:, got] >= 0, g[:, got], tent[:, got])
    w0 = (both >= 0).astype(float)
    w, X, _ = prune_views(dets.uv[both], w0, R, t, cams.scale, anchor_px, loo_px=anchor_px,
                          pred_uv=uvp[:, got])
    added = (g[:, got] >= 0) & ((w > 0) | keep_all)
    # keep the point's own views even if the pruning would now drop one of them
    ok = ((w > 0) | (tent[:, got] >= 0) | ~(g[:, got] >= 0)).all(0) | keep_all
    add = added & ok[None, :]
    if not np.any(add):
        return
    cols = got[add.any(0)]
    new_g = np.where(add, g[:, got], tent[:, got])
    tent[:, got] = new_g
    claimed[g[:, got][add]] = True
    Xa[cols] = X[np.isin(got, cols)]


def reclaim(dets: FrameDetections, strong: np.ndarray, weak: np.ndarray, X: np.ndarray, tent: np.ndarray,
            claimed: np.ndarray, R: np.ndarray, t: np.ndarray, cams: CameraSet) -> tuple[np.ndarray, np.ndarray]:
    """Give back to well-placed points the detections that poorly placed ones took from them.

    In a fast expression the motion-model predictions are off by millimetres, so a point
    can take, in round 0, a neighbour's detection in a camera where it is itself hidden; with
    two views (one caddy each) the wrong pair may still triangulate consistently. A point
    placed by :data:`RECLAIM_VIEWS` views or more (``strong``) whose projection in a camera
    it was not matched in lies within :data:`RECLAIM_PX` of a detection held by a ``weak``
    point with only two views has a far better claim to it: the detection is released
    (``tent`` and ``claimed`` updated in place) so that :func:`complete_anchors` can give it
    to the strong point.

    Returns
    -------
    weakened, claimants : bool arrays (T,)
        Points that lost a view; points that may now take it.
    """
    C, T = tent.shape
    lost_view = np.zeros(T, bool)
    gained = np.zeros(T, bool)
    nv = (tent >= 0).sum(0)
    strong = strong & (nv >= RECLAIM_VIEWS)
    holders = weak & (nv == 2)
    if not np.any(strong) or not np.any(holders) or len(dets) == 0:
        return lost_view, gained
    pc = cams.to_pixels(cams.project_uv(np.where(strong[:, None], X, np.nan), R, t))        # (C, T, 2)
    ask = strong[None, :] & (tent < 0) & np.isfinite(pc).all(-1)
    cq, tq = np.nonzero(ask)
    if len(cq) == 0:
        return lost_view, gained
    q = pc[cq, tq].copy()
    q[:, 0] += cq * 1.0e6
    d, g = dets.tree.query(q, k=1, distance_upper_bound=RECLAIM_PX)
    found = g < len(dets)
    owner = np.full(len(dets) + 1, -1, np.int64)
    hc, ht = np.nonzero(holders[None, :] & (tent >= 0))
    owner[tent[hc, ht]] = ht
    h = np.where(found, owner[np.minimum(g, len(dets))], -1)
    take = found & (h >= 0) & (h != tq)
    if not np.any(take):
        return lost_view, gained
    gi, hi = g[take], h[take]
    cam = dets.cam[gi]
    tent[cam, hi] = -1
    claimed[gi] = False
    lost_view[hi] = True
    gained[tq[take]] = True
    return lost_view, gained


def occluded(X: np.ndarray, members: np.ndarray, occluders: np.ndarray, pc: np.ndarray, R: np.ndarray,
              t: np.ndarray) -> np.ndarray:
    """Points hidden behind another point in a camera, bool (C, T).

    A member and an occluder (a point whose position is trusted) projecting within
    :data:`OCCLUSION_PX` of each other, the member more than :data:`OCCLUSION_DEPTH_MM`
    behind: the detection there is the front marker's.
    """
    C, T = pc.shape[:2]
    ok = (members | occluders)[None, :] & np.isfinite(pc).all(-1)
    flat = np.flatnonzero(ok.ravel())
    out = np.zeros(C * T, bool)
    if len(flat) < 2:
        return out.reshape(C, T)
    key = pc.reshape(-1, 2)[flat].copy()
    key[:, 0] += (flat // T) * 1.0e6
    pairs = cKDTree(key, balanced_tree=False, compact_nodes=False).query_pairs(OCCLUSION_PX, output_type="ndarray")
    if len(pairs) == 0:
        return out.reshape(C, T)
    a, b = flat[pairs[:, 0]], flat[pairs[:, 1]]
    z = (np.matmul(np.where(np.isfinite(X), X, 0.0), R[:, 2, :].T).T + t[:, 2:3]).ravel()   # depth (C*T,)
    dz = z[a] - z[b]
    pa, pb = a % T, b % T
    out[a[(dz > OCCLUSION_DEPTH_MM) & members[pa] & occluders[pb]]] = True
    out[b[(dz < -OCCLUSION_DEPTH_MM) & members[pb] & occluders[pa]]] = True
    return out.reshape(C, T)


def elastic_radius(Xel: np.ndarray, sigma: np.ndarray, R: np.ndarray, t: np.ndarray, cams: CameraSet,
                    cap: float) -> np.ndarray:
    """Search radius ``(C, T)`` px around elastic predictions: the gate times the prediction's
    uncertainty seen from each camera, plus a pixel, within ``[2 px, cap]``."""
    z = np.matmul(np.where(np.isfinite(Xel), Xel, 0.0), R[:, 2, :].T).T + t[:, 2:3]      # (C, T) depth
    with np.errstate(invalid="ignore", divide="ignore"):
        r = GATE * sigma[None, :] * cams.f[:, None] / z + 1.0
    return np.clip(np.where(np.isnan(r) | (r == np.inf), cap, r), MIN_RADIUS_PX, cap)
