"""The XCP camera model: the one module that owns projection and distortion.

Conventions (stated once for the whole project)
-----------------------------------------------
* **Pixels.** 2D coordinates are *raw sensor pixels* (as recorded, lens distortion included).
  The centre of the top-left pixel is ``(0, 0)``; ``x`` grows to the right, ``y`` downwards.
  This is OpenCV's convention, so OpenCV results are used without a half-pixel shift.
* **Poses.** ``R`` rotates world to camera, ``t`` is the translation, so a world point ``X``
  has camera coordinates ``R @ X + t``. An XCP ``POSITION`` is the camera *centre* ``C``
  in world coordinates (this is what Vicon Nexus writes; see ``docs/camera-model.md``),
  hence ``t = -R @ C``. The camera looks along its ``+z`` axis.
* **Quaternions** are ``(x, y, z, w)``: the real part last, as in XCP ``ORIENTATION``.
* **Units.** Millimetres in 3D, pixels in 2D.

Radial model (reference guide, "Radial distortion model")
---------------------------------------------------------
A raw point ``p_r`` is corrected with::

    dp = (x_r - c_x, a (y_r - c_y)),  r = |dp|,  s = 1 + k1 r^2 + k2 r^4 + k3 r^6
    p_c = (c_x + s dp_x, c_y + s dp_y / a)

``VICON_RADIAL="w0 w1"`` gives ``k1, k2`` with the distortion centre at the principal point;
``VICON_RADIAL2="Vicon3Parameter cx cy k1 k2 k3"`` gives its own centre and three terms.
(The guide prints ``(s dy + y_pp) / a`` for the last component; that would move the principal
point itself to ``y_pp / a`` when ``a != 1``, so we use the self-consistent ``y_pp + s dy / a``.
Both agree for ``a = 1``, which is every real file we have seen.)

Projection: corrected pixels ``~ K (R X + t)`` with
``K = [[f, skew, x_pp], [0, f / a, y_pp], [0, 0, 1]]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = [
    "Intrinsics",
    "quat_to_matrix",
    "matrix_to_quat",
    "rodrigues",
    "camera_centre",
    "undistort",
    "distort",
    "project",
    "project_corrected",
    "backproject",
    "fundamental_matrix",
    "symmetric_epipolar_distance",
]


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsic parameters of one camera, as in an XCP file.

    Attributes
    ----------
    focal_length : float
        ``FOCAL_LENGTH`` in pixels.
    principal_point : tuple of float
        ``PRINCIPAL_POINT`` (x, y) in raw pixels.
    aspect : float
        ``PIXEL_ASPECT_RATIO`` ``a``.
    skew : float
        ``SKEW`` ``k`` (pixels).
    radial : tuple of float
        ``(k1, k2, k3)``: coefficients of ``r^2, r^4, r^6`` with ``r`` in pixels.
    distortion_centre : tuple of float or None
        Centre of the radial correction; ``None`` means the principal point.
    sensor_size : tuple of int
        ``SENSOR_SIZE`` (width, height) in pixels.
    """

    focal_length: float
    principal_point: tuple[float, float]
    sensor_size: tuple[int, int] = (0, 0)
    aspect: float = 1.0
    skew: float = 0.0
    radial: tuple[float, float, float] = (0.0, 0.0, 0.0)
    distortion_centre: tuple[float, float] | None = field(default=None)

    def __post_init__(self) -> None:
        if not np.isfinite(self.focal_length) or self.focal_length <= 0:
            raise ValueError(f"focal length must be positive, got {self.focal_length}")
        if not np.isfinite(self.aspect) or self.aspect <= 0:
            raise ValueError(f"pixel aspect ratio must be positive, got {self.aspect}")
        if len(self.radial) != 3:
            raise ValueError(f"radial must hold three coefficients (k1, k2, k3), got {self.radial}")

    @property
    def centre(self) -> np.ndarray:
        """Distortion centre (2,) in raw pixels."""
        c = self.principal_point if self.distortion_centre is None else self.distortion_centre
        return np.asarray(c, dtype=float)

    @property
    def K(self) -> np.ndarray:
        """Calibration matrix (3, 3)."""
        f, a = self.focal_length, self.aspect
        x0, y0 = self.principal_point
        return np.array([[f, self.skew, x0], [0.0, f / a, y0], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(k != 0.0 for k in self.radial)

    def with_(self, **changes: object) -> "Intrinsics":
        """A copy with some fields replaced."""
        return replace(self, **changes)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from quaternions.

    Parameters
    ----------
    q : array (..., 4)
        Quaternions ``(x, y, z, w)``, real part last; normalised here.

    Returns
    -------
    R : array (..., 3, 3)
    """
    q = np.asarray(q, dtype=float)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternions must have 4 components, got shape {q.shape}")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0):
        raise ValueError("zero quaternion")
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternions ``(x, y, z, w)`` with ``w >= 0`` from rotation matrices ``(..., 3, 3)``."""
    R = np.asarray(R, dtype=float)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # Shepperd's method, choosing the numerically largest component.
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.empty((m.shape[0], 4))
    for case in range(4):
        s = k == case
        if not np.any(s):
            continue
        r = m[s]
        if case == 0:
            w = 0.5 * np.sqrt(1 + tr[s])
            q[s] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / (4 * w), (r[:, 0, 2] - r[:, 2, 0]) / (4 * w),
                             (r[:, 1, 0] - r[:, 0, 1]) / (4 * w), w], axis=1)
        else:
            i = case - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            v = 0.5 * np.sqrt(np.maximum(1 + r[:, i, i] - r[:, j, j] - r[:, l, l], 0.0))
            out = np.empty((r.shape[0], 4))
            out[:, i] = v
            out[:, j] = (r[:, j, i] + r[:, i, j]) / (4 * v)
            out[:, l] = (r[:, l, i] + r[:, i, l]) / (4 * v)
            out[:, 3] = (r[:, l, j] - r[:, j, l]) / (4 * v)
            q[s] = out
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric cross-product matrices ``(..., 3, 3)`` of vectors ``(..., 3)``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1),
                     np.stack([-y, x, zero], -1)], -2)


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from axis-angle vectors ``(..., 3)`` (radians)."""
    rvec = np.asarray(rvec, dtype=float)
    theta = np.linalg.norm(rvec, axis=-1)[..., None, None]
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    Kx = _cross_matrix(rvec) / th
    eye = np.broadcast_to(np.eye(3), Kx.shape)
    # For tiny angles use the first-order expansion sin(th)/th -> 1, (1 - cos th)/th^2 -> 1/2.
    a = np.where(small, 1.0, np.sin(th))
    b = np.where(small, 0.5, (1 - np.cos(th)))
    Kx = np.where(small, _cross_matrix(rvec), Kx)
    return eye + a * Kx + b * (Kx @ Kx)


def camera_centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centres ``C = -R^T t``: ``R (..., 3, 3)``, ``t (..., 3)`` -> ``(..., 3)`` mm."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    return -np.einsum("...ji,...j->...i", R, t)


# --------------------------------------------------------------------------------------
# Distortion
# --------------------------------------------------------------------------------------


def undistort(xy: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Raw pixels to corrected pixels (the guide's radial correction).

    Parameters
    ----------
    xy : array (..., 2)
        Raw pixel coordinates; NaN propagates.

    Returns
    -------
    array (..., 2)
        Corrected pixel coordinates.
    """
    xy = np.asarray(xy, dtype=float)
    if not intr.has_distortion and intr.aspect == 1.0:
        return xy.copy()
    c = intr.centre
    a = intr.aspect
    dx = xy[..., 0] - c[0]
    dy = a * (xy[..., 1] - c[1])
    r2 = dx * dx + dy * dy
    k1, k2, k3 = intr.radial
    s = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    out = np.empty_like(xy)
    out[..., 0] = c[0] + s * dx
    out[..., 1] = c[1] + s * dy / a
    return out


