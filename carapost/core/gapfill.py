"""Gap interpolation: neighbour-driven forward/backward prediction blended across a gap.

The reference guide's algorithm ("Gap interpolation algorithm"): a missing point is predicted
from its last known position and from how its neighbouring points moved between the frame
where it was last present and the current frame (*forwards*), and likewise from the first
frame after the gap (*backwards*); the two predictions are blended across the gap, weighted by
the position in the gap. With single-sensor gap filling, a point attached to one detection is
moved onto that detection's ray, so it reprojects exactly onto the blob centre.

How a neighbourhood's motion is applied to the point (:func:`neighbour_motion`):

1. the ``k`` "nearest" points present in both frames are found; nearness is
   ``c^2 = d^2 + (alpha s)^2``, with ``d`` the distance in the source frame and ``s`` the
   spread (standard deviation over the take) of the pair's distance, so neighbours that move
   with the point are preferred to ones that merely sit close to it (``alpha = 0``: plain
   distance);
2. a weighted rigid transform (Kabsch; weights ``1 / (c^2 + c_k^2)``, ``c_k`` the cost of
   the ``k``-th neighbour) maps them from the source to the destination frame; where a
   neighbour's residual exceeds ``2 x median residual + 0.5 mm`` the fit is repeated with
   Cauchy weights on that scale, so a neighbour whose trajectory is swapped or mislabelled
   is ignored;
3. *elastic* correction: the neighbours' residuals after the rigid fit are added back,
   weighted by inverse squared cost, so local stretching (a smile pulling a cheek) moves
   the point as well as the rigid part does.

The guide's algorithm only uses the neighbours. A point whose own motion is not shared by any
neighbour (an upper eyelid during a blink) cannot be predicted from them; so each prediction
may also carry on the point's own motion relative to its neighbourhood just before (after) the
gap, damped with a time constant of ``velocity_frames`` frames (the extrapolated displacement
saturates at ``velocity * velocity_frames``). ``velocity_frames=0`` gives the guide's algorithm
exactly. See ``docs/gap-filling.md`` for measurements of both.

Array contract: ``xyz (F, P, 3)`` mm with NaN gaps; masks ``(F, P)`` bool.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "checked_fill_arrays",
    "GapFillResult",
    "fill_gaps",
    "neighbour_motion",
    "weighted_rigid_fit",
    "gap_runs",
    "distance_spread",
    "hide_runs",
    "constrain_to_rays",
]

#: Samples processed per block in :func:`neighbour_motion` (bounds the (N, P, 3) temporaries).
_BLOCK = 4096
#: Robust reweighting of the neighbourhood fit: iterations, and the Cauchy scale
#: ``_ROBUST_C * median residual + _ROBUST_FLOOR_MM``.
_ROBUST_ITERATIONS = 3
_ROBUST_C = 2.0
_ROBUST_FLOOR_MM = 0.5


@dataclass
class GapFillResult:
    """Output of :func:`fill_gaps`.

    Attributes
    ----------
    xyz : float64 array (F, P, 3)
        The input positions with the filled samples replaced (a new array).
    filled : bool array (F, P)
        Samples given a new position.
    on_ray : bool array (F, P)
        Filled samples constrained to a single detection's ray.
    """

    xyz: np.ndarray
    filled: np.ndarray
    on_ray: np.ndarray

    @property
    def n_filled(self) -> int:
        return int(self.filled.sum())


def weighted_rigid_fit(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched weighted Kabsch: the rotation and translation mapping ``src`` onto ``dst``.

    Parameters
    ----------
    src, dst : arrays (..., K, 3)
        Corresponding points, mm. Rows with zero weight are ignored (they may hold anything
        finite).
    w : array (..., K)
        Non-negative weights; a batch whose weights sum to 0 gets the identity.

    Returns
    -------
    R : array (..., 3, 3)
    t : array (..., 3)
        ``dst ~ src @ R.T + t``. With fewer than three non-collinear weighted points the
        rotation is whatever SVD gives for the degenerate covariance (a pure translation fit
        if the covariance is zero).
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    w = np.asarray(w, dtype=float)
    ws = w.sum(-1, keepdims=True)
    safe = np.where(ws > 0, ws, 1.0)
    wn = w / safe
    cs = np.einsum("...k,...kd->...d", wn, src)
    cd = np.einsum("...k,...kd->...d", wn, dst)
    H = np.einsum("...k,...ki,...kj->...ij", wn, src - cs[..., None, :], dst - cd[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.swapaxes(-1, -2) @ U.swapaxes(-1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = Vt.swapaxes(-1, -2) @ D @ U.swapaxes(-1, -2)
    zero = np.abs(H).sum((-1, -2)) < 1e-300
    R = np.where(zero[..., None, None], np.eye(3), R)
    t = cd - np.einsum("...ij,...j->...i", R, cs)
    return R, t


def neighbour_motion(xyz: np.ndarray, known: np.ndarray, points: np.ndarray, src: np.ndarray, dst: np.ndarray,
                     *, n_neighbours: int = 8, elastic: bool = True,
                     start: np.ndarray | None = None,
                     rank_cost: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move points from a source frame to a destination frame the way their neighbours moved.

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm.
    known : bool array (F, P)
        Samples usable as neighbours (finite).
    points, src, dst : int arrays (N,)
        For each query: the point column, the source frame and the destination frame.
    n_neighbours : int
        ``k``: neighbours used per query (fewer if fewer are present in both frames).
    elastic : bool
        Add the neighbours' distance-weighted residuals after the rigid fit.
    start : array (N, 3), optional
        Position to move (default ``xyz[src, points]``). Neighbours are ranked by distance
        to it.
    rank_cost : array (P, P), optional
        Extra squared cost (mm^2) of point ``j`` as a neighbour of point ``p``, added to the
        squared distance for the ranking and the weights.

    Returns
    -------
    moved : array (N, 3)
        Predicted positions in the destination frames, mm. With no usable neighbour the
        start position is returned unchanged.
    R : array (N, 3, 3)
        The local rotation of each query (identity with fewer than three neighbours).
    n_used : int array (N,)
        Neighbours used.
    """
    xyz = np.asarray(xyz, dtype=float)
    F, P, _ = xyz.shape
    points = np.asarray(points, dtype=np.int64)
    src = np.asarray(src, dtype=np.int64)
    dst = np.asarray(dst, dtype=np.int64)
    N = len(points)
    if start is None:
        start = xyz[src, points]
    start = np.asarray(start, dtype=float)
    moved = np.empty((N, 3))
    Rout = np.empty((N, 3, 3))
    used = np.zeros(N, np.int64)
    k = max(1, min(int(n_neighbours), P - 1)) if P > 1 else 1
    if P < 2:
        moved[:] = start
        Rout[:] = np.eye(3)
        return moved, Rout, used
    for b0 in range(0, N, _BLOCK):
        sl = slice(b0, min(N, b0 + _BLOCK))
        p, fs, fd, x0 = points[sl], src[sl], dst[sl], start[sl]
        n = len(p)
        ok = known[fs] & known[fd]
        ok[np.arange(n), p] = False
        Xs = xyz[fs]                                   # (n, P, 3)
        d2 = np.where(ok, np.einsum("npd,npd->np", Xs - x0[:, None], Xs - x0[:, None]), np.inf)
        if rank_cost is not None:
            d2 = d2 + rank_cost[p]
        kk = min(k, P)
        nb = np.argpartition(d2, kk - 1, axis=1)[:, :kk] if kk < P else np.tile(np.arange(P), (n, 1))
        rows = np.arange(n)[:, None]
        dn2 = d2[rows, nb]                             # (n, k), inf where unusable
        valid = np.isfinite(dn2)
        cnt = valid.sum(1)
        used[sl] = cnt
        A = np.where(valid[..., None], Xs[rows, nb], 0.0)
        B = np.where(valid[..., None], xyz[fd[:, None], nb], 0.0)
        dk2 = np.max(np.where(valid, dn2, 0.0), axis=1, keepdims=True)
        w = np.where(valid, 1.0 / (np.where(valid, dn2, 0.0) + dk2 + 1e-6), 0.0)
        R, t = weighted_rigid_fit(A, B, w)
        rigid = cnt >= 3
        # robust reweighting: neighbours that moved unlike the rest (a swapped or mislabelled
        # trajectory) lose their weight
        rob = np.ones_like(w)
        rows = np.arange(n)
        for it in range(_ROBUST_ITERATIONS):
            Ar, Br, vr = A[rows], B[rows], valid[rows]
            r = np.linalg.norm(Br - (np.einsum("nij,nkj->nki", R[rows], Ar) + t[rows, None, :]), axis=-1)
            rs = np.sort(np.where(vr, r, np.inf), axis=1)
            med = rs[np.arange(len(rows)), np.maximum(vr.sum(1) - 1, 0) // 2]
            c = _ROBUST_C * np.where(np.isfinite(med), med, 0.0)[:, None] + _ROBUST_FLOOR_MM
            new_rob = np.where(vr, 1.0 / (1.0 + (r / c) ** 2), 0.0)
            if it == 0:
                # only neighbourhoods with an outlier (residual beyond the scale) are refitted
                flagged = (vr & (r > c)).any(1)
                rows, new_rob = rows[flagged], new_rob[flagged]
                if not len(rows):
                    break
            rob[rows] = new_rob
            R[rows], t[rows] = weighted_rigid_fit(A[rows], B[rows], w[rows] * rob[rows])
        w = w * rob
        # fewer than three neighbours: translation only (their weighted mean displacement)
        ws = np.maximum(w.sum(1, keepdims=True), 1e-300)
        shift = ((B - A) * w[..., None]).sum(1) / ws
        R = np.where(rigid[:, None, None], R, np.eye(3))
        pred = np.where(rigid[:, None], np.einsum("nij,nj->ni", R, x0) + t, x0 + shift)
        if elastic:
            res = B - (np.einsum("nij,nkj->nki", R, A) + np.where(rigid[:, None], t, shift)[:, None, :])
            we = np.where(valid, rob / (np.where(valid, dn2, 0.0) + 1e-2 * dk2 + 1e-6), 0.0)
            wes = np.maximum(we.sum(1, keepdims=True), 1e-300)
            pred = pred + np.where(rigid[:, None], (res * we[..., None]).sum(1) / wes, 0.0)
        none = cnt == 0
        pred[none] = x0[none]
        moved[sl] = pred
        Rout[sl] = R
    return moved, Rout, used


def distance_spread(xyz: np.ndarray, known: np.ndarray | None = None, *, max_frames: int = 1000) -> np.ndarray:
    """How rigidly each pair of points moves together: the standard deviation over frames of
    their distance, mm.

    Parameters
    ----------
    xyz : array (F, P, 3)
    known : bool array (F, P), optional
        Samples to use (default finite ones).
    max_frames : int
        At most this many frames (evenly spaced) are used.

    Returns
    -------
    array (P, P)
        0 on the diagonal; pairs never seen together get the largest spread found (or 0 if
        none was measurable).
    """
    xyz = np.asarray(xyz, dtype=float)
    F, P, _ = xyz.shape
    ok = np.isfinite(xyz).all(-1) if known is None else np.asarray(known, bool) & np.isfinite(xyz).all(-1)
    fr = np.unique(np.linspace(0, F - 1, min(F, max_frames)).round().astype(np.int64))
    n = np.zeros((P, P))
    s1 = np.zeros((P, P))
    s2 = np.zeros((P, P))
    for b0 in range(0, len(fr), 64):
        f = fr[b0:b0 + 64]
        X = np.where(ok[f][..., None], xyz[f], 0.0)
        X = X - X.sum(1, keepdims=True) / np.maximum(ok[f].sum(1), 1)[:, None, None]   # centred: less rounding
        sq = (X * X).sum(-1)
        D = np.sqrt(np.maximum(sq[:, :, None] + sq[:, None, :] - 2.0 * (X @ X.transpose(0, 2, 1)), 0.0))
        both = (ok[f][:, :, None] & ok[f][:, None, :]).astype(float)
        n += both.sum(0)
        s1 += (D * both).sum(0)
        s2 += (D * D * both).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / n
        var = np.maximum(s2 / n - mean * mean, 0.0)
    sd = np.sqrt(var)
    seen = n >= 2
    fill = float(sd[seen].max()) if seen.any() else 0.0
    sd = np.where(seen, sd, fill)
    np.fill_diagonal(sd, 0.0)
    return sd


def gap_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximal runs of true values down each column of ``mask (F, P)``.

    Returns
    -------
    point, first, last : int arrays (G,)
        Column and first/last frame (inclusive) of each run, sorted by point then frame.
    """
    mask = np.asarray(mask, dtype=bool)
    F, P = mask.shape
    pad = np.zeros((1, P), np.int8)
    d = np.diff(np.concatenate([pad, mask.astype(np.int8), pad]), axis=0)  # (F+1, P)
    sf, sp = np.nonzero(d.T == 1)
    ef, ep = np.nonzero(d.T == -1)
    return sf.astype(np.int64), sp.astype(np.int64), ep.astype(np.int64) - 1


def _last_known(known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every (frame, point): the last known frame before it and the next one after it
    (-1 if none)."""
    F, P = known.shape
    idx = np.where(known, np.arange(F)[:, None], -1)
    before = np.maximum.accumulate(idx, axis=0)
    before = np.concatenate([np.full((1, P), -1), before[:-1]])
    idx2 = np.where(known, np.arange(F)[:, None], F)
    after = np.minimum.accumulate(idx2[::-1], axis=0)[::-1]
    after = np.concatenate([after[1:], np.full((1, P), F)])
    after = np.where(after >= F, -1, after)
    return before, after


def _residual_velocity(xyz: np.ndarray, known: np.ndarray, points: np.ndarray, anchor: np.ndarray, step: int,
                       n_neighbours: int, elastic: bool, rank_cost: np.ndarray | None) -> np.ndarray:
    """The point's own motion per frame relative to its neighbourhood, arriving at ``anchor``
    from the side away from the gap (``step`` -1: from the frames before, for a forward
    prediction; +1: from the frames after, for a backward one). Zero where not measurable."""
    F = xyz.shape[0]
    prev = anchor + 2 * step
    ok = (prev >= 0) & (prev < F)
    prev = np.clip(prev, 0, F - 1)
    mid = np.clip(anchor + step, 0, F - 1)
    ok &= known[prev, points] & known[mid, points]
    v = np.zeros((len(points), 3))
    if not ok.any():
        return v
    i = np.flatnonzero(ok)
    pred, _, n = neighbour_motion(xyz, known, points[i], prev[i], anchor[i], n_neighbours=n_neighbours,
                                  elastic=elastic, rank_cost=rank_cost)
    good = n > 0
    # two-frame span: average motion per frame (less sensitive to noise than one frame)
    v[i[good]] = (xyz[anchor[i[good]], points[i[good]]] - pred[good]) / 2.0
    return v


def constrain_to_rays(X: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The points of rays closest to ``X``: ``X (..., 3)``, ``origin``/``direction (..., 3)``
    (unit or not). Rays with NaN leave the point unchanged."""
    X = np.asarray(X, dtype=float)
    o = np.asarray(origin, dtype=float)
    d = np.asarray(direction, dtype=float)
    dn = d / np.linalg.norm(d, axis=-1, keepdims=True)
    s = np.einsum("...d,...d->...", X - o, dn)
    s = np.maximum(s, 0.0)
    out = o + s[..., None] * dn
    return np.where(np.isfinite(out).all(-1, keepdims=True), out, X)


def checked_fill_arrays(xyz: np.ndarray, fill: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``xyz`` as float (F, P, 3) and ``fill`` as bool (F, P), or ValueError naming the bad shape."""
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"xyz must have shape (F, P, 3), got {xyz.shape}")
    fill = np.asarray(fill, dtype=bool)
    if fill.shape != xyz.shape[:2]:
        raise ValueError(f"fill mask must have shape {xyz.shape[:2]}, got {fill.shape}")
    return xyz, fill


def fill_gaps(xyz: np.ndarray, fill: np.ndarray, *, known: np.ndarray | None = None, forwards: bool = True,
              backwards: bool = True, n_neighbours: int = 8, elastic: bool = True,
              velocity_frames: float = 0.0, rays: tuple[np.ndarray, np.ndarray] | None = None,
              rigidity_weight: float = 30.0) -> GapFillResult:
    """Interpolate gaps ("Interpolate Gaps") by neighbour-driven prediction.

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm, NaN in gaps. Not modified.
    fill : bool array (F, P)
        Samples to (re)compute: gaps, and existing filled samples when overwriting.
    known : bool array (F, P), optional
        Samples to predict from and to use as neighbours; default ``finite & ~fill``.
    forwards, backwards : bool
        "Use Forwards Prediction" (from the last known position before a gap) and "Use
        Backwards Prediction" (from the first known position after it). Where both exist the
        predictions are blended linearly by position in the gap; where only one is allowed
        or exists, it alone is used.
    n_neighbours : int
        Neighbours per prediction (>= 1).
    elastic : bool
        Elastic correction of the rigid neighbourhood fit (see the module docstring).
    rigidity_weight : float
        ``alpha``: neighbours are ranked (and weighted) by ``d^2 + (alpha * s)^2``, ``d`` their
        distance and ``s`` the spread of their distance to the point over the take
        (:func:`distance_spread`), so points that move with the point count as its
        neighbours. 0 ranks by distance only.
    velocity_frames : float
        Time constant (frames) of the damped continuation of the point's own motion relative
        to its neighbourhood; 0 disables it (the guide's algorithm).
    rays : (origin, direction) arrays (F, P, 3), optional
        Single-sensor constraint: where finite, a filled sample is moved to the closest point
        of that ray (so it reprojects exactly onto the detection).

    Returns
    -------
    GapFillResult

    Raises
    ------
    ValueError
        For mismatched shapes, ``n_neighbours < 1`` or negative weights / time constants.

    Examples
    --------
    >>> import numpy as np
    >>> xyz = np.zeros((3, 4, 3)); xyz[:, :, 0] = np.arange(4); xyz[:, :, 1] = np.arange(3)[:, None]
    >>> gap = np.zeros((3, 4), bool); gap[1, 0] = True; xyz[1, 0] = np.nan
    >>> fill_gaps(xyz, gap).xyz[1, 0].round(6)
    array([0., 1., 0.])
    """
    xyz, fill = checked_fill_arrays(xyz, fill)
    F, P, _ = xyz.shape
    if n_neighbours < 1:
        raise ValueError(f"n_neighbours must be at least 1, got {n_neighbours}")
    if velocity_frames < 0:
        raise ValueError(f"velocity_frames must not be negative, got {velocity_frames}")
    if rigidity_weight < 0:
        raise ValueError(f"rigidity_weight must not be negative, got {rigidity_weight}")
    finite = np.isfinite(xyz).all(-1)
    known = finite & ~fill if known is None else np.asarray(known, dtype=bool) & finite & ~fill
    out = xyz.copy()
    filled = np.zeros((F, P), bool)
    on_ray = np.zeros((F, P), bool)
    if not (forwards or backwards) or not fill.any():
        return GapFillResult(out, filled, on_ray)
    rank_cost = (rigidity_weight * distance_spread(xyz, known)) ** 2 if rigidity_weight > 0 else None
    before, after = _last_known(known)
    ff, pp = np.nonzero(fill)
    a = before[ff, pp] if forwards else np.full(len(ff), -1)
    b = after[ff, pp] if backwards else np.full(len(ff), -1)
    has_a, has_b = a >= 0, b >= 0
    keep = has_a | has_b
    ff, pp, a, b, has_a, has_b = ff[keep], pp[keep], a[keep], b[keep], has_a[keep], has_b[keep]
    pred_a = np.zeros((len(ff), 3))
    pred_b = np.zeros((len(ff), 3))
    for has, anchor, pred, step in ((has_a, a, pred_a, -1), (has_b, b, pred_b, 1)):
        i = np.flatnonzero(has)
        if not len(i):
            continue
        moved, R, _ = neighbour_motion(xyz, known, pp[i], anchor[i], ff[i], n_neighbours=n_neighbours,
                                       elastic=elastic, rank_cost=rank_cost)
        if velocity_frames > 0:
            # the point's own motion, estimated once per (point, anchor)
            key = pp[i] * (F + 1) + anchor[i]
            _, first, inv = np.unique(key, return_index=True, return_inverse=True)
            v = _residual_velocity(xyz, known, pp[i][first], anchor[i][first], step, n_neighbours, elastic,
                                   rank_cost)[inv]
            n = np.abs(ff[i] - anchor[i]).astype(float)
            g = velocity_frames * (1.0 - np.exp(-n / velocity_frames))
            moved = moved + g[:, None] * np.einsum("nij,nj->ni", R, v)
        pred[i] = moved
    both = has_a & has_b
    wb = np.where(both, (ff - a) / np.where(both, b - a, 1), has_b.astype(float))
    X = (1.0 - wb)[:, None] * pred_a + wb[:, None] * pred_b
    if rays is not None:
        o, d = (np.asarray(r, dtype=float) for r in rays)
        if o.shape != (F, P, 3) or d.shape != (F, P, 3):
            raise ValueError(f"rays must be two arrays of shape {(F, P, 3)}")
        ro, rd = o[ff, pp], d[ff, pp]
        has_ray = np.isfinite(ro).all(-1) & np.isfinite(rd).all(-1)
        X[has_ray] = constrain_to_rays(X[has_ray], ro[has_ray], rd[has_ray])
        on_ray[ff[has_ray], pp[has_ray]] = True
    out[ff, pp] = X
    filled[ff, pp] = True
    return GapFillResult(out, filled, on_ray)


def hide_runs(valid: np.ndarray, fraction: float, *, min_len: int = 5, max_len: int = 30,
              seed: int | np.random.Generator = 0) -> np.ndarray:
    """Choose gap-like runs of known samples to hide (to measure a gap filler's error).

    Runs of ``min_len..max_len`` frames are drawn at random inside runs of valid samples,
    each leaving at least one valid frame on both sides (so both anchors exist) and at least
    one valid frame between two hidden runs, until ``fraction`` of the valid samples are
    hidden (or no room is left).

    Parameters
    ----------
    valid : bool array (F, P)
    fraction : float
        Target share of the valid samples to hide, 0..1.
    min_len, max_len : int
        Run lengths, frames.
    seed : int or numpy Generator

    Returns
    -------
    bool array (F, P)
        The samples to hide (a subset of ``valid``).
    """
    valid = np.asarray(valid, dtype=bool)
    if not 0 <= fraction <= 1:
        raise ValueError(f"fraction must be within 0..1, got {fraction}")
    if not 1 <= min_len <= max_len:
        raise ValueError(f"need 1 <= min_len <= max_len, got {min_len}, {max_len}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    F, P = valid.shape
    hidden = np.zeros((F, P), bool)
    target = int(round(fraction * valid.sum()))
    # blocked: samples that are hidden or next to a hidden one, or not valid
    free = valid.copy()
    total = 0
    tries = 0
    while total < target and tries < 50 * (target // max(min_len, 1) + 10):
        tries += 1
        n = int(rng.integers(min_len, max_len + 1))
        p = int(rng.integers(P))
        f0 = int(rng.integers(1, max(2, F - n)))
        f1 = f0 + n
        if f1 >= F or not free[f0 - 1:f1 + 1, p].all():
            continue
        hidden[f0:f1, p] = True
        free[f0:f1, p] = False
        total += n
    return hidden
