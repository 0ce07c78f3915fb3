"""Step 2 of the brim solve: attach detections to the projected brim dots, re-estimate the pose.

Matching is by mutual nearest neighbours with a ratio test (:func:`match_projections`); the
pose is re-estimated by least trimmed squares with an outlier threshold from the robust noise
level (:func:`attach_dots`). Pure functions on arrays; raw pixels, mm.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .camera import Intrinsics, normalized_rays, project
from .pose import refine_pose, reprojection_px

__all__ = ["Attachment", "match_projections", "attach_dots"]

#: The noise level of a camera's attachments starts from the ``_Q`` quantile of their
#: residual magnitudes (robust to up to 70% of attachments being wrong): for isotropic
#: Gaussian noise of ``sigma`` px per axis that quantile is ``_RAYLEIGH_Q * sigma``.
_Q = 0.3
_RAYLEIGH_Q = float(np.sqrt(-2 * np.log(1 - _Q)))


class Attachment(NamedTuple):
    """Result of :func:`attach_dots` for one camera."""

    R: np.ndarray                             #: (3, 3) refined world-to-camera rotation
    t: np.ndarray                             #: (3,) translation, mm
    att: np.ndarray                           #: (B,) detection index per dot, -1 none
    rms: float                                #: RMS reprojection error of the attached dots, px
    dropped: list[tuple[int, int, float]]     #: user correspondences overruled: (dot, detection, px)

    @property
    def n(self) -> int:
        """Number of attached dots."""
        return int((self.att >= 0).sum())


def match_projections(proj: np.ndarray, det: np.ndarray, *, radius: float, ratio: float,
                      banned: np.ndarray | None = None) -> np.ndarray:
    """Attach detections to projected dots: mutual nearest neighbours with a ratio test.

    Parameters
    ----------
    proj : array (B, 2)
        Projected dots, raw px (NaN: not projected).
    det : array (n, 2)
        Detections, raw px (NaN rows ignored).
    radius : float
        Largest distance, px.
    ratio : float
        The nearest detection must be closer than ``ratio`` times the second nearest.
    banned : bool array (B, n), optional
        Pairs that may not be attached.

    Returns
    -------
    int array (B,)
        Detection index per dot, -1 where none is unambiguous.
    """
    B, n = len(proj), len(det)
    out = np.full(B, -1, np.int64)
    if n == 0 or B == 0:
        return out
    D = np.hypot(proj[:, None, 0] - det[None, :, 0], proj[:, None, 1] - det[None, :, 1])
    D = np.where(np.isfinite(D), D, np.inf)
    if banned is not None:
        D = np.where(banned, np.inf, D)
    rows = np.arange(B)
    j1 = np.argmin(D, axis=1)
    e1 = D[rows, j1]
    if n > 1:
        e2 = np.partition(D, 1, axis=1)[:, 1]
    else:
        e2 = np.full(B, np.inf)
    nearest_dot = np.argmin(D, axis=0)
    ok = (e1 <= radius) & (nearest_dot[j1] == rows) & (e1 <= ratio * e2)
    out[ok] = j1[ok]
    return out


def attach_dots(xyz: np.ndarray, det: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray,
                forced: dict[int, int], *, radius: float, ratio: float, min_outlier_px: float,
                max_iterations: int) -> Attachment:
    """Attach detections to the brim dots of one camera: match, re-estimate, until stable.

    Parameters
    ----------
    xyz : array (B, 3)
        Brim dots, mm.
    det : array (n, 2)
        Detections, raw px.
    intr : Intrinsics
    R, t : arrays (3, 3), (3,)
        Starting pose.
    forced : dict ``{dot: detection}``
        The user's correspondences: always attached, unless at least four other attached
        dots pin the pose and the correspondence's error exceeds three times the outlier
        threshold (then it is overruled and stays out).
    radius, ratio : float
        Matching radius (px) and ratio test of :func:`match_projections`.
    min_outlier_px : float
        Floor of the outlier threshold ``4.5 sigma`` (capped at ``radius / 2``).
    max_iterations : int
        Rounds of matching and re-estimation.

    Returns
    -------
    Attachment
        Outliers are dropped for the current round only (an early, rough pose may wrongly
        reject a good pair); the loop ends when the attachments stop changing.
    """
    B, n = len(xyz), len(det)
    uv = normalized_rays(det, intr)[:, :2] if n else np.zeros((0, 2))
    banned = np.zeros((B, n), bool)
    forced = dict(forced)
    dropped: list[tuple[int, int, float]] = []
    att = np.full(B, -1, np.int64)
    for _ in range(max_iterations):
        fb = np.array(list(forced), np.int64)
        fd = np.array([forced[b] for b in fb], np.int64)
        ban = banned.copy()
        ban[fb, :] = True
        ban[:, fd] = True
        new = match_projections(project(xyz, intr, R, t), det, radius=radius, ratio=ratio, banned=ban)
        new[fb] = fd
        is_forced = np.zeros(B, bool)
        is_forced[fb] = True
        # user correspondences are only questioned once enough other dots pin the pose
        protect = int(((new >= 0) & ~is_forced).sum()) < 4
        fit = _robust_refit(xyz, det, uv, intr, R, t, new, is_forced if protect else np.zeros(B, bool),
                            min_outlier_px, radius / 2)
        if fit is not None:
            R, t, err, thr = fit
            # a user correspondence needs a clearly larger error to be overruled
            bad = (new >= 0) & (err > np.where(is_forced, max(3 * thr, 2 * min_outlier_px), thr))
            bad &= ~(is_forced & protect)
            for b in np.flatnonzero(bad & is_forced):  # an overruled click stays out
                banned[b, new[b]] = True
                dropped.append((int(b), int(new[b]), float(err[b])))
                del forced[int(b)]
            if bad.any():
                new[bad] = -1
                if (new >= 0).sum() >= 4:
                    m = new >= 0
                    R, t = refine_pose(xyz[m], uv[new[m]], R, t)
        if np.array_equal(new, att):
            break
        att = new
    m = att >= 0
    rms = float(np.sqrt(np.mean(reprojection_px(xyz[m], det[att[m]], intr, R, t) ** 2))) if m.any() else np.inf
    return Attachment(R, t, att, rms, dropped)


def _robust_refit(xyz: np.ndarray, det: np.ndarray, uv: np.ndarray, intr: Intrinsics, R: np.ndarray,
                  t: np.ndarray, pairs: np.ndarray, keep: np.ndarray, min_outlier_px: float,
                  max_outlier_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Pose from the attached pairs ``pairs (B,)`` by least trimmed squares (LTS).

    Concentration steps refit on the half of the pairs (plus ``keep``) with the smallest
    errors until that half stops changing (from two starts: the given pose and the fit to
    every pair). The noise level ``sigma`` starts from a low quantile of the errors; then the
    pose is refitted on the pairs within ``thr = max(min_outlier_px, 4.5 sigma)`` (at most
    ``max_outlier_px``) and ``sigma`` re-estimated from their residuals, three times. Returns ``R, t, err (B,) px, thr`` (``err``
    0 for unattached dots), or None with fewer than 4 pairs.
    """
    idx = np.flatnonzero(pairs >= 0)
    if len(idx) < 4:
        return None
    h = max(4, int(np.ceil(0.5 * len(idx))))

    def concentrate(R: np.ndarray, t: np.ndarray, sel: np.ndarray | None) -> tuple:
        for _ in range(10):
            e = reprojection_px(xyz[idx], det[pairs[idx]], intr, R, t)
            new_sel = np.union1d(idx[np.argsort(e, kind="stable")[:h]], idx[keep[idx]])
            if sel is not None and np.array_equal(new_sel, sel):
                break
            sel = new_sel
            R, t = refine_pose(xyz[sel], uv[pairs[sel]], R, t)
        e = reprojection_px(xyz[idx], det[pairs[idx]], intr, R, t)
        return float(np.sum(np.sort(e)[:h] ** 2)), R, t

    # two starts: the incoming pose (unbiased by new pairs) and the fit to every pair
    starts = [concentrate(R, t, None), concentrate(*refine_pose(xyz[idx], uv[pairs[idx]], R, t), None)]
    _, R, t = min(starts, key=lambda s: s[0])
    e = reprojection_px(xyz[idx], det[pairs[idx]], intr, R, t)
    sigma = float(np.quantile(e, _Q)) / _RAYLEIGH_Q  # biased low by the trimmed fit: start only
    hi = max(max_outlier_px, min_outlier_px)
    for _ in range(3):
        thr = min(max(min_outlier_px, 4.5 * sigma), hi)
        ok = (e <= thr) | keep[idx]
        inl = idx[ok]
        if len(inl) < 4:
            break
        R, t = refine_pose(xyz[inl], uv[pairs[inl]], R, t)
        e = reprojection_px(xyz[idx], det[pairs[idx]], intr, R, t)
        # per-axis noise from the inliers' residuals: sum |e|^2 = (2 n - 6) sigma^2
        sigma = float(np.sqrt(np.sum(e[ok] ** 2) / max(2 * len(inl) - 6, 1)))
    thr = min(max(min_outlier_px, 4.5 * sigma), hi)
    err = np.zeros(len(xyz))
    err[idx] = e
    return R, t, err, thr
