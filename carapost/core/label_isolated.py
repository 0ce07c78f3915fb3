"""Labels no shape allows, and the marker nothing else can name.

A marker missing for a long time has a vague prediction, and a point far from every other
marker - a sync marker a metre away from the athlete - may take its name when nothing else
claims that point (``kinematics_basket_sprint``: ``Sync:Sync`` named ``HandL`` and
``ForearmL:Marker4`` while those were missing). Two checks after the labelling:

1. :func:`impossible_pieces`: a *piece* (a run of one tracklet under one label) whose label's
   partners near the reference frame (:func:`~carapost.core.label_shape.reference_model`:
   the shape check's 6 most rigid partners), where at least two of them are present, are mostly (3 in 4)
   farther from their distance than ``far_mm`` plus 10 spreads, in most of those frames,
   cannot be that marker: no body bends a marker's neighbourhood by 10 cm all at once. It
   is unnamed.
2. :func:`name_unseen`: when exactly one marker has no labelled sample in the whole take
   (and is absent from the reference frame), the unlabelled tracklets that are *isolated*
   (in nearly all their frames, farther than ``isolation`` x the reference frame's median
   nearest-marker spacing from every other point), long enough, not present in the reference
   frame (a point left unlabelled there is not a marker) and never present at the same
   time, take its name: a marker set's one marker placed apart from all others, seen only
   there, is that marker (elimination). With two or more unseen markers, or isolated
   tracklets overlapping in time, nothing is named.
3. :func:`attached_pieces`: a piece (at least ``min_length`` frames) whose label's partners
   are absent (or present only far from their distance, under wrong names themselves) in
   nearly all its frames cannot be checked by its shape; but when its
   distances to at least two present labelled markers stay constant over the piece (range at
   most ``max_range`` mm), it rides on their body: it is that body's marker. When two or more
   of those markers belong to one rigid group (:mod:`carapost.core.label_rigid`) that has
   exactly one member absent over the whole piece, the piece takes that member's name; if
   its own label belongs to one of those groups it is kept; otherwise it is unnamed
   (``kinematics_basket_sprint`` after frame 2200: arm-cluster points named after the head
   and scapula markers, which never come back).
"""

from __future__ import annotations

import numpy as np

from .label_shape import ShapeModel

__all__ = ["impossible_pieces", "name_unseen", "attached_pieces"]


_KEY_BASE = 1 << 20  # more markers than any marker set


def _piece_keys(labels: np.ndarray, tid: np.ndarray) -> np.ndarray:
    """Key of the piece of every point (one tracklet under one label), -1 where unlabelled or
    not on a tracklet."""
    ok = (labels >= 0) & (tid >= 0)
    return np.where(ok, tid.astype(np.int64) * _KEY_BASE + labels, -1)


