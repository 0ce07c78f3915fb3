"""Stabilization: remove the head's rigid motion so only facial deformation is left.

Every frame ``f`` gets a rigid transform ``T_f(X) = R_f X + t_f`` mapping it onto the *base
frame* ``b`` (``T_b`` is the identity); the stabilized data are ``T_f`` applied to all points.
The raw data are never changed.

* **Manual** (:func:`stabilize_manual`, "Stabilize Data [Manual]"): ``T_f`` is the least-squares
  rigid transform (Kabsch) mapping three or more user-selected, gap-free points of frame ``f``
  onto the same points of the base frame.
* **Assisted** (:func:`stabilize_assisted`, "Stabilize Data [Assisted]"): the selection is
  extended with further stable points — the candidates whose distances to the selected points
  vary least over the range (median over the selected points, so one badly chosen point does
  not spoil the start) — which give the starting transforms; then alternately (1) choose in
  each frame the ``Stable Points Percent`` most stable of the candidate points (the face points, and the brim points if asked; a point's
  instability is its weighted squared distance from its base-frame position and from its
  previous frame's position, both after stabilization), and (2) update every ``T_f`` to
  minimise the *stabilization error* over those points. The guide defines that error as a
  weighted sum (``Base Frame Weighting``, ``Inter Frame Weighting``) of

  - the *base frame stabilization error*: the RMS distance between the stable points of each
    frame and the same points in the base frame, and
  - the *inter frame stabilization error*: the RMS distance between the stable points of each
    frame and the same points in the previous frame,

  over the active range. Step (2) is a red-black block Gauss-Seidel sweep: with its
  neighbours fixed, each frame's transform is a weighted Procrustes fit onto the weighted mean
  of its targets (base-frame positions, stabilized previous- and next-frame positions). The
  loop stops after ``Max Processing Iterations`` or when the error stops decreasing; the
  transforms with the lowest error are returned.

Array contract: ``xyz (F, P, 3)`` mm, NaN gaps; transforms ``R (F, 3, 3)``, ``t (F, 3)``;
``F`` counts the frames handed in (the ops pass the active range).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gapfill import distance_spread, weighted_rigid_fit

__all__ = ["StabilizeResult", "stabilize_manual", "stabilize_assisted", "apply_transforms",
           "stabilization_error"]


@dataclass
class StabilizeResult:
    """Output of the stabilizers.

    Attributes
    ----------
    R : array (F, 3, 3)
    t : array (F, 3)
        ``X_stabilized = R X + t`` per frame (NaN where a frame could not be stabilized).
    xyz : array (F, P, 3)
        Stabilized positions of every point, mm.
    used : bool array (F, P)
        Points the transform of each frame was fitted to.
    error : float
        Stabilization error: ``base_weight * base_error + inter_weight * inter_error``, mm.
    base_error, inter_error : float
        RMS base-frame and inter-frame errors over the used points, mm.
    iterations : int
        Optimisation iterations run (0 for manual).
    """

    R: np.ndarray
    t: np.ndarray
    xyz: np.ndarray
    used: np.ndarray
    error: float
    base_error: float
    inter_error: float
    iterations: int = 0


def apply_transforms(xyz: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``R[f] @ xyz[f, p] + t[f]`` for all frames and points: ``(F, P, 3)`` -> ``(F, P, 3)``."""
    return np.einsum("fij,fpj->fpi", R, xyz) + t[:, None, :]


def stabilization_error(stab: np.ndarray, used: np.ndarray, base: int, *, base_weight: float = 1.0,
                        inter_weight: float = 1.0) -> tuple[float, float, float]:
    """The guide's stabilization error of stabilized data.

    Parameters
    ----------
    stab : array (F, P, 3)
        Stabilized positions, mm.
    used : bool array (F, P)
        Points counted in each frame (the stable points).
    base : int
        Base frame (index into ``stab``).

    Returns
    -------
    total, base_error, inter_error : float
        ``base_weight * base_error + inter_weight * inter_error``; the RMS distance of the used
        points from their base-frame positions; the RMS distance of points used in two
        consecutive frames between those frames. NaN where nothing is counted.
    """
    ok = used & np.isfinite(stab).all(-1)
    ref = stab[base]
    okb = ok & np.isfinite(ref).all(-1)[None, :]
    db = np.where(okb, ((stab - ref[None]) ** 2).sum(-1), 0.0)
    base_err = float(np.sqrt(db.sum() / okb.sum())) if okb.any() else float("nan")
    oki = ok[1:] & ok[:-1]
    di = np.where(oki, ((stab[1:] - stab[:-1]) ** 2).sum(-1), 0.0)
    inter_err = float(np.sqrt(di.sum() / oki.sum())) if oki.any() else float("nan")
    tot = base_weight * np.nan_to_num(base_err) + inter_weight * np.nan_to_num(inter_err)
    return float(tot), base_err, inter_err


