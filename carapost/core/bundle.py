"""Bundle adjustment: refine camera poses and 3D points against detection centres.

The reference guide's "Bundle Current Frame [Unconstrained]" and "Bundle Sequence
[Unconstrained]": minimise the raw-pixel reprojection error of every observation over the
camera poses (per frame, or one pose per camera shared by all frames) and the free 3D points.
Points marked *fixed* (the calibration brim's dots, whose positions are the brim model in the
brim frame) pin the world frame; a weak prior on every pose keeps a camera that sees neither
brim nor enough face points from drifting.

The Jacobian is analytic and sparse (two rows per observation: 6 pose columns and 3 point
columns), chained through the XCP radial model, and handed to ``scipy.optimize.least_squares``
(``trf`` with LSMR). ``jac="2-point"`` uses scipy's finite differences on the same sparsity
pattern instead (kept for the benchmark).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix

from .camera import Intrinsics, _cross_matrix, project, rodrigues
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


def _distortion_jacobian(raw: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Jacobian ``d corrected / d raw`` (N, 2, 2) of the radial correction at raw points (N, 2)."""
    c = intr.centre
    a = intr.aspect
    dx = raw[:, 0] - c[0]
    dy = raw[:, 1] - c[1]
    r2 = dx * dx + (a * dy) ** 2
    k1, k2, k3 = intr.radial
    s = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    ds = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # ds / d(r^2)
    J = np.empty((len(raw), 2, 2))
    # corrected = (c_x + s dx, c_y + s dy) with r^2 = dx^2 + a^2 dy^2 (see core/camera.py)
    J[:, 0, 0] = s + ds * 2 * dx * dx
    J[:, 0, 1] = ds * 2 * a * a * dy * dx
    J[:, 1, 0] = ds * 2 * dx * dy
    J[:, 1, 1] = s + ds * 2 * a * a * dy * dy
    return J


