"""Rejection of bad matches for the frame-to-frame tracker (step 4 of the guide's algorithm).

* :func:`prune_views` — *Remove Bad 2D Projections*: triangulate and detach observations
  that reproject farther than the threshold, or that lie far from the point triangulated
  from the *other* views (leave-one-out residuals: two cameras of one caddy leave depth free,
  so a wrong detection in a third camera can hide behind small ordinary residuals). A bad
  point keeps its largest self-consistent subset of views.
* :func:`elastic_prediction`, :func:`mahalanobis`, :func:`consistent_views` — *Remove Bad
  3D Points*: a point is compared with the prediction its neighbours give (leave-one-out),
  with the prediction's uncertainty (how differently the neighbours moved) and the
  triangulation's own (depth of a caddy pair is uncertain); if it disagrees, the view whose
  removal brings it back is detached, or all of them.
* :func:`single_sensor` — *Single Sensor Tracking*: a point seen by one camera is placed on
  that camera's ray where it passes closest to the elastic prediction, and kept only if that
  is within the Single Sensor Tracking Threshold.

Shapes: ``C`` cameras, ``T`` points; observation arrays are camera-first ``(C, T, ...)``.
"""

from __future__ import annotations

import numpy as np

from .track_cameras import information, loo_residuals, ray_nearest_points, solve3, triangulate_uv
from .track_predict import NeighbourGraph

__all__ = ["prune_views", "single_sensor", "elastic_prediction", "mahalanobis",
           "consistent_views"]

#: Smallest uncertainty of an elastic prediction, mm (added to the neighbours' spread).
SIGMA_FLOOR_MM = 0.05
#: Mahalanobis distance beyond which a point disagrees with its neighbours.
GATE = 4.5
#: Assumed detection noise, px.
PIXEL_SIGMA = 0.3
#: Reprojection error a point's views must stay within to be trusted, px.
ANCHOR_RES_PX = 2.0