def _check(xyz: np.ndarray, points: np.ndarray, base: int) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"xyz must have shape (F, P, 3), got {xyz.shape}")
    F, P, _ = xyz.shape
    points = np.unique(np.asarray(points, dtype=np.int64))
    if len(points) < 3:
        raise ValueError(f"stabilization needs at least 3 points, got {len(points)}")
    if points.min() < 0 or points.max() >= P:
        raise ValueError(f"point indices must be within 0..{P - 1}")
    if not 0 <= base < F:
        raise ValueError(f"base frame {base} is outside the {F} frames")
    return xyz, points


def stabilize_manual(xyz: np.ndarray, points: np.ndarray, base: int, *, base_weight: float = 1.0,
                     inter_weight: float = 1.0) -> StabilizeResult:
    """"Stabilize Data [Manual]": map the selected points of every frame onto the base frame.

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm.
    points : int array
        At least three point columns, present in every frame.
    base : int
        Base frame (index into ``xyz``).
    base_weight, inter_weight : float
        Weights of the reported error.

    Returns
    -------
    StabilizeResult
        ``used`` marks the selected points in every frame.

    Raises
    ------
    ValueError
        Fewer than three points, or a selected point missing in some frame (the message
        names the first such frame), or the points are collinear in the base frame.
    """
    xyz, points = _check(xyz, points, base)
    F, P, _ = xyz.shape
    sel = xyz[:, points]
    missing = ~np.isfinite(sel).all(-1)
    if missing.any():
        f, j = np.argwhere(missing)[0]
        raise ValueError(f"Stabilize Data [Manual] needs gap-free points: point column {points[j]} is missing "
                         f"in frame {f} (of the range)")
    if _collinear(sel[base]):
        raise ValueError("the selected points are (nearly) collinear in the base frame")
    w = np.ones(sel.shape[:2])
    R, t = weighted_rigid_fit(sel, np.broadcast_to(sel[base], sel.shape), w)
    R[base], t[base] = np.eye(3), 0.0
    used = np.zeros((F, P), bool)
    used[:, points] = True
    stab = apply_transforms(xyz, R, t)
    tot, be, ie = stabilization_error(stab, used, base, base_weight=base_weight, inter_weight=inter_weight)
    return StabilizeResult(R, t, stab, used, tot, be, ie, 0)


def _collinear(X: np.ndarray) -> bool:
    c = X - X.mean(0)
    s = np.linalg.svd(c, compute_uv=False)
    return bool(s[1] < 1e-6 * max(s[0], 1e-12))


def _select_stable(stab: np.ndarray, avail: np.ndarray, base: int, k: np.ndarray, wb: float,
                   wi: float) -> np.ndarray:
    """The ``k[f]`` candidates of each frame with the lowest instability (see module doc)."""
    F, P, _ = stab.shape
    ref = stab[base]
    cost = np.where(avail, wb * ((stab - ref[None]) ** 2).sum(-1), np.inf)
    if wi > 0:
        prev = np.concatenate([stab[:1], stab[:-1]])
        d = ((stab - prev) ** 2).sum(-1)
        d[0] = 0.0
        d = np.where(np.isfinite(d), d, 0.0)
        cost = cost + np.where(avail, wi * d, 0.0)
    order = np.argsort(cost, axis=1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(P)[None, :].repeat(F, 0), axis=1)
    return avail & (rank < k[:, None])


