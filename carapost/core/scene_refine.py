"""Refine static cameras' poses from static scene landmarks.

A few landmarks that do not move (bolt heads, cone tops, corners), picked or matched in two
or more views, against a calibration whose poses are roughly right: the poses of all but one
camera and the landmarks' positions are adjusted so that the landmarks reproject onto their
observations, with a Gaussian prior that keeps every camera near its starting pose (few
landmarks do not determine 6 degrees of freedom per camera on their own, and the prior also
fixes the scale). The fixed camera defines the frame.

Used by ``benchmarks/bench_pose2sim.py --static`` to test whether the Pose2Sim demo's
calibration can be corrected from its static scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from carapost.core.camera import Intrinsics, camera_centre, project, rodrigues
from carapost.core.triangulate import triangulate

__all__ = ["SceneRefinement", "refine_poses", "pose_change"]


@dataclass(frozen=True)
class SceneRefinement:
    """Result of :func:`refine_poses`.

    Attributes
    ----------
    R, t : arrays (C, 3, 3), (C, 3)
        Refined world-to-camera poses (mm).
    xyz : array (P, 3)
        Landmarks, mm (NaN where seen by fewer than two views).
    residuals : array (P, C)
        Reprojection error per observation with the refined poses, raw px (NaN: no observation).
    initial_residuals : array (P, C)
        The same with the starting poses (landmarks triangulated with them).
    turned_deg, moved_mm : arrays (C,)
        How far each camera was turned and its centre moved from its starting pose.
    """

    R: np.ndarray
    t: np.ndarray
    xyz: np.ndarray
    residuals: np.ndarray
    initial_residuals: np.ndarray
    turned_deg: np.ndarray
    moved_mm: np.ndarray


def pose_change(R0: np.ndarray, t0: np.ndarray, R1: np.ndarray, t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle (deg) and centre displacement (mm) from poses 0 to 1, each ``(C,)``."""
    cos = (np.trace(R1 @ np.swapaxes(R0, -1, -2), axis1=-2, axis2=-1) - 1.0) / 2.0
    turned = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    moved = np.linalg.norm(camera_centre(R1, t1) - camera_centre(R0, t0), axis=-1)
    return turned, moved


def _residuals_px(xy: np.ndarray, xyz: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray,
                  t: np.ndarray) -> np.ndarray:
    err = np.full(xy.shape[:2], np.nan)
    for c in range(xy.shape[1]):
        err[:, c] = np.linalg.norm(project(xyz, intrinsics[c], R[c], t[c]) - xy[:, c], axis=-1)
    return err


def refine_poses(xy: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, *,
                 fixed: int | Sequence[int] = 0, rotation_sigma_deg: float = 1.0, centre_sigma_mm: float = 50.0,
                 loss: str = "soft_l1", f_scale_px: float = 2.0) -> SceneRefinement:
    """Adjust the poses of static cameras to static landmarks.

    Parameters
    ----------
    xy : array (P, C, 2)
        Raw-pixel observations of P landmarks in C cameras, NaN where not seen; landmarks seen
        by fewer than two cameras are ignored.
    intrinsics : sequence of C Intrinsics
        Kept as they are.
    R, t : arrays (C, 3, 3), (C, 3)
        Starting world-to-camera poses (mm).
    fixed : int or sequence of int
        The camera(s) whose poses are kept (one defines the frame; more when their relative
        poses are trusted).
    rotation_sigma_deg, centre_sigma_mm : float
        Standard deviations of the prior on each other camera's rotation and centre change: a
        change of one sigma costs as much as a 1 px residual.
    loss, f_scale_px : str, float
        Robust loss of :func:`scipy.optimize.least_squares` on the reprojection residuals.

    Returns
    -------
    SceneRefinement

    Raises
    ------
    ValueError
        Mismatched shapes, or no landmark seen by two cameras.
    """
    xy = np.asarray(xy, float)
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    P, C = xy.shape[:2]
    if xy.shape != (P, C, 2) or R.shape != (C, 3, 3) or t.shape != (C, 3) or len(intrinsics) != C:
        raise ValueError(f"refine_poses: xy {xy.shape}, R {R.shape}, t {t.shape} and {len(intrinsics)} "
                         "intrinsics do not describe the same cameras")
    fixed_set = {int(fixed)} if np.isscalar(fixed) else {int(c) for c in fixed}
    if not fixed_set or not all(0 <= c < C for c in fixed_set):
        raise ValueError(f"refine_poses: fixed cameras {sorted(fixed_set)} are not among the {C} cameras")
    seen = np.isfinite(xy).all(-1)
    use = seen.sum(1) >= 2
    if not use.any():
        raise ValueError("refine_poses: no landmark is seen by two cameras")
    xyz0 = np.full((P, 3), np.nan)
    xyz0[use] = triangulate(xy[use], intrinsics, R, t).xyz
    free = [c for c in range(C) if c not in fixed_set]
    centres0 = camera_centre(R, t)
    sig_r = np.radians(rotation_sigma_deg)
    obs_p, obs_c = np.nonzero(seen & use[:, None])
    target = xy[obs_p, obs_c]
    pts = np.flatnonzero(use)
    index = np.full(P, -1)
    index[pts] = np.arange(len(pts))

    def unpack(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Rn, tn = R.copy(), t.copy()
        for k, c in enumerate(free):
            w, dc = v[6 * k:6 * k + 3], v[6 * k + 3:6 * k + 6]
            Rn[c] = rodrigues(w) @ R[c]
            tn[c] = -Rn[c] @ (centres0[c] + dc)
        X = v[6 * len(free):].reshape(-1, 3)
        return Rn, tn, X

    def fun(v: np.ndarray) -> np.ndarray:
        Rn, tn, X = unpack(v)
        res = np.empty((len(obs_p), 2))
        for c in range(C):
            sel = obs_c == c
            if sel.any():
                res[sel] = project(X[index[obs_p[sel]]], intrinsics[c], Rn[c], tn[c]) - target[sel]
        prior = np.concatenate([np.r_[v[6 * k:6 * k + 3] / sig_r, v[6 * k + 3:6 * k + 6] / centre_sigma_mm]
                                for k in range(len(free))]) if free else np.zeros(0)
        return np.concatenate([res.ravel(), prior])

    n_res = 2 * len(obs_p)

    def robust(v: np.ndarray) -> np.ndarray:
        r = fun(v)
        a = r[:n_res] / f_scale_px
        if loss == "soft_l1":
            a = np.sign(a) * np.sqrt(2.0 * (np.sqrt(1.0 + a * a) - 1.0))
        elif loss == "cauchy":
            a = np.sign(a) * np.sqrt(np.log1p(a * a))
        elif loss != "linear":
            raise ValueError(f"refine_poses: loss must be linear, soft_l1 or cauchy, got {loss!r}")
        return np.concatenate([a * f_scale_px, r[n_res:]])

    v0 = np.concatenate([np.zeros(6 * len(free)), xyz0[pts].ravel()])
    sol = least_squares(robust, v0, method="trf", x_scale="jac", max_nfev=200)
    Rn, tn, X = unpack(sol.x)
    xyz = np.full((P, 3), np.nan)
    xyz[pts] = X
    turned, moved = pose_change(R, t, Rn, tn)
    return SceneRefinement(R=Rn, t=tn, xyz=xyz, residuals=_residuals_px(xy, xyz, intrinsics, Rn, tn),
                           initial_residuals=_residuals_px(xy, xyz0, intrinsics, R, t),
                           turned_deg=turned, moved_mm=moved)
