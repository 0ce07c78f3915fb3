"""Linearisation of the XCP projection for bundle adjustment.

Shared by the Schur-complement Levenberg-Marquardt solver (:mod:`.bundle_lm`) and the scipy
path (:mod:`.bundle_scipy`): per observation, the raw projection and its Jacobian with respect
to the point in camera coordinates, chained through the radial model.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .camera import Intrinsics, _cross_matrix, project

__all__ = ["project_observations", "raw_jacobian", "pose_point_jacobians", "so3_left_jacobian"]


def project_observations(X: np.ndarray, R: np.ndarray, t: np.ndarray, cam: np.ndarray,
                         intrinsics: Sequence[Intrinsics]) -> np.ndarray:
    """Raw projections (N, 2) of points ``X (N, 3)`` in the cameras ``cam (N,)`` posed ``R, t``."""
    raw = np.full((len(X), 2), np.nan)
    for c, intr in enumerate(intrinsics):
        sel = cam == c
        if np.any(sel):
            raw[sel] = project(X[sel], intr, R[sel], t[sel])
    return raw


def distortion_jacobian(raw: np.ndarray, intr: Intrinsics) -> np.ndarray:
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


def raw_jacobian(Xc: np.ndarray, raw: np.ndarray, cam: np.ndarray, intrinsics: Sequence[Intrinsics]) -> np.ndarray:
    """``d raw / d Xc`` (N, 2, 3) at camera-frame points ``Xc (N, 3)`` projecting to ``raw (N, 2)``."""
    N = len(Xc)
    z = Xc[:, 2]
    z = np.where(np.abs(z) > 1e-9, z, 1e-9)
    fx = np.array([i.focal_length for i in intrinsics])[cam]
    sk = np.array([i.skew for i in intrinsics])[cam]
    fy = fx / np.array([i.aspect for i in intrinsics])[cam]
    xn, yn = Xc[:, 0] / z, Xc[:, 1] / z
    Jp = np.zeros((N, 2, 3))  # d corrected / d Xc
    Jp[:, 0, 0] = fx / z
    Jp[:, 0, 1] = sk / z
    Jp[:, 0, 2] = -(fx * xn + sk * yn) / z
    Jp[:, 1, 1] = fy / z
    Jp[:, 1, 2] = -fy * yn / z
    # d raw / d corrected is the inverse of the correction's Jacobian at the raw point.
    Jd = np.empty((N, 2, 2))
    for c, intr in enumerate(intrinsics):
        sel = cam == c
        if np.any(sel):
            Jd[sel] = distortion_jacobian(np.nan_to_num(raw[sel]), intr)
    return np.linalg.solve(Jd, Jp)


def pose_point_jacobians(X: np.ndarray, R: np.ndarray, t: np.ndarray, cam: np.ndarray,
                         intrinsics: Sequence[Intrinsics]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projection and Jacobians for pose updates ``R <- exp(d) R, t <- t + dt`` at ``d = 0``.

    Returns
    -------
    raw : (N, 2) raw projections
    J_pose : (N, 2, 6) derivative with respect to ``(d, dt)``
    J_point : (N, 2, 3) derivative with respect to the world point
    """
    RX = np.einsum("nij,nj->ni", R, X)
    raw = project_observations(X, R, t, cam, intrinsics)
    Jraw = raw_jacobian(RX + t, raw, cam, intrinsics)
    J_pose = np.concatenate([Jraw @ (-_cross_matrix(RX)), Jraw], axis=2)
    return raw, J_pose, Jraw @ R


def so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l (N, 3, 3)`` of SO(3) at rotation vectors ``phi (N, 3)``."""
    th = np.linalg.norm(phi, axis=-1)[:, None, None]
    K = _cross_matrix(phi)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ths)) / ths ** 2)
    b = np.where(small, 1.0 / 6 - th ** 2 / 120, (ths - np.sin(ths)) / ths ** 3)
    return np.eye(3) + a * K + b * (K @ K)