def stabilize_assisted(xyz: np.ndarray, points: np.ndarray, base: int, *, candidates: np.ndarray | None = None,
                       base_weight: float = 1.0, inter_weight: float = 1.0, stable_fraction: float = 0.25,
                       max_iterations: int = 50, tol: float = 1e-6) -> StabilizeResult:
    """"Stabilize Data [Assisted]": the manual solution refined over the most stable points.

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm.
    points : int array
        The user's selection: at least three point columns present in every frame; they give
        the starting transforms.
    base : int
        Base frame (index into ``xyz``).
    candidates : int array, optional
        Columns that may serve as stable points (default all); the selection is added.
    base_weight, inter_weight : float
        "Base Frame Weighting" and "Inter Frame Weighting" (>= 0, not both 0).
    stable_fraction : float
        "Stable Points Percent" (0..1): share of the candidates present in a frame used as
        its stable points (at least 3).
    max_iterations : int
        "Max Processing Iterations".
    tol : float
        Stop when an iteration lowers the error by less than this (relative).

    Returns
    -------
    StabilizeResult
        ``used`` holds each frame's stable points. Frames with fewer than three available
        candidates keep their manual transform.

    Raises
    ------
    ValueError
        As :func:`stabilize_manual`, and for weights or fractions out of range.
    """
    if base_weight < 0 or inter_weight < 0 or base_weight + inter_weight <= 0:
        raise ValueError("the base and inter frame weightings must be >= 0 and not both 0")
    if not 0 < stable_fraction <= 1:
        raise ValueError(f"stable points percent must be within (0, 1], got {stable_fraction}")
    if max_iterations < 1:
        raise ValueError(f"max processing iterations must be at least 1, got {max_iterations}")
    man = stabilize_manual(xyz, points, base, base_weight=base_weight, inter_weight=inter_weight)
    xyz = np.asarray(xyz, dtype=float)
    F, P, _ = xyz.shape
    cand = np.zeros(P, bool)
    cand[np.arange(P) if candidates is None else np.asarray(candidates, dtype=np.int64)] = True
    cand[np.asarray(points, dtype=np.int64)] = True
    avail = np.isfinite(xyz).all(-1) & cand[None, :] & np.isfinite(xyz[base]).all(-1)[None, :]
    n_av = avail.sum(1)
    k = np.maximum(3, np.ceil(stable_fraction * n_av)).astype(np.int64)
    R, t = man.R.copy(), man.t.copy()
    # start: the candidates that keep their distances to the selection best over the range
    # (median over the selected points, so one badly chosen point does not spoil it)
    spread = distance_spread(xyz, avail)
    score = np.median(spread[:, np.unique(np.asarray(points, dtype=np.int64))], axis=1)
    score[~cand] = np.inf
    k0 = max(3, int(np.ceil(stable_fraction * cand.sum())))
    start = np.zeros(P, bool)
    start[np.argsort(score, kind="stable")[:k0]] = True
    w0 = (avail & start[None, :]).astype(float)
    good = (w0.sum(1) >= 3) & np.isfinite(xyz[base][start]).all()
    good[base] = False
    if good.any():
        Xs = np.where(w0[..., None] > 0, xyz, 0.0)
        Rs, ts = weighted_rigid_fit(Xs[good], np.broadcast_to(np.where(w0[base][:, None] > 0, xyz[base], 0.0),
                                                                (int(good.sum()), P, 3)), w0[good])
        R[good], t[good] = Rs, ts
    stab = apply_transforms(xyz, R, t)
    used = _select_stable(stab, avail, base, k, base_weight, inter_weight)
    best = stabilization_error(stab, used, base, base_weight=base_weight, inter_weight=inter_weight)[0]
    keep = (R.copy(), t.copy(), stab.copy(), used.copy())
    fitted = n_av >= 3
    fitted[base] = False
    parity = np.arange(F) % 2
    Xz = np.where(avail[..., None], xyz, 0.0)
    ref = np.where(avail[base][:, None], xyz[base], 0.0)
    it = 0
    for it in range(1, max_iterations + 1):
        for colour in (0, 1):
            frames = np.flatnonzero(fitted & (parity == colour))
            if not len(frames):
                continue
            u = used[frames]
            num = base_weight * ref[None] * u[..., None]
            den = base_weight * u.astype(float)
            if inter_weight > 0:
                for nb in (frames - 1, frames + 1):
                    inside = (nb >= 0) & (nb < F)
                    nbc = np.clip(nb, 0, F - 1)
                    both = u & used[nbc] & inside[:, None]
                    num = num + inter_weight * np.where(both[..., None], stab[nbc], 0.0)
                    den = den + inter_weight * both
            target = num / np.where(den > 0, den, 1.0)[..., None]
            Rf, tf = weighted_rigid_fit(Xz[frames], target, den)
            R[frames], t[frames] = Rf, tf
            stab[frames] = apply_transforms(xyz[frames], Rf, tf)
        used = _select_stable(stab, avail, base, k, base_weight, inter_weight)
        err = stabilization_error(stab, used, base, base_weight=base_weight, inter_weight=inter_weight)[0]
        improved = best - err
        if err < best:
            best, keep = err, (R.copy(), t.copy(), stab.copy(), used.copy())
        if improved <= tol * max(best, 1e-12):
            break
    R, t, stab, used = keep
    tot, be, ie = stabilization_error(stab, used, base, base_weight=base_weight, inter_weight=inter_weight)
    return StabilizeResult(R, t, stab, used, tot, be, ie, it)
