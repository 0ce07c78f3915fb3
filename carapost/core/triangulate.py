"""N-view triangulation of raw-pixel observations.

A linear solution (the inhomogeneous DLT: two equations per view, solved as 3x3 normal
equations) followed by Gauss-Newton refinement of the reprojection error. Everything is
vectorised over points; views with NaN observations are ignored.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .camera import Intrinsics, normalized_rays, project

__all__ = ["TriangulationResult", "triangulate", "min_views_mask"]


@dataclass(frozen=True)
class TriangulationResult:
    """Result of :func:`triangulate`.

    Attributes
    ----------
    xyz : array (..., 3)
        Points in mm; NaN where fewer than ``min_views`` views observed the point.
    residuals : array (..., V)
        Reprojection error per view in raw pixels; NaN for views without an observation.
    n_views : array (...) int
        Number of views used.
    """

    xyz: np.ndarray
    residuals: np.ndarray
    n_views: np.ndarray


def min_views_mask(xy: np.ndarray, min_views: int = 2) -> np.ndarray:
    """Mask ``(...)`` of points seen in at least ``min_views`` views of ``xy (..., V, 2)``."""
    return np.isfinite(xy).all(-1).sum(-1) >= min_views


def triangulate(xy: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                *, min_views: int = 2, iterations: int = 3) -> TriangulationResult:
    """Triangulate points seen in several cameras.

    Parameters
    ----------
    xy : array (..., V, 2)
        Raw-pixel observations per view, NaN where a view has none.
    intrinsics : sequence of V Intrinsics
    R : array (V, 3, 3) or (..., V, 3, 3)
        World-to-camera rotations, broadcast against ``xy``'s leading axes (e.g. per-frame
        poses ``(F, 1, V, 3, 3)`` against observations ``(F, P, V, 2)``).
    t : array (V, 3) or (..., V, 3)
        Translations, mm.
    min_views : int
        Points with fewer valid views are NaN in the result.
    iterations : int
        Gauss-Newton refinement steps after the linear solution (0 = linear only).

    Returns
    -------
    TriangulationResult
    """
    xy = np.asarray(xy, dtype=float)
    V = len(intrinsics)
    if xy.ndim < 2 or xy.shape[-2:] != (V, 2):
        raise ValueError(f"observations must have shape (..., {V}, 2) for {V} cameras, got {xy.shape}")
    if min_views < 1:
        raise ValueError("min_views must be at least 1")
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    lead = xy.shape[:-2]
    Rb = np.broadcast_to(R, lead + (V, 3, 3))
    tb = np.broadcast_to(t, lead + (V, 3))

    valid = np.isfinite(xy).all(-1)  # (..., V)
    # Normalised camera coordinates (x/z, y/z) of each observation.
    rays = np.empty(lead + (V, 3))
    for v, intr in enumerate(intrinsics):
        rays[..., v, :] = normalized_rays(xy[..., v, :], intr)
    u = np.where(valid, rays[..., 0], 0.0)
    w = np.where(valid, rays[..., 1], 0.0)

    # Linear: (u r3 - r1) . X = t1 - u t3, (w r3 - r2) . X = t2 - w t3.
    r1, r2, r3 = Rb[..., 0, :], Rb[..., 1, :], Rb[..., 2, :]
    a1 = u[..., None] * r3 - r1
    a2 = w[..., None] * r3 - r2
    b1 = tb[..., 0] - u * tb[..., 2]
    b2 = tb[..., 1] - w * tb[..., 2]
    m = valid.astype(float)
    A = np.einsum("...v,...vi,...vj->...ij", m, a1, a1) + np.einsum("...v,...vi,...vj->...ij", m, a2, a2)
    b = np.einsum("...v,...vi,...v->...i", m, a1, b1) + np.einsum("...v,...vi,...v->...i", m, a2, b2)
    n_views = valid.sum(-1)
    ok = n_views >= max(min_views, 2)  # a single view defines a ray, not a point
    X = _solve3(A, b, ok)

    # Gauss-Newton on the normalised-coordinate error scaled to pixels by each focal length.
    m = m * np.array([intr.focal_length for intr in intrinsics]) ** 2
    for _ in range(iterations):
        Xc = np.einsum("...vij,...j->...vi", Rb, X) + tb
        z = Xc[..., 2]
        zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
        eu = Xc[..., 0] / zs - u
        ew = Xc[..., 1] / zs - w
        wgt = m / (zs * zs)  # d(x/z)/dX = (r1 - (x/z) r3) / z
        ju = (r1 - (Xc[..., 0] / zs)[..., None] * r3)
        jw = (r2 - (Xc[..., 1] / zs)[..., None] * r3)
        H = np.einsum("...v,...vi,...vj->...ij", wgt, ju, ju) + np.einsum("...v,...vi,...vj->...ij", wgt, jw, jw)
        g = np.einsum("...v,...vi,...v->...i", wgt * zs, ju, eu) + np.einsum("...v,...vi,...v->...i", wgt * zs, jw, ew)
        X = X - _solve3(H, g, ok)

    X[~ok] = np.nan
    residuals = np.full(lead + (V,), np.nan)
    for v, intr in enumerate(intrinsics):
        proj = project(X, intr, Rb[..., v, :, :], tb[..., v, :])
        d = np.linalg.norm(proj - xy[..., v, :], axis=-1)
        residuals[..., v] = np.where(valid[..., v], d, np.nan)
    return TriangulationResult(xyz=X, residuals=residuals, n_views=n_views)


def _solve3(A: np.ndarray, b: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Solve the batched 3x3 systems where ``ok``; zeros elsewhere."""
    out = np.zeros(b.shape)
    if not np.any(ok):
        return out
    Ao = A[ok]
    bo = b[ok]
    det = np.linalg.det(Ao)
    good = np.abs(det) > 1e-300
    sol = np.zeros(bo.shape)
    if np.any(good):
        sol[good] = np.linalg.solve(Ao[good], bo[good][..., None])[..., 0]
    out[ok] = sol
    return out
