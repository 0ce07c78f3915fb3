"""Bundle adjustment through ``scipy.optimize.least_squares`` (trf with LSMR).

Kept alongside the Schur-complement solver (:mod:`.bundle_lm`, the default) for comparison: the
same problem with our analytic sparse Jacobian or with scipy's finite differences on the same
sparsity pattern (the common approach), as measured in ``benchmarks/bench_bundle.py``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix

from .bundle_jac import project_observations, raw_jacobian, so3_left_jacobian
from .camera import Intrinsics, _cross_matrix, rodrigues

__all__ = ["BundleProblem", "solve_scipy"]


class BundleProblem:
    """One bundle problem: which observations, poses and points take part, and the flat
    parameter vector, residuals and analytic sparse Jacobian scipy works on."""

    def __init__(self, obs_xy: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                 xyz: np.ndarray, fixed_points: np.ndarray, shared_cameras: bool, fix_cameras: np.ndarray,
                 pose_prior: float):
        F, P, C = obs_xy.shape[:3]
        self.intr = list(intrinsics)
        self.shared = shared_cameras
        self.R0, self.t0, self.xyz0 = R, t, xyz
        valid = np.isfinite(obs_xy).all(-1)
        has_pos = np.isfinite(xyz).all(-1)
        fixed = np.broadcast_to(fixed_points[None, :], (F, P)) & has_pos
        n_views = valid.sum(-1)
        free_pt = (~fixed) & (n_views >= 2) & has_pos
        use_obs = valid & (fixed | free_pt)[..., None]
        # Cameras with observations become parameters (per frame or shared).
        cam_used = use_obs.any(axis=1)  # (F, C)
        if shared_cameras:
            cam_used = np.broadcast_to(cam_used.any(axis=0), (F, C))
        cam_used = cam_used & ~fix_cameras[None, :]
        if shared_cameras:
            self.cam_param = np.full(C, -1, np.int64)
            used = np.flatnonzero(cam_used[0])
            self.cam_param[used] = np.arange(len(used))
            cam_index = np.broadcast_to(self.cam_param[None, :], (F, C))
            self.n_cam = len(used)
            self.cam_fc = np.stack([np.zeros(len(used), np.int64), used], 1)
        else:
            cam_index = np.full((F, C), -1, np.int64)
            fc = np.argwhere(cam_used)
            cam_index[fc[:, 0], fc[:, 1]] = np.arange(len(fc))
            self.n_cam = len(fc)
            self.cam_fc = fc
        self.cam_index = cam_index
        pt_index = np.full((F, P), -1, np.int64)
        fp = np.argwhere(free_pt)
        pt_index[fp[:, 0], fp[:, 1]] = np.arange(len(fp))
        self.pt_fp = fp
        self.pt_index = pt_index
        o = np.argwhere(use_obs)  # (N, 3): f, p, c
        self.of, self.op, self.oc = o[:, 0], o[:, 1], o[:, 2]
        self.obs = obs_xy[self.of, self.op, self.oc].astype(float)
        self.obs_cam = cam_index[self.of, self.oc]
        self.obs_pt = pt_index[self.of, self.op]
        self.pose_prior = pose_prior
        self.n_params = 6 * self.n_cam + 3 * len(fp)
        self.n_res = 2 * len(self.of) + (6 * self.n_cam if pose_prior > 0 else 0)

    # ------------------------------------------------------------------ parameter mapping
    def x0(self) -> np.ndarray:
        x = np.zeros(self.n_params)
        x[6 * self.n_cam:] = self.xyz0[self.pt_fp[:, 0], self.pt_fp[:, 1]].ravel()
        return x

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-observation R (N, 3, 3), t (N, 3) and X (N, 3) for parameters ``x``."""
        cam = x[:6 * self.n_cam].reshape(-1, 6)
        Rc = rodrigues(cam[:, :3]) @ self.R0[self.cam_fc[:, 0], self.cam_fc[:, 1]]
        tc = self.t0[self.cam_fc[:, 0], self.cam_fc[:, 1]] + cam[:, 3:]
        pts = x[6 * self.n_cam:].reshape(-1, 3)
        ci, pi = self.obs_cam, self.obs_pt
        R = np.where((ci >= 0)[:, None, None], Rc[np.maximum(ci, 0)] if len(Rc) else 0.0,
                     self.R0[self.of, self.oc])
        t = np.where((ci >= 0)[:, None], tc[np.maximum(ci, 0)] if len(tc) else 0.0, self.t0[self.of, self.oc])
        X = np.where((pi >= 0)[:, None], pts[np.maximum(pi, 0)] if len(pts) else 0.0, self.xyz0[self.of, self.op])
        return R, t, X

    def finish(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Full pose and point arrays for parameters ``x``."""
        R, t, xyz = self.R0.copy(), self.t0.copy(), self.xyz0.copy()
        cam = x[:6 * self.n_cam].reshape(-1, 6)
        if self.n_cam:
            Rc = rodrigues(cam[:, :3]) @ self.R0[self.cam_fc[:, 0], self.cam_fc[:, 1]]
            tc = self.t0[self.cam_fc[:, 0], self.cam_fc[:, 1]] + cam[:, 3:]
            if self.shared:  # one pose for every frame
                R[:, self.cam_fc[:, 1]] = Rc[None]
                t[:, self.cam_fc[:, 1]] = tc[None]
            else:
                R[self.cam_fc[:, 0], self.cam_fc[:, 1]] = Rc
                t[self.cam_fc[:, 0], self.cam_fc[:, 1]] = tc
        xyz[self.pt_fp[:, 0], self.pt_fp[:, 1]] = x[6 * self.n_cam:].reshape(-1, 3)
        return R, t, xyz

    # ------------------------------------------------------------------ residuals and Jacobian
    def _project(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per observation: R (N, 3, 3), R X (N, 3), t (N, 3) and the raw projection (N, 2)."""
        R, t, X = self.unpack(x)
        RX = np.einsum("nij,nj->ni", R, X)
        return R, RX, t, project_observations(X, R, t, self.oc, self.intr)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        raw = self._project(x)[3]
        r = (raw - self.obs).ravel()
        r = np.where(np.isfinite(r), r, 1e3)  # behind a camera: a large, finite penalty
        if self.pose_prior > 0:
            r = np.concatenate([r, self.pose_prior * x[:6 * self.n_cam]])
        return r

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        R, RX, t, raw = self._project(x)
        N = len(self.of)
        Jraw = raw_jacobian(RX + t, raw, self.oc, self.intr)  # (N, 2, 3): d raw / d Xc
        rows, cols, vals = [], [], []
        base = 2 * np.arange(N)
        ci, pi = self.obs_cam, self.obs_pt
        cam_obs = np.flatnonzero(ci >= 0)
        if len(cam_obs):
            # Xc = exp(d) R0 X + t0 + dt: d Xc / d d = -[R X]x J_l(d), d Xc / d dt = I
            delta = x[:6 * self.n_cam].reshape(-1, 6)[ci[cam_obs], :3]
            Jrot = Jraw[cam_obs] @ (-_cross_matrix(RX[cam_obs])) @ so3_left_jacobian(delta)
            Jcam = np.concatenate([Jrot, Jraw[cam_obs]], axis=2)  # (n, 2, 6)
            r_idx = base[cam_obs][:, None, None] + np.arange(2)[None, :, None]
            c_idx = 6 * ci[cam_obs][:, None, None] + np.arange(6)[None, None, :]
            rows.append(np.broadcast_to(r_idx, Jcam.shape).ravel())
            cols.append(np.broadcast_to(c_idx, Jcam.shape).ravel())
            vals.append(Jcam.ravel())
        pt_obs = np.flatnonzero(pi >= 0)
        if len(pt_obs):
            Jpt = Jraw[pt_obs] @ R[pt_obs]  # (n, 2, 3)
            r_idx = base[pt_obs][:, None, None] + np.arange(2)[None, :, None]
            c_idx = 6 * self.n_cam + 3 * pi[pt_obs][:, None, None] + np.arange(3)[None, None, :]
            rows.append(np.broadcast_to(r_idx, Jpt.shape).ravel())
            cols.append(np.broadcast_to(c_idx, Jpt.shape).ravel())
            vals.append(Jpt.ravel())
        if self.pose_prior > 0 and self.n_cam:
            k = np.arange(6 * self.n_cam)
            rows.append(2 * N + k)
            cols.append(k)
            vals.append(np.full(len(k), self.pose_prior))
        J = coo_matrix((np.concatenate(vals) if vals else np.zeros(0),
                        (np.concatenate(rows) if rows else np.zeros(0, int),
                         np.concatenate(cols) if cols else np.zeros(0, int))),
                       shape=(self.n_res, self.n_params))
        return J.tocsr()

    def sparsity(self) -> csr_matrix:
        """The Jacobian's non-zero pattern (for the finite-difference comparison)."""
        J = self.jacobian(self.x0())
        J.data[:] = 1.0
        return J



def solve_scipy(prob: "BundleProblem", *, jac: str, loss: str, f_scale: float, max_nfev: int | None,
                ftol: float, xtol: float) -> tuple[np.ndarray, float, int, bool, str]:
    """Run least_squares; returns ``(x, cost, nfev, success, message)``."""
    kw = dict(method="trf", loss=loss, f_scale=f_scale, x_scale="jac", tr_solver="lsmr",
              ftol=ftol, xtol=xtol, gtol=1e-12, max_nfev=max_nfev)
    if jac == "analytic":
        sol = least_squares(prob.residuals, prob.x0(), jac=prob.jacobian, **kw)
    else:
        sol = least_squares(prob.residuals, prob.x0(), jac="2-point", jac_sparsity=prob.sparsity(), **kw)
    return sol.x, float(sol.cost), int(sol.nfev), bool(sol.success), str(sol.message)
