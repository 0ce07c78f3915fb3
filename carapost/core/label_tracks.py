"""Tracklets: chains of points linked from frame to frame where the link is unambiguous.

:func:`link_frames` links each point of frame ``f`` to a point of frame ``f - 1`` when the two
are *mutual* nearest neighbours after a constant-velocity prediction and the match passes a
ratio test in both directions (the nearest is much nearer than the second nearest, for the
point and for its match). It is vectorised over blocks of frames (no per-point Python).
Ambiguous points are left unlinked: whoever resolves them (the assignment labeller) sees a
tracklet start there.

:func:`build_tracklets` numbers the chains; :func:`segments_from_trajectories` makes
"tracklets" from labelled trajectories instead (runs of each marker cut at given frames), so
that the same assignment engine can relabel them (swap repair).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Tracklets", "link_frames", "build_tracklets", "segments_from_trajectories", "LinkStats"]


@dataclass
class LinkStats:
    """Residuals of the accepted links of the last pass (mm): median and 90th percentile."""

    median: float
    p90: float
    n_links: int


@dataclass
class Tracklets:
    """Chains of points.

    Attributes
    ----------
    tid : int32 (F, N)
        Tracklet of each point, -1 for empty slots.
    start, end : int64 (T,)
        First and last frame (inclusive) of each tracklet.
    offsets : int64 (T + 1,)
        Samples of tracklet ``t`` are ``offsets[t]:offsets[t + 1]`` of the arrays below.
    frames : int64 (S,)
        Frame of each sample, tracklet-major and increasing within a tracklet.
    index : int64 (S,)
        Point index (column of ``points``) of each sample.
    xyz : float64 (S, 3)
        Position of each sample, mm.
    n_frames : int
    """

    tid: np.ndarray
    start: np.ndarray
    end: np.ndarray
    offsets: np.ndarray
    frames: np.ndarray
    index: np.ndarray
    xyz: np.ndarray
    n_frames: int

    def __len__(self) -> int:
        return int(len(self.start))

    def sample_at(self, t: int, frame: int) -> np.ndarray | None:
        """Position (3,) of tracklet ``t`` at ``frame``, or None if it has no sample there."""
        a, b = self.offsets[t], self.offsets[t + 1]
        k = a + int(np.searchsorted(self.frames[a:b], frame))
        if k < b and self.frames[k] == frame:
            return self.xyz[k]
        return None


# -------------------------------------------------------------------------------- links
_FAR = np.float32(1e5)  # where empty slots are put (mm): never a plausible match
_APPEAR_RATIO2 = 16.0  # a new point within 4 x a link's residual makes the link doubtful


def _link_block(cur: np.ndarray, cur_ok: np.ndarray, pred: np.ndarray, pred_ok: np.ndarray,
                ratio2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Links of a block of ``c`` frame pairs.

    ``cur`` (c, N, 3) points of frames f, ``pred`` (c, N, 3) predicted positions at f of the
    points of frames f - 1 (with validity masks). Returns the (c, N) previous index or -1 and
    the squared residual of each accepted link (NaN otherwise; the rows of invalid predictions
    must be finite, e.g. 0), and per frame whether the frame
    is *hard* (points left unlinked in both frames, or a link longer than a quarter of the
    distance to the second candidate: a better prediction could change the links there). Distances are computed in
    float32 through ``|a|^2 + |b|^2 - 2 a.b`` after centring each frame (empty slots are moved
    far away instead of masked); residuals of the accepted links are recomputed exactly.
    """
    c, N, _ = cur.shape
    npred = np.maximum(pred_ok.sum(1), 1)[:, None]
    centre = np.matmul(pred_ok[:, None, :].astype(np.float64), pred)[:, 0] / npred  # mean valid prediction
    a = np.where(cur_ok[..., None], cur - centre[:, None], -_FAR).astype(np.float32)
    b = np.where(pred_ok[..., None], pred - centre[:, None], _FAR).astype(np.float32)
    # |a|^2 + |b|^2 - 2 a.b as one matrix product of (a, |a|^2, 1) and (-2 b, 1, |b|^2)
    A = np.empty((c, N, 5), np.float32)
    A[..., :3] = a
    A[..., 3] = (a * a).sum(-1)
    A[..., 4] = 1.0
    B = np.empty((c, 5, N), np.float32)
    B[:, :3] = b.transpose(0, 2, 1) * np.float32(-2.0)
    B[:, 3] = 1.0
    B[:, 4] = (b * b).sum(-1)
    d = np.matmul(A, B)
    ci = np.arange(c)[:, None]
    ni = np.arange(N)[None, :]
    rarg = d.argmin(axis=2)
    rbest = d[ci, ni, rarg]
    cmin = d.min(axis=1)
    mutual = np.take_along_axis(cmin, rarg, 1) >= rbest
    d[ci, ni, rarg] = np.inf
    rsecond = d.min(axis=2) if N > 1 else np.full((c, N), np.inf, np.float32)
    d[ci, ni, rarg] = rbest
    # second best of each matched column: hide the (mutual) best row, take the column minimum
    cc, jj = np.nonzero(mutual)
    ii = rarg[cc, jj]
    d[cc, jj, ii] = np.inf
    csecond = d.min(axis=1) if N > 1 else np.full((c, N), np.inf, np.float32)
    col_second = np.take_along_axis(csecond, rarg, 1)
    lim = np.float32(1e8)  # (1e4 mm)^2: anything farther is an empty slot
    ok = (cur_ok & mutual & (rbest < lim) & (rbest <= ratio2 * rsecond) & (rbest <= ratio2 * col_second))
    # a point appearing (unlinked) near a link's prediction may be the real continuation:
    # leave such links to the assignment, which also weighs the neighbourhood shape
    new = cur_ok & ~ok
    if new.any():
        d[ci, ni, rarg] = rbest
        # nearest new point per column: the few new rows only, reduced per frame
        nc, nj = np.nonzero(new)
        comp = np.full((c, N), np.inf, np.float32)
        starts = np.flatnonzero(np.r_[True, nc[1:] != nc[:-1]])
        comp[nc[starts]] = np.minimum.reduceat(d[nc, nj], starts, axis=0)
        cnt = np.maximum(ok.sum(1), 1)
        noise = np.sort(np.where(ok, rbest, np.inf), axis=1)[np.arange(c), (cnt - 1) // 2]
        scale = np.maximum(rbest, np.where(np.isfinite(noise), noise, 0.0)[:, None])
        ok &= ~(np.take_along_axis(comp, rarg, 1) < np.float32(_APPEAR_RATIO2) * scale)
    # links must be one to one: a column claimed twice (exact ties, duplicated points) is
    # ambiguous
    cc, jj = np.nonzero(ok)
    claims = np.bincount(cc * N + rarg[cc, jj], minlength=c * N).reshape(c, N)
    ok &= np.take_along_axis(claims, rarg, 1) == 1
    links = np.where(ok, rarg, -1).astype(np.int32)
    res = np.full((c, N), np.nan)
    cc, jj = np.nonzero(ok)
    dv = cur[cc, jj] - pred[cc, links[cc, jj]]
    res[cc, jj] = np.einsum("ij,ij->i", dv, dv)
    prev_linked = np.zeros((c, N), bool)
    prev_linked[cc, links[cc, jj]] = True
    # re-linking can only help where an unlinked point could still pair with an unlinked
    # predecessor, or where a link is long compared with its alternatives
    hard = (((cur_ok & ~ok).any(1) & (pred_ok & ~prev_linked).any(1))
            | (ok & (rbest > np.float32(0.0625) * rsecond)).any(1))
    return links, res, hard


def link_frames(points: np.ndarray, *, hints: np.ndarray | None = None, ratio: float = 0.5, passes: int = 2,
                block_elements: int = 250_000) -> tuple[np.ndarray, LinkStats]:
    """Unambiguous links between the points of consecutive frames.

    Parameters
    ----------
    points : float (F, N, 3)
        Point clouds, NaN rows empty (see :mod:`carapost.core.labelling`).
    hints : int (F, N), optional
        Known marker indices (-1 unknown). Two points hinted with different markers are never
        linked; two points hinted with the same marker in consecutive frames always are.
    ratio : float
        Ratio test: a link's distance must be at most ``ratio`` times the second-nearest
        distance, both for the point and for its match.
    passes : int
        1: zero-velocity prediction only. 2 or more: each further pass re-links the *hard*
        frames (an unlinked point, or a link that is long compared with the second candidate),
        predicting every linked point with its velocity from the previous pass's links.
    block_elements : int
        Distance-matrix entries computed at once (1 MB of float32: the passes over a block
        stay in cache; 4x larger blocks were 20 % slower).

    Returns
    -------
    links : int32 (F, N)
        Index of the linked point in frame ``f - 1``, -1 if none (always -1 in frame 0).
    stats : LinkStats
        Residuals (distance from prediction) of the accepted links of the last pass.
    """
    pts = np.asarray(points, np.float64)
    F, N, _ = pts.shape
    valid = np.isfinite(pts).all(-1)
    P = np.where(valid[..., None], pts, 0.0)
    links = np.full((F, N), -1, np.int32)
    resid = np.full((F, N), np.nan)
    hard = np.zeros(F, bool)
    chunk = max(1, block_elements // max(N * N, 1))
    r2 = float(ratio) ** 2
    for a in range(1, F, chunk):  # pass 1: zero velocity, every frame
        b = min(F, a + chunk)
        links[a:b], resid[a:b], hard[a:b] = _link_block(P[a:b], valid[a:b], P[a - 1:b - 1], valid[a - 1:b - 1], r2)
    # frames where few points linked: fast common motion? retry with the centroid shift
    n_valid = valid.sum(1)
    poor = np.flatnonzero((links >= 0).sum(1) < 0.8 * n_valid)
    poor = poor[poor > 0]
    for k in range(0, poor.size, chunk):
        idx = poor[k:k + chunk]
        shift = _centroid(P[idx], valid[idx]) - _centroid(P[idx - 1], valid[idx - 1])
        lk, rs, hd = _link_block(P[idx], valid[idx], P[idx - 1] + shift[:, None], valid[idx - 1], r2)
        better = (lk >= 0).sum(1) > (links[idx] >= 0).sum(1)
        links[idx[better]], resid[idx[better]], hard[idx[better]] = lk[better], rs[better], hd[better]
    if hints is not None:
        links = _apply_hints(links, hints, valid)
    for _ in range(1, max(1, passes)):  # further passes: constant velocity, hard frames only
        todo = np.flatnonzero(hard)
        if todo.size == 0:
            break
        # frames whose predecessor is not re-linked have final velocities: batch them; the
        # others (runs of hard frames) go in order, each using its predecessor's new links
        head = ~np.isin(todo - 1, todo)
        for idx in [todo[head][k:k + chunk] for k in range(0, int(head.sum()), chunk)] + \
                [np.array([f]) for f in todo[~head]]:
            pred = P[idx - 1] + _velocities(P, links, idx - 1)
            lk, rs, hd = _link_block(P[idx], valid[idx], pred, valid[idx - 1], r2)
            if hints is not None:
                lk = _apply_hints_block(lk, idx, hints, valid)
            links[idx], resid[idx], hard[idx] = lk, rs, hd
    ok = links >= 0
    r = np.sqrt(resid[ok & np.isfinite(resid)])
    stats = LinkStats(float(np.median(r)) if r.size else 0.0, float(np.percentile(r, 90)) if r.size else 0.0,
                      int(ok.sum()))
    return links, stats


def _centroid(P: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Centroid (c, 3) of the valid points of each frame of a block (0 if none)."""
    n = np.maximum(valid.sum(1), 1)[:, None]
    return np.where(valid[..., None], P, 0.0).sum(1) / n


def _velocities(P: np.ndarray, links: np.ndarray, frames: np.ndarray, k: int = 3) -> np.ndarray:
    """Displacement of each point of the given frames from its linked predecessor,
    (len(frames), N, 3). An unlinked point gets the mean displacement of the ``k`` linked
    points nearest to it in its frame (the local motion) when at least ``k`` are linked,
    else 0."""
    lk = links[frames]
    ok = (lk >= 0) & (frames > 0)[:, None]
    prev = np.take_along_axis(P[np.maximum(frames - 1, 0)], np.maximum(lk, 0)[..., None], axis=1)
    v = np.where(ok[..., None], P[frames] - prev, 0.0)
    need = ~ok & (ok.sum(1) >= k)[:, None]
    rows, cols = np.nonzero(need)
    if rows.size:
        X = P[frames]
        d = ((X[rows] - X[rows, cols][:, None, :]) ** 2).sum(-1)  # (S, N) to every point of the frame
        d[~ok[rows]] = np.inf
        near = np.argpartition(d, k - 1, axis=1)[:, :k]
        v[rows, cols] = v[rows[:, None], near].mean(1)
    return v


def _apply_hints_block(lk: np.ndarray, idx: np.ndarray, hints: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """:func:`_apply_hints` for the links ``lk`` of frames ``idx`` only."""
    F = hints.shape[0]
    full = np.full((2 * len(idx), lk.shape[1]), -1, np.int32)
    full[1::2] = lk
    h = np.stack([hints[idx - 1], hints[idx]], 1).reshape(-1, hints.shape[1])
    v = np.stack([valid[idx - 1], valid[idx]], 1).reshape(-1, valid.shape[1])
    out = _apply_hints(full, h, v)
    del F
    return out[1::2]


def _apply_hints(links: np.ndarray, hints: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Cut links between differently hinted points; force links between equally hinted ones."""
    F, N = links.shape
    h = np.where(valid, hints, -1)
    out = links.copy()
    prev_h = np.take_along_axis(h[:-1], np.maximum(out[1:], 0), axis=1)
    bad = (out[1:] >= 0) & (h[1:] >= 0) & (prev_h >= 0) & (prev_h != h[1:])
    out[1:][bad] = -1
    if not (h >= 0).any():
        return out
    M = int(h.max()) + 1
    inv = np.full((F, M), -1, np.int32)
    f, j = np.nonzero(h >= 0)
    inv[f, h[f, j]] = j
    forced = np.full((F, N), -1, np.int32)
    forced[1:] = np.where(h[1:] >= 0, np.take_along_axis(inv[:-1], np.maximum(h[1:], 0), axis=1), -1)
    has = forced >= 0
    # a previous point taken by a forced link cannot keep another link
    taken = np.zeros((F, N), bool)
    fr, jj = np.nonzero(has)
    taken[fr - 1, forced[fr, jj]] = True
    prev_taken = np.zeros((F, N), bool)
    prev_taken[1:] = np.take_along_axis(taken[:-1], np.maximum(out[1:], 0), axis=1) & (out[1:] >= 0)
    out[prev_taken & ~has] = -1
    out[has] = forced[has]
    return out


# ---------------------------------------------------------------------------- tracklets
def build_tracklets(points: np.ndarray, links: np.ndarray) -> Tracklets:
    """Number the chains of linked points.

    Parameters
    ----------
    points : float (F, N, 3)
    links : int (F, N)
        From :func:`link_frames`.

    Returns
    -------
    Tracklets
        Numbered by their first point, in (frame, index) order.

    Raises
    ------
    ValueError
        A link points at an empty slot of the previous frame.
    """
    pts = np.asarray(points, np.float64)
    F, N, _ = pts.shape
    valid = np.isfinite(pts).all(-1)
    # chains, numbered by their first point in (frame, index) order: a linked point takes its
    # predecessor's number, frame after frame
    lk = np.asarray(links)
    has = np.zeros((F, N), bool)
    has[1:] = (lk[1:] >= 0) & valid[1:]
    root = valid & ~has
    tid = np.full((F, N), -1, np.int32)
    tid[root] = np.arange(int(root.sum()), dtype=np.int32)
    prev = np.maximum(lk, 0)
    for f in np.flatnonzero(has.any(1)):
        hf = has[f]
        tid[f, hf] = tid[f - 1, prev[f, hf]]
    if (tid[valid] < 0).any():
        raise ValueError("links point at empty slots of the previous frame")
    return _tracklets_from_tid(pts, tid, int(root.sum()))


def _tracklets_from_tid(pts: np.ndarray, tid: np.ndarray, T: int) -> Tracklets:
    F, N = tid.shape
    flat = np.flatnonzero(tid.ravel() >= 0)  # frame-major
    f, j = np.divmod(flat, N)
    t = tid.ravel()[flat]
    counts = np.bincount(t, minlength=T)
    offsets = np.zeros(T + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    # a tracklet is a run of consecutive frames with one sample each: a sample's place is its
    # tracklet's offset plus its distance from the tracklet's first frame (no sort needed)
    first = np.full(T, F, np.int64)
    np.minimum.at(first, t, f)
    last = np.full(T, -1, np.int64)
    np.maximum.at(last, t, f)
    if np.array_equal(last - first + 1, counts):
        order = np.empty(len(t), np.int64)
        order[offsets[t] + f - first[t]] = np.arange(len(t))
    else:  # not runs of consecutive frames: a stable sort by tracklet keeps frames in order
        order = np.argsort(t, kind="stable")
    flat, f, j = flat[order], f[order], j[order]
    start = f[offsets[:-1]] if T else np.zeros(0, np.int64)
    end = f[offsets[1:] - 1] if T else np.zeros(0, np.int64)
    xyz = np.take(pts.reshape(-1, 3), flat, axis=0)
    return Tracklets(tid=tid, start=start.astype(np.int64), end=end.astype(np.int64), offsets=offsets,
                     frames=f.astype(np.int64), index=j.astype(np.int64), xyz=xyz, n_frames=F)


def segments_from_trajectories(xyz: np.ndarray, cuts: np.ndarray | None = None) -> tuple[Tracklets, np.ndarray]:
    """Tracklets made of labelled trajectories: each marker's runs of valid samples, cut again
    at the given frames.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories (column = marker).
    cuts : bool (F, M), optional
        ``cuts[f, m]``: a new segment of marker ``m`` starts at frame ``f``.

    Returns
    -------
    tracks : Tracklets
        ``index`` holds the marker (column) of each sample.
    owner : int64 (T,)
        The marker each segment came from.
    """
    x = np.asarray(xyz, np.float64)
    F, M, _ = x.shape
    valid = np.isfinite(x).all(-1)
    brk = np.zeros((F, M), bool)
    brk[0] = valid[0]
    brk[1:] = valid[1:] & ~valid[:-1]
    if cuts is not None:
        brk |= np.asarray(cuts, bool) & valid
    # segment id = running count of breaks, per marker (column-major numbering)
    order_fm = brk.T.ravel()
    cum = np.cumsum(order_fm).reshape(M, F).T - 1  # (F, M)
    tid = np.where(valid, cum, -1).astype(np.int32)
    T = int(order_fm.sum())
    tracks = _tracklets_from_tid(x, tid, T)
    owner = tracks.index[tracks.offsets[:-1]] if T else np.zeros(0, np.int64)
    return tracks, owner
