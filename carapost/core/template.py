"""Marker-set templates and "Label From Template".

A :class:`MarkerTemplate` is a labelled frame of a range-of-motion (ROM) take: the marker
names, their neutral positions and the sticks between them. After Initialize 3D (or Initialize
from ROM) the points of a frame are unlabelled; :func:`label_from_template` gives each its
name:

1. **Rigid (similarity) fit** with unknown correspondences: iterative closest points with a
   scale, started from the identity (both in the brim frame), from the principal axes of the
   two point sets (the four proper sign choices) and from the best of those turned by 90
   degree steps; the start whose fit explains most points best wins.
2. **Non-rigid fit**: the template is warped by a smooth displacement field (Gaussian-weighted
   average of the matched markers' displacements, narrowing over the iterations), so that an
   expression different from the template's does not confuse the matching.
3. **Optimal assignment** (Hungarian) between the warped template and the points. A point
   farther than ``max_distance`` from its marker stays unlabelled; markers without a point
   are reported missing.

File I/O of templates is :mod:`carapost.io.marker_template`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

__all__ = ["MarkerTemplate", "TemplateFit", "template_from_frame", "label_from_template", "similarity_fit"]


@dataclass
class MarkerTemplate:
    """A marker set: names, neutral positions, sticks.

    Attributes
    ----------
    names : list of str (M,)
    xyz : float64 (M, 3)
        Neutral positions, mm; NaN rows for markers the labelled frame lacked.
    sticks : int64 (S, 2)
        Marker index pairs.
    source : str
        Where the template came from (take name and frame), free text.
    """

    names: list[str]
    xyz: np.ndarray
    sticks: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    source: str = ""

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, np.float64).reshape(-1, 3)
        self.sticks = np.asarray(self.sticks, np.int64).reshape(-1, 2)
        M = len(self.names)
        if self.xyz.shape != (M, 3):
            raise ValueError(f"template has {M} names but positions of shape {self.xyz.shape}")
        if len(set(self.names)) != M:
            raise ValueError("template marker names must be unique")
        if self.sticks.size and (self.sticks.min() < 0 or self.sticks.max() >= M):
            raise ValueError(f"template sticks must join markers 0..{M - 1}")

    def __len__(self) -> int:
        return len(self.names)


@dataclass
class TemplateFit:
    """Result of :func:`label_from_template`.

    Attributes
    ----------
    labels : int64 (N,)
        Template marker index of each point, -1 unlabelled (also for NaN points).
    unlabelled : int64 (K,)
        Valid points that could not be labelled.
    missing : int64 (J,)
        Template markers no point was given.
    scale : float
        Template-to-points scale of the similarity fit.
    R : (3, 3), t : (3,)
        Similarity: ``points ~ scale * R @ template + t``.
    residual : float64 (N,)
        Distance of each labelled point to its warped template marker, mm (NaN otherwise).
    rms_rigid : float
        RMS distance of the labelled points to the rigidly fitted template, mm.
    """

    labels: np.ndarray
    unlabelled: np.ndarray
    missing: np.ndarray
    scale: float
    R: np.ndarray
    t: np.ndarray
    residual: np.ndarray
    rms_rigid: float


def template_from_frame(xyz: np.ndarray, names: Sequence[str], sticks: np.ndarray | None = None,
                        source: str = "") -> MarkerTemplate:
    """A template from one labelled frame.

    Parameters
    ----------
    xyz : float (M, 3)
        Marker positions in that frame, mm (NaN for markers missing there).
    names : sequence of str (M,)
    sticks : int (S, 2), optional
        Marker index pairs.
    source : str
    """
    x = np.asarray(xyz, np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] != len(names):
        raise ValueError(f"xyz must have shape ({len(names)}, 3), got {x.shape}")
    if not np.isfinite(x).all(1).any():
        raise ValueError("the frame has no marker position to make a template from")
    return MarkerTemplate(list(names), x.copy(), np.zeros((0, 2), np.int64) if sticks is None else sticks,
                          source)


def similarity_fit(a: np.ndarray, b: np.ndarray, *, scale: bool = True,
                   weights: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``b ~ s R a + t`` (Umeyama).

    Parameters
    ----------
    a, b : float (K, 3)
    scale : bool
        Fit the scale (else 1).
    weights : float (K,), optional

    Returns
    -------
    s : float, R : (3, 3), t : (3,)
    """
    w = np.ones(len(a)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    A, B = a - ca, b - cb
    H = (A * w[:, None]).T @ B
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.array([1.0, 1.0, d])
    R = Vt.T @ np.diag(D) @ U.T
    var_a = float((w * (A * A).sum(1)).sum())
    s = float((S * D).sum() / var_a) if (scale and var_a > 0) else 1.0
    return s, R, cb - s * R @ ca


def _starts(T: np.ndarray, Q: np.ndarray) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Initial similarities: identity and principal-axes alignments (4 proper sign choices)."""
    out = [(1.0, np.eye(3), np.zeros(3))]
    ct, cq = T.mean(0), Q.mean(0)
    ut = np.linalg.svd(T - ct, full_matrices=False)[2]
    uq = np.linalg.svd(Q - cq, full_matrices=False)[2]
    st = np.sqrt(((T - ct) ** 2).sum(1).mean())
    sq = np.sqrt(((Q - cq) ** 2).sum(1).mean())
    s = sq / st if st > 0 else 1.0
    for sx in (1, -1):
        for sy in (1, -1):
            S = np.diag([sx, sy, sx * sy])  # proper: det = +1 after the frame determinants
            R = uq.T @ S @ ut
            if np.linalg.det(R) < 0:
                R = uq.T @ np.diag([sx, sy, -sx * sy]) @ ut
            out.append((s, R, cq - s * R @ ct))
    return out


def _icp(T: np.ndarray, Q: np.ndarray, tree: cKDTree, s: float, R: np.ndarray, t: np.ndarray, *,
         scale: bool, iters: int = 40) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Trimmed ICP (similarity); returns the fit and its score (trimmed mean squared distance,
    over the markers with a mutual nearest point)."""
    score = np.inf
    for _ in range(iters):
        X = s * T @ R.T + t
        d, j = tree.query(X)
        back = cKDTree(X).query(Q[j])[1]
        mutual = back == np.arange(len(T))
        if mutual.sum() < 3:
            return s, R, t, np.inf
        keep = mutual & (d <= np.percentile(d[mutual], 80) * 2.5 + 1e-9)
        if keep.sum() < 3:
            keep = mutual
        s2, R2, t2 = similarity_fit(T[keep], Q[j[keep]], scale=scale)
        moved = np.abs(s2 - s) + np.abs(R2 - R).max() + np.abs(t2 - t).max() / max(s2, 1e-9)
        s, R, t = s2, R2, t2
        # score: unexplained fraction weighted against residual (mean squared, trimmed)
        dm = np.sort(d[mutual])[: max(3, int(0.8 * mutual.sum()))]
        score = float((dm ** 2).mean()) * (len(T) / mutual.sum()) ** 2
        if moved < 1e-7:
            break
    return s, R, t, score


def _gauss_warp(T: np.ndarray, disp: np.ndarray, have: np.ndarray, radius: float) -> np.ndarray:
    """Smooth displacement field at all template markers from the matched ones."""
    d2 = ((T[:, None, :] - T[None, have, :]) ** 2).sum(-1)
    w = np.exp(-0.5 * d2 / radius ** 2)
    wsum = w.sum(1, keepdims=True)
    return np.where(wsum > 1e-12, (w @ disp[have]) / np.maximum(wsum, 1e-12), 0.0)


def label_from_template(points: np.ndarray, template: MarkerTemplate | np.ndarray, *,
                        max_distance: float | None = None, scale: bool = True, nonrigid: bool = True,
                        iterations: int = 8) -> TemplateFit:
    """Label one frame of unlabelled points from a template.

    Parameters
    ----------
    points : float (N, 3)
        The points (e.g. after Initialize 3D), mm; NaN rows are ignored.
    template : MarkerTemplate or float (M, 3)
        Neutral positions (NaN rows are markers the template does not know).
    max_distance : float, optional
        Largest distance between a point and its warped template marker, mm (default: 0.4 x
        the template's median nearest-marker distance, scaled by the fit).
    scale : bool
        Fit a scale (another actor's face); else rigid.
    nonrigid : bool
        Warp the template towards the points before the final assignment.
    iterations : int
        Non-rigid iterations.

    Returns
    -------
    TemplateFit

    Raises
    ------
    ValueError
        Fewer than three template markers or points, bad shapes.
    """
    tp = template.xyz if isinstance(template, MarkerTemplate) else np.asarray(template, np.float64)
    if tp.ndim != 2 or tp.shape[1] != 3:
        raise ValueError(f"template positions must have shape (M, 3), got {tp.shape}")
    P = np.asarray(points, np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {P.shape}")
    tm = np.flatnonzero(np.isfinite(tp).all(1))
    pv = np.flatnonzero(np.isfinite(P).all(1))
    if tm.size < 3 or pv.size < 3:
        raise ValueError(f"need at least 3 template markers and 3 points (got {tm.size} and {pv.size})")
    T, Q = tp[tm], P[pv]
    tree = cKDTree(Q)
    best = None
    starts = _starts(T, Q)
    for s0, R0, t0 in starts:
        fit = _icp(T, Q, tree, s0, R0, t0, scale=scale)
        if best is None or fit[3] < best[3]:
            best = fit
    # also try quarter turns about the best fit's axes (symmetric marker sets)
    s, R, t, sc = best
    for axis in np.eye(3):
        for ang in (np.pi / 2, np.pi, 3 * np.pi / 2):
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            Rq = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
            c = T.mean(0)
            R0 = R @ Rq
            t0 = s * R @ c + t - s * R0 @ c
            fit = _icp(T, Q, tree, s, R0, t0, scale=scale)
            if fit[3] < best[3]:
                best = fit
    s, R, t, _ = best
    dt = np.sqrt(((T[:, None] - T[None]) ** 2).sum(-1))
    np.fill_diagonal(dt, np.inf)
    spacing0 = float(np.median(dt.min(1)))

    def assign(Y: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
        """Optimal one-to-one pairs within ``limit``; leaving a marker or a point unpaired costs
        ``limit**2`` (so no chain of shifted pairs is made just to pair one more)."""
        D2 = ((Y[:, None, :] - Q[None]) ** 2).sum(-1)
        m, n = D2.shape
        big = 1e12
        C = np.full((m + n, n + m), big)
        C[:m, :n] = np.where(D2 <= limit ** 2, D2, big)
        C[np.arange(m), n + np.arange(m)] = limit ** 2
        C[m + np.arange(n), np.arange(n)] = limit ** 2
        C[m:, n:] = 0.0
        r, c = linear_sum_assignment(C)
        ok = (r < m) & (c < n)
        r, c = r[ok], c[ok]
        keep = D2[r, c] <= limit ** 2
        return r[keep], c[keep]

    # refine the similarity with one-to-one (Hungarian) correspondences, robustly
    for _ in range(10):
        X = s * T @ R.T + t
        r, c = assign(X, 1.5 * spacing0 * s)
        if r.size < 3:
            break
        e = np.sqrt(((X[r] - Q[c]) ** 2).sum(1))
        w = 1.0 / np.maximum(e, 0.05 * spacing0 * s)  # IRLS (L1-like): outliers weigh less
        s2, R2, t2 = similarity_fit(T[r], Q[c], scale=scale, weights=w)
        done = abs(s2 - s) < 1e-9 and np.abs(R2 - R).max() < 1e-9 and np.abs(t2 - t).max() < 1e-6
        s, R, t = s2, R2, t2
        if done:
            break
    X = s * T @ R.T + t
    spacing = spacing0 * s
    gate = 0.4 * spacing if max_distance is None else float(max_distance)
    r, c = assign(X, gate)
    rms_rigid = float(np.sqrt(((X[r] - Q[c]) ** 2).sum(1).mean())) if r.size else np.inf
    local = dt.min(1) * s  # each marker's own spacing, scaled

    def quality(Y: np.ndarray, r: np.ndarray, c: np.ndarray) -> tuple[int, float]:
        # tight matches first (a warp that merely reaches a spurious point gains nothing),
        # then the smaller total residual
        e2 = ((Y[r] - Q[c]) ** 2).sum(1) / gate ** 2
        return int((e2 <= 0.25).sum()), -float(e2.sum())

    Y, best_q = X, quality(X, r, c)
    if nonrigid and r.size >= 3:
        W = X
        radius = 3.0 * spacing
        for it in range(max(iterations, 0)):
            # coarse to fine: a wide search and loose confidence first (an open jaw moves
            # markers by more than their spacing), then mutual nearest neighbours within half
            # the local spacing
            reach = max(3 * gate, spacing * (2.5 - 0.5 * it))
            rr, cc = assign(W, reach)
            if rr.size < 3:
                break
            e = np.sqrt(((W[rr] - Q[cc]) ** 2).sum(1))
            nearest = cKDTree(W).query(Q[cc])[1] == rr
            conf = nearest & (e <= (reach if it < 3 else 0.5 * local[rr]))
            if conf.sum() < 3:
                break
            disp = np.zeros_like(W)
            have = np.zeros(len(W), bool)
            disp[rr[conf]] = Q[cc[conf]] - W[rr[conf]]
            have[rr[conf]] = True
            W = W + _gauss_warp(W, disp, have, radius)
            radius = max(radius * 0.6, spacing)
            r2, c2 = assign(W, gate)
            q = quality(W, r2, c2)
            if q > best_q:
                Y, best_q, r, c = W, q, r2, c2
    labels = np.full(len(P), -1, np.int64)
    labels[pv[c]] = tm[r]
    residual = np.full(len(P), np.nan)
    residual[pv[c]] = np.sqrt(((Y[r] - Q[c]) ** 2).sum(1))
    missing = np.setdiff1d(tm, tm[r])
    unl = np.setdiff1d(pv, pv[c])
    return TemplateFit(labels, unl.astype(np.int64), missing.astype(np.int64), float(s), R, t, residual, rms_rigid)