def _so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l (N, 3, 3)`` of SO(3) at rotation vectors ``phi (N, 3)``."""
    th = np.linalg.norm(phi, axis=-1)[:, None, None]
    K = _cross_matrix(phi)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ths)) / ths ** 2)
    b = np.where(small, 1.0 / 6 - th ** 2 / 120, (ths - np.sin(ths)) / ths ** 3)
    return np.eye(3) + a * K + b * (K @ K)


class _Problem:
    """Index bookkeeping for one bundle problem (observations, pose and point parameters)."""

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
        raw = np.empty((len(X), 2))
        for c, intr in enumerate(self.intr):
            sel = self.oc == c
            if np.any(sel):
                raw[sel] = project(X[sel], intr, R[sel], t[sel])
        return R, RX, t, raw

    def residuals(self, x: np.ndarray) -> np.ndarray:
        raw = self._project(x)[3]
        r = (raw - self.obs).ravel()
        r = np.where(np.isfinite(r), r, 1e3)  # behind a camera: a large, finite penalty
        if self.pose_prior > 0:
            r = np.concatenate([r, self.pose_prior * x[:6 * self.n_cam]])
        return r

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        R, RX, t, raw = self._project(x)
        Xc = RX + t
        N = len(self.of)
        z = Xc[:, 2]
        z = np.where(np.abs(z) > 1e-9, z, 1e-9)
        # d corrected / d Xc
        Jp = np.zeros((N, 2, 3))
        fx = np.array([i.focal_length for i in self.intr])[self.oc]
        sk = np.array([i.skew for i in self.intr])[self.oc]
        fy = fx / np.array([i.aspect for i in self.intr])[self.oc]
        xn, yn = Xc[:, 0] / z, Xc[:, 1] / z
        Jp[:, 0, 0] = fx / z
        Jp[:, 0, 1] = sk / z
        Jp[:, 0, 2] = -(fx * xn + sk * yn) / z
        Jp[:, 1, 1] = fy / z
        Jp[:, 1, 2] = -fy * yn / z
        # d raw / d corrected = inverse of the correction's Jacobian at the projected raw point
        Jd = np.empty((N, 2, 2))
        for c, intr in enumerate(self.intr):
            sel = self.oc == c
            if np.any(sel):
                Jd[sel] = _distortion_jacobian(np.nan_to_num(raw[sel]), intr)
        Jraw = np.linalg.solve(Jd, Jp)  # (N, 2, 3): d raw / d Xc
        rows, cols, vals = [], [], []
        base = 2 * np.arange(N)
        ci, pi = self.obs_cam, self.obs_pt
        cam_obs = np.flatnonzero(ci >= 0)
        if len(cam_obs):
            # Xc = exp(d) R0 X + t0 + dt: d Xc / d d = -[R X]x J_l(d), d Xc / d dt = I
            delta = x[:6 * self.n_cam].reshape(-1, 6)[ci[cam_obs], :3]
            Jrot = Jraw[cam_obs] @ (-_cross_matrix(RX[cam_obs])) @ _so3_left_jacobian(delta)
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


def bundle_adjust(obs_xy: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                  xyz: np.ndarray, *, fixed_points: np.ndarray | None = None, shared_cameras: bool = False,
                  fix_cameras: np.ndarray | None = None, loss: str = "linear", f_scale: float = 1.0,
                  max_nfev: int | None = None, jac: str = "analytic", pose_prior: float = 1e-3,
                  ftol: float = 1e-10, xtol: float = 1e-10) -> BundleResult:
    """Refine camera poses and points to minimise the reprojection error.

    Parameters
    ----------
    obs_xy : array (F, P, C, 2)
        Observed detection centres, raw px; NaN where a point has no observation.
    intrinsics : sequence of C Intrinsics
        Fixed camera intrinsics.
    R, t : arrays (F, C, 3, 3), (F, C, 3)
        Initial world-to-camera poses per frame (NaN for unknown cameras are not allowed where
        a camera has observations).
    xyz : array (F, P, 3)
        Initial points, mm. Free points without an initial position are triangulated first.
    fixed_points : bool array (P,), optional
        Points whose positions are held fixed (the brim's dots): they pin the world frame.
    shared_cameras : bool
        One pose per camera for all frames (a rigid, static rig) instead of per-frame poses.
    fix_cameras : bool array (C,), optional
        Cameras whose poses are not adjusted.
    loss, f_scale : str, float
        Robust loss of ``scipy.optimize.least_squares`` (``"linear"``, ``"huber"``,
        ``"soft_l1"``, ``"cauchy"``) and its scale in px.
    jac : {"analytic", "2-point"}
        Analytic sparse Jacobian, or scipy's finite differences on the same sparsity.
    pose_prior : float
        Weight (per radian / mm, in px) of a prior keeping each pose near its start; resolves
        poses the observations leave undetermined without noticeably biasing the others.

    Returns
    -------
    BundleResult
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
    if loss not in ("linear", "huber", "soft_l1", "cauchy", "arctan"):
        raise ValueError(f"unknown loss {loss!r}")
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

    prob = _Problem(obs_xy, intrinsics, R, t, xyz, fixed, shared_cameras, fixc, pose_prior)
    if prob.n_params == 0 or len(prob.of) == 0:
        res = reprojection_errors(obs_xy, intrinsics, R, t, xyz)
        return BundleResult(R, t, xyz, res, _rms(res), 0.0, 0.0, 0, True, "nothing to adjust")
    x0 = prob.x0()
    kw = dict(method="trf", loss=loss, f_scale=f_scale, x_scale="jac", tr_solver="lsmr",
              ftol=ftol, xtol=xtol, gtol=1e-12, max_nfev=max_nfev)
    if jac == "analytic":
        sol = least_squares(prob.residuals, x0, jac=prob.jacobian, **kw)
    else:
        sol = least_squares(prob.residuals, x0, jac="2-point", jac_sparsity=prob.sparsity(), **kw)
    r0 = prob.residuals(x0)
    initial_cost = float(0.5 * np.sum(_rho(r0, loss, f_scale)))
    Rn, tn, xyzn = prob.finish(sol.x)
    res = reprojection_errors(obs_xy, intrinsics, Rn, tn, xyzn)
    return BundleResult(Rn, tn, xyzn, res, _rms(res), initial_cost, float(sol.cost), int(sol.nfev),
                        bool(sol.success), str(sol.message))


def _rms(res: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        sq = np.where(np.isfinite(res), res ** 2, 0.0).sum(axis=(0, 1))
        n = np.isfinite(res).sum(axis=(0, 1))
        return np.where(n > 0, np.sqrt(sq / np.maximum(n, 1)), np.nan)


def _rho(r: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """scipy's robust loss applied to squared residuals (for reporting the initial cost)."""
    z = (r / f_scale) ** 2
    if loss == "linear":
        rho = z
    elif loss == "huber":
        rho = np.where(z <= 1, z, 2 * np.sqrt(z) - 1)
    elif loss == "soft_l1":
        rho = 2 * (np.sqrt(1 + z) - 1)
    elif loss == "cauchy":
        rho = np.log1p(z)
    else:
        rho = np.arctan(z)
    return rho * f_scale ** 2
