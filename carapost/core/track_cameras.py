"""Small, fast camera geometry for the frame-to-frame tracker.

The tracker works on a few hundred observations per frame, where the general routines of
:mod:`.camera`, :mod:`.triangulate` and :mod:`.bundle` spend most of their time in per-call
overhead (a bundle adjustment of one frame's four cameras costs ~75 ms; the tracker's budget
for a whole frame is ~10 ms). This module packs the cameras' intrinsics into arrays and works
in *normalised* coordinates ``(u, v)`` — raw pixels with the radial correction and ``K``
undone, once per detection — so projection, triangulation and the per-frame re-estimation of
the camera poses from the brim are a handful of batched array operations over all points and
cameras at once.

Distances are compared in *corrected* pixels (``K`` applied to normalised coordinates); they
differ from raw pixels only by the local radial scale (below 1 % for the XCP lenses).

Layout: camera axis first. ``C`` cameras, ``T`` points, ``N`` observations per camera.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .camera import Intrinsics, distort, normalized_rays

__all__ = ["CameraSet", "inv3", "triangulate_uv", "ray_nearest_points", "solve3", "information",
           "reprojection", "loo_residuals", "bundle_frame"]


class CameraSet:
    """The intrinsics of ``C`` cameras as arrays.

    Parameters
    ----------
    intrinsics : sequence of Intrinsics
    """

    def __init__(self, intrinsics: Sequence[Intrinsics]) -> None:
        self.intrinsics = list(intrinsics)
        C = len(self.intrinsics)
        self.f = np.array([i.focal_length for i in self.intrinsics], float).reshape(C)
        self.fy = self.f / np.array([i.aspect for i in self.intrinsics], float).reshape(C)
        self.skew = np.array([i.skew for i in self.intrinsics], float).reshape(C)
        self.pp = np.array([i.principal_point for i in self.intrinsics], float).reshape(C, 2)
        #: pixels per normalised unit along (u, v), (C, 2)
        self.scale = np.stack([self.f, self.fy], axis=1)

    def __len__(self) -> int:
        return len(self.intrinsics)

    def normalise(self, camera: int, xy: np.ndarray) -> np.ndarray:
        """Raw pixels ``(..., 2)`` of one camera to normalised coordinates ``(..., 2)``."""
        return normalized_rays(np.asarray(xy, float), self.intrinsics[camera])[..., :2]

    def to_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Normalised ``(C, ..., 2)`` to corrected pixels ``(C, ..., 2)``."""
        uv = np.asarray(uv, float)
        shape = (len(self),) + (1,) * (uv.ndim - 2)
        out = np.empty_like(uv)
        out[..., 0] = self.f.reshape(shape) * uv[..., 0] + self.skew.reshape(shape) * uv[..., 1] \
            + self.pp[:, 0].reshape(shape)
        out[..., 1] = self.fy.reshape(shape) * uv[..., 1] + self.pp[:, 1].reshape(shape)
        return out

    def to_raw(self, camera: int, uv: np.ndarray) -> np.ndarray:
        """Normalised ``(..., 2)`` of one camera to raw pixels ``(..., 2)``."""
        uv = np.asarray(uv, float)
        pc = np.empty_like(uv)
        pc[..., 0] = self.f[camera] * uv[..., 0] + self.skew[camera] * uv[..., 1] + self.pp[camera, 0]
        pc[..., 1] = self.fy[camera] * uv[..., 1] + self.pp[camera, 1]
        return distort(pc, self.intrinsics[camera])

    @staticmethod
    def project_uv(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Project points into every camera.

        Parameters
        ----------
        X : array (T, 3)
            World points, mm (NaN propagates).
        R, t : arrays (C, 3, 3), (C, 3)

        Returns
        -------
        uv : array (C, T, 2)
            Normalised coordinates; NaN for points behind a camera.
        """
        Xc = np.matmul(X, R.transpose(0, 2, 1)) + t[:, None, :]
        z = Xc[..., 2:]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(z > 1e-6, Xc[..., :2] / z, np.nan)


def solve3(A: np.ndarray, b: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Batched symmetric 3x3 solves ``A (T, 3, 3) x = b (T, 3)`` where ``ok (T,)``; NaN elsewhere
    (and where ``A`` is singular). By the adjugate: a few array operations, no LAPACK calls."""
    a, bb, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    i00 = d * f - e * e
    i01 = c * e - bb * f
    i02 = bb * e - c * d
    i11 = a * f - c * c
    i12 = bb * c - a * e
    i22 = a * d - bb * bb
    det = a * i00 + bb * i01 + c * i02
    scale = (np.abs(a) + np.abs(d) + np.abs(f)) ** 3 + 1e-300
    good = ok & (np.abs(det) > 1e-12 * scale)
    inv = np.where(good, 1.0 / np.where(good, det, 1.0), np.nan)
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    x = np.empty_like(b)
    x[:, 0] = (i00 * b0 + i01 * b1 + i02 * b2) * inv
    x[:, 1] = (i01 * b0 + i11 * b1 + i12 * b2) * inv
    x[:, 2] = (i02 * b0 + i12 * b1 + i22 * b2) * inv
    return x


def inv3(A: np.ndarray) -> np.ndarray:
    """Inverses ``(T, 3, 3)`` of batched symmetric 3x3 matrices (NaN where singular)."""
    a, bb, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    out = np.empty((len(A), 3, 3))
    i00, i01, i02 = d * f - e * e, c * e - bb * f, bb * e - c * d
    out[:, 0, 0] = i00
    out[:, 0, 1] = out[:, 1, 0] = i01
    out[:, 0, 2] = out[:, 2, 0] = i02
    out[:, 1, 1] = a * f - c * c
    out[:, 1, 2] = out[:, 2, 1] = bb * c - a * e
    out[:, 2, 2] = a * d - bb * bb
    det = a * i00 + bb * i01 + c * i02
    good = np.abs(det) > 1e-12 * ((np.abs(a) + np.abs(d) + np.abs(f)) ** 3 + 1e-300)
    out *= np.where(good, 1.0 / np.where(good, det, 1.0), np.nan)[:, None, None]
    return out


def triangulate_uv(uv: np.ndarray, weight: np.ndarray, R: np.ndarray, t: np.ndarray, scale: np.ndarray, *,
                   iterations: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate points from normalised observations in several cameras.

    The inhomogeneous linear solution (two equations per view, normal equations weighted
    by the pixel scale), optionally followed by Gauss-Newton steps on the reprojection error.

    Parameters
    ----------
    uv : array (C, T, 2)
        Normalised observations (ignored where ``weight`` is 0; NaN allowed there).
    weight : array (C, T)
        Weight of each observation (0 = not used; 1 = normal).
    R, t : arrays (C, 3, 3), (C, 3)
    scale : array (C, 2)
        Pixels per normalised unit (:attr:`CameraSet.scale`): residuals are in px.
    iterations : int
        Gauss-Newton steps after the linear solution.

    Returns
    -------
    X : array (T, 3)
        Points, mm; NaN where fewer than two observations are used.
    residuals : array (C, T)
        Reprojection error of each used observation, corrected px (NaN where not used, inf
        behind the camera).
    """
    use = weight > 0
    ok = use.sum(0) >= 2
    uvz = np.where(use[..., None], uv, 0.0)
    w = weight * (scale[:, 0] * scale[:, 1])[:, None]                      # (C, T)
    # rows (u r3 - r1) X = t1 - u t3 and (v r3 - r2) X = t2 - v t3, for both coordinates at once
    a = uvz[..., :, None] * R[:, None, 2:3, :] - R[:, None, 0:2, :]         # (C, T, 2, 3)
    rhs = t[:, None, 0:2] - uvz * t[:, None, 2:3]                          # (C, T, 2)
    aw = a * w[..., None, None]
    C = len(R)
    A = np.matmul(aw.transpose(1, 3, 0, 2).reshape(-1, 3, 2 * C), a.transpose(1, 0, 2, 3).reshape(-1, 2 * C, 3))
    b = (aw * rhs[..., None]).sum((0, 2))
    X = solve3(A, b, ok)
    for _ in range(iterations):
        X = _gauss_newton(X, uvz, use, R, t, scale, ok)
    res = reprojection(X, uv, use, R, t, scale)
    return X, res


def _gauss_newton(X: np.ndarray, uv: np.ndarray, use: np.ndarray, R: np.ndarray, t: np.ndarray,
                  scale: np.ndarray, ok: np.ndarray) -> np.ndarray:
    Xs = np.where(ok[:, None], X, 0.0)
    Xc = np.matmul(Xs, R.transpose(0, 2, 1)) + t[:, None, :]               # (C, T, 3)
    z = np.where(np.abs(Xc[..., 2:]) > 1e-9, Xc[..., 2:], 1e-9)
    p = Xc[..., :2] / z                                                     # (C, T, 2)
    J = (R[:, None, 0:2, :] - p[..., None] * R[:, None, 2:3, :]) / z[..., None]   # (C, T, 2, 3)
    s2 = (scale ** 2)[:, None, :] * use[..., None]                          # (C, T, 2)
    Jw = J * s2[..., None]
    C = len(R)
    A = np.matmul(Jw.transpose(1, 3, 0, 2).reshape(-1, 3, 2 * C), J.transpose(1, 0, 2, 3).reshape(-1, 2 * C, 3))
    b = (Jw * (uv - p)[..., None]).sum((0, 2))
    return X + solve3(A, b, ok)


def information(X: np.ndarray, use: np.ndarray, R: np.ndarray, t: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Fisher information ``(T, 3, 3)`` of triangulated points, px^2 per mm^2.

    ``J^T J`` summed over the used views, ``J`` the 2x3 Jacobian of the projection (px/mm):
    with isotropic detection noise ``s`` px, ``s^2 inv(information)`` is the covariance of
    the point. Two cameras of one caddy see nearly the same ray, so their information is
    small along it (depth is poorly determined).
    """
    Xs = np.where(np.isfinite(X), X, 0.0)
    Xc = np.matmul(Xs, R.transpose(0, 2, 1)) + t[:, None, :]
    z = np.where(np.abs(Xc[..., 2:]) > 1e-9, Xc[..., 2:], 1e-9)
    p = Xc[..., :2] / z
    J = (R[:, None, 0:2, :] - p[..., None] * R[:, None, 2:3, :]) / z[..., None] * scale[:, None, :, None]
    J = J * use[..., None, None]
    C = len(R)
    return np.matmul(J.transpose(1, 3, 0, 2).reshape(-1, 3, 2 * C), J.transpose(1, 0, 2, 3).reshape(-1, 2 * C, 3))


def loo_residuals(X: np.ndarray, uv: np.ndarray, weight: np.ndarray, R: np.ndarray, t: np.ndarray,
                  scale: np.ndarray) -> np.ndarray:
    """Leave-one-out reprojection errors ``(C, T)`` px of triangulated points.

    For each used view, how far its observation lies from the point triangulated from the
    *other* views — computed from the full solution by the leverage formula
    ``r_loo = (I - H) ^ -1 r``, ``H = J inv(A) J^T`` (exact for the linearised problem), without
    re-triangulating. A wrong detection in one camera can hide behind a small ordinary
    residual when the other cameras leave the depth free (two cameras of one caddy); its
    leave-one-out residual cannot. NaN where a view is unused or its removal would leave
    fewer than two.
    """
    use = weight > 0
    Xs = np.where(np.isfinite(X), X, 0.0)
    Xc = np.matmul(Xs, R.transpose(0, 2, 1)) + t[:, None, :]
    z = np.where(np.abs(Xc[..., 2:]) > 1e-9, Xc[..., 2:], 1e-9)
    p = Xc[..., :2] / z
    J = (R[:, None, 0:2, :] - p[..., None] * R[:, None, 2:3, :]) / z[..., None] * scale[:, None, :, None]
    Jw = J * (weight[..., None, None] ** 0.5)
    C = len(R)
    A = np.matmul(Jw.transpose(1, 3, 0, 2).reshape(-1, 3, 2 * C), Jw.transpose(1, 0, 2, 3).reshape(-1, 2 * C, 3))
    ok = use.sum(0) >= 3
    A = np.where(ok[:, None, None], A, np.eye(3))
    Ainv = inv3(A)                                                           # (T, 3, 3)
    H = np.matmul(np.matmul(Jw, Ainv[None]), Jw.transpose(0, 1, 3, 2))      # (C, T, 2, 2)
    r = (uv - p) * scale[:, None, :] * (weight[..., None] ** 0.5)            # (C, T, 2) weighted px
    M = np.eye(2) - H
    det = M[..., 0, 0] * M[..., 1, 1] - M[..., 0, 1] * M[..., 1, 0]
    good = use & ok[None, :] & (np.abs(det) > 1e-9)
    dets = np.where(good, det, 1.0)
    lx = (M[..., 1, 1] * r[..., 0] - M[..., 0, 1] * r[..., 1]) / dets
    ly = (-M[..., 1, 0] * r[..., 0] + M[..., 0, 0] * r[..., 1]) / dets
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(lx * lx + ly * ly) / np.where(use, weight, 1.0) ** 0.5
    return np.where(good, out, np.nan)


def reprojection(X: np.ndarray, uv: np.ndarray, use: np.ndarray, R: np.ndarray, t: np.ndarray,
                 scale: np.ndarray) -> np.ndarray:
    """Reprojection errors ``(C, T)`` (corrected px) of points ``X (T, 3)`` against ``uv (C, T, 2)``.

    NaN where ``use`` is False or the point is unknown; inf behind a camera.
    """
    Xc = np.matmul(X, R.transpose(0, 2, 1)) + t[:, None, :]
    z = Xc[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        d = (uv - Xc[..., :2] / z[..., None]) * scale[:, None, :]
        e = np.sqrt((d * d).sum(-1))
    e = np.where(z > 0, e, np.where(np.isnan(z), np.nan, np.inf))
    return np.where(use, e, np.nan)


def reprojection_fixed(X: np.ndarray, uv: np.ndarray, use: np.ndarray, R: np.ndarray, t: np.ndarray,
                       scale: np.ndarray) -> np.ndarray:
    """Reprojection errors ``(C, N)`` of per-camera points ``X (C, N, 3)`` against ``uv (C, N, 2)``."""
    Xc = np.matmul(X, R.transpose(0, 2, 1)) + t[:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        d = (uv - Xc[..., :2] / Xc[..., 2:]) * scale[:, None, :]
        e = np.sqrt((d * d).sum(-1))
    return np.where(use, e, np.nan)


def _pose_point_jacobians(X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray,
                          scale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals ``(C, N, 2)`` px and Jacobians for pose ``(C, N, 2, 6)`` and point ``(C, N, 2, 3)``
    of points ``X (C, N, 3)`` (NaN-free) observed at ``uv (C, N, 2)``."""
    RX = np.matmul(X, R.transpose(0, 2, 1))
    Xc = RX + t[:, None, :]
    z = np.where(np.abs(Xc[..., 2]) > 1e-9, Xc[..., 2], 1e-9)
    p = Xc[..., :2] / z[..., None]
    iz = 1.0 / z
    G = np.zeros(Xc.shape[:2] + (2, 3))
    G[..., 0, 0] = iz
    G[..., 1, 1] = iz
    G[..., :, 2] = -p * iz[..., None]
    G *= scale[:, None, :, None]
    Jc = np.empty(Xc.shape[:2] + (2, 6))
    # rotation part: RX x g for both rows of G at once (g = G[..., k, :])
    a0, a1, a2 = RX[..., 0:1], RX[..., 1:2], RX[..., 2:3]
    g0, g1, g2 = G[..., 0], G[..., 1], G[..., 2]                         # (C, N, 2) each
    Jc[..., 0] = a1 * g2 - a2 * g1
    Jc[..., 1] = a2 * g0 - a0 * g2
    Jc[..., 2] = a0 * g1 - a1 * g0
    Jc[..., 3:] = G
    Jp = np.matmul(G, R[:, None])
    r = (uv - p) * scale[:, None, :]
    return r, Jc, Jp


def bundle_frame(brim_X: np.ndarray, brim_uv: np.ndarray, brim_use: np.ndarray, uv: np.ndarray, weight: np.ndarray,
                 X: np.ndarray, R: np.ndarray, t: np.ndarray, scale: np.ndarray, *, iterations: int = 2,
                 pose_prior: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bundle-adjust one frame: camera poses and face points free, brim dots fixed.

    Gauss-Newton on the reprojection error with the Schur complement on the points (a
    ``6C x 6C`` camera system), all batched. The brim's dots (known positions in the brim
    frame) pin the world; the face points, seen by several cameras, tie the cameras to each
    other — the brim alone, a small card above the face, leaves each camera's pose poorly
    determined where the face is.

    Parameters
    ----------
    brim_X : array (C, B, 3)
        Fixed points seen by each camera, mm (anything where ``brim_use`` is False).
    brim_uv : array (C, B, 2)
    brim_use : bool array (C, B)
    uv : array (C, T, 2)
        Face observations, normalised.
    weight : array (C, T)
        Their weights (0 = none); only points with two or more are adjusted.
    X : array (T, 3)
        Starting face points, mm.
    R, t : arrays (C, 3, 3), (C, 3)
        Starting poses.
    scale : array (C, 2)
        Pixels per normalised unit.
    iterations : int
    pose_prior : float
        Weight keeping each pose near its start (relative to its diagonal), px^2.

    Returns
    -------
    R, t : arrays (C, 3, 3), (C, 3)
    X : array (T, 3)
        Adjusted points (NaN / unchanged where not adjusted).
    """
    C = len(R)
    R = np.array(R, float)
    t = np.array(t, float)
    X = np.array(X, float)
    free_all = ((weight > 0).sum(0) >= 2) & np.isfinite(X).all(1)
    sel = np.flatnonzero(free_all)
    # only the free points take part (the others would be identity blocks of the Schur system)
    w = weight[:, sel]
    wb = brim_use.astype(float)
    bX = np.where(brim_use[..., None], brim_X, 0.0)
    buv = np.where(brim_use[..., None], brim_uv, 0.0)
    fuv = np.where(w[..., None] > 0, uv[:, sel], 0.0)
    Xf = X[sel]
    T = len(Xf)
    for _ in range(iterations):
        rb, Jb, _ = _pose_point_jacobians(bX, buv, R, t, scale)
        r, Jc, Jp = _pose_point_jacobians(np.broadcast_to(Xf, (C,) + Xf.shape), fuv, R, t, scale)
        Jbw = (Jb * wb[..., None, None]).reshape(C, -1, 6)
        Jcw = Jc * w[..., None, None]
        Jpw = Jp * w[..., None, None]
        Jcw2 = Jcw.reshape(C, -1, 6)
        U = (np.matmul(Jbw.transpose(0, 2, 1), Jb.reshape(C, -1, 6))
             + np.matmul(Jcw2.transpose(0, 2, 1), Jc.reshape(C, -1, 6)))                      # (C, 6, 6)
        U += np.eye(6) * (pose_prior * (np.einsum("cii->ci", U)[:, :, None] + 1.0))
        gc = (np.matmul(Jbw.transpose(0, 2, 1), rb.reshape(C, -1, 1))
              + np.matmul(Jcw2.transpose(0, 2, 1), r.reshape(C, -1, 1)))[..., 0]               # (C, 6)
        Jpt = Jp.transpose(1, 0, 2, 3).reshape(T, 2 * C, 3)
        Jpwt = Jpw.transpose(1, 0, 2, 3).reshape(T, 2 * C, 3)
        V = np.matmul(Jpwt.transpose(0, 2, 1), Jpt)                                              # (T, 3, 3)
        gp = np.matmul(Jpwt.transpose(0, 2, 1), r.transpose(1, 0, 2).reshape(T, 2 * C, 1))[..., 0]   # (T, 3)
        W = np.matmul(Jcw.transpose(0, 1, 3, 2), Jp)                                             # (C, T, 6, 3)
        Vinv = inv3(V)
        Y = np.matmul(W, Vinv[None])                                                             # (C, T, 6, 3)
        Yr = Y.transpose(0, 2, 1, 3).reshape(6 * C, 3 * T)
        Wr = W.transpose(0, 2, 1, 3).reshape(6 * C, 3 * T)
        S = -(Yr @ Wr.T)
        for c in range(C):
            S[6 * c:6 * c + 6, 6 * c:6 * c + 6] += U[c]
        rhs = gc.reshape(6 * C) - Yr @ gp.reshape(3 * T)
        try:
            dc = np.linalg.solve(S, rhs).reshape(C, 6)
        except np.linalg.LinAlgError:
            break
        WTdc = W.transpose(1, 3, 0, 2).reshape(T, 3, 6 * C) @ dc.reshape(6 * C)                  # (T, 3)
        dp = np.matmul(Vinv, (gp - WTdc)[..., None])[..., 0]
        R = _small_rotations(dc[:, :3]) @ R
        t = t + dc[:, 3:]
        Xf = Xf + dp
    out = X.copy()
    out[sel] = Xf
    return R, t, out


def _small_rotations(w: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(C, 3, 3)`` of axis-angle vectors ``(C, 3)`` (radians): Rodrigues'
    formula written out for a few vectors (``camera.rodrigues`` is general and slower)."""
    theta = np.sqrt((w * w).sum(1))
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)                      # sin(th) / th
    b = np.where(small, 0.5, (1.0 - np.cos(th)) / (th * th))       # (1 - cos th) / th^2
    x, y, z = w[:, 0], w[:, 1], w[:, 2]
    out = np.empty((len(w), 3, 3))
    out[:, 0, 0] = 1.0 - b * (y * y + z * z)
    out[:, 1, 1] = 1.0 - b * (x * x + z * z)
    out[:, 2, 2] = 1.0 - b * (x * x + y * y)
    out[:, 0, 1] = b * x * y - a * z
    out[:, 1, 0] = b * x * y + a * z
    out[:, 0, 2] = b * x * z + a * y
    out[:, 2, 0] = b * x * z - a * y
    out[:, 1, 2] = b * y * z - a * x
    out[:, 2, 1] = b * y * z + a * x
    return out


def ray_nearest_points(uv: np.ndarray, R: np.ndarray, t: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Points on camera rays nearest to target points (single-sensor tracking).

    Parameters
    ----------
    uv : array (T, 2)
        Normalised observation of each point in its one camera.
    R, t : arrays (T, 3, 3), (T, 3)
        The pose of that camera, per point.
    target : array (T, 3)
        Expected positions, mm.

    Returns
    -------
    array (T, 3)
        The point of each ray (in front of the camera) closest to its target, mm.
    """
    d_cam = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1)
    d = np.einsum("tji,tj->ti", R, d_cam)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = -np.einsum("tji,tj->ti", R, t)
    s = np.maximum(np.einsum("ti,ti->t", target - o, d), 0.0)
    return o + s[:, None] * d
