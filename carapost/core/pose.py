"""Camera pose from known 3D points (PnP) with the XCP camera model.

Observations are raw pixels; they are corrected and normalised once with
:func:`carapost.core.camera.normalized_rays` (radial correction, aspect, skew and focal
length), so OpenCV's solvers run with an identity camera matrix and no distortion.
Errors are always reported in raw pixels, through :func:`carapost.core.camera.project`.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import cv2
import numpy as np

from .camera import Intrinsics, camera_centre, normalized_rays, project

__all__ = ["PoseFit", "is_planar", "is_degenerate", "pnp_candidates", "p3p_candidates", "refine_pose",
           "reprojection_px", "robust_pnp", "compose_relative"]

_EYE = np.eye(3)


@dataclass(frozen=True)
class PoseFit:
    """A camera pose fitted to 2D-3D correspondences.

    Attributes
    ----------
    R : array (3, 3)
    t : array (3,)
        World-to-camera pose (``x_cam = R X + t``), mm.
    inliers : bool array (N,)
        Correspondences consistent with the pose.
    errors : array (N,)
        Reprojection error of every correspondence, raw px.
    """

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    errors: np.ndarray

    @property
    def rms(self) -> float:
        """RMS reprojection error over the inliers, px."""
        e = self.errors[self.inliers]
        return float(np.sqrt(np.mean(e * e))) if len(e) else float("nan")


def is_planar(xyz: np.ndarray, tol: float = 1e-6) -> bool:
    """True if the points ``(N, 3)`` lie on a plane (thickness below ``tol`` x extent)."""
    xyz = np.asarray(xyz, float)
    if len(xyz) < 4:
        return True
    s = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    return bool(s[2] <= tol * max(s[0], 1e-12))


def is_degenerate(xyz: np.ndarray, tol: float = 0.05) -> bool:
    """True if the points ``(N, 3)`` are (nearly) collinear: their second principal extent
    is below ``tol`` times the first, so they cannot fix a camera's roll about their line."""
    xyz = np.asarray(xyz, float)
    if len(xyz) < 3:
        return True
    s = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    return bool(s[1] <= tol * max(s[0], 1e-12))


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of one rotation vector (3,) (OpenCV's Rodrigues, fast)."""
    return cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))[0]