def prune_views(uv: np.ndarray, weight: np.ndarray, R: np.ndarray, t: np.ndarray, scale: np.ndarray,
                max_px: float, *, loo_px: float | None = None, pred_uv: np.ndarray | None = None,
                Xel: np.ndarray | None = None, sigma: np.ndarray | None = None,
                iterations: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate, detaching observations until every one reprojects within ``max_px``.

    An observation is bad if it reprojects farther than ``max_px``, or (with three or more
    views) lies farther than ``loo_px`` from the point triangulated from the *other* views
    (:func:`~.track_cameras.loo_residuals`): two cameras of one caddy leave the depth free, so
    a wrong detection in a third camera drags the point along it while keeping every
    ordinary residual small. A bad point keeps its largest self-consistent subset of views
    (when several are as large — a caddy pair against a caddy pair — the one closest to its
    elastic prediction). With two views the residuals are equal and the view farther from
    its predicted projection goes.

    Parameters
    ----------
    uv : array (C, T, 2)
        Normalised observations.
    weight : array (C, T)
        Observation weights (0 = none).
    R, t : arrays (C, 3, 3), (C, 3)
    scale : array (C, 2)
        Pixels per normalised unit.
    max_px : float
        Largest allowed reprojection error, px (``inf`` = keep everything).
    loo_px : float, optional
        Largest allowed leave-one-out reprojection error, px (default ``1.5 * max_px``).
    pred_uv : array (C, T, 2), optional
        Predicted projections (which of two disagreeing views to drop; else both go).
    Xel, sigma : arrays (T, 3), (T,), optional
        Elastic predictions and their uncertainty (NaN = none).
    iterations : int
        Gauss-Newton steps of each triangulation.

    Returns
    -------
    weight : array (C, T)
        Weights with the detached observations zeroed.
    X : array (T, 3)
        Points from the kept observations (NaN with fewer than two).
    residuals : array (C, T)
        Reprojection errors of the kept observations, px.
    """
    weight = np.array(weight, float)
    C = len(weight)
    X, res = triangulate_uv(uv, weight, R, t, scale, iterations=iterations)
    if not np.isfinite(max_px):
        return weight, X, res
    loo_px = 1.5 * max_px if loo_px is None else loo_px
    idx = _bad_points(X, uv, weight, res, R, t, scale, max_px, loo_px, np.arange(weight.shape[1]))
    for _ in range(max(C - 1, 1)):
        if len(idx) == 0:
            break
        n = (weight[:, idx] > 0).sum(0)
        many = idx[n >= 3]
        if len(many):
            _best_subset(uv, weight, many, R, t, scale, max_px, loo_px, Xel, sigma)
        two = idx[n == 2]
        if len(two):
            if pred_uv is not None:
                d = np.where(weight[:, two] > 0,
                             np.nan_to_num(((uv[:, two] - pred_uv[:, two]) * scale[:, None, :]) ** 2,
                                           nan=np.inf).sum(-1), -1.0)
                weight[np.argmax(d, axis=0), two] = 0.0
            else:
                weight[:, two] = 0.0
        Xi, ri = triangulate_uv(uv[:, idx], weight[:, idx], R, t, scale, iterations=iterations)
        X[idx] = Xi
        res[:, idx] = ri
        idx = idx[np.isin(idx, _bad_points(Xi, uv[:, idx], weight[:, idx], ri, R, t, scale, max_px, loo_px, idx))]
    return weight, X, res


def _bad_points(X: np.ndarray, uv: np.ndarray, weight: np.ndarray, res: np.ndarray, R: np.ndarray, t: np.ndarray,
                scale: np.ndarray, max_px: float, loo_px: float, ids: np.ndarray) -> np.ndarray:
    """The ``ids`` of points with a residual above ``max_px`` or (three views or more) a
    leave-one-out residual above ``loo_px``."""
    n = (weight > 0).sum(0)
    worst = np.nanmax(np.where(np.isnan(res), -1.0, res), axis=0)
    bad = (n >= 2) & (worst > max_px)
    three = n >= 3
    if np.any(three):
        sel = np.flatnonzero(three)
        loo = loo_residuals(X[sel], uv[:, sel], weight[:, sel], R, t, scale)
        bad[sel] |= np.nanmax(np.where(np.isnan(loo), -1.0, loo), axis=0) > loo_px
    return ids[bad]


def _best_subset(uv: np.ndarray, weight: np.ndarray, idx: np.ndarray, R: np.ndarray, t: np.ndarray,
                 scale: np.ndarray, max_px: float, loo_px: float, Xel: np.ndarray | None,
                 sigma: np.ndarray | None) -> None:
    """Keep (in place) the best self-consistent subset of each point's views.

    Every subset of two or more of a point's views is triangulated at once; a subset is
    consistent if all its residuals are within ``max_px`` and (three views or more) all its
    leave-one-out residuals within ``loo_px``. The largest consistent subset wins; among
    equally large ones, the one closest to the elastic prediction (or with the smallest
    residual). Points with no consistent pair lose every view.
    """
    C = len(weight)
    n = len(idx)
    masks = _subset_masks(C)                                                 # (S, C)
    S = len(masks)
    wb = weight[:, idx]                                                      # (C, n)
    used = wb > 0
    valid = ~(masks[:, :, None] & ~used[None]).any(1)                        # (S, n) subset within the used views
    W = (masks[:, :, None] * wb[None]).transpose(1, 0, 2).reshape(C, S * n)  # (C, S*n)
    U = np.broadcast_to(uv[:, idx][:, None], (C, S, n, 2)).reshape(C, S * n, 2)
    Xs, res = triangulate_uv(U, W, R, t, scale)
    rmax = np.nanmax(np.where(W > 0, res, -1.0), axis=0)
    loo = loo_residuals(Xs, U, W, R, t, scale)
    lmax = np.nanmax(np.where(np.isnan(loo), -1.0, loo), axis=0)
    fit = valid.reshape(-1) & (rmax <= max_px) & (lmax <= loo_px) & np.isfinite(Xs).all(1)
    size = masks.sum(1)[:, None].repeat(n, 1).reshape(-1)
    tie = rmax
    if Xel is not None and sigma is not None:
        Xe = np.broadcast_to(Xel[idx][None], (S, n, 3)).reshape(-1, 3)
        sg = np.broadcast_to(sigma[idx][None], (S, n)).reshape(-1)
        dm = mahalanobis(Xs, Xe, sg, information(Xs, W > 0, R, t, scale))
        tie = np.where(np.isfinite(dm), dm, rmax)
    key = np.where(fit, size * 1e6 - np.minimum(tie, 1e5), -np.inf).reshape(S, n)
    best = np.argmax(key, axis=0)
    ok = np.isfinite(key[best, np.arange(n)])
    keep = masks[best].T                                                     # (C, n)
    weight[:, idx] = np.where(ok[None, :] & keep, wb, 0.0)


_MASKS: dict[int, np.ndarray] = {}


def _subset_masks(C: int) -> np.ndarray:
    """All subsets of ``C`` views with at least two members, bool (S, C)."""
    if C not in _MASKS:
        codes = np.arange(1 << C)
        m = ((codes[:, None] >> np.arange(C)) & 1).astype(bool)
        _MASKS[C] = m[m.sum(1) >= 2]
    return _MASKS[C]


def elastic_prediction(graph: NeighbourGraph, X: np.ndarray, Xcv: np.ndarray, have: np.ndarray, *,
                       weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leave-one-out elastic prediction of every point from the measured ones.

    Parameters
    ----------
    graph : NeighbourGraph
    X : array (T, 3)
        Measured positions (used where ``have``).
    Xcv : array (T, 3)
        Motion-model predictions.
    have : bool array (T,)
    weight : array (T, k), optional
        Neighbour weights (default the graph's).

    Returns
    -------
    Xel : array (T, 3)
        ``Xcv`` plus the neighbours' mean surprise (``Xcv`` where not supported).
    sigma : array (T,)
        Uncertainty of ``Xel``, mm: the neighbours' spread plus :data:`SIGMA_FLOOR_MM`
        (NaN where not supported).
    supported : bool array (T,)
    """
    have = have & np.isfinite(X).all(1) & np.isfinite(Xcv).all(1)
    innov = np.where(have[:, None], X - Xcv, 0.0)
    mean, spread, sup = graph.average_spread(innov, have, weight=weight)
    return Xcv + mean, spread + SIGMA_FLOOR_MM, sup


def mahalanobis(X: np.ndarray, Xel: np.ndarray, sigma: np.ndarray, info: np.ndarray,
                pixel_sigma: float = PIXEL_SIGMA) -> np.ndarray:
    """Distance of measured points from their elastic prediction, in standard deviations.

    The covariance is the prediction's ``sigma^2 I`` plus the triangulation's
    ``pixel_sigma^2 inv(info)``: a depth error of two cameras of one caddy is forgiven as
    noise, but a third camera's detection that drags the point along that depth is not.

    Parameters
    ----------
    X, Xel : arrays (T, 3)
    sigma : array (T,)
        Prediction uncertainty, mm (NaN = none: distance NaN).
    info : array (T, 3, 3)
        Information of the triangulation (:func:`~.track_cameras.information`).
    pixel_sigma : float
        Detection noise, px.

    Returns
    -------
    array (T,)
    """
    d = np.where(np.isfinite(X), X - Xel, 0.0)
    s2 = np.where(np.isfinite(sigma), sigma, 1.0) ** 2
    # (s2 I + p2 inv(A))^-1 = (s2 A + p2 I)^-1 A : defined even where A is singular
    M = s2[:, None, None] * info + pixel_sigma ** 2 * np.eye(3)
    y = solve3(M, np.matmul(info, d[..., None])[..., 0], np.ones(len(d), bool))
    out = np.sqrt(np.maximum((d * y).sum(1), 0.0))
    return np.where(np.isfinite(sigma) & np.isfinite(X).all(1), out, np.nan)


def consistent_views(uv: np.ndarray, w: np.ndarray, X: np.ndarray, Xel: np.ndarray, sigma: np.ndarray,
                     check: np.ndarray, R: np.ndarray, t: np.ndarray, scale: np.ndarray, *,
                     gate: float = GATE, max_mm: float | np.ndarray = np.inf,
                     loo_checked: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep points whose triangulation agrees with their elastic prediction.

    A point that disagrees (Mahalanobis distance above ``gate`` — unless four
    consistent views see it — or farther than ``max_mm``) gets the one view whose removal
    brings it back detached; if none does, it fails.

    Parameters
    ----------
    uv : array (C, T, 2)
    w : array (C, T)
        Observation weights.
    X : array (T, 3)
        Their triangulation.
    Xel, sigma : arrays (T, 3), (T,)
        Elastic predictions and their uncertainty.
    check : bool array (T,)
        Points to check (supported ones with two or more views).
    max_mm : float or array (T,)
        Largest allowed distance from the prediction, mm.
    R, t, scale
        Poses and pixel scale.
    loo_checked : bool
        Every leave-one-out residual is already known to be within :data:`ANCHOR_RES_PX`.

    Returns
    -------
    w : array (C, T)
    X : array (T, 3)
    ok : bool array (T,)
        Checked points that agree (possibly after dropping a view); True for unchecked ones.
    """
    ok = np.ones(len(X), bool)
    idx = np.flatnonzero(check)
    if len(idx) == 0:
        return w, X, ok
    info = information(X[idx], w[:, idx] > 0, R, t, scale)
    d = mahalanobis(X[idx], Xel[idx], sigma[idx], info)
    # four views (two caddies, each view checked by the other three: depth is over-determined)
    # agreeing closely are evidence enough that the point moved on its own (an eyelid in a
    # blink): only the parameter's distance applies to them
    strong = (w[:, idx] > 0).sum(0) >= min(4, len(w))
    if np.any(strong) and not loo_checked:
        loo = loo_residuals(X[idx], uv[:, idx], w[:, idx], R, t, scale)
        strong &= ~(np.nanmax(np.where(np.isnan(loo), -1.0, loo), axis=0) > ANCHOR_RES_PX)
    with np.errstate(invalid="ignore"):
        lim = np.broadcast_to(max_mm, X.shape[:1])
        bad = ~(((d <= gate) | strong) & (np.linalg.norm(X[idx] - Xel[idx], axis=1) <= lim[idx]))
    if not np.any(bad):
        return w, X, ok
    w = w.copy()
    X = X.copy()
    b = idx[bad]
    C = len(w)
    nb = len(b)
    # every "drop view c" trial of every bad point at once: columns (c, point)
    diag = np.arange(C)
    trial = np.repeat(w[:, b][:, None, :], C, axis=1)                      # (C views, C trials, nb)
    has = trial[diag, diag] > 0                                              # (C trials, nb)
    trial[diag, diag] = 0.0
    trial = trial.reshape(C, C * nb)
    usable = has.reshape(-1) & ((trial > 0).sum(0) >= 2)
    U = np.broadcast_to(uv[:, b][:, None], (C, C, nb, 2)).reshape(C, C * nb, 2)
    Xc, res = triangulate_uv(U, trial, R, t, scale)
    Xe = np.tile(Xel[b], (C, 1))
    dc = mahalanobis(Xc, Xe, np.tile(sigma[b], C), information(Xc, trial > 0, R, t, scale))
    with np.errstate(invalid="ignore"):
        good = usable & (dc <= gate) & (np.linalg.norm(Xc - Xe, axis=1) <= np.tile(lim[b], C)) \
            & ~(np.nanmax(np.where(trial > 0, res, 0.0), axis=0) > ANCHOR_RES_PX)
    score = np.where(good, dc, np.inf).reshape(C, nb)
    best_c = np.argmin(score, axis=0)
    cols = np.arange(nb)
    fixed = np.isfinite(score[best_c, cols])
    w[best_c[fixed], b[fixed]] = 0.0
    X[b[fixed]] = Xc.reshape(C, nb, 3)[best_c[fixed], cols[fixed]]
    ok[b[~fixed]] = False
    return w, X, ok


def single_sensor(uv: np.ndarray, camera: np.ndarray, R: np.ndarray, t: np.ndarray, target: np.ndarray,
                  threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Single-sensor positions of points seen by one camera.

    Parameters
    ----------
    uv : array (n, 2)
        Normalised observation of each point.
    camera : int array (n,)
        The camera that sees it.
    R, t : arrays (C, 3, 3), (C, 3)
    target : array (n, 3)
        Elastic predictions, mm.
    threshold : float
        Single Sensor Tracking Threshold, mm.

    Returns
    -------
    X : array (n, 3)
        Positions on the rays, mm.
    ok : bool array (n,)
        Within ``threshold`` of the prediction.
    """
    if len(uv) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    X = ray_nearest_points(uv, R[camera], t[camera], target)
    with np.errstate(invalid="ignore"):
        ok = np.linalg.norm(X - target, axis=1) <= threshold
    return X, ok & np.isfinite(X).all(1)
