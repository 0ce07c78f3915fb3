"""Naming pieces by the marker set's distances learnt over the take ("labelling skeleton").

The other checks rest on the shape around the reference frame. When whole body segments
vanish for good (``kinematics_basket_sprint`` after frame 2200: head, scapula and hand never
come back) the returning points of the segments still seen take the names of absent markers
or stay unnamed, and no reference-frame partner can object. A human labeller uses the
marker set instead: "the forehead is never within 300 mm of the forearm; this forearm marker
stays 49 +- 1 mm from that one".

1. :func:`learn_ranges`: for every pair of labels, the median distance and a robust spread
   (the 90 % quantile of the deviation / 1.645, floored) over frames sampled over the whole
   take where both are named *confidently* - on runs of one tracklet under one label of at
   least ``min_run`` frames. Pairs on one segment have spreads of a few mm, pairs across
   joints tens of mm; a quantile, not the MAD, because a pair rigid while the subject sits
   still (most of a take) may move apart in the rest.
2. :func:`take_groups`: the rigid groups of the whole take; fitted in every frame by
   :func:`~carapost.core.label_rigid.rigid_relabel`, where :func:`range_tiebreak` tells the
   two placements of a near-symmetric cluster apart by the learnt distances (to confirmed
   markers, and to markers of no rigid group, which can never be confirmed).
3. :func:`range_relabel`: every unnamed piece (a run of one tracklet left unlabelled) and
   every named piece whose label does not fit its tight partners (spread of a few mm) is
   scored against the labels absent over it (:func:`range_costs`: per sampled frame, the
   -2 log-likelihood of its distances to the labelled markers present under a Cauchy law
   per pair - heavy tails for pairs across joints, and ``2 ln S`` so that a vague label
   does not beat a precise one). The best label takes the piece when its tight partners
   are present and fit and it beats the second best (and the piece's own label) by
   ``margin`` per frame (a label attached to nothing - an object apart from the subject -
   needs no tight partner); a re-checked named piece far from all its label's distances is
   unnamed. Decisions are applied most certain first, never giving one label to two
   pieces at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RangeModel", "learn_ranges", "range_costs", "range_relabel", "range_tiebreak", "take_groups"]


@dataclass
class RangeModel:
    """Distances between labels over the take.

    Attributes
    ----------
    dist : float (M, M)
        Median distance of each pair of labels, mm (NaN where unknown, and on the diagonal).
    spread : float (M, M)
        Robust spread of that distance (a normalised quantile of the deviation, at least
        ``floor_mm + floor_rel x dist``), mm; inf where unknown.
    count : int (M, M)
        Sampled frames where both labels were confidently named.
    """

    dist: np.ndarray
    spread: np.ndarray
    count: np.ndarray


def _run_lengths(pieces: np.ndarray) -> np.ndarray:
    """Length (frames) of the run of equal values through each entry of ``pieces`` (F, M) along
    axis 0; 0 where ``pieces < 0``."""
    F, M = pieces.shape
    change = np.ones((F, M), bool)
    change[1:] = pieces[1:] != pieces[:-1]
    rid = np.cumsum(change.T.ravel()) - 1  # column-major: runs never span two columns
    size = np.bincount(rid)
    return np.where(pieces >= 0, size[rid].reshape(M, F).T, 0)


def learn_ranges(xyz: np.ndarray, pieces: np.ndarray, *, min_run: int = 20, samples: int = 300,
                 floor_mm: float = 1.0, floor_rel: float = 0.01, min_count: int = 10,
                 quantile: float = 0.9) -> RangeModel:
    """Learn every pair's distance and spread over the take from the confident samples.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, mm (NaN missing).
    pieces : int (F, M)
        Tracklet carrying each sample (-1 none); a sample is confident when its run on one
        tracklet lasts at least ``min_run`` frames.
    samples : int
        Frames sampled evenly over the take.
    floor_mm, floor_rel : float
        Least spread: ``floor_mm + floor_rel * dist``.
    min_count : int
        Pairs seen together confidently in fewer sampled frames are unknown.
    quantile : float
        The spread is this quantile of the absolute deviation from the median, divided by
        the normal law's (1.645 for 0.9): a pair that leaves its distance in more than
        1 - ``quantile`` of the frames is loose.

    Returns
    -------
    RangeModel
    """
    from scipy.special import ndtri

    from .label_rigid import _distances
    from .label_shape import _nan_median0
    F, M, _ = xyz.shape
    fr = np.unique(np.linspace(0, F - 1, min(F, samples)).astype(int))
    conf = _run_lengths(pieces)[fr] >= min_run
    iu, ju = np.triu_indices(M, 1)  # the distance matrix is symmetric: the upper triangle only
    d = _distances(np.where(conf[..., None], xyz[fr], np.nan))[:, iu, ju]
    n = np.isfinite(d).sum(0)
    med = _nan_median0(d, n)
    dev = np.sort(np.abs(d - med), axis=0)  # NaN last
    q = np.take_along_axis(dev, np.minimum((quantile * n).astype(int), np.maximum(n - 1, 0))[None], 0)[0]
    known = n >= min_count
    sp = np.maximum(q / ndtri(0.5 + 0.5 * quantile), floor_mm + floor_rel * med)
    dist = np.full((M, M), np.nan)
    spread = np.full((M, M), np.inf)
    count = np.zeros((M, M), np.int64)
    dist[iu, ju] = dist[ju, iu] = np.where(known, med, np.nan)
    spread[iu, ju] = spread[ju, iu] = np.where(known, sp, np.inf)
    count[iu, ju] = count[ju, iu] = n
    return RangeModel(dist, spread, count)


def range_costs(X: np.ndarray, partners: np.ndarray, model: RangeModel, *, tight: np.ndarray,
                labels: np.ndarray | None = None, cap: float = 25.0,
                neutral: float = 2.0 * np.log(2.0) + 2.0 * np.log(300.0)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Costs of a point under candidate labels, per frame.

    Parameters
    ----------
    X : float (k, 3)
        The point in ``k`` frames, mm.
    partners : float (k, M, 3)
        The labelled markers present in those frames (NaN absent; the point's own sample
        excluded).
    tight : bool (M, M)
        The pairs that are constraints (small spread).
    labels : int (C,), optional
        Candidate labels (default all ``M``).

    Returns
    -------
    cost : float (k, C)
        -2 log-likelihood of each label ``L`` under a Cauchy law of each pair's distance:
        ``sum_q 2 ln(1 + z^2) + 2 ln S[L, q]``, ``z = (|X - partner_q| - D[L, q]) / S[L, q]``,
        over the present partners ``q`` (``neutral`` for a pair without a model).
    far : float (k, C)
        ``sum_q 2 ln(1 + z^2)`` alone (how far the label is from its distances).
    fit, nfit : float (k, C), int (k, C)
        Sum of ``min(z^2, cap)`` over the present *tight* partners of each label, and their number.
    """
    M = model.dist.shape[0]
    L = np.arange(M) if labels is None else np.asarray(labels, np.int64)
    D, S, T = model.dist[L], model.spread[L], tight[L]  # (C, M)
    d = np.linalg.norm(partners - X[:, None], axis=-1)  # (k, M)
    pres = np.isfinite(d)
    kn = np.isfinite(D)
    known = kn[None] & pres[:, None, :]  # (k, C, M)
    z2 = np.where(known, (d[:, None, :] - np.where(kn, D, 0.0)[None]) / S[None], 0.0) ** 2
    lz = 2.0 * np.log1p(z2)
    lnS = np.where(kn, 2.0 * np.log(np.maximum(S, 1.0)), 0.0)
    cost = lz.sum(-1) + pres.astype(np.float64) @ lnS.T + neutral * (pres[:, None, :] & ~kn[None]).sum(-1)
    tk = known & T[None]
    fit = np.where(tk, np.minimum(z2, cap), 0.0).sum(-1)
    return cost, lz.sum(-1), fit, tk.sum(-1)


