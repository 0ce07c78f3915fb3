"""Long-range shape check: re-identify markers against the shape around a trusted frame.

Frame-to-frame labelling (and the jump-based :func:`~carapost.core.swaps.detect_swaps`) can
lock into a wrong permutation when markers are confused during fast motion or while the
source's own labels are inconsistent: once past the confusion, continuity alone never undoes
it. This module compares the labelled take with the *shape* it has around a trusted reference
frame:

1. :func:`shape_model`: for every marker, its ``k`` most rigidly attached partners (smallest
   robust spread of their distance), the median distance ``D`` and a spread ``S`` (1.4826 x
   MAD, at least ``floor_mm + rel_floor * D``), from the frames near the reference frame
   where the labels are *trusted*: those before the first tracklet change (a labelling
   decision) among the marker's nearest neighbours on either side of the reference frame.
2. The cost of marker ``L`` at a position is the mean over its present partners of
   ``min(((|x - x_partner| - D) / S)^2, tau^2)`` (a truncated squared z-score: a partner that
   is not rigid during some motion costs at most ``tau^2``).
3. In frames (every ``stride``-th) where some marker's cost is anomalous and the marker would
   fit clearly better at the position of one of its nearest markers, the labels of those
   markers are re-decided by an optimal assignment (Hungarian), with a bonus for the current
   labels (clear evidence is needed to change one).
4. Runs of the same proposed permutation cycle are extended over the frames where the points
   involved stay on the same tracklets (``pieces``: labels only change where tracklets start),
   trimmed to the sub-range of largest total gain, and kept when the take's total shape cost
   over the range drops clearly (``min_gain`` per frame and marker moved, in most frames).
   Optionally (``propagate``) a kept repair's permutation is tried on the tracklet segments
   next to it, and so on.

:func:`shape_relabels` returns the repairs as :class:`~carapost.core.swaps.Relabel` objects
(apply them with :func:`~carapost.core.swaps.apply_relabel` or
:func:`~carapost.core.swaps.relabel_points`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from .swaps import Relabel, _group, apply_relabel

__all__ = ["ShapeModel", "shape_model", "shape_costs", "shape_relabels", "reference_model", "relabel_gain",
           "take_rigidity", "rigid_over_take"]


@dataclass(frozen=True)
class ShapeModel:
    """Rigid partners of every marker near a trusted frame.

    Attributes
    ----------
    partners : int64 (M, K)
        Partner markers, most rigid first; -1 where fewer than ``K`` qualify.
    dist, spread : float64 (M, K)
        Median distance to each partner and its robust spread, mm (NaN / inf where none).
    """

    partners: np.ndarray
    dist: np.ndarray
    spread: np.ndarray


def shape_model(xyz: np.ndarray, frames: np.ndarray, *, trusted: np.ndarray | None = None, k: int = 6,
                floor_mm: float = 0.5, rel_floor: float = 0.02, min_frames: int = 5,
                max_spread_mm: float = np.inf) -> ShapeModel:
    """Rigid partners, distances and spreads from the labelled ``frames`` of ``xyz``.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, mm, NaN gaps.
    frames : int (S,)
        Frames whose labels are trusted (e.g. around the reference frame).
    trusted : bool (S, M), optional
        Which samples of those frames are trusted (default all).
    k : int
        Partners per marker.
    floor_mm, rel_floor : float
        Lower bound of a spread: ``floor_mm + rel_floor * distance``.
    min_frames : int
        A pair is used only when both markers are present in this many of the frames
        (at most a third of them).
    max_spread_mm : float
        ... and when its spread is at most this plus 1 % of its distance (rigidly attached:
        the same body segment, or neighbours on a face).

    Returns
    -------
    ShapeModel
    """
    x = np.asarray(xyz, np.float64)
    M = x.shape[1]
    X = x[np.asarray(frames, np.int64)]
    if trusted is not None:
        X = np.where(np.asarray(trusted, bool)[..., None], X, np.nan)
    sq = np.einsum("smi,smi->sm", X, X)
    d = np.sqrt(np.maximum(sq[:, :, None] + sq[:, None, :] - 2.0 * np.matmul(X, X.transpose(0, 2, 1)), 0.0))
    n = np.isfinite(d).sum(0)
    ok = n >= max(1, min(min_frames, len(X) // 3 + 1))
    np.fill_diagonal(ok, False)
    D = _nan_median0(d, n)
    mad = _nan_median0(np.abs(d - D[None]), n)
    S = np.maximum(1.4826 * np.nan_to_num(mad, nan=np.inf), floor_mm + rel_floor * np.nan_to_num(D, nan=0.0))
    score = np.where(ok & (S <= max_spread_mm + 0.01 * np.nan_to_num(D, nan=np.inf)),
                     S + 0.01 * np.nan_to_num(D, nan=0.0), np.inf)
    K = min(k, max(M - 1, 0))
    order = np.argsort(score, axis=1, kind="stable")[:, :K]
    fin = np.isfinite(np.take_along_axis(score, order, 1))
    partners = np.where(fin, order, -1).astype(np.int64)
    dist = np.where(fin, np.take_along_axis(D, order, 1), np.nan)
    spread = np.where(fin, np.take_along_axis(S, order, 1), np.inf)
    return ShapeModel(partners, dist, spread)


def _nan_median0(a: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN (``n`` the finite counts); NaN where ``n == 0``."""
    srt = np.sort(a, axis=0)  # NaN last
    lo = np.maximum((n - 1) // 2, 0)
    hi = np.maximum(n // 2, 0)
    med = 0.5 * (np.take_along_axis(srt, lo[None], 0)[0] + np.take_along_axis(srt, hi[None], 0)[0])
    return np.where(n > 0, med, np.nan)


def shape_costs(xyz: np.ndarray, model: ShapeModel, *, tau: float = 3.0, min_partners: int = 2,
                unknown: float = 0.0, rows: np.ndarray | None = None) -> np.ndarray:
    """Shape cost of every marker (or of the markers ``rows``) in every frame, (F, M) (or
    (F, len(rows))): 0 where the marker is missing, ``unknown`` where fewer than
    ``min_partners`` of its partners are present."""
    x = np.asarray(xyz, np.float32)  # float32: the costs are coarse, the data are mm
    F = x.shape[0]
    R = np.arange(x.shape[1]) if rows is None else np.asarray(rows, np.int64)
    P = np.maximum(model.partners[R], 0)
    has = model.partners[R] >= 0
    dist = model.dist[R].astype(np.float32)[None]
    inv_s = (1.0 / model.spread[R]).astype(np.float32)[None]
    t2 = np.float32(tau * tau)
    out = np.zeros((F, len(R)))
    step = max(1, 1_000_000 // max(len(R) * P.shape[1] * 3, 1))
    for a in range(0, F, step):
        b = min(F, a + step)
        X = x[a:b]
        diff = X[:, R, None, :] - X[:, P]
        d = np.sqrt(np.einsum("fmki,fmki->fmk", diff, diff))  # (c, M, K)
        d -= dist
        d *= inv_s
        z2 = np.minimum(d * d, t2)
        v = np.isfinite(z2) & has[None]
        cnt = v.sum(-1)
        s = np.where(v, z2, np.float32(0.0)).sum(-1)
        here = np.isfinite(X[:, R, 0])
        out[a:b] = np.where(cnt >= min_partners, s / np.maximum(cnt, 1), np.where(here, unknown, 0.0))
    return out


def _frame_problem(Xf: np.ndarray, ms: np.ndarray, labs: np.ndarray, model: ShapeModel, tau: float,
                   bonus: float, min_partners: int) -> np.ndarray:
    """Cost (n, k) of giving the point now labelled ``ms[i]`` the label ``labs[j]`` in one frame
    (``Xf`` (M, 3) the frame's labelled positions; ``labs`` starts with ``ms``, then labels
    missing in the frame); the current labels get ``-bonus``. A present label with too few
    partners costs ``tau^2 / 2`` (no evidence), a missing one ``tau^2`` (no reason to move a
    point to it)."""
    n = len(ms)
    P = model.partners[labs]  # (k, K)
    has = P >= 0
    Y = Xf[np.maximum(P, 0)]  # (k, K, 3) partner positions of each label
    diff = Xf[ms][:, None, None, :] - Y[None]
    d = np.sqrt(np.einsum("abkc,abkc->abk", diff, diff))  # (n pts, k labels, K)
    z2 = np.minimum(((d - model.dist[labs][None]) / model.spread[labs][None]) ** 2, tau * tau)
    v = np.isfinite(z2) & has[None] & (P[None] != ms[:, None, None])  # a point is not its own partner
    cnt = v.sum(-1)
    none = np.where(np.arange(len(labs)) < n, 0.5 * tau * tau, tau * tau)[None]
    need = np.where(np.arange(len(labs)) < n, min_partners, max(min_partners, 3))[None]
    C = np.where(cnt >= need, np.where(v, z2, 0.0).sum(-1) / np.maximum(cnt, 1), none)
    C[np.arange(n), np.arange(n)] -= bonus
    return C


def _proposals(x: np.ndarray, model: ShapeModel, cost: np.ndarray, *, anomaly: float, tau: float,
               bonus: float, near: int, allowed: np.ndarray, min_partners: int,
               to_missing: bool) -> np.ndarray:
    """Per-frame label permutations ``src`` (F, M) (``new[f, m] = old[f, src[f, m]]``) proposed
    by the assignment in frames with anomalous markers; with ``to_missing`` a point may also
    move to a missing label related to (a partner of, or partnered by) the markers re-decided."""
    F, M, _ = x.shape
    src = np.tile(np.arange(M), (F, 1))
    valid = np.isfinite(x[..., 0])
    P = model.partners
    rel = np.zeros((M, M), bool)
    r, c = np.nonzero(P >= 0)
    rel[r, P[r, c]] = True
    rel |= rel.T
    absent = ~valid & allowed[None] & to_missing
    bad = (cost > anomaly) & allowed[None]
    near_absent = bad & ((absent.astype(np.float32) @ rel.astype(np.float32)) > 0)
    bad &= near_absent | _fits_elsewhere(x, model, cost, bad, tau=tau, bonus=bonus, near=near, allowed=allowed,
                                         min_partners=min_partners)
    for f in np.flatnonzero(bad.any(1)):
        Xf = x[f]
        pres = np.flatnonzero(valid[f] & allowed)
        if pres.size < 1:
            continue
        an = np.flatnonzero(bad[f])
        dd = ((Xf[an][:, None] - Xf[pres][None]) ** 2).sum(-1)
        kk = min(near + 1, pres.size)
        nb = pres[np.argpartition(dd, kk - 1, axis=1)[:, :kk]]
        ms = np.unique(np.concatenate([an, nb.ravel()]))
        miss = np.flatnonzero(absent[f] & rel[ms].any(0))
        if ms.size + miss.size < 2:
            continue
        labs = np.concatenate([ms, miss])
        C = _frame_problem(Xf, ms, labs, model, tau, bonus, min_partners)
        ri, ci = linear_sum_assignment(C)
        new = labs[ci]
        src[f, new] = ms[ri]
        # labels left without a point take the missing labels' (empty) columns
        free_new = np.setdiff1d(labs, new)
        free_old = miss  # the sources are ``ms``; the missing labels' columns are unused
        keep = np.intersect1d(free_new, free_old)
        src[f, keep] = keep
        src[f, np.setdiff1d(free_new, keep)] = np.setdiff1d(free_old, keep)
    return src


def _fits_elsewhere(x: np.ndarray, model: ShapeModel, cost: np.ndarray, bad: np.ndarray, *, tau: float,
                    bonus: float, near: int, allowed: np.ndarray, min_partners: int) -> np.ndarray:
    """Which anomalous (frame, marker) entries of ``bad`` would cost at least ``bonus`` less at
    the position of one of the ``near`` markers nearest to it (a necessary condition for a
    relabelling to pay; vectorised, so that the per-frame assignments run only where they can
    change something). bool (F, M)."""
    out = np.zeros_like(bad)
    fa, ma = np.nonzero(bad)
    if fa.size == 0:
        return out
    F, M, _ = x.shape
    xs = x.astype(np.float32)
    ok = np.isfinite(xs[..., 0]) & allowed[None]
    kk = min(near, M - 1)
    if kk < 1:
        return out
    P = np.maximum(model.partners, 0)
    has = model.partners >= 0
    t2 = np.float32(tau * tau)
    step = max(1, 200_000 // max(M, 1))
    for a in range(0, fa.size, step):
        f, m = fa[a:a + step], ma[a:a + step]
        X = xs[f]  # (S, M, 3)
        d2 = ((X - xs[f, m][:, None]) ** 2).sum(-1)
        d2[~ok[f]] = np.inf
        d2[np.arange(len(f)), m] = np.inf
        nb = np.argpartition(d2, kk - 1, axis=1)[:, :kk]  # (S, kk)
        Z = np.take_along_axis(X, nb[..., None], 1)  # candidate positions
        Pm = P[m]
        Y = np.take_along_axis(X, Pm[..., None], 1)  # (S, K, 3) partners of the label
        diff = Z[:, :, None, :] - Y[:, None]
        dd = np.sqrt(np.einsum("snki,snki->snk", diff, diff))
        z = (dd - model.dist[m][:, None].astype(np.float32)) / model.spread[m][:, None].astype(np.float32)
        z2 = np.minimum(z * z, t2)
        v = np.isfinite(z2) & has[m][:, None] & (Pm[:, None, :] != nb[:, :, None])
        cnt = v.sum(-1)
        alt = np.where(cnt >= min_partners, np.where(v, z2, 0).sum(-1) / np.maximum(cnt, 1), np.inf)
        good = np.isfinite(np.take_along_axis(d2, nb, 1)) & (alt < cost[f, m][:, None] - bonus)
        out[f, m] = good.any(1)
    return out


def _trusted_spans(x: np.ndarray, pieces: np.ndarray | None, t0: int, window: int, *, near: int = 6,
                   least: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``lo[m] .. hi[m]`` (inclusive) where marker ``m``'s labels are trusted: within
    ``window`` of the reference frame and, with ``pieces``, between the tracklet changes of
    the ``near`` markers nearest to it (around the reference frame) closest to ``t0`` (a
    tracklet start is a decision, possibly a wrong one); at least ``least`` frames either
    side."""
    F, M, _ = x.shape
    lo = np.full(M, max(0, t0 - window))
    hi = np.full(M, min(F - 1, t0 + window))
    if pieces is None:
        return lo, hi
    X = x[t0]
    ok = np.isfinite(X[:, 0])
    change = pieces[1:] != pieces[:-1]  # change[f]: between f and f + 1
    for m in range(M):
        if ok[m] and ok.sum() > 1:
            d = ((X[ok] - X[m]) ** 2).sum(1)
            nb = np.flatnonzero(ok)[np.argsort(d)[:near + 1]]
        else:
            nb = np.array([m])
        ev = np.flatnonzero(change[:, nb].any(1))
        before = ev[ev < t0]
        after = ev[ev >= t0]
        if before.size:
            lo[m] = max(lo[m], min(int(before[-1]) + 1, t0 - least))
        if after.size:
            hi[m] = min(hi[m], max(int(after[0]), t0 + least))
    return np.maximum(lo, 0), np.minimum(hi, F - 1)


def _neighbour_segments(pieces: np.ndarray, r: Relabel, F: int, t0: int) -> list[tuple[int, int]]:
    """The frame ranges just before and just after ``r`` over which the points of its markers
    stay on the same pieces, never over frame ``t0``."""
    out = []
    if r.end < F:
        s, e = _snap(pieces, Relabel(r.end, r.end + 1, r.perm), F)
        s = r.end
        if not (s <= t0 < e):
            out.append((s, e))
    if r.start > 0:
        s, e = _snap(pieces, Relabel(r.start - 1, r.start, r.perm), F)
        e = r.start
        if not (s <= t0 < e):
            out.append((s, e))
    return out


def _snap(pieces: np.ndarray | None, r: Relabel, F: int) -> tuple[int, int]:
    """Extend ``r``'s frame range while the points of its markers stay on the same pieces."""
    s, e = r.start, r.end
    if pieces is None:
        return s, e
    ms = r.markers
    p0 = pieces[s, ms]
    if (p0 >= 0).any():
        other = np.flatnonzero((pieces[:s, ms] != p0).any(1))
        s = int(other[-1]) + 1 if other.size else 0
    p1 = pieces[e - 1, ms]
    if (p1 >= 0).any():
        other = np.flatnonzero((pieces[e:, ms] != p1).any(1))
        e = e + int(other[0]) if other.size else F
    return s, e


def shape_relabels(xyz: np.ndarray, reference_frame: int, *, pieces: np.ndarray | None = None,
                   window: int = 100, k: int = 6, tau: float = 3.0, anomaly: float = 2.0, bonus: float = 1.0,
                   near: int = 3, min_run: int = 4, min_gain: float = 3.0, support: float = 0.6,
                   stride: int = 2, to_missing: bool = False,
                   fixed: Sequence[int] = (), iterations: int = 3,
                   model: ShapeModel | None = None,
                   accept: Callable[[np.ndarray, Relabel, float], bool] | None = None,
                   propagate: bool = False) -> list[Relabel]:
    """Label permutations that make the take consistent with its shape near a trusted frame.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, mm, NaN gaps.
    reference_frame : int
        A frame whose labels are trusted; no repair covers it. The shape model is made from
        the frames within ``window`` of it (only the samples on the tracklets that carry the
        reference frame's labels, when ``pieces`` is given).
    pieces : int (F, M), optional
        Id of the tracklet carrying each marker's sample (-1 none): a repair found in a few
        frames is extended over the frames where its points stay on the same tracklets.
    window : int
        Frames either side of the reference frame used for the shape model.
    k, tau : int, float
        Partners per marker; truncation of the per-partner squared z-score.
    anomaly : float
        Frames where a marker's mean squared z-score exceeds this are re-decided.
    bonus : float
        Cost bonus of the current labels in the per-frame assignment.
    near : int
        Nearest markers (in the frame) re-decided together with each anomalous marker.
    min_run : int
        A proposed permutation must hold in this many consecutive frames.
    stride : int
        Proposals are made in every ``stride``-th frame (repairs are then decided frame by
        frame).
    min_gain : float
        A repair is kept when the take's total shape cost drops by at least this much per
        frame and marker it moves ...
    support : float
        ... and drops in at least this share of its frames.
    to_missing : bool
        Also propose moving a point to a label missing in its frame (a partner of the markers
        re-decided). Off by default: on the real files it fixes some re-identifications and
        breaks others (see ``docs/labelling.md``).
    fixed : sequence of int
        Markers never relabelled.
    iterations : int
        Rounds of proposals (a repair can reveal another).
    model : ShapeModel, optional
        A precomputed model (else from the frames around ``reference_frame``).
    accept : callable, optional
        ``accept(xyz, relabel, gain)``: a further condition on a repair that passed the gain
        test (``xyz`` the trajectories before it, ``gain`` its shape gain per frame and marker
        moved), e.g. that it does not break a rigid group.
    propagate : bool
        With ``pieces``: after each round, try every repair's permutation on the segments
        next to it (the frames over which its markers' points stay on the same pieces, at
        least ``min_run``), with the same tests, and so on from each one kept: a confusion
        that continuity carried on over many tracklets, where the proposals of some segments
        are muddled by other markers (Facial-Sing's mouth markers).

    Returns
    -------
    list of Relabel
        In the order found; apply in that order.
    """
    x = np.array(xyz, np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"trajectories must have shape (frames, markers, 3), got {x.shape}")
    F, M, _ = x.shape
    if not 0 <= int(reference_frame) < F:
        raise ValueError(f"reference frame {reference_frame} is outside 0..{F - 1}")
    if pieces is not None and np.shape(pieces) != (F, M):
        raise ValueError(f"pieces must have shape {(F, M)}, got {np.shape(pieces)}")
    t0 = int(reference_frame)
    if F < 2 or M < 3:
        return []
    pc = None if pieces is None else np.array(pieces, np.int64)
    if model is None:
        model = reference_model(x, t0, pieces=pc, window=window, k=k)
    allowed = np.ones(M, bool)
    allowed[list(fixed)] = False
    out: list[Relabel] = []
    stride = max(1, int(stride))
    zeros = np.zeros((len(range(0, F, stride)), M))
    for _ in range(max(1, iterations)):
        xs = x[::stride]
        cost = shape_costs(xs, model, tau=tau)
        src = _proposals(xs, model, cost, anomaly=anomaly, tau=tau, bonus=bonus, near=near, allowed=allowed,
                         min_partners=2, to_missing=to_missing)
        need = max(1, min_run // stride)
        runs = [Relabel(r.start * stride, min(F, (r.end - 1) * stride + 1), r.perm)
                for r in _group(src, zeros) if r.end - r.start >= need]
        cands = {}
        for r in runs:
            if r.start <= t0 < r.end:
                continue
            s, e = _snap(pc, r, F)
            # never over the reference frame
            s, e = (max(s, t0 + 1), e) if r.start > t0 else (s, min(e, t0))
            c = _best_bounds(x, model, Relabel(s, e, r.perm), r.start, r.end, tau)
            cands[(c.start, c.end, tuple(r.perm.tolist()))] = c
        scored = []
        for c in cands.values():
            g, sup = _gain(x, model, c, tau)
            scored.append((g / ((c.end - c.start) * len(c.markers)), sup, c))
        scored.sort(key=lambda t: -t[0])
        accepted = 0
        done: list[Relabel] = []
        for g_n, sup, c in scored:
            n = (c.end - c.start) * len(c.markers)
            if any(r.start < c.end and c.start < r.end for r in done):
                g, sup = _gain(x, model, c, tau)  # again: an earlier repair changed its frames
                g_n = g / n
            if g_n < min_gain or sup < support:
                continue
            if accept is not None and not accept(x, c, g_n):
                continue
            x = apply_relabel(x, [c])
            if pc is not None:
                pc = apply_relabel(pc, [c])
            out.append(Relabel(c.start, c.end, c.perm, float(g_n)))
            done.append(c)
            accepted += 1
        if propagate and pc is not None:
            # a confusion carried on by continuity spans several tracklet segments: try each
            # repair's permutation on the segments next to it (at least ``min_run`` frames),
            # with the same tests, as far as they pass
            frontier = list(done)
            while frontier:
                r = frontier.pop()
                for s, e in _neighbour_segments(pc, r, F, t0):
                    if e - s < max(1, min_run):
                        continue
                    c = Relabel(s, e, r.perm)
                    n = (e - s) * len(c.markers)
                    g, sup = _gain(x, model, c, tau)
                    if g / n < min_gain or sup < support or (accept is not None and not accept(x, c, g / n)):
                        continue
                    x = apply_relabel(x, [c])
                    pc = apply_relabel(pc, [c])
                    out.append(Relabel(s, e, c.perm, float(g / n)))
                    frontier.append(c)
                    accepted += 1
        if not accepted:
            break
    return out


def reference_model(xyz: np.ndarray, reference_frame: int, *, pieces: np.ndarray | None = None,
                    window: int = 100, k: int = 6) -> ShapeModel:
    """The shape model :func:`shape_relabels` uses: from the frames within ``window`` of the
    reference frame, only the samples whose labels are trusted (see the module docstring)."""
    x = np.asarray(xyz, np.float64)
    pc = None if pieces is None else np.asarray(pieces, np.int64)
    lo, hi = _trusted_spans(x, pc, int(reference_frame), window)
    a, b = int(lo.min()), int(hi.max()) + 1
    fr = np.unique(np.linspace(a, b - 1, min(b - a, 120)).astype(int))
    tr = (fr[:, None] >= lo[None]) & (fr[:, None] <= hi[None])
    return shape_model(x, fr, trusted=tr, k=k)


def take_rigidity(model: ShapeModel, xyz: np.ndarray, *, factor: float = 2.0, samples: int = 400,
                  min_samples: int = 20) -> np.ndarray:
    """How rigid each pair of the model is over the whole take: the share of ``samples``
    frames spread over the take (where both markers are labelled) in which the pair's
    distance is within ``factor`` spreads of the model's distance ``D``. (M, K), NaN where the
    pair is seen together in fewer than ``min_samples`` sampled frames.

    Near the reference frame a pair may look rigid because the body barely moves there (a
    scapula and a forearm marker while the athlete sits still): over the take, such a pair
    keeps its distance in few frames. A share, not a spread, because the labels over the take
    are the ones being checked (a rigid pair with a third of its samples mislabelled still
    keeps its distance in two thirds of them).

    Parameters
    ----------
    model : ShapeModel
        Partners (M, K), distances and spreads near the reference frame.
    xyz : float (F, M, 3)
        Labelled trajectories, mm, NaN gaps.
    """
    x = np.asarray(xyz, np.float64)
    F = x.shape[0]
    fr = np.unique(np.linspace(0, F - 1, min(F, samples)).astype(int))
    X = x[fr]
    P = np.maximum(model.partners, 0)
    d = np.linalg.norm(X[:, :, None, :] - X[:, P], axis=-1)  # (S, M, K)
    dev = np.abs(d - model.dist[None])
    seen = np.isfinite(dev)
    n = seen.sum(0)
    within = (seen & (dev <= factor * model.spread[None])).sum(0)
    return np.where((model.partners >= 0) & (n >= min_samples), within / np.maximum(n, 1), np.nan)


def rigid_over_take(model: ShapeModel, xyz: np.ndarray, *, min_share: float = 0.5, k: int | None = None,
                    **kw) -> ShapeModel:
    """The model without the pairs that are not rigid over the whole take: those keeping their
    distance in less than ``min_share`` of the take (:func:`take_rigidity`); pairs that
    cannot be measured are kept. With ``k``, at most the ``k`` first partners left are kept
    (give a model with more candidates than needed)."""
    share = take_rigidity(model, xyz, **kw)
    keep = (model.partners >= 0) & (np.nan_to_num(share, nan=1.0) >= min_share)
    K = model.partners.shape[1] if k is None else min(k, model.partners.shape[1])
    order = np.argsort(~keep, axis=1, kind="stable")[:, :K]  # kept partners first, in their order
    ok = np.take_along_axis(keep, order, 1)
    return ShapeModel(np.where(ok, np.take_along_axis(model.partners, order, 1), -1),
                      np.where(ok, np.take_along_axis(model.dist, order, 1), np.nan),
                      np.where(ok, np.take_along_axis(model.spread, order, 1), np.inf))


def relabel_gain(xyz: np.ndarray, model: ShapeModel, relabel: Relabel, *, tau: float = 3.0) -> float:
    """How much a repair lowers the take's shape cost, per frame and marker it moves (negative:
    the repair breaks the shape)."""
    n = (relabel.end - relabel.start) * max(len(relabel.markers), 1)
    return _gain(np.asarray(xyz, np.float64), model, relabel, tau)[0] / max(n, 1)


def _frame_gains(x: np.ndarray, model: ShapeModel, r: Relabel, tau: float) -> np.ndarray:
    """Drop of the total shape cost in each of ``r``'s frames if it is applied, (end - start,)."""
    seg = x[r.start:r.end]
    ms = np.array(r.markers)
    # markers whose cost can change: the moved ones and those with a moved partner
    aff = np.flatnonzero(np.isin(model.partners, ms).any(1) | np.isin(np.arange(x.shape[1]), ms))
    before = shape_costs(seg, model, tau=tau, unknown=0.5 * tau * tau, rows=aff).sum(1)
    after = shape_costs(seg[:, r.perm], model, tau=tau, unknown=0.5 * tau * tau, rows=aff).sum(1)
    return before - after


def _gain(x: np.ndarray, model: ShapeModel, r: Relabel, tau: float) -> tuple[float, float]:
    """Drop of the total shape cost over ``r``'s frames if applied, and the share of frames
    where it drops (among the frames where it changes)."""
    d = _frame_gains(x, model, r, tau)
    moved = d != 0
    return float(d.sum()), float((d[moved] > 0).mean()) if moved.any() else 0.0


def _best_bounds(x: np.ndarray, model: ShapeModel, r: Relabel, a: int, b: int, tau: float) -> Relabel:
    """Within ``r``'s (snapped) range, the sub-range containing the proposed run ``a..b`` with
    the largest total gain (extended through frames of no change)."""
    if r.end - r.start <= b - a:
        return r
    d = _frame_gains(x, model, r, tau)
    i, j = a - r.start, b - r.start
    left = np.concatenate([[0.0], np.cumsum(d[:i][::-1])])  # gain of starting k frames earlier
    k = int(np.flatnonzero(left >= left.max() - 1e-9).max())
    right = np.concatenate([[0.0], np.cumsum(d[j:])])
    q = int(np.flatnonzero(right >= right.max() - 1e-9).max())
    return Relabel(a - k, b + q, r.perm, 0.0)
