"""Levenberg-Marquardt bundle adjustment with the Schur complement on the points.

The standard structure of bundle adjustment: every observation involves one camera pose and one
point, so the normal equations have 6x6 camera blocks, 3x3 point blocks and one 6x3 coupling
block per observation. Eliminating the points leaves a small dense system per *group* of
cameras that share points — one group per frame for per-frame poses, one for a shared rig — which
is solved directly; the points follow by back-substitution. Robust losses enter as iteratively
reweighted least squares. Rotations are updated on the manifold, ``R <- exp(d) R``, so the
analytic Jacobian is exact at every linearisation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

from .bundle_jac import pose_point_jacobians
from .camera import Intrinsics, matrix_to_quat, rodrigues

__all__ = ["LMSolution", "solve_lm", "loss_weights", "loss_rho"]


@dataclass(frozen=True)
class LMSolution:
    R: np.ndarray        # (n_cam, 3, 3) free camera rotations
    t: np.ndarray        # (n_cam, 3)
    X: np.ndarray        # (n_pt, 3) free points
    initial_cost: float
    cost: float
    iterations: int
    success: bool
    message: str


def loss_rho(s: np.ndarray, loss: str) -> np.ndarray:
    """scipy's robust loss ``rho(s)`` of squared, scaled residuals ``s``."""
    if loss == "linear":
        return s
    if loss == "huber":
        return np.where(s <= 1, s, 2 * np.sqrt(s) - 1)
    if loss == "soft_l1":
        return 2 * (np.sqrt(1 + s) - 1)
    if loss == "cauchy":
        return np.log1p(s)
    if loss == "arctan":
        return np.arctan(s)
    raise ValueError(f"unknown loss {loss!r}")


def loss_weights(s: np.ndarray, loss: str) -> np.ndarray:
    """IRLS weights ``rho'(s)``."""
    if loss == "linear":
        return np.ones_like(s)
    if loss == "huber":
        return np.where(s <= 1, 1.0, 1.0 / np.sqrt(np.maximum(s, 1e-300)))
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1 + s)
    if loss == "cauchy":
        return 1.0 / (1 + s)
    if loss == "arctan":
        return 1.0 / (1 + s * s)
    raise ValueError(f"unknown loss {loss!r}")