def _tight_partners(model: RangeModel, tight: np.ndarray, k: int) -> np.ndarray:
    """Each label's ``k`` tightest partners (smallest spread), int (M, k), -1 where fewer."""
    rank = np.where(tight, model.spread, np.inf)
    order = np.argsort(rank, axis=1, kind="stable")[:, :k]
    return np.where(np.isfinite(np.take_along_axis(rank, order, 1)), order, -1)


def _named_fit(xyz: np.ndarray, model: RangeModel, partners: np.ndarray, frames: np.ndarray,
               cap: float) -> tuple[np.ndarray, np.ndarray]:
    """Fit of every labelled sample of ``frames`` to its label's tight ``partners`` (M, K):
    the sum of truncated squared z-scores over those present, and their number, (S, M)."""
    X = xyz[frames].astype(np.float32)  # (S, M, 3)
    P = np.maximum(partners, 0)
    has = partners >= 0
    Y = np.take(X, P.ravel(), axis=1).reshape(len(frames), *P.shape, 3)
    d = np.linalg.norm(Y - X[:, :, None], axis=-1)  # (S, M, K)
    D = np.take_along_axis(model.dist, P, 1).astype(np.float32)
    S = np.take_along_axis(model.spread, P, 1).astype(np.float32)
    ok = np.isfinite(d) & has[None]
    z2 = np.where(ok, np.minimum(((np.where(ok, d, 0) - np.nan_to_num(D)[None]) / S[None]) ** 2, cap), 0)
    return z2.sum(-1), ok.sum(-1)


