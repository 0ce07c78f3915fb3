"""Bundle adjustment: refine camera poses and 3D points against detection centres.

The reference guide's "Bundle Current Frame [Unconstrained]" and "Bundle Sequence
[Unconstrained]": minimise the raw-pixel reprojection error of every observation over the
camera poses (per frame, or one pose per camera shared by all frames) and the free 3D points.
Points marked *fixed* (the calibration brim's dots, whose positions are the brim model in the
brim frame) pin the world frame; a weak prior on every pose keeps a camera that sees neither
brim nor enough face points from drifting.

The Jacobian is analytic (:mod:`.bundle_jac`: two rows per observation, 6 pose and 3 point
columns, chained through the XCP radial model). The default solver is Levenberg-Marquardt with
the Schur complement on the points (:mod:`.bundle_lm`); ``solver="scipy"`` hands the same
sparse Jacobian to ``scipy.optimize.least_squares`` (trf with LSMR), and ``jac="2-point"``
with it uses scipy's finite differences on the same sparsity pattern (both kept for the benchmark).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from .bundle_lm import loss_rho, solve_lm
from .bundle_scipy import BundleProblem, solve_scipy
from .camera import Intrinsics, project
from .triangulate import triangulate

__all__ = ["BundleResult", "bundle_adjust", "reprojection_errors"]


@dataclass(frozen=True)
class BundleResult:
    """Result of :func:`bundle_adjust`.

    Attributes
    ----------
    R : array (F, C, 3, 3)
    t : array (F, C, 3)
        Refined world-to-camera poses (unchanged where a camera had no observations).
    xyz : array (F, P, 3)
        Refined points, mm (fixed points unchanged; points with fewer than two views unchanged).
    residuals : array (F, P, C)
        Reprojection errors after the adjustment, raw px (NaN where unobserved).
    rms_per_camera : array (C,)
        RMS reprojection error per camera, px.
    initial_cost, final_cost : float
        ``0.5 * sum(rho(r^2))`` before and after (scipy's cost, robust loss applied).
    nfev : int
    success : bool
    message : str
    """

    R: np.ndarray
    t: np.ndarray
    xyz: np.ndarray
    residuals: np.ndarray
    rms_per_camera: np.ndarray
    initial_cost: float
    final_cost: float
    nfev: int
    success: bool
    message: str


def reprojection_errors(obs_xy: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                        xyz: np.ndarray) -> np.ndarray:
    """Reprojection error ``(F, P, C)`` in raw px of observations ``obs_xy (F, P, C, 2)``."""
    out = np.full(obs_xy.shape[:3], np.nan)
    for c, intr in enumerate(intrinsics):
        proj = project(xyz, intr, R[:, None, c], t[:, None, c])
        out[..., c] = np.hypot(*(proj - obs_xy[..., c, :]).transpose(2, 0, 1))
    return out


def bundle_adjust(obs_xy: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                  xyz: np.ndarray, *, fixed_points: np.ndarray | None = None, shared_cameras: bool = False,
                  fix_cameras: np.ndarray | None = None, loss: str = "linear", f_scale: float = 1.0,
                  max_iterations: int = 50, solver: str = "lm", jac: str = "analytic", pose_prior: float = 1e-3,
                  ftol: float = 1e-10, xtol: float = 1e-10) -> BundleResult:
    """Refine camera poses and points to minimise the reprojection error.

    Parameters
    ----------
    obs_xy : array (F, P, C, 2)
        Observed detection centres, raw px; NaN where a point has no observation.
    intrinsics : sequence of C Intrinsics
        Fixed camera intrinsics.
    R, t : arrays (F, C, 3, 3), (F, C, 3)
        Initial world-to-camera poses per frame (a camera with observations must have one).
    xyz : array (F, P, 3)
        Initial points, mm. Free points without an initial position are triangulated first.
    fixed_points : bool array (P,), optional
        Points whose positions are held fixed (the brim's dots): they pin the world frame.
    shared_cameras : bool
        One pose per camera for all frames (a rigid, static rig) instead of per-frame poses.
    fix_cameras : bool array (C,), optional
        Cameras whose poses are not adjusted.
    loss, f_scale : str, float
        Robust loss (``"linear"``, ``"huber"``, ``"soft_l1"``, ``"cauchy"``, ``"arctan"``, as in
        scipy) and its scale in px.
    max_iterations : int
        Iterations of the LM solver (function evaluations for scipy).
    solver : {"lm", "scipy"}
        Schur-complement Levenberg-Marquardt (default) or ``scipy.optimize.least_squares``.
    jac : {"analytic", "2-point"}
        With ``solver="scipy"``: the analytic sparse Jacobian or scipy's finite differences.
    pose_prior : float
        Weight (px per radian / per mm) of a prior keeping each pose near its start; resolves
        poses the observations leave undetermined without noticeably biasing the others.

    Returns
    -------
    BundleResult

    Raises
    ------
    ValueError
        On inconsistent shapes, unknown options, or a camera with observations but no pose.
    """
    obs_xy = np.asarray(obs_xy, dtype=float)
    if obs_xy.ndim != 4 or obs_xy.shape[-1] != 2:
        raise ValueError(f"observations must have shape (F, P, C, 2), got {obs_xy.shape}")
    F, P, C = obs_xy.shape[:3]
    if len(intrinsics) != C:
        raise ValueError(f"{len(intrinsics)} intrinsics for {C} cameras")
    R = np.array(R, dtype=float)
    t = np.array(t, dtype=float)
    xyz = np.array(xyz, dtype=float)
    if R.shape != (F, C, 3, 3) or t.shape != (F, C, 3) or xyz.shape != (F, P, 3):
        raise ValueError(f"poses/points have shapes {R.shape}, {t.shape}, {xyz.shape}; expected "
                         f"({F}, {C}, 3, 3), ({F}, {C}, 3), ({F}, {P}, 3)")
    loss_rho(np.zeros(1), loss)  # validates the name
    if solver not in ("lm", "scipy"):
        raise ValueError(f"solver must be 'lm' or 'scipy', got {solver!r}")
    if jac not in ("analytic", "2-point"):
        raise ValueError(f"jac must be 'analytic' or '2-point', got {jac!r}")
    fixed = np.zeros(P, bool) if fixed_points is None else np.asarray(fixed_points, bool)
    fixc = np.zeros(C, bool) if fix_cameras is None else np.asarray(fix_cameras, bool)

    seen = np.isfinite(obs_xy).all(-1)
    cam_needed = seen.any(axis=1)
    bad = cam_needed & ~np.isfinite(R).all((-1, -2)) | cam_needed & ~np.isfinite(t).all(-1)
    if np.any(bad):
        f, c = np.argwhere(bad)[0]
        raise ValueError(f"camera {c} has observations in frame {f} but no initial pose")
    # Free points without a starting position: triangulate them with the initial poses.
    need = ~fixed[None, :] & ~np.isfinite(xyz).all(-1) & (seen.sum(-1) >= 2)
    if np.any(need):
        fr = np.flatnonzero(need.any(axis=1))
        tri = triangulate(obs_xy[fr], intrinsics, R[fr][:, None], t[fr][:, None])
        xyz[fr] = np.where(need[fr][..., None], tri.xyz, xyz[fr])

    prob = BundleProblem(obs_xy, intrinsics, R, t, xyz, fixed, shared_cameras, fixc, pose_prior)
    if prob.n_params == 0 or len(prob.of) == 0:
        res = reprojection_errors(obs_xy, intrinsics, R, t, xyz)
        return BundleResult(R, t, xyz, res, _rms(res), 0.0, 0.0, 0, True, "nothing to adjust")
    if solver == "scipy":
        x, cost, nfev, success, message = solve_scipy(prob, jac=jac, loss=loss, f_scale=f_scale,
                                                      max_nfev=max_iterations, ftol=ftol, xtol=xtol)
        initial_cost = float(0.5 * np.sum(_rho(prob.residuals(prob.x0()), loss, f_scale)))
        Rn, tn, xyzn = prob.finish(x)
    else:
        Rn, tn, xyzn, initial_cost, cost, nfev, success, message = _run_lm(prob, loss, f_scale, pose_prior,
                                                                           max_iterations, ftol)
    res = reprojection_errors(obs_xy, intrinsics, Rn, tn, xyzn)
    return BundleResult(Rn, tn, xyzn, res, _rms(res), initial_cost, cost, nfev, success, message)


def _run_lm(prob: BundleProblem, loss: str, f_scale: float, pose_prior: float, max_iterations: int,
            ftol: float) -> tuple:
    """Map the problem's bookkeeping onto :func:`solve_lm` and back."""
    fc = prob.cam_fc
    R0 = prob.R0[fc[:, 0], fc[:, 1]]
    t0 = prob.t0[fc[:, 0], fc[:, 1]]
    X0 = prob.xyz0[prob.pt_fp[:, 0], prob.pt_fp[:, 1]]
    if prob.shared:
        group = np.zeros(len(fc), np.int64)
    else:
        _, group = np.unique(fc[:, 0], return_inverse=True)
    sol = solve_lm(prob.obs, prob.oc, prob.obs_cam, prob.obs_pt,
                   prob.R0[prob.of, prob.oc], prob.t0[prob.of, prob.oc], prob.xyz0[prob.of, prob.op],
                   R0, t0, X0, group.astype(np.int64), fc[:, 1].astype(np.int64), len(prob.intr), prob.intr,
                   loss=loss, f_scale=f_scale, pose_prior=pose_prior, max_iterations=max_iterations, ftol=ftol)
    R, t, xyz = prob.R0.copy(), prob.t0.copy(), prob.xyz0.copy()
    if prob.shared:
        R[:, fc[:, 1]] = sol.R[None]
        t[:, fc[:, 1]] = sol.t[None]
    elif len(fc):
        R[fc[:, 0], fc[:, 1]] = sol.R
        t[fc[:, 0], fc[:, 1]] = sol.t
    xyz[prob.pt_fp[:, 0], prob.pt_fp[:, 1]] = sol.X
    return R, t, xyz, sol.initial_cost, sol.cost, sol.iterations, sol.success, sol.message


def _rms(res: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        sq = np.where(np.isfinite(res), res ** 2, 0.0).sum(axis=(0, 1))
        n = np.isfinite(res).sum(axis=(0, 1))
        return np.where(n > 0, np.sqrt(sq / np.maximum(n, 1)), np.nan)


def _rho(r: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """Robust loss of residuals ``r`` in px, as scipy's cost sums it."""
    return loss_rho((r / f_scale) ** 2, loss) * f_scale ** 2