def _group_sum(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of ``values (N, ...)`` into ``n`` bins by ``index (N,)``."""
    if len(index) == 0:
        return np.zeros((n,) + values.shape[1:])
    flat = values.reshape(len(values), -1)
    S = csr_matrix((np.ones(len(index)), (index, np.arange(len(index)))), shape=(n, len(index)))
    return np.asarray(S @ flat).reshape((n,) + values.shape[1:])


def _rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3)."""
    q = matrix_to_quat(R)
    s = np.linalg.norm(q[:, :3], axis=1)
    ang = 2 * np.arctan2(s, q[:, 3])
    scale = np.where(s > 1e-12, ang / np.where(s > 1e-12, s, 1.0), 2.0)
    return q[:, :3] * scale[:, None]


def solve_lm(obs: np.ndarray, cam: np.ndarray, obs_cam: np.ndarray, obs_pt: np.ndarray,
             R_fixed: np.ndarray, t_fixed: np.ndarray, X_fixed: np.ndarray,
             R0: np.ndarray, t0: np.ndarray, X0: np.ndarray, cam_group: np.ndarray, cam_slot: np.ndarray,
             n_slots: int, intrinsics: Sequence[Intrinsics], *, loss: str = "linear", f_scale: float = 1.0,
             pose_prior: float = 0.0, max_iterations: int = 50, ftol: float = 1e-10) -> LMSolution:
    """Minimise the robust reprojection error over free camera poses and free points.

    Parameters
    ----------
    obs : (N, 2) observed raw px; ``cam (N,)`` the camera (intrinsics index) of each observation.
    obs_cam : (N,) free-camera index of each observation or -1 (pose fixed: ``R_fixed/t_fixed``).
    obs_pt : (N,) free-point index or -1 (point fixed: ``X_fixed``).
    R_fixed, t_fixed, X_fixed : (N, 3, 3), (N, 3), (N, 3) per-observation values used where fixed.
    R0, t0 : (n_cam, 3, 3), (n_cam, 3) initial free poses; ``X0 (n_pt, 3)`` initial free points.
    cam_group, cam_slot : (n_cam,) the dense group and slot of each free camera (cameras of one
        group share points); ``n_slots`` slots per group.
    """
    n_cam, n_pt = len(R0), len(X0)
    n_grp = int(cam_group.max()) + 1 if n_cam else 0
    has_c = obs_cam >= 0
    has_p = obs_pt >= 0
    oc_i = np.maximum(obs_cam, 0)
    op_i = np.maximum(obs_pt, 0)

    def per_obs(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Ro = np.where(has_c[:, None, None], R[oc_i] if n_cam else 0.0, R_fixed)
        to = np.where(has_c[:, None], t[oc_i] if n_cam else 0.0, t_fixed)
        Xo = np.where(has_p[:, None], X[op_i] if n_pt else 0.0, X_fixed)
        return Ro, to, Xo

    def cost_of(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[float, np.ndarray, tuple]:
        Ro, to, Xo = per_obs(R, t, X)
        raw, Jc, Jp = pose_point_jacobians(Xo, Ro, to, cam, intrinsics)
        r = raw - obs
        ok = np.isfinite(r).all(1)
        r = np.where(ok[:, None], r, 0.0)
        s = (r * r).sum(1) / f_scale ** 2
        c = 0.5 * f_scale ** 2 * float(np.sum(np.where(ok, loss_rho(s, loss), 0.0)))
        c += 0.5 * (1e6 * float(np.sum(~ok)))  # behind a camera: a large, finite penalty
        prior = np.zeros((n_cam, 6))
        if pose_prior > 0 and n_cam:
            prior[:, :3] = _rotation_log(R @ np.transpose(R0, (0, 2, 1)))
            prior[:, 3:] = t - t0
            c += 0.5 * pose_prior ** 2 * float(np.sum(prior ** 2))
        return c, prior, (r, s, ok, Jc, Jp)

    R, t, X = R0.copy(), t0.copy(), X0.copy()
    cost, prior, lin = cost_of(R, t, X)
    initial_cost = cost
    lam = 1e-3
    message = "maximum iterations reached"
    success = False
    it = 0
    for it in range(1, max_iterations + 1):
        r, s, ok, Jc, Jp = lin
        w = np.where(ok, loss_weights(s, loss), 0.0)
        wJc = Jc * w[:, None, None]
        wJp = Jp * w[:, None, None]
        Hcc = _group_sum(oc_i[has_c], np.einsum("nai,naj->nij", wJc[has_c], Jc[has_c]), n_cam)
        gc = _group_sum(oc_i[has_c], np.einsum("nai,na->ni", wJc[has_c], r[has_c]), n_cam)
        Hpp = _group_sum(op_i[has_p], np.einsum("nai,naj->nij", wJp[has_p], Jp[has_p]), n_pt)
        gp = _group_sum(op_i[has_p], np.einsum("nai,na->ni", wJp[has_p], r[has_p]), n_pt)
        both = has_c & has_p
        Hcp = np.einsum("nai,naj->nij", wJc[both], Jp[both])  # (nb, 6, 3)
        if pose_prior > 0:
            Hcc = Hcc + pose_prior ** 2 * np.eye(6)
            gc = gc + pose_prior ** 2 * prior
        accepted = False
        while lam <= 1e12:
            step = _solve_damped(Hcc, gc, Hpp, gp, Hcp, oc_i[both], op_i[both], cam_group, cam_slot, n_grp,
                                 n_slots, lam)
            if step is None:
                lam *= 10
                continue
            dc, dp = step
            Rn = rodrigues(dc[:, :3]) @ R if n_cam else R
            Xn = X + dp
            new_cost, new_prior, new_lin = cost_of(Rn, t + dc[:, 3:], Xn)
            if new_cost <= cost:
                reduction = cost - new_cost
                R, t, X, prior, lin = Rn, t + dc[:, 3:], Xn, new_prior, new_lin
                old, cost = cost, new_cost
                lam = max(lam / 3, 1e-12)
                accepted = True
                break
            lam *= 4
        if not accepted:
            message = "converged: no step reduces the cost"
            success = True
            break
        if reduction <= ftol * max(old, 1e-300):
            message = "converged: relative cost reduction below ftol"
            success = True
            break
    return LMSolution(R, t, X, initial_cost, cost, it, success, message)


def _solve_damped(Hcc: np.ndarray, gc: np.ndarray, Hpp: np.ndarray, gp: np.ndarray, Hcp: np.ndarray,
                  cam_of: np.ndarray, pt_of: np.ndarray, cam_group: np.ndarray, cam_slot: np.ndarray,
                  n_grp: int, n_slots: int, lam: float) -> tuple[np.ndarray, np.ndarray] | None:
    """One damped Gauss-Newton step by the Schur complement; ``None`` if a block is singular."""
    n_cam, n_pt = len(Hcc), len(Hpp)
    Hpp_d = Hpp + lam * (Hpp * np.eye(3)) + 1e-12 * np.eye(3)
    try:
        Hpp_inv = np.linalg.inv(Hpp_d) if n_pt else Hpp_d
    except np.linalg.LinAlgError:
        return None
    if n_cam == 0:
        return np.zeros((0, 6)), -np.einsum("pij,pj->pi", Hpp_inv, gp)
    T = Hcp @ Hpp_inv[pt_of]  # (nb, 6, 3): Hcp Hpp^-1 per observation
    # Reduced camera system, dense per group: S = Hcc - sum Hcp Hpp^-1 Hpc, b = -gc + sum T gp.
    D = n_slots * 6
    S = np.zeros((n_grp, n_slots, 6, n_slots, 6))
    Hcc_d = Hcc + lam * (Hcc * np.eye(6)) + 1e-12 * np.eye(6)
    S[cam_group, cam_slot, :, cam_slot, :] += Hcc_d
    b = np.zeros((n_grp, n_slots, 6))
    b[cam_group, cam_slot] = -gc
    b_red = _group_sum(cam_of, np.einsum("nij,nj->ni", T, gp[pt_of]), n_cam)
    b[cam_group, cam_slot] += b_red
    # Pairs of observations of the same point couple their cameras.
    order = np.argsort(pt_of, kind="stable")
    pts_sorted = pt_of[order]
    starts = np.flatnonzero(np.r_[True, pts_sorted[1:] != pts_sorted[:-1]])
    counts = np.diff(np.r_[starts, len(order)])
    rank = np.arange(len(order)) - np.repeat(starts, counts)
    max_k = int(counts.max()) if len(counts) else 0
    table = np.full((len(starts), max_k), -1, np.int64)
    table[np.repeat(np.arange(len(starts)), counts), rank] = order
    for a in range(max_k):
        for c in range(max_k):
            sel = (table[:, a] >= 0) & (table[:, c] >= 0)
            ia, ic = table[sel, a], table[sel, c]
            if len(ia) == 0:
                continue
            blk = T[ia] @ np.transpose(Hcp[ic], (0, 2, 1))  # (n, 6, 6)
            ka, kc = cam_of[ia], cam_of[ic]
            ga = cam_group[ka]
            key = (ga * n_slots + cam_slot[ka]) * n_slots + cam_slot[kc]
            summed = _group_sum(key, blk, n_grp * n_slots * n_slots).reshape(n_grp, n_slots, n_slots, 6, 6)
            S -= np.transpose(summed, (0, 1, 3, 2, 4))
    S = S.reshape(n_grp, D, D)
    b = b.reshape(n_grp, D)
    # Slots without a free camera: identity rows, zero step.
    present = np.zeros((n_grp, n_slots), bool)
    present[cam_group, cam_slot] = True
    absent = np.repeat(~present, 6, axis=1)
    S[absent] = 0.0
    S = S + np.einsum("gi,ij->gij", absent.astype(float), np.eye(D))
    try:
        x = np.linalg.solve(S, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(x)):
        return None
    dc = x.reshape(n_grp, n_slots, 6)[cam_group, cam_slot]
    rhs = -gp - _group_sum(pt_of, np.einsum("nji,nj->ni", Hcp, dc[cam_of]), n_pt)
    dp = np.einsum("pij,pj->pi", Hpp_inv, rhs)
    return dc, dp
