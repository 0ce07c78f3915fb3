"""Motion bridge: short pieces named by which marker's motion they continue.

Where a cluster is seen for one to three frames at a time (the forearm triangle of
``kinematics_basket_sprint`` after frame 2200, the wheel's triplets), nothing in the frame
tells mirror placements apart (ForearmL Marker1 from Marker4), and the take check leaves
the points unnamed or names them after markers that are not there. Across a short gap the
markers' own motion does: a point that lies where a marker's constant-velocity motion
(from the frames just before or just after) puts it, and far from where every other free
marker's puts it, is that marker.

:func:`motion_bridge` works on tracklets of at most ``max_len`` frames, grouped into
clusters of overlapping ones, and decides each cluster's names at once (Hungarian method on
the mean distance of each tracklet's points to each marker's predicted positions).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["fitting_samples", "motion_bridge", "motion_predictions"]


def fitting_samples(points: np.ndarray, labels: np.ndarray, select: np.ndarray, dist: np.ndarray,
                    spread: np.ndarray, *, tight_mm: float = 3.0, tight_rel: float = 0.03,
                    max_z: float = 3.0) -> np.ndarray:
    """The selected labelled samples whose label keeps its tight pairs with the frame's labels.

    Parameters
    ----------
    points : float (F, N, 3)
        Points, mm.
    labels : int (F, N)
        Labels (-1 unnamed).
    select : bool (F, N)
        Samples to judge.
    dist, spread : float (M, M)
        Each pair's distance and spread over the take, mm (a
        :class:`~carapost.core.label_ranges.RangeModel`'s).
    tight_mm, tight_rel : float
        Pairs with a spread of at most ``tight_mm + tight_rel * dist`` are constraints.
    max_z : float
        Largest deviation, in spreads, from every tight partner present.

    Returns
    -------
    bool (F, N)
        True for the selected samples with at least one tight partner present, all within
        ``max_z`` spreads.
    """
    F, N, _ = points.shape
    M = dist.shape[0]
    out = np.zeros((F, N), bool)
    f, n = np.nonzero(select & (labels >= 0))
    if not f.size:
        return out
    xyz = np.full((F, M, 3), np.nan)
    lf = np.nonzero(labels >= 0)
    xyz[lf[0], labels[lf]] = points[lf]
    L = labels[f, n]
    tight = np.isfinite(dist) & (spread <= tight_mm + tight_rel * np.nan_to_num(dist))
    d = np.linalg.norm(xyz[f] - points[f, n][:, None], axis=-1)  # (s, M)
    use = tight[L] & np.isfinite(d)
    use[np.arange(L.size), L] = False
    z = np.where(use, np.abs(d - np.nan_to_num(dist[L])) / spread[L], 0.0)
    out[f, n] = use.any(1) & (z <= max_z).all(1)
    return out


def motion_predictions(xyz: np.ndarray, frames: np.ndarray, a: int, b: int, reach: int) -> np.ndarray:
    """Each marker's position in ``frames`` predicted from its samples outside ``[a, b]``.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, mm (NaN missing); the samples inside ``[a, b]`` are ignored.
    frames : int (k,)
        Frames to predict (inside ``[a, b]``).
    a, b : int
        First and last frame of the gap.
    reach : int
        Samples farther than ``reach`` frames from the gap are not used.

    Returns
    -------
    float (k, M, 3)
        Linear interpolation between the last sample before and the first after the gap when
        both are within ``reach``; else constant velocity from the two nearest samples on one
        side (within ``reach``); else NaN.
    """
    F, M, _ = xyz.shape
    lo, hi = max(0, a - reach), min(F, b + reach + 1)
    pre = np.isfinite(xyz[lo:a, :, 0])  # (a - lo, M)
    post = np.isfinite(xyz[b + 1:hi, :, 0])
    out = np.full((len(frames), M, 3), np.nan)
    for m in range(M):
        bf = lo + np.flatnonzero(pre[:, m])
        af = b + 1 + np.flatnonzero(post[:, m])
        if bf.size and af.size:
            f0, f1 = bf[-1], af[0]
            w = ((frames - f0) / (f1 - f0))[:, None]
            out[:, m] = (1 - w) * xyz[f0, m] + w * xyz[f1, m]
        elif bf.size >= 2:
            f0, f1 = bf[-2], bf[-1]
            v = (xyz[f1, m] - xyz[f0, m]) / (f1 - f0)
            out[:, m] = xyz[f1, m] + (frames - f1)[:, None] * v
        elif af.size >= 2:
            f0, f1 = af[0], af[1]
            v = (xyz[f1, m] - xyz[f0, m]) / (f1 - f0)
            out[:, m] = xyz[f0, m] + (frames - f0)[:, None] * v
    return out


def motion_bridge(points: np.ndarray, labels: np.ndarray, tid: np.ndarray, n_markers: int, *,
                  protected: np.ndarray | None = None, anchors: np.ndarray | None = None,
                  max_len: int = 3, reach: int = 8,
                  rel: float = 0.25, abs_mm: float = 30.0, margin: float = 3.0) -> tuple[np.ndarray, int]:
    """Name the short pieces whose points continue a free marker's motion.

    Parameters
    ----------
    points : float (F, N, 3)
        Points of each frame, mm (NaN empty slots).
    labels : int (F, N)
        Current labels (-1 unnamed).
    tid : int (F, N)
        Tracklet of each point (-1 none).
    protected : bool (F, N), optional
        Points whose label must not change (hints, ignored markers): their tracklets are left.
    anchors : bool (F, N), optional
        Samples of short tracklets trusted as well to predict their markers' motion (e.g.
        :func:`fitting_samples`); the samples of longer tracklets always are.
    max_len : int
        Longest tracklet (frames) treated as a short piece.
    reach : int
        Frames on either side of a cluster from which markers' motion is predicted.
    rel, abs_mm : float
        A tracklet takes marker ``L`` only when its mean distance to ``L``'s predicted
        positions is at most ``abs_mm`` and ``rel`` x the distance from ``L``'s prediction to
        the nearest other candidate marker's.
    margin : float
        ... and every other candidate (and the tracklet's current label, when that has a
        prediction) is ``margin`` times farther.

    Returns
    -------
    labels : int32 (F, N)
        The new labels.
    changed : int
        Tracklets renamed or named.
    """
    F, N, _ = points.shape
    M = n_markers
    labels = labels.astype(np.int32, copy=True)
    valid = tid >= 0
    if not valid.any():
        return labels, 0
    T = int(tid.max()) + 1
    tf = np.nonzero(valid)
    t_of = tid[tf]
    start = np.full(T, F, np.int64)
    end = np.full(T, -1, np.int64)
    np.minimum.at(start, t_of, tf[0])
    np.maximum.at(end, t_of, tf[0])
    short = (end - start + 1) <= max_len
    if protected is not None and protected.any():
        short[np.unique(tid[protected & valid])] = False
    cand = np.flatnonzero(short & (end >= 0))
    if not cand.size:
        return labels, 0
    # the anchors' trajectories: samples of tracklets longer than max_len (or protected), and
    # of short ones given in ``anchors``
    xyz = np.full((F, M, 3), np.nan)
    lf = np.nonzero((labels >= 0) & valid)
    long_ = ~short[tid[lf]] if anchors is None else ~short[tid[lf]] | anchors[lf]
    lf = (lf[0][long_], lf[1][long_])
    xyz[lf[0], labels[lf]] = points[lf]
    cand = cand[np.argsort(start[cand], kind="stable")]
    clusters, cur, cur_end = [], [int(cand[0])], int(end[cand[0]])
    for t in cand[1:]:
        if start[t] <= cur_end:
            cur.append(int(t))
            cur_end = max(cur_end, int(end[t]))
        else:
            clusters.append(cur)
            cur, cur_end = [int(t)], int(end[t])
    clusters.append(cur)
    changed = 0
    for C in clusters:
        a, b = int(start[C].min()), int(end[C].max())
        frames = np.arange(a, b + 1)
        mine = np.isin(tid[a:b + 1], C)  # (k, N)
        pred = motion_predictions(xyz, frames, a, b, reach)  # (k, M, 3); samples in [a, b] unused
        has = np.isfinite(pred[..., 0]).any(0)
        if not has.any():
            continue
        # a marker is free in a frame when no point outside the cluster holds it there
        held = np.zeros((len(frames), M), bool)
        fo, no = np.nonzero(~mine & (labels[a:b + 1] >= 0))
        held[fo, labels[a:b + 1][fo, no]] = True
        Ls = np.flatnonzero(has)
        cost = np.full((len(C), Ls.size), np.inf)
        for i, t in enumerate(C):
            fi, ni = np.nonzero(tid[a:b + 1] == t)
            d = np.linalg.norm(points[a + fi, ni][:, None] - pred[fi][:, Ls], axis=-1)  # (s, L)
            ok = ~held[fi][:, Ls].any(0) & np.isfinite(d).all(0)
            cost[i, ok] = d[:, ok].mean(0)
        if not np.isfinite(cost).any():
            continue
        big = 1e9
        r, c = linear_sum_assignment(np.where(np.isfinite(cost), cost, big))
        accepted: dict[int, int] = {}  # tracklet -> new marker
        for i, j in zip(r, c):
            e = cost[i, j]
            if not np.isfinite(e):
                continue
            t, L = C[i], int(Ls[j])
            fi, ni = np.nonzero(tid[a:b + 1] == t)
            # distance from L's prediction to the nearest other candidate marker's, over t's frames
            P = pred[fi][:, Ls]
            sep = np.linalg.norm(P - P[:, j:j + 1], axis=-1).mean(0)
            sep[j] = np.inf
            sep = np.where(np.isfinite(sep), sep, np.inf).min()
            others = np.delete(cost[i], j)
            if e > abs_mm or e > rel * sep or (others.size and np.nanmin(others) < margin * e):
                continue
            cur_lab = labels[a + fi, ni]
            if (cur_lab == L).all():
                continue
            L0 = int(cur_lab[0])
            d0 = np.nan
            if L0 >= 0 and (cur_lab == L0).all() and has[L0]:
                d0 = np.linalg.norm(points[a + fi, ni] - pred[fi, L0], axis=-1).mean()
            if np.isfinite(d0):
                if d0 < margin * e:  # its own name's motion explains it about as well
                    continue
            elif L0 >= 0 and anchors is not None and anchors[a + fi, ni].all():
                continue  # no motion of its own name to judge, and that name keeps its tight pairs
            accepted[t] = L
        # a name is taken from another of the cluster's points only when that point is renamed too
        # (an exchange), never leaving it unnamed
        while accepted:
            drop = []
            for t, L in accepted.items():
                fi = np.flatnonzero((tid[a:b + 1] == t).any(1))
                holders = np.unique(tid[a:b + 1][fi][labels[a:b + 1][fi] == L])
                if any(h != t and h not in accepted for h in holders.tolist()):
                    drop.append(t)
            if not drop:
                break
            for t in drop:
                del accepted[t]
        new = labels[a:b + 1].copy()
        for t, L in accepted.items():
            new[tid[a:b + 1] == t] = L
        labels[a:b + 1] = new
        changed += len(accepted)
    return labels, changed