def range_relabel(points: np.ndarray, labels: np.ndarray, tid: np.ndarray, n_markers: int, *,
                  model: RangeModel | None = None, protected: np.ndarray | None = None,
                  ignore: np.ndarray | None = None, min_length: int = 1, frames_per_piece: int = 24,
                  min_partners: int = 3, min_frames: int = 1, tight_mm: float = 3.0, tight_rel: float = 0.03,
                  max_fit: float = 4.0, suspect: float = 9.0, impossible: float = 8.0, margin: float = 6.0,
                  unattached_rel: float = 0.1,
                  cap: float = 25.0, min_run: int = 20,
                  stride: int = 3) -> tuple[np.ndarray, int, int, RangeModel | None]:
    """Name unnamed pieces and re-check badly fitting named ones by the learnt distances.

    Parameters
    ----------
    points : float (F, N, 3)
    labels : int (F, N)
    tid : int (F, N)
        Tracklet of each point (-1 none).
    n_markers : int
    model : RangeModel, optional
        Learnt here from ``labels`` (:func:`learn_ranges`) when not given.
    protected : bool (F, N), optional
        Hinted points: their pieces are left alone.
    ignore : bool (M,), optional
        Markers never given and never taken.
    min_length : int
        Pieces shorter than this (frames) are left alone.
    frames_per_piece : int
        Frames sampled evenly over a piece.
    min_partners, min_frames : int
        A sampled frame is evidence with at least ``min_partners`` labelled markers present; a
        piece is judged on at least ``min_frames`` evidence frames.
    tight_mm, tight_rel : float
        Pairs with a spread of at most ``tight_mm + tight_rel * dist`` are constraints.
    max_fit : float
        A label is given only when its mean squared z-score over its tight partners present
        (truncated at ``cap``) is at most this, with a tight partner present in half the
        evidence frames.
    suspect : float
        A named piece is re-checked when its own label fits its tight partners worse than
        this, or has none present in half its frames.
    impossible : float
        A re-checked named piece is unnamed (when no label is given instead) when its label's
        mean ``2 ln(1 + z^2)`` per partner exceeds this (``z`` above ~50 for 8).
    margin : float
        -2 log-likelihood per frame by which the best label must beat the second best free
        label (and a named piece's own label).
    unattached_rel : float
        A label whose every pair has a spread of at least this share of its distance is
        attached to nothing (an object apart from the subject: ``Sync`` of
        ``kinematics_basket_sprint``, spreads of 18 % and more; a body marker has a partner
        within 4-6 %, across a joint): it needs no tight partner and is given on its costs
        alone (Sync's points named ForearmL Marker3 at 989-994 and left unnamed at 3463-3464).
    stride : int
        Named pieces are screened on every ``stride``-th frame; a piece with no screened
        frame is re-checked.

    Returns
    -------
    labels : int32 (F, N)
    named, unnamed : int
        Pieces given a (new) name, and named pieces unnamed.
    model : RangeModel or None
    """
    lab = np.array(labels, np.int32)
    F, N = lab.shape
    M = int(n_markers)
    on = tid >= 0
    if not on.any():
        return lab, 0, 0, model
    key = np.where(on, tid.astype(np.int64) * (M + 1) + np.where(lab >= 0, lab, M), -1)
    f, j = np.nonzero(on)
    uk, q = np.unique(key[f, j], return_inverse=True)
    size = np.bincount(q, minlength=len(uk))
    big = size >= min_length
    plab = (uk % (M + 1)).astype(int)
    plab = np.where(plab == M, -1, plab)
    if protected is not None:
        pk = key[np.asarray(protected, bool) & on]
        big &= ~np.isin(uk, pk)
    allowed = np.ones(M, bool) if ignore is None else ~np.asarray(ignore, bool)
    big &= (plab < 0) | allowed[np.maximum(plab, 0)]
    if not big.any():
        return lab, 0, 0, model
    # trajectories and occupancy
    xyz = np.full((F, M, 3), np.nan)
    lf, lj = np.nonzero(lab >= 0)
    xyz[lf, lab[lf, lj]] = points[lf, lj]
    pres = np.isfinite(xyz[..., 0])
    if model is None:
        pieces = np.full((F, M), -1, np.int64)
        pieces[lf, lab[lf, lj]] = tid[lf, lj]
        model = learn_ranges(xyz, pieces, min_run=min_run)
    tight = np.isfinite(model.dist) & (model.spread <= tight_mm + tight_rel * np.nan_to_num(model.dist))
    # labels attached to nothing (every pair's spread above ``unattached_rel`` of its distance):
    # no partner can confirm them, their costs alone decide
    with np.errstate(invalid="ignore", divide="ignore"):
        loose = ~(np.isfinite(model.dist) & (model.spread < unattached_rel * np.nan_to_num(model.dist))).any(1)
    loose &= np.isfinite(model.dist).any(1)
    # named pieces whose label fits its tight partners (checked every ``stride`` frames, vectorised)
    # are left alone; the others are re-checked below
    fr = np.arange(0, F, max(1, int(stride)))
    fsum, fn = _named_fit(xyz, model, _tight_partners(model, tight, 6), fr, cap)
    pkey = np.full((F, M), -1, np.int64)
    pkey[lf, lab[lf, lj]] = key[lf, lj]
    sf, sm = np.nonzero(pkey[fr] >= 0)
    kq = np.searchsorted(uk, pkey[fr[sf], sm])
    nsamp = np.bincount(kq, minlength=len(uk))
    seen_t = np.bincount(kq, weights=fn[sf, sm] > 0, minlength=len(uk))
    mean_fit = np.bincount(kq, weights=fsum[sf, sm], minlength=len(uk)) / np.maximum(
        np.bincount(kq, weights=fn[sf, sm], minlength=len(uk)), 1)
    fine = (plab >= 0) & (nsamp > 0) & (seen_t >= 0.5 * nsamp) & (mean_fit <= suspect)
    todo = np.flatnonzero(big & ~fine)
    order = np.argsort(q, kind="stable")
    starts = np.r_[0, np.cumsum(size)]
    decisions = []  # (certainty, piece, new label)
    for k in todo.tolist():
        idx = order[starts[k]:starts[k + 1]]
        ff, jj = f[idx], j[idx]
        s = np.unique(np.linspace(0, len(ff) - 1, min(len(ff), frames_per_piece)).astype(int))
        fs, js = ff[s], jj[s]
        own = int(plab[k])
        free = allowed & ~pres[fs].any(0)
        if own >= 0:
            free[own] = False
        if not free.any() and own < 0:
            continue
        cand = np.flatnonzero(free)
        if own >= 0:
            cand = np.r_[cand, own]
        P = xyz[fs].copy()
        if own >= 0:
            P[:, own] = np.nan
        n = np.isfinite(P[..., 0]).sum(1)
        ev = n >= min_partners
        if ev.sum() < min_frames:
            continue
        cost, far, fit, nfit = range_costs(points[fs[ev], js[ev]].astype(np.float64), P[ev], model, tight=tight,
                                           labels=cand, cap=cap)
        good = ((nfit > 0).mean(0) >= 0.5) & (fit.sum(0) / np.maximum(nfit.sum(0), 1) <= max_fit) | loose[cand]
        C = cost.mean(0)
        nf = int(free.sum())
        best, c2 = -1, np.inf
        if nf:
            o = np.argsort(C[:nf])
            best = int(o[0])
            c2 = C[o[1]] if nf > 1 else np.inf
        if own >= 0:
            c2 = min(c2, C[nf])
        if best >= 0 and good[best] and c2 - C[best] >= margin:
            decisions.append((float(c2 - C[best]), int(k), int(cand[best])))
        elif own >= 0 and far[:, nf].sum() / n[ev].sum() > impossible:
            decisions.append((0.0, int(k), -1))
    named = unnamed = 0
    for _, k, new in sorted(decisions, key=lambda t: -t[0]):
        idx = order[starts[k]:starts[k + 1]]
        ff, jj = f[idx], j[idx]
        own = int(plab[k])
        if new >= 0 and pres[ff, new].any():
            continue
        if own >= 0:
            pres[ff, own] = False
        if new >= 0:
            pres[ff, new] = True
            named += 1
        else:
            unnamed += 1
        lab[ff, jj] = new
    return lab, named, unnamed, model


