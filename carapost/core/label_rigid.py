"""Rigid-group re-identification: name returning rigid clusters of points as a whole.

Frame-to-frame labelling names a point that appears after a gap from the predictions of the
missing markers; when a whole rigid cluster (a wheelchair's markers, an arm's cluster) vanishes
and comes back, every prediction of its markers is vague and the returning points can take
the names of other missing markers (markers that never come back). The shape check
(:mod:`carapost.core.label_shape`) cannot see it: the wrong names' partners are absent. This
module looks at the points' mutual distances instead:

1. :func:`rigid_groups`: from trusted frames near the reference frame, the sets of markers whose
   mutual distances all stay constant (robust spread at most ``max_spread_mm`` plus
   ``rel_spread`` of the distance): the rigid bodies of the marker set. Each group keeps a
   reference configuration (the trusted frame where its distances are closest to their
   medians) and a tolerance per marker.
2. :func:`fit_groups` (one frame): for every group, hypotheses from triplets of points whose
   mutual distances match a triplet of the group's markers; each is a rigid (Kabsch) fit of
   the group's configuration, whose predicted markers take the points within their tolerance.
   A group's best fit is kept when it names at least 3 points and no fit naming the points
   differently is about as good (a symmetric cluster says nothing).
3. :func:`rigid_relabel` (the take): the fits of sampled frames vote for the names of the
   *pieces* (runs of one tracklet under one label); a piece whose votes clearly and
   consistently name another marker takes that name for its whole run, the pieces it displaces
   are left unnamed (and take their old name back where it is free afterwards).

Only clear evidence changes a name: a vote needs a fit of at least 3 points with distances
within the group's tolerance, and a piece moves only when most of its sampled frames vote for
the same new name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from .label_engine import kabsch

__all__ = ["RigidGroups", "rigid_groups", "fit_groups", "confirmed_labels", "rigid_relabel", "keeps_rigid_groups"]


@dataclass(frozen=True)
class RigidGroups:
    """Rigid clusters of markers.

    Attributes
    ----------
    members : list of int64 (g,)
        Marker indices of each group (at least 3).
    config : list of float64 (g, 3)
        Reference configuration of each group, mm (positions in one trusted frame).
    dist : list of float64 (g, g)
        Median distances between the group's markers, mm.
    tol : list of float64 (g,)
        Distance tolerance of each member, mm.
    """

    members: list
    config: list
    dist: list
    tol: list

    def __len__(self) -> int:
        return len(self.members)


def rigid_groups(xyz: np.ndarray, frames: np.ndarray, *, trusted: np.ndarray | None = None,
                 check_frames: np.ndarray | None = None, max_spread_mm: float = 1.5, rel_spread: float = 0.005,
                 min_size: int = 3, min_frames: int = 10, spacing_share: float = 0.3,
                 check_share: float = 0.6, tol_mm: float = 2.5) -> RigidGroups:
    """Rigid clusters of markers from the trusted samples of ``frames``.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, mm, NaN gaps.
    frames : int (S,)
        Frames whose labels are trusted (e.g. around the reference frame).
    trusted : bool (S, M), optional
        Which samples of those frames are trusted (default all).
    max_spread_mm, rel_spread : float
        A pair of markers is rigid when the robust spread (1.4826 x MAD) of its distance is at
        most ``max_spread_mm + rel_spread * distance``.
    check_frames : int (S2,), optional
        Frames of the whole take (labels mostly right): a pair must keep its distance there
        too, within twice the spread limit, in at least ``check_share`` of the frames where
        both are labelled. A face barely moving near the reference frame looks rigid there,
        not over the take; a share, not a spread, because the labels there may be wrong.
    min_size : int
        Smallest group kept.
    min_frames : int
        A pair counts only when both markers are present in this many frames (at most half
        the frames).
    spacing_share : float
        A member's tolerance is at most this share of its distance to the nearest other
        marker in the reference configuration (so that a fit never names a neighbour).
    tol_mm : float
        A member's tolerance: this plus 3 times its largest spread to a group-mate.

    Returns
    -------
    RigidGroups
        Every pair of a group is rigid; a marker is in at most one group (greedily, most
        rigid pairs first).
    """
    x = np.asarray(xyz, np.float64)
    fr = np.asarray(frames, np.int64)
    X = x[fr]
    if trusted is not None:
        X = np.where(np.asarray(trusted, bool)[..., None], X, np.nan)
    M = X.shape[1]
    d, D, S, ok = _pair_spread(X, max_spread_mm, rel_spread, min_frames)
    if check_frames is not None:
        d2 = _distances(x[np.asarray(check_frames, np.int64)])
        lim = 2.0 * (max_spread_mm + rel_spread * np.nan_to_num(D, nan=np.inf))
        both = np.isfinite(d2)
        within = (both & (np.abs(d2 - D[None]) <= lim[None])).sum(0)
        ok &= within >= check_share * np.maximum(both.sum(0), 1)
    np.fill_diagonal(ok, False)
    Dn = np.where(np.isfinite(D), D, np.inf)
    np.fill_diagonal(Dn, np.inf)
    spacing = Dn.min(1)
    Sx = np.where(ok, S, np.inf)
    free = np.ones(M, bool)
    members, configs, dists, tols = [], [], [], []
    while True:
        cand = np.where(free[:, None] & free[None], Sx, np.inf)
        if not np.isfinite(cand).any():
            break
        a, b = np.unravel_index(np.argmin(cand), cand.shape)
        grp = [int(a), int(b)]
        while True:
            inside = ok[:, grp].all(1) & free
            inside[grp] = False
            if not inside.any():
                break
            worst = Sx[:, grp].max(1)
            grp.append(int(np.argmin(np.where(inside, worst, np.inf))))
        free[grp] = False
        if len(grp) < min_size:
            continue
        g = np.array(sorted(grp), np.int64)
        Xg = X[:, g]
        full = np.isfinite(Xg[..., 0]).all(1)
        if not full.any():
            continue
        dg = d[:, g][:, :, g]
        err = np.abs(dg - D[np.ix_(g, g)][None]).sum((1, 2))
        best = int(np.flatnonzero(full)[np.argmin(err[full])])
        Sg = S[np.ix_(g, g)].copy()
        np.fill_diagonal(Sg, 0.0)
        members.append(g)
        configs.append(Xg[best].copy())
        dists.append(D[np.ix_(g, g)].copy())
        tols.append(np.minimum(tol_mm + 3.0 * Sg.max(1), spacing_share * spacing[g]))
    return RigidGroups(members, configs, dists, tols)


def _distances(X: np.ndarray) -> np.ndarray:
    """Pairwise distances (S, M, M) of the frames ``X`` (S, M, 3), float32, NaN where either
    point is missing (each frame centred first: float32 keeps its precision)."""
    X = np.asarray(X, np.float64)
    ok = np.isfinite(X[..., 0])
    c = np.where(ok[..., None], X, 0.0).sum(1) / np.maximum(ok.sum(1), 1)[:, None]
    Y = (X - c[:, None]).astype(np.float32)
    sq = np.einsum("smi,smi->sm", Y, Y)
    d2 = sq[:, :, None] + sq[:, None, :] - 2.0 * np.matmul(Y, Y.transpose(0, 2, 1))
    return np.sqrt(np.maximum(d2, 0.0))


def _pair_spread(X: np.ndarray, max_spread_mm: float, rel_spread: float,
                 min_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Distances (S, M, M) of the frames ``X`` (S, M, 3), their medians and robust spreads
    (M, M), and which pairs are rigid (present in enough frames, spread within the limit)."""
    from .label_shape import _nan_median0
    d = _distances(X)
    n = np.isfinite(d).sum(0)
    D = _nan_median0(d, n).astype(np.float64)
    S = 1.4826 * _nan_median0(np.abs(d - D[None].astype(np.float32)), n).astype(np.float64)
    ok = (n >= max(3, min(min_frames, len(X) // 2))) & (S <= max_spread_mm + rel_spread * np.nan_to_num(D, nan=np.inf))
    return d, D, S, ok


# ------------------------------------------------------------------------------ one frame
def _seed_members(cfg: np.ndarray, limit: int = 5) -> np.ndarray:
    """Up to ``limit`` well spread members of a configuration (farthest-point order), whose
    triplets seed the hypotheses."""
    g = len(cfg)
    if g <= limit:
        return np.arange(g)
    d = np.linalg.norm(cfg - cfg.mean(0), axis=1)
    pick = [int(np.argmax(d))]
    dmin = np.linalg.norm(cfg - cfg[pick[0]], axis=1)
    while len(pick) < limit:
        k = int(np.argmax(dmin))
        pick.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(cfg - cfg[k], axis=1))
    return np.array(pick)


def _place(P: np.ndarray, cfg: np.ndarray, tol: np.ndarray, src: np.ndarray,
           dst: np.ndarray) -> tuple[np.ndarray, float]:
    """Rigid fit of ``cfg[src]`` to ``P[dst]``; every member takes the point within its
    tolerance of its predicted position (optimal assignment). Returns the mapping (g,) (point
    index or -1) and the rms residual of the named points."""
    R, ca, cb = kabsch(cfg[src], P[dst])
    pred = (cfg - ca) @ R.T + cb
    e = np.linalg.norm(pred[:, None, :] - P[None], axis=-1)  # (g, n)
    C = np.where(e <= tol[:, None], e, 1e6)
    ri, ci = linear_sum_assignment(C)
    good = C[ri, ci] < 1e6
    mp = np.full(len(cfg), -1, np.int64)
    mp[ri[good]] = ci[good]
    res = e[ri[good], ci[good]]
    return mp, (float(np.sqrt(np.mean(res * res))) if good.any() else np.inf)


def _fit_one(P: np.ndarray, cfg: np.ndarray, D: np.ndarray, tol: np.ndarray,
             dP: np.ndarray, with_rival: bool = False) -> tuple:
    """Best rigid placement of one group among the points ``P`` (n, 3) (``dP`` their distance
    matrix, diagonal negative), from triplets of points matching triplets of well spread
    members. Returns ``(mapping (g,) point index or -1, rms, unique)``; mapping None when no
    triplet of points matches. ``with_rival``: also the placement that makes it not unique
    (or None).
    """
    from itertools import combinations
    hyps: dict[tuple, tuple[int, float]] = {}
    for a, b, c in combinations(_seed_members(cfg).tolist(), 3):
        tab, tac, tbc = (max(tol[a], tol[b]), max(tol[a], tol[c]), max(tol[b], tol[c]))
        ii, jj = np.nonzero(np.abs(dP - D[a, b]) <= tab)
        if ii.size == 0:
            continue
        K = (np.abs(dP[ii] - D[a, c]) <= tac) & (np.abs(dP[jj] - D[b, c]) <= tbc)
        K[np.arange(ii.size), ii] = False
        K[np.arange(ii.size), jj] = False
        pi, kk = np.nonzero(K)
        if pi.size > 100:  # too many coincidences: this triplet says little
            continue
        for i, j, k in zip(ii[pi].tolist(), jj[pi].tolist(), kk.tolist()):
            mp, rms = _place(P, cfg, tol, np.array([a, b, c]), np.array([i, j, k]))
            key = tuple(mp.tolist())
            if key not in hyps:
                hyps[key] = (int((mp >= 0).sum()), rms)
    if not hyps:
        return (None, np.inf, False, None) if with_rival else (None, np.inf, False)
    ranked = sorted(hyps.items(), key=lambda kv: (-kv[1][0], kv[1][1]))
    best, (n_in, rms) = ranked[0]
    bm = np.array(best)
    unique = True
    rival = None
    for key, (n2, r2) in ranked[1:]:
        km = np.array(key)
        both = (bm >= 0) & (km >= 0)
        if not (km[both] != bm[both]).any() and n2 <= n_in:
            continue  # a subset of the best placement
        if n2 >= n_in and r2 <= 2.0 * rms + 0.5:
            unique = False
            rival = km
        break
    if with_rival:
        return bm, rms, unique, rival
    return bm, rms, unique


def fit_groups(points: np.ndarray, groups: RigidGroups, *, labels: np.ndarray | None = None,
               confirmed: np.ndarray | None = None, min_points: int = 3, tiebreak=None,
               partial: bool = False) -> np.ndarray:
    """Names of one frame's points from rigid fits of the groups.

    Parameters
    ----------
    points : float (N, 3)
        The frame's points, mm (NaN rows empty).
    groups : RigidGroups
    labels : int (N,), optional
        Current labels of the points (-1 none) ...
    confirmed : bool (N,), optional
        ... and which of them are confirmed (consistent with at least two group-mates, see
        :func:`confirmed_labels`). A confirmed point keeps its name and is no candidate for
        another group; a group with at least 3 confirmed members is placed from them alone.
    min_points : int
        Fewest points a group's fit must name.
    tiebreak : callable, optional
        ``tiebreak(points, labels, confirmed, members, [mapping, rival])`` -> 0, 1 or None:
        chooses between two placements of a group that fit about equally well (mappings
        (g,) member -> point index or -1); None (default) leaves the group unnamed there.
    partial : bool
        Where two placements stay tied, name the points both name alike (the apex of a
        near-isosceles triangle: ForearmL Marker2 of ``kinematics_basket_sprint`` between
        Marker1 and Marker4, 49 and 50 mm away); these fits rank below every full fit.

    Returns
    -------
    int64 (N,)
        Marker index of each point from its group's fit, -1 where no clear fit names it.
        Fits naming more points win a point claimed twice.
    """
    P = np.asarray(points, np.float64)
    ok = np.isfinite(P).all(1)
    out = np.full(len(P), -1, np.int64)
    if ok.sum() < min_points or len(groups) == 0:
        return out
    lab = np.full(len(P), -1, np.int64) if labels is None else np.asarray(labels, np.int64)
    conf = np.zeros(len(P), bool) if confirmed is None else np.asarray(confirmed, bool) & ok & (lab >= 0)
    free = np.flatnonzero(ok & ~conf)
    fits = []
    for gi in range(len(groups)):
        mem, cfg, tol = groups.members[gi], groups.config[gi], groups.tol[gi]
        own = np.flatnonzero(conf & np.isin(lab, mem))
        if own.size == len(mem):
            out[own] = lab[own]
            continue
        if own.size >= 3:
            # placed by its confirmed members; only the others look for points
            src = np.searchsorted(mem, lab[own])
            miss = np.setdiff1d(np.arange(len(mem)), src)
            mp = np.full(len(mem), -1, np.int64)
            mp[src] = own
            if free.size:
                R, ca, cb = kabsch(cfg[src], P[own])
                e = np.linalg.norm(((cfg[miss] - ca) @ R.T + cb)[:, None] - P[free][None], axis=-1)
                C = np.where(e <= tol[miss][:, None], e, 1e6)
                if (C < 1e6).any():
                    ri, ci = linear_sum_assignment(C)
                    good = C[ri, ci] < 1e6
                    mp[miss[ri[good]]] = free[ci[good]]
            fits.append((int((mp >= 0).sum()), 0.0, gi, mp))
            continue
        cand = np.concatenate([own, free])
        if cand.size < min_points:
            continue
        Q = P[cand]
        dP = np.linalg.norm(Q[:, None] - Q[None], axis=-1)
        np.fill_diagonal(dP, -1e9)
        mp, rms, unique, rival = _fit_one(Q, cfg, groups.dist[gi], tol, dP, with_rival=True)
        if mp is not None and not unique and tiebreak is not None and rival is not None:
            # a near-symmetric cluster: other evidence (e.g. distances learnt over the take)
            # may tell the two placements apart
            maps = [np.where(m >= 0, cand[np.maximum(m, 0)], -1) for m in (mp, rival)]
            pick = tiebreak(P, lab, conf, mem, maps)
            if pick is not None:
                unique = True
                mp = (mp, rival)[pick]
        if mp is not None and not unique and partial and rival is not None and (mp >= 0).sum() >= min_points:
            same = np.where((mp == rival) & (mp >= 0), mp, -1)  # the points both placements name alike
            if (same >= 0).any():
                fits.append((0, -rms, gi, np.where(same >= 0, cand[np.maximum(same, 0)], -1)))
            continue
        if mp is None or not unique or (mp >= 0).sum() < min_points:
            continue
        fits.append((int((mp >= 0).sum()), -rms, gi, np.where(mp >= 0, cand[np.maximum(mp, 0)], -1)))
    fits.sort(key=lambda t: (t[0], t[1]), reverse=True)
    for _n, _r, gi, mp in fits:
        sel = mp >= 0
        pts = mp[sel]
        if (out[pts] >= 0).any():
            continue
        out[pts] = groups.members[gi][sel]
    return out


def confirmed_labels(xyz: np.ndarray, groups: RigidGroups, *, anchors: int = 4) -> np.ndarray:
    """Which labelled samples agree with their rigid group: bool (F, M), True where the marker
    is present and its distances to at least two present group-mates (among its ``anchors``
    nearest in the configuration) are within tolerance."""
    x = np.asarray(xyz, np.float32)
    out = np.zeros(x.shape[:2], bool)
    for mem, cfg, D, tol in zip(groups.members, groups.config, groups.dist, groups.tol):
        g = len(mem)
        dc = np.linalg.norm(cfg[:, None] - cfg[None], axis=-1)
        np.fill_diagonal(dc, np.inf)
        K = min(anchors, g - 1)
        nb = np.argsort(dc, axis=1)[:, :K]  # (g, K)
        X = x[:, mem]
        diff = X[:, :, None, :] - X[:, nb]  # (F, g, K, 3)
        d = np.sqrt(np.einsum("fgki,fgki->fgk", diff, diff))
        lim = np.maximum(tol[:, None], tol[nb]).astype(np.float32)
        good = np.abs(d - np.take_along_axis(D, nb, 1).astype(np.float32)[None]) <= lim[None]
        out[:, mem] = good.sum(2) >= 2
    return out


def _place_batch(Xg: np.ndarray, cm: np.ndarray, cfg: np.ndarray, tol: np.ndarray, P: np.ndarray,
                 free: np.ndarray, mem: np.ndarray, claims: np.ndarray, rows: np.ndarray) -> None:
    """Place one group in many frames from its confirmed members (at least 3 in each) and let
    its other members claim the nearest free point within tolerance (vectorised).

    ``Xg`` (S, g, 3) the members' labelled positions, ``cm`` (S, g) which are confirmed, ``P``
    (S, N, 3) the frames' points, ``free`` (S, N) the unconfirmed ones; writes the claimed
    marker indices into ``claims[rows]`` (a point two groups claim: -2, no one's)."""
    w = cm.astype(np.float64)[..., None]  # (S, g, 1)
    A = np.where(cm[..., None], np.broadcast_to(cfg, Xg.shape), 0.0)
    B = np.where(cm[..., None], Xg, 0.0)
    n = w.sum(1)  # (S, 1)
    ca, cb = A.sum(1) / n, B.sum(1) / n  # (S, 3)
    H = np.einsum("sgi,sgj->sij", (A - ca[:, None]) * w, (B - cb[:, None]) * w)
    U, _s, Vt = np.linalg.svd(H)
    dsign = np.sign(np.linalg.det(np.einsum("sji,skj->sik", Vt, U)))
    dsign[dsign == 0] = 1.0
    Vt[:, 2, :] *= dsign[:, None]
    R = np.einsum("sji,skj->sik", Vt, U)  # V D U^T
    pred = np.einsum("sij,sgj->sgi", R, cfg[None] - ca[:, None]) + cb[:, None]  # (S, g, 3)
    fs, fj = np.nonzero(free)
    if fs.size == 0:
        return
    e = np.linalg.norm(pred[fs] - P[fs, fj][:, None, :], axis=-1)  # (free points, g)
    e = np.where(~cm[fs] & (e <= tol[None]), e, np.inf)
    m_ = e.argmin(1)
    hit = np.isfinite(e[np.arange(fs.size), m_])
    fs, fj, m_ = fs[hit], fj[hit], m_[hit]
    # a member claiming two points is no one's; a point another group claimed is no one's
    key = fs * len(mem) + m_
    uk, cnt = np.unique(key, return_counts=True)
    dup = np.isin(key, uk[cnt > 1])
    r_ = rows[fs]
    prev = claims[r_, fj]
    take = ~dup & (prev == -1)
    claims[r_[take], fj[take]] = mem[m_[take]]
    clash = ~dup & (prev != -1)
    claims[r_[clash], fj[clash]] = -2


# ------------------------------------------------------------------------------ the take
def rigid_relabel(points: np.ndarray, labels: np.ndarray, tid: np.ndarray, groups: RigidGroups, *,
                  frames: np.ndarray | None = None, stride: int = 4, min_votes: int = 3,
                  agreement: float = 0.8, coverage: float = 0.5,
                  protected: np.ndarray | None = None, tiebreak=None,
                  judged: bool = False, exchange: bool = False,
                  partial: bool = False) -> tuple[np.ndarray, dict]:
    """Rename pieces whose rigid-group fits clearly name another marker.

    Parameters
    ----------
    points : float (F, N, 3)
    labels : int (F, N)
        Current labels (-1 unlabelled).
    tid : int (F, N)
        Tracklet of every point (-1 empty).
    groups : RigidGroups
    frames : int array, optional
        Frames to fit (default every ``stride``-th frame).
    stride : int
    min_votes : int
        A piece moves only with at least this many votes for its new name ...
    agreement : float
        ... which are at least this share of its votes ...
    coverage : float
        ... and of its sampled frames (with ``judged``, of its *judged* frames: those where
        a fit named its point or it was confirmed).
    protected : bool (F, N), optional
        Points that keep their label (hints).
    tiebreak : callable, optional
        Passed to :func:`fit_groups` (near-symmetric clusters).
    judged : bool
        Coverage over the judged frames only. With every frame fitted (the take check), a
        piece of a returning cluster is judged only where 3 of the cluster's points are seen
        (``kinematics_basket_sprint``: ForearmL Marker2 named Marker3 over 35 frames, three
        forearm points seen in 7 of them); the other frames say nothing either way.
    partial : bool
        Passed to :func:`fit_groups` (the points a tied fit names alike).
    exchange : bool
        A displaced piece whose old name is taken takes the old name of the piece that
        displaced it where that is free (the two were exchanged: ``kinematics_basket_sprint``
        at 2089-2097, HandL and WheelchairL Marker3; the hand, in no rigid group, has no fit
        of its own to name it).

    Returns
    -------
    labels : int32 (F, N)
    report : dict
        ``pieces_renamed``, ``samples_renamed``, ``frames_searched`` (frames that needed
        the triplet search).
    """
    pts = np.asarray(points, np.float64)
    lab = np.array(labels, np.int32)
    F, N = lab.shape
    fr = np.arange(0, F, max(1, stride)) if frames is None else np.unique(np.asarray(frames, np.int64))
    rep = {"pieces_renamed": 0, "samples_renamed": 0, "frames_searched": 0}
    if fr.size == 0 or len(groups) == 0:
        return lab, rep
    valid = tid >= 0
    # pieces: runs of one tracklet under one label
    M1 = int(max(lab.max(), 0)) + 2
    key = np.where(valid, tid.astype(np.int64) * M1 + (lab + 1), -1)
    uk, piece = np.unique(key, return_inverse=True)
    piece = piece.reshape(F, N)
    if uk.size and uk[0] == -1:
        piece = piece - 1
        uk = uk[1:]
    piece = np.where(valid, piece, -1)
    P = len(uk)
    cur = (uk % M1 - 1).astype(np.int64)
    # confirmed samples vote for their own labels; frames with unconfirmed points and an
    # incompletely named group are fitted
    Mg = int(max(lab.max(), max(int(m.max()) for m in groups.members))) + 1
    S = fr.size
    lf = lab[fr]
    X = np.full((S, Mg, 3), np.nan)
    s_, j_ = np.nonzero(lf >= 0)
    X[s_, lf[s_, j_]] = pts[fr[s_], j_]
    conf_m = confirmed_labels(X, groups)  # (S, Mg)
    conf = (lf >= 0) & np.take_along_axis(conf_m, np.maximum(lf, 0), 1)
    fit = np.where(conf, lf, -1).astype(np.int64)
    ok = tid[fr] >= 0
    free = ok & ~conf
    has_free = free.any(1)
    slow = np.zeros(S, bool)  # frames where a group needs the triplet search
    claims = np.full((S, N), -1, np.int64)
    for mem, cfg, tol in zip(groups.members, groups.config, groups.tol):
        cm = conf_m[:, mem]
        nc = cm.sum(1)
        need = has_free & (nc < len(mem))
        slow |= need & (nc < 3) & ((free.sum(1) + nc) >= 3)
        rows = np.flatnonzero(need & (nc >= 3))
        if rows.size:
            _place_batch(X[rows][:, mem], cm[rows], cfg, tol, pts[fr[rows]], free[rows], mem, claims, rows)
    fit = np.where(claims >= 0, claims, fit)
    todo = np.flatnonzero(slow)
    for i in todo.tolist():
        fit[i] = fit_groups(pts[fr[i]], groups, labels=lf[i], confirmed=conf[i], tiebreak=tiebreak,
                            partial=partial)
    rep["frames_searched"] = int(todo.size)
    pf = piece[fr]
    sampled = np.bincount(pf[pf >= 0], minlength=P)
    v = (pf >= 0) & (fit >= 0)
    Mx = int(max(fit.max(), lab.max(), 0)) + 1
    votes = np.bincount(pf[v] * Mx + fit[v], minlength=P * Mx).reshape(P, Mx)
    total = votes.sum(1)
    top = votes.argmax(1)
    nt = votes[np.arange(P), top]
    move = (nt >= min_votes) & (nt >= agreement * total) & (nt >= coverage * (total if judged else sampled)) & (
        top != cur)
    if protected is not None:
        prot = np.zeros(P, bool)
        pp = piece[np.asarray(protected, bool) & valid]
        prot[pp] = True
        move &= ~prot
    if not move.any():
        return lab, rep
    confirmed = (nt >= min_votes) & (nt >= agreement * total) & (top == cur)
    # frames of every piece
    pflat = piece.ravel()
    order = np.argsort(pflat, kind="stable")
    cnt = np.bincount(pflat[pflat >= 0], minlength=P)
    starts = np.concatenate([[0], np.cumsum(cnt)]) + int((pflat < 0).sum())
    cells = order  # flat indices sorted by piece

    def cells_of(p: int) -> np.ndarray:
        return cells[starts[p]:starts[p + 1]]

    new = lab.ravel().copy()
    old = new.copy()
    movers = np.flatnonzero(move)
    movers = movers[np.argsort(-nt[movers], kind="stable")]
    displaced: set[int] = set()
    by: dict[int, int] = {}  # displaced piece -> the mover that took its name
    for p in movers.tolist():
        new[cells_of(p)] = -1
    # each mover takes its name where no confirmed piece holds it; the holders are unnamed
    frm = np.repeat(np.arange(F), N)
    for p in movers.tolist():
        c = cells_of(p)
        L = int(top[p])
        f = frm[c]
        nf = new.reshape(F, N)
        occ = np.argwhere(nf[f] == L) if c.size else np.zeros((0, 2), int)
        others = {int(piece[f[r], j]) for r, j in occ}
        if any(confirmed[o] or (protected is not None and prot[o]) for o in others):
            continue
        for o in others:
            new[cells_of(o)] = -1
            displaced.add(o)
            by.setdefault(o, p)
        new[c] = L
        rep["pieces_renamed"] += 1
        rep["samples_renamed"] += int(c.size)
    # movers not moved and displaced pieces take their old label back where it is free
    back = [p for p in movers.tolist() if new[cells_of(p)[0]] < 0] + sorted(displaced)
    nf = new.reshape(F, N)
    for p in back:
        c = cells_of(p)
        if not c.size:
            continue
        f = frm[c]
        names = [int(cur[p])]
        if exchange and p in by:
            names.append(int(cur[by[p]]))
        for L in names:
            if L >= 0 and not (nf[f] == L).any():
                new[c] = L
                break
    out = new.reshape(F, N).astype(np.int32)
    rep["samples_renamed"] = int(((out != old.reshape(F, N)) & (out >= 0)).sum())
    return out, rep


def keeps_rigid_groups(xyz: np.ndarray, relabel, groups: RigidGroups, *, presence: float = 0.5) -> bool:
    """Whether a label permutation (a :class:`~carapost.core.swaps.Relabel`) respects the rigid
    groups of the markers it moves.

    False when it moves only markers of one group of 3 or more while, in at least
    ``1 - presence`` of its frames, no other member of the group is present (seen through
    the permuted markers alone, a rigid body cannot tell them apart: whatever moved them was
    weaker evidence). A pair of rigidly attached markers alone is not vetoed: the shape of
    their other neighbours does tell them apart (a wrist from a finger). (Vetoing repairs
    that lower the number of samples confirmed by their groups was tried: it blocks right
    repairs of mouth markers on Facial-Sing, whose near-rigid face groups include them.)

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories before the permutation.
    relabel : Relabel
    groups : RigidGroups
    """
    ms = np.asarray(relabel.markers, np.int64)
    if ms.size == 0 or len(groups) == 0:
        return True
    seg = np.asarray(xyz, np.float64)[relabel.start:relabel.end]
    M = seg.shape[1]
    gid = np.full(M, -1, np.int64)
    for i, mem in enumerate(groups.members):
        gid[mem[mem < M]] = i
    gs = np.unique(gid[ms])
    if gs.size == 1 and gs[0] >= 0:
        others = np.setdiff1d(groups.members[int(gs[0])], ms)
        if others.size:
            seen = np.isfinite(seg[:, others, 0]).any(1)
            if seen.mean() < presence:
                return False
    return True