def _radius_scale_inverse(rho: np.ndarray, radial: tuple[float, float, float]) -> np.ndarray:
    """Solve ``r s(r) = rho`` for ``r`` (Newton), returning ``r / rho`` (1 where rho = 0)."""
    k1, k2, k3 = radial
    r = rho / (1.0 + k1 * rho * rho)  # first-order inverse: Newton then needs 2-3 steps
    for _ in range(30):
        r2 = r * r
        g = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) - rho
        dg = 1.0 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))
        step = g / dg
        r -= step
        if not np.any(np.abs(step) > 1e-10):
            break
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(rho > 0, r / np.where(rho > 0, rho, 1.0), 1.0)


def distort(xy: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Corrected pixels to raw pixels: the inverse of :func:`undistort`.

    Newton iterations on the radius, converged to better than 1e-6 px wherever the
    correction is monotonic over the sensor.

    Parameters
    ----------
    xy : array (..., 2)
        Corrected pixel coordinates.

    Returns
    -------
    array (..., 2)
        Raw pixel coordinates.
    """
    xy = np.asarray(xy, dtype=float)
    if not intr.has_distortion and intr.aspect == 1.0:
        return xy.copy()
    c = intr.centre
    a = intr.aspect
    ux = xy[..., 0] - c[0]
    uy = a * (xy[..., 1] - c[1])
    rho = np.sqrt(ux * ux + uy * uy)
    scale = _radius_scale_inverse(rho, intr.radial)
    out = np.empty_like(xy)
    out[..., 0] = c[0] + scale * ux
    out[..., 1] = c[1] + scale * uy / a
    return out


# --------------------------------------------------------------------------------------
# Projection and rays
# --------------------------------------------------------------------------------------


def project_corrected(X: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World points to *corrected* pixels (no distortion).

    ``X (..., 3)`` mm; ``R (..., 3, 3)`` and ``t (..., 3)`` broadcast against ``X``'s leading
    axes. Points behind the camera come out as NaN.
    """
    X = np.asarray(X, dtype=float)
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    x, y, zw = X[..., 0], X[..., 1], X[..., 2]
    xc = R[..., 0, 0] * x + R[..., 0, 1] * y + R[..., 0, 2] * zw + t[..., 0]
    yc = R[..., 1, 0] * x + R[..., 1, 1] * y + R[..., 1, 2] * zw + t[..., 1]
    z = R[..., 2, 0] * x + R[..., 2, 1] * y + R[..., 2, 2] * zw + t[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(z > 0, 1.0 / np.where(z > 0, z, 1.0), np.nan)
    xn = xc * inv
    yn = yc * inv
    x0, y0 = intr.principal_point
    f = intr.focal_length
    out = np.empty(xn.shape + (2,))
    out[..., 0] = f * xn + intr.skew * yn + x0
    out[..., 1] = (f / intr.aspect) * yn + y0
    return out


def project(X: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World points to raw pixels: ``K (R X + t)``, then the inverse radial correction.

    Parameters
    ----------
    X : array (..., 3)
        World points, mm. NaN propagates.
    intr : Intrinsics
    R : array (3, 3) or (..., 3, 3)
        World-to-camera rotation(s), broadcast against ``X``.
    t : array (3,) or (..., 3)
        Translation(s), mm.

    Returns
    -------
    array (..., 2)
        Raw pixels; NaN for points behind the camera.
    """
    return distort(project_corrected(X, intr, R, t), intr)


def backproject(xy: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Raw pixels to world rays.

    Parameters
    ----------
    xy : array (..., 2)
        Raw pixels.
    R, t : arrays (3, 3), (3,) or broadcastable (..., 3, 3), (..., 3)
        World-to-camera pose.

    Returns
    -------
    origin : array (..., 3)
        Camera centre in world coordinates, mm.
    direction : array (..., 3)
        Unit direction of the ray in world coordinates.
    """
    d_cam = normalized_rays(xy, intr)
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    d = np.einsum("...ji,...j->...i", R, d_cam)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    origin = np.broadcast_to(camera_centre(R, t), d.shape).copy()
    return origin, d


def normalized_rays(xy: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Raw pixels ``(..., 2)`` to camera-frame ray vectors ``(..., 3)`` with ``z = 1``."""
    pc = undistort(xy, intr)
    x0, y0 = intr.principal_point
    f = intr.focal_length
    yn = (pc[..., 1] - y0) * intr.aspect / f
    xn = (pc[..., 0] - x0 - intr.skew * yn) / f
    return np.stack([xn, yn, np.ones_like(xn)], axis=-1)


# --------------------------------------------------------------------------------------
# Epipolar geometry
# --------------------------------------------------------------------------------------


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=float)


def fundamental_matrix(intr1: Intrinsics, R1: np.ndarray, t1: np.ndarray,
                       intr2: Intrinsics, R2: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Fundamental matrix (3, 3) between two cameras in *corrected* pixels: ``x2^T F x1 = 0``."""
    R = np.asarray(R2) @ np.asarray(R1).T
    t = np.asarray(t2) - R @ np.asarray(t1)
    E = _skew(t) @ R
    F = np.linalg.inv(intr2.K).T @ E @ np.linalg.inv(intr1.K)
    return F / np.linalg.norm(F)


def symmetric_epipolar_distance(xy1: np.ndarray, xy2: np.ndarray,
                                intr1: Intrinsics, R1: np.ndarray, t1: np.ndarray,
                                intr2: Intrinsics, R2: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance between raw-pixel points in two cameras.

    The mean of the distance from ``x2`` to the epipolar line of ``x1`` in camera 2 and the
    distance from ``x1`` to the epipolar line of ``x2`` in camera 1, measured in corrected
    pixels (which differ from raw pixels only by the local radial scale).

    Parameters
    ----------
    xy1 : array (..., 2)
        Raw pixels in camera 1.
    xy2 : array (..., 2)
        Raw pixels in camera 2, broadcast against ``xy1`` (e.g. ``(N, 1, 2)`` against
        ``(1, M, 2)`` gives the ``N x M`` distance table).

    Returns
    -------
    array (...)
        Distances in pixels.
    """
    F = fundamental_matrix(intr1, R1, t1, intr2, R2, t2)
    p1 = undistort(xy1, intr1)
    p2 = undistort(xy2, intr2)
    h1 = np.concatenate([p1, np.ones(p1.shape[:-1] + (1,))], axis=-1)
    h2 = np.concatenate([p2, np.ones(p2.shape[:-1] + (1,))], axis=-1)
    l2 = h1 @ F.T  # lines in image 2: F x1
    l1 = h2 @ F    # lines in image 1: F^T x2
    num = np.abs(np.sum(h2 * l2, axis=-1))  # |x2^T F x1|, broadcast
    d2 = num / np.hypot(l2[..., 0], l2[..., 1])
    d1 = num / np.hypot(l1[..., 0], l1[..., 1])
    return 0.5 * (d1 + d2)