def take_groups(xyz: np.ndarray, pieces: np.ndarray, *, min_run: int = 20, samples: int = 300,
                max_spread_mm: float = 4.0, check_share: float = 0.9):
    """Rigid groups over the whole take (:func:`~carapost.core.label_rigid.rigid_groups` on
    the confident samples - runs of at least ``min_run`` frames on one tracklet - of frames
    sampled over the take; every pair must keep its distance in ``check_share`` of the
    sampled frames where both are labelled). Unlike the groups near the reference frame,
    these hold segments that flex elsewhere (a forearm cluster next to a flexing hand) and
    leave out pairs rigid only while the subject sits still."""
    from .label_rigid import rigid_groups
    F = xyz.shape[0]
    fr = np.unique(np.linspace(0, F - 1, min(F, samples)).astype(int))
    conf = _run_lengths(pieces)[fr] >= min_run
    return rigid_groups(xyz, fr, trusted=conf, check_frames=fr, check_share=check_share,
                        max_spread_mm=max_spread_mm)


def range_tiebreak(model: RangeModel, *, groups=None, margin: float = 10.0, min_partners: int = 2):
    """A tie-breaker for :func:`~carapost.core.label_rigid.fit_groups`: of two placements of a
    near-symmetric group naming as many points, the one whose points fit the learnt distances
    to the frame's confirmed markers outside the group better (summed -2 log-likelihood of
    :func:`range_costs`) by at least ``margin``; None when neither does or fewer than
    ``min_partners`` such markers are present.

    With ``groups`` (the :class:`~carapost.core.label_rigid.RigidGroups` being fitted), the
    labelled points whose label belongs to no group count as partners as well: they can
    never be confirmed (a hand flexing against the forearm), yet their learnt distances may
    be the only evidence in the frame (``kinematics_basket_sprint`` at 2154-2160: three
    forearm points and the hand, 65 mm from ForearmL Marker4 and 127 mm from Marker1)."""
    M = model.dist.shape[0]
    none_tight = np.zeros((M, M), bool)
    grouped = np.full(M, groups is None)  # without groups: confirmed partners only
    if groups is not None:
        for mem in groups.members:
            grouped[mem[mem < M]] = True

    def pick(P: np.ndarray, lab: np.ndarray, conf: np.ndarray, members: np.ndarray, maps: list):
        ok = (conf | ~grouped[np.clip(lab, 0, M - 1)]) & (lab >= 0) & (lab < M) & ~np.isin(lab, members)
        if ok.sum() < min_partners or len({int((m >= 0).sum()) for m in maps}) != 1:
            return None
        part = np.full((M, 3), np.nan)
        part[lab[ok]] = P[ok]
        costs = []
        for mp in maps:
            sel = mp >= 0
            X = P[mp[sel]]
            c = range_costs(X, np.broadcast_to(part, (len(X), M, 3)), model, tight=none_tight)[0]
            costs.append(float(c[np.arange(len(X)), np.asarray(members)[sel]].sum()))
        d = costs[1] - costs[0]
        return 0 if d >= margin else 1 if d <= -margin else None
    return pick