def _rt(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return _rotation(np.asarray(rvec, float).ravel()), np.asarray(tvec, float).ravel().copy()


def pnp_candidates(xyz: np.ndarray, uv: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate poses from ``N >= 4`` points ``xyz (N, 3)`` mm and normalised image
    coordinates ``uv (N, 2)`` (``x / z, y / z`` in the camera frame).

    Coplanar points give both IPPE solutions (the second resolves the flip ambiguity of a
    small planar target seen nearly face-on). Nearly coplanar points (a curved brim) are
    flattened onto their best plane for IPPE and the two poses refined on the true points.
    SQPNP's solution is always added. Poses that put any point behind the camera are dropped.

    Returns
    -------
    list of (R (3, 3), t (3,))
    """
    xyz = np.asarray(xyz, dtype=float)
    obj = np.ascontiguousarray(xyz).reshape(-1, 1, 3)
    img = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    raw: list[tuple[np.ndarray, np.ndarray]] = []
    mean = xyz.mean(axis=0)
    _, sv, Vt = np.linalg.svd(xyz - mean)
    planar = len(xyz) >= 4 and sv[2] <= 1e-6 * max(sv[0], 1e-12)
    if len(xyz) >= 4 and not planar and sv[2] <= 0.25 * sv[0]:
        flat = xyz - np.outer((xyz - mean) @ Vt[2], Vt[2])
        for R, t in _solve(flat.reshape(-1, 1, 3), img, cv2.SOLVEPNP_IPPE):
            raw.append(refine_pose(xyz, uv, R, t))
    if planar:
        raw += _solve(obj, img, cv2.SOLVEPNP_IPPE)
    raw += _solve(obj, img, cv2.SOLVEPNP_SQPNP)
    out = []
    for R, t in raw:
        if np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.all(xyz @ R[2] + t[2] > 0):
            out.append((R, t))
    return out


def _solve(obj: np.ndarray, img: np.ndarray, flag: int) -> list[tuple[np.ndarray, np.ndarray]]:
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, _EYE, None, flags=flag)
    except cv2.error:
        return []
    return [_rt(rv, tv) for rv, tv in zip(rvecs[:n], tvecs[:n])]


def p3p_candidates(xyz: np.ndarray, uv: np.ndarray, *, n_grid: int = 4000) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every pose fitting three points ``xyz (3, 3)`` mm seen at normalised coordinates
    ``uv (3, 2)`` (usually at most four; poses with a point behind the camera dropped).

    The distances ``s_i`` of the points from the camera satisfy the three law-of-cosines
    equations of the triangle; ``s_2`` and ``s_3`` follow from ``s_1`` (two branches each),
    and the remaining equation is solved for ``s_1`` by scanning ``n_grid`` values for sign
    changes and bisecting. Each solution's rotation comes from aligning the triangle with
    its camera-frame image (Kabsch). Near-solutions (a residual minimum just short of zero,
    where noise has removed a double root) are returned too, so the result is approximate
    there. Sturdier than OpenCV's closed forms near degenerate triangles, which can return NaN.
    """
    X = np.asarray(xyz, dtype=float)
    j = np.c_[np.asarray(uv, dtype=float), np.ones(3)]
    j /= np.linalg.norm(j, axis=1, keepdims=True)
    a2 = float(np.sum((X[1] - X[2]) ** 2))
    b2 = float(np.sum((X[0] - X[2]) ** 2))
    c2 = float(np.sum((X[0] - X[1]) ** 2))
    ca, cb, cg = float(j[1] @ j[2]), float(j[0] @ j[2]), float(j[0] @ j[1])
    sb2, sg2 = 1 - cb * cb, 1 - cg * cg
    if min(a2, b2, c2) <= 0 or sb2 <= 0 or sg2 <= 0:
        return []
    s_max = min(np.sqrt(c2 / sg2), np.sqrt(b2 / sb2))

    def third(s1: np.ndarray, e2: np.ndarray, e3: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residual of the third equation and ``s2, s3`` on the branches ``e2, e3 = +-1``."""
        s2 = s1 * cg + e2 * np.sqrt(np.maximum(c2 - s1 * s1 * sg2, 0.0))
        s3 = s1 * cb + e3 * np.sqrt(np.maximum(b2 - s1 * s1 * sb2, 0.0))
        return s2 * s2 + s3 * s3 - 2 * s2 * s3 * ca - a2, s2, s3

    # s1 = s_max sin(theta): the square roots below become smooth (cos theta) at s_max
    grid = s_max * np.sin(np.linspace(1e-6, np.pi / 2, n_grid))
    signs = np.array([(1, 1), (1, -1), (-1, 1), (-1, -1)], float)
    g = third(grid[None], signs[:, :1], signs[:, 1:])[0]            # (4, n_grid)
    # Sign changes between grid points bracket roots. Where |g| has a small local minimum
    # without a sign change, either two roots share a grid cell or noise has lifted a double
    # root just above zero: find the extremum there (golden section); if it crosses zero it
    # splits the cell into two brackets, otherwise it is kept as a near-solution (distance
    # inconsistency under 0.25% of the triangle's side).
    k, i = np.nonzero(np.sign(g[:, :-1]) * np.sign(g[:, 1:]) < 0)
    lo, hi, kb = list(grid[i]), list(grid[i + 1]), list(k)
    ag = np.abs(g)
    km, im = np.nonzero((ag[:, 1:-1] <= ag[:, :-2]) & (ag[:, 1:-1] <= ag[:, 2:]) &
                        (ag[:, 1:-1] < 0.005 * a2) & (np.sign(g[:, :-2]) == np.sign(g[:, 2:])))
    near_s: list[float] = []
    near_k: list[int] = []
    if len(km):
        sg = np.sign(g[km, im + 1])
        a, b = grid[im], grid[im + 2]
        gr = (np.sqrt(5) - 1) / 2
        for _ in range(60):  # minimise sg * g on [a, b]
            x1, x2 = b - gr * (b - a), a + gr * (b - a)
            f1 = sg * third(x1, signs[km, 0], signs[km, 1])[0]
            f2 = sg * third(x2, signs[km, 0], signs[km, 1])[0]
            a, b = np.where(f1 < f2, a, x1), np.where(f1 < f2, x2, b)
        xm = 0.5 * (a + b)
        fm = sg * third(xm, signs[km, 0], signs[km, 1])[0]
        for kk, ii, x, f in zip(km, im, xm, fm):
            if f < 0:  # two roots in one cell
                lo += [grid[ii], x]
                hi += [x, grid[ii + 2]]
                kb += [kk, kk]
            else:
                near_s.append(float(x))
                near_k.append(int(kk))
    kb_a = np.array(kb, int)
    e2, e3 = signs[kb_a, 0], signs[kb_a, 1]
    lo_a, hi_a = np.array(lo, float), np.array(hi, float)
    g_lo = third(lo_a, e2, e3)[0]
    for _ in range(60):  # bisection of every bracket at once
        mid = 0.5 * (lo_a + hi_a)
        gm = third(mid, e2, e3)[0]
        left = np.sign(gm) == np.sign(g_lo)
        lo_a, g_lo, hi_a = np.where(left, mid, lo_a), np.where(left, gm, g_lo), np.where(left, hi_a, mid)
    nk = np.array(near_k, int)
    s1 = np.r_[0.5 * (lo_a + hi_a), near_s]
    e2, e3 = np.r_[e2, signs[nk, 0]], np.r_[e3, signs[nk, 1]]
    _, s2, s3 = third(s1, e2, e3)
    ok = (s2 > 0) & (s3 > 0)
    sols = np.c_[s1, s2, s3][ok]
    out: list[tuple[np.ndarray, np.ndarray]] = []
    for d in sols:
        P = j * d[:, None]  # camera-frame points
        R, t = _kabsch(X, P)
        if np.any(X @ R[2] + t[2] <= 0):
            continue
        if all(np.abs(R - R2).max() > 1e-6 or np.abs(t - t2).max() > 1e-6 for R2, t2 in out):
            out.append((R, t))
    return out


def _kabsch(X: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation with ``P ~ R X + t`` (least squares, proper rotation)."""
    mx, mp = X.mean(axis=0), P.mean(axis=0)
    H = (X - mx).T @ (P - mp)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mp - R @ mx


def refine_pose(xyz: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray, *,
                max_iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt refinement of a pose on normalised coordinates.

    Minimises ``sum |pi(R X + t) - uv|^2`` over a left rotation increment and the
    translation, with the analytic Jacobian.

    Parameters
    ----------
    xyz : array (N, 3)
        Points, mm (N >= 3).
    uv : array (N, 2)
        Normalised image coordinates.
    R, t : arrays (3, 3), (3,)
        Starting pose.

    Returns
    -------
    R (3, 3), t (3,)
        The refined pose (the start if no step reduced the error).
    """
    X = np.asarray(xyz, dtype=float)
    uv = np.asarray(uv, dtype=float)
    R = np.asarray(R, dtype=float).copy()
    t = np.asarray(t, dtype=float).copy()

    def residuals(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = X @ R.T          # rotated points (N, 3)
        p = q + t            # camera frame
        z = p[:, 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            r = p[:, :2] / z - uv
        return r, q, p

    r, q, p = residuals(R, t)
    cost = float(np.sum(r * r)) if np.all(p[:, 2] > 0) else np.inf
    lam = 1e-3
    for _ in range(max_iterations):
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        Jp = np.zeros((len(X), 2, 3))  # d pi / d p
        Jp[:, 0, 0] = 1 / z
        Jp[:, 0, 2] = -x / z ** 2
        Jp[:, 1, 1] = 1 / z
        Jp[:, 1, 2] = -y / z ** 2
        # d p / d omega = -[q]x (left increment), d p / d t = I
        qx = np.zeros((len(X), 3, 3))
        qx[:, 0, 1], qx[:, 0, 2], qx[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
        qx[:, 1, 0], qx[:, 2, 0], qx[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
        J = np.concatenate([-Jp @ qx, Jp], axis=2).reshape(-1, 6)
        g = J.T @ r.reshape(-1)
        H = J.T @ J
        improved = False
        prev_cost = cost
        for _ in range(10):
            try:
                step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            R2 = _rotation(step[:3]) @ R
            t2 = t + step[3:]
            r2, q2, p2 = residuals(R2, t2)
            cost2 = float(np.sum(r2 * r2)) if np.all(p2[:, 2] > 0) else np.inf
            if cost2 < cost:
                R, t, r, q, p, cost = R2, t2, r2, q2, p2, cost2
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        if not improved or np.linalg.norm(step) < 1e-12 * (1 + np.linalg.norm(t)) or \
                cost < 1e-30 or prev_cost - cost <= 1e-12 * prev_cost:
            break
    U, _, Vt = np.linalg.svd(R)  # keep R exactly orthonormal
    return U @ Vt, t


def reprojection_px(xyz: np.ndarray, xy: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Reprojection errors ``(N,)`` in raw px of points ``xyz (N, 3)`` against ``xy (N, 2)``
    (``inf`` for a point behind the camera)."""
    p = project(xyz, intr, R, t)
    e = np.hypot(p[:, 0] - xy[:, 0], p[:, 1] - xy[:, 1])
    return np.where(np.isfinite(e), e, np.inf)


def robust_pnp(xyz: np.ndarray, xy: np.ndarray, intr: Intrinsics, *, threshold_px: float,
               max_subsets: int = 400, rng: np.random.Generator | None = None) -> list[PoseFit]:
    """Poses consistent with most of the correspondences ``xyz (N, 3)`` <-> raw ``xy (N, 2)``.

    With ``N == 4`` every candidate pose of the four points is returned (best first). With
    more, every 4-point subset (or ``max_subsets`` random ones) proposes poses, each scored
    by its number of correspondences within ``threshold_px``; the best are refitted on their
    inliers. A wrong correspondence among five or more is thus left out (leave-one-out).

    Returns
    -------
    list of PoseFit
        Distinct hypotheses sorted by (most inliers, lowest inlier RMS); empty if the points
        are degenerate (collinear) or no pose puts them in front of the camera.
    """
    xyz = np.asarray(xyz, float)
    xy = np.asarray(xy, float)
    n = len(xyz)
    if n < 4:
        raise ValueError(f"a pose needs at least 4 correspondences, got {n}")
    uv = normalized_rays(xy, intr)[:, :2]
    subsets: list[tuple[int, ...]]
    all_sub = list(combinations(range(n), 4)) if n <= 12 else None
    if all_sub is not None and len(all_sub) <= max_subsets:
        subsets = all_sub
    else:
        rng = rng or np.random.default_rng(0)
        subsets = [tuple(sorted(rng.choice(n, 4, replace=False))) for _ in range(max_subsets)]
    fits: list[PoseFit] = []
    for sub in subsets:
        idx = list(sub)
        if is_degenerate(xyz[idx]):
            continue
        for R, t in pnp_candidates(xyz[idx], uv[idx]):
            err = reprojection_px(xyz, xy, intr, R, t)
            inl = err <= threshold_px
            if inl.sum() >= 4:
                R, t = refine_pose(xyz[inl], uv[inl], R, t)
                err = reprojection_px(xyz, xy, intr, R, t)
                inl = err <= threshold_px
            fits.append(PoseFit(R, t, inl, err))
        if n > 4 and any(f.inliers.all() for f in fits):
            break  # every correspondence agrees: no subset can do better
    fits.sort(key=lambda f: (-int(f.inliers.sum()), f.rms if f.inliers.any() else np.inf,
                             float(np.sqrt(np.mean(np.minimum(f.errors, 1e6) ** 2)))))
    # keep distinct hypotheses (camera centres more than 1 mm or rotations 0.5 degree apart)
    out: list[PoseFit] = []
    for f in fits:
        c = camera_centre(f.R, f.t)
        if all(np.linalg.norm(c - camera_centre(g.R, g.t)) > 1.0 or
               np.trace(f.R @ g.R.T) < 1 + 2 * np.cos(np.deg2rad(0.5)) for g in out):
            out.append(f)
    return out


def compose_relative(R_from: np.ndarray, t_from: np.ndarray, R_rel: np.ndarray,
                     t_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose of a camera whose pose relative to another is ``(R_rel, t_rel)``
    (``x_cam = R_rel x_other + t_rel``), given the other's world pose ``(R_from, t_from)``."""
    return R_rel @ R_from, R_rel @ t_from + t_rel