def impossible_pieces(points: np.ndarray, labels: np.ndarray, tid: np.ndarray, model: ShapeModel, *,
                      far_mm: float = 100.0, far_spreads: float = 10.0, min_partners: int = 2,
                      share: float = 0.5, min_frames: int = 3,
                      rule_out: float = 0.75, stride: int = 3,
                      protected: np.ndarray | None = None) -> np.ndarray:
    """Which labelled points sit on pieces their label's shape rules out, bool (F, N).

    Parameters
    ----------
    points : float (F, N, 3)
        Point clouds, mm.
    labels : int (F, N)
        Marker of each point, -1 unlabelled.
    tid : int (F, N)
        Tracklet of each point, -1 none.
    model : ShapeModel
        Partners of each marker (e.g. its 6 most rigid near the reference frame).
    far_mm, far_spreads : float
        A partner rules a position out when its distance differs from the model's by more than
        ``far_mm + far_spreads * spread``.
    min_partners : int
        A frame is evidence when at least this many partners of the label are present, and
        rules the label out when ``rule_out`` of them (a share) rule it out.
    share : float
        A piece is ruled out in more than this share of its evidence frames, ...
    min_frames : int
        ... of which it needs at least this many.
    stride : int
        Frames checked: every ``stride``-th (a piece is judged by its frames among them).
    protected : bool (F, N), optional
        Points (hinted) whose pieces are never ruled out.

    Returns
    -------
    bool (F, N)
    """
    F, N = labels.shape
    M = model.partners.shape[0]
    out = np.zeros((F, N), bool)
    fr = np.arange(0, F, max(1, int(stride)))
    lab = labels[fr]
    xyz = np.full((len(fr), M, 3), np.nan, np.float32)
    f, j = np.nonzero(lab >= 0)
    xyz[f, lab[f, j]] = points[fr[f], j]
    P = np.maximum(model.partners, 0)
    has_p = model.partners >= 0
    lim = (far_mm + far_spreads * model.spread).astype(np.float32)
    dist = model.dist.astype(np.float32)
    # only the sampled points on pieces that may be ruled out (not hinted ones)
    ks = _piece_keys(labels[fr[f], j], tid[fr[f], j])
    check = ks >= 0
    if protected is not None:
        pm = np.asarray(protected, bool) & (labels >= 0)
        check &= ~np.isin(ks, _piece_keys(labels[pm], tid[pm]))
    if not check.any():
        return out
    cf, cm, ks = f[check], lab[f[check], j[check]], ks[check]
    ev = np.zeros(len(cf), bool)
    imp = np.zeros(len(cf), bool)
    step = max(1, 1_000_000 // max(P.shape[1] * 3, 1))
    for a in range(0, len(cf), step):
        sf, sm = cf[a:a + step], cm[a:a + step]
        diff = xyz[sf, sm][:, None, :] - xyz[sf[:, None], P[sm]]
        dev = np.abs(np.sqrt(np.einsum("ski,ski->sk", diff, diff)) - dist[sm])  # (S, K)
        seen = np.isfinite(dev) & has_p[sm]
        n = seen.sum(-1)
        out_n = (seen & (dev > lim[sm])).sum(-1)
        ev[a:a + step] = n >= min_partners
        imp[a:a + step] = ev[a:a + step] & (out_n >= rule_out * n)
    if not imp.any():
        return out
    uk, q = np.unique(ks, return_inverse=True)
    e = np.bincount(q, weights=ev, minlength=len(uk))
    i = np.bincount(q, weights=imp, minlength=len(uk))
    bad = uk[(e >= min_frames) & (i > share * e)]
    if not bad.size:
        return out
    return np.isin(_piece_keys(labels, tid), bad)


def name_unseen(points: np.ndarray, labels: np.ndarray, tid: np.ndarray, n_markers: int, reference_frame: int, *,
                isolation: float = 3.0, min_length: int = 10, isolated_share: float = 0.9,
                ignore: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Give the one marker that has no labelled sample the isolated unlabelled tracklets.

    Parameters
    ----------
    points : float (F, N, 3)
        Point clouds, mm.
    labels : int (F, N)
        Marker of each point, -1 unlabelled.
    tid : int (F, N)
        Tracklet of each point, -1 none.
    n_markers : int
    reference_frame : int
        Its labelled points give the marker spacing; the unseen marker must be absent there,
        and so must the tracklets named.
    isolation : float
        A point is isolated when farther than this x the median nearest-marker spacing of the
        reference frame from every other point of its frame ...
    isolated_share : float
        ... and a tracklet is isolated when this share of its points are.
    min_length : int
        Tracklets shorter than this are left alone (spurious points).
    ignore : bool (M,), optional
        Markers never named (ignored markers).

    Returns
    -------
    labels : int32 (F, N)
        With the isolated tracklets named, if any.
    n : int
        Tracklets named.
    """
    lab = np.array(labels, np.int32)
    seen = np.zeros(n_markers, bool)
    seen[lab[lab >= 0]] = True
    if ignore is not None:
        seen |= np.asarray(ignore, bool)
    unseen = np.flatnonzero(~seen)
    if unseen.size != 1:
        return lab, 0
    ref = lab[reference_frame]
    R = points[reference_frame][ref >= 0]
    if len(R) < 3:
        return lab, 0
    dr = np.linalg.norm(R[:, None] - R[None], axis=-1)
    np.fill_diagonal(dr, np.inf)
    limit = isolation * float(np.median(dr.min(1)))
    cand = (lab < 0) & (tid >= 0) & np.isfinite(points[..., 0])
    f, j = np.nonzero(cand)
    if not f.size:
        return lab, 0
    P = points[f]  # (S, N, 3)
    d = np.linalg.norm(P - points[f, j][:, None], axis=-1)
    d[np.arange(len(f)), j] = np.inf
    iso = np.nan_to_num(d, nan=np.inf).min(1) > limit
    t = tid[f, j]
    ut, inv = np.unique(t, return_inverse=True)
    n = np.bincount(inv)
    k = np.bincount(inv, weights=iso)
    good = (n >= min_length) & (k >= isolated_share * n)
    # a point present, and left unlabelled, in the reference frame is not a marker
    good &= ~np.isin(ut, tid[reference_frame][tid[reference_frame] >= 0])
    if not good.any():
        return lab, 0
    # never two at the same time
    frames = f[good[inv]]
    if len(np.unique(frames)) != len(frames):
        return lab, 0
    take = good[inv]
    lab[f[take], j[take]] = unseen[0]
    return lab, int(good.sum())


def attached_pieces(points: np.ndarray, labels: np.ndarray, tid: np.ndarray, model: ShapeModel,
                    groups: list | None = None, *, min_length: int = 5, max_range: float = 6.0,
                    min_present: float = 0.8, min_attached: int = 2, confirm_mm: float = 10.0,
                    confirm_spreads: float = 3.0, anchored_share: float = 0.2, stride: int = 3,
                    protected: np.ndarray | None = None) -> tuple[np.ndarray, int, int]:
    """Rename or unname pieces whose label's partners are all absent but which ride rigidly on
    other present markers.

    Parameters
    ----------
    points : float (F, N, 3)
        Point clouds, mm.
    labels : int (F, N)
        Marker of each point, -1 unlabelled.
    tid : int (F, N)
        Tracklet of each point, -1 none.
    model : ShapeModel
        Partners of each marker near the reference frame. A point is *anchored* when one of
        its label's partners is present within ``confirm_mm + confirm_spreads * spread`` of
        the model's distance; a piece is judged only when at most ``anchored_share`` of its
        points are (its label's partners are absent, or present only under wrong names),
        counted on every ``stride``-th frame.
    groups : list of int arrays, optional
        Members of each rigid group (``RigidGroups.members``).
    min_length : int
        Pieces shorter than this (frames) are left alone.
    max_range : float
        mm; a labelled marker present in ``min_present`` of the piece's frames whose distance
        to the piece varies by at most this much is *attached* to it.
    min_attached : int
        Attached markers needed to judge the piece.
    protected : bool (F, N), optional
        Hinted points: their pieces are left alone.

    Returns
    -------
    labels : int32 (F, N)
    renamed, unnamed : int
        Pieces renamed and unnamed.
    """
    lab = np.array(labels, np.int32)
    F, N = lab.shape
    M = model.partners.shape[0]
    P = np.maximum(model.partners, 0)
    has_p = model.partners >= 0
    # on every ``stride``-th frame (float32): a point is anchored when some partner of its
    # label is present at about its distance
    fr = np.arange(0, F, max(1, int(stride)))
    ks = _piece_keys(lab[fr], tid[fr])
    sf, sj = np.nonzero(ks >= 0)
    if not len(sf):
        return lab, 0, 0
    L = lab[fr[sf], sj]
    Xs = np.full((len(fr), M, 3), np.nan, np.float32)
    Xs[sf, L] = points[fr[sf], sj]
    # (frames, M, K, 3), per marker (denser than per point; np.take is the fast gather)
    diff = np.take(Xs, P.ravel(), axis=1).reshape(len(fr), M, -1, 3) - Xs[:, :, None]
    dev = np.abs(np.sqrt(np.einsum("fmkc,fmkc->fmk", diff, diff)) - model.dist.astype(np.float32))
    with np.errstate(invalid="ignore"):
        near = dev <= (confirm_mm + confirm_spreads * model.spread).astype(np.float32)
    anchored = ((near & has_p).any(-1) | ~has_p.any(-1))[sf, L]
    uk, q = np.unique(ks[sf, sj], return_inverse=True)
    ns = np.bincount(q, minlength=len(uk))
    cand = np.bincount(q, weights=anchored, minlength=len(uk)) <= anchored_share * ns
    if protected is not None and cand.any():
        pm = np.asarray(protected, bool) & (lab >= 0)
        cand &= ~np.isin(uk, _piece_keys(lab, tid)[pm])
    if not cand.any():
        return lab, 0, 0
    # the candidate pieces over all their frames
    keys = _piece_keys(lab, tid)
    f, j = np.nonzero(keys >= 0)
    xyz = np.full((F, M, 3), np.nan, np.float32)
    xyz[f, lab[f, j]] = points[f, j]
    pres = np.isfinite(xyz[..., 0])
    on = np.isin(keys[f, j], uk[cand])
    f, j = f[on], j[on]
    uk, q = np.unique(keys[f, j], return_inverse=True)
    bad = np.bincount(q, minlength=len(uk)) >= min_length
    if not bad.any():
        return lab, 0, 0
    group_of = np.full(M, -1)
    members = list(groups or [])
    for g, mem in enumerate(members):
        group_of[np.asarray(mem)] = g
    renamed = unnamed = 0
    for k in np.flatnonzero(bad):
        sel = q == k
        ff, jj = f[sel], j[sel]
        L = int(lab[ff[0], jj[0]])
        d = np.linalg.norm(xyz[ff] - points[ff, jj].astype(np.float32)[:, None], axis=-1)  # (n, M)
        seen = np.isfinite(d)
        ok = seen.mean(0) >= min_present
        ok[L] = False
        if not ok.any():
            continue
        dd = np.where(seen, d, np.nan)[:, ok]
        rng = np.nanmax(dd, 0) - np.nanmin(dd, 0)
        att = np.flatnonzero(ok)[rng <= max_range]
        if len(att) < min_attached:
            continue
        new = -1
        gs = np.unique(group_of[att][group_of[att] >= 0])
        gs = [g for g in gs if (group_of[att] == g).sum() >= min_attached]
        if group_of[L] >= 0 and group_of[L] in gs:
            continue  # it rides on its own rigid group
        if len(gs) == 1:
            mem = np.asarray(members[gs[0]])
            miss = mem[~pres[ff][:, mem].any(0)]
            if len(miss) == 1:
                new = int(miss[0])
        lab[ff, jj] = new
        xyz[ff, L] = np.nan
        pres[ff, L] = False
        if new >= 0:
            xyz[ff, new] = points[ff, jj]
            pres[ff, new] = True
            renamed += 1
        else:
            unnamed += 1
    return lab, renamed, unnamed
