"""Lens models other than the XCP radial correction, and conversion between them.

OpenCV's Brown model (``k1, k2, p1, p2[, k3[, k4, k5, k6]]``, also Qualisys') and fisheye
model act on *normalised* coordinates and go from undistorted to distorted. The XCP model
(:mod:`carapost.core.camera`) goes the other way, from raw to corrected *pixels*, with a
polynomial in the pixel radius. Neither direction is exactly representable in the other, so
the conversions are linear least-squares fits over the image, each reporting its largest
residual in pixels.

All functions are vectorised over points; nothing here reads files.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from carapost.core.camera import Intrinsics, undistort

__all__ = [
    "brown_distort",
    "brown_undistort",
    "fisheye_distort",
    "fisheye_undistort",
    "pixel_grid",
    "pixels_to_normalised",
    "normalised_to_pixels",
    "fit_radial_correction",
    "monotonic_radius",
    "fit_brown_distortion",
]


def _brown_coeffs(coeffs: Sequence[float] | np.ndarray) -> np.ndarray:
    c = np.asarray(coeffs, dtype=float).ravel()
    if c.size not in (0, 4, 5, 8):
        raise ValueError(f"OpenCV distortion needs 4, 5 or 8 coefficients, got {c.size}")
    out = np.zeros(8)
    out[:c.size] = c
    return out


def brown_distort(xy: np.ndarray, coeffs: Sequence[float] | np.ndarray) -> np.ndarray:
    """OpenCV/Brown distortion of normalised coordinates.

    Parameters
    ----------
    xy : array (..., 2)
        Undistorted normalised coordinates ``(X/Z, Y/Z)``.
    coeffs : sequence of float
        ``k1, k2, p1, p2[, k3[, k4, k5, k6]]`` (OpenCV order; 4, 5 or 8 values).

    Returns
    -------
    array (..., 2)
        Distorted normalised coordinates.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = _brown_coeffs(coeffs)
    xy = np.asarray(xy, dtype=float)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    out = np.empty_like(xy, dtype=float)
    out[..., 0] = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    out[..., 1] = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return out


def brown_undistort(xy_d: np.ndarray, coeffs: Sequence[float] | np.ndarray) -> np.ndarray:
    """Invert :func:`brown_distort` by fixed-point iteration (as OpenCV does).

    ``xy_d (..., 2)`` distorted normalised coordinates to undistorted ``(..., 2)``.

    NaN where the iteration does not converge to 1e-10 (folded or extreme regions).
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = _brown_coeffs(coeffs)
    xy_d = np.asarray(xy_d, dtype=float)
    x = xy_d[..., 0].copy()
    y = xy_d[..., 1].copy()
    with np.errstate(all="ignore"):
        for _ in range(100):
            r2 = x * x + y * y
            icdist = (1 + r2 * (k4 + r2 * (k5 + r2 * k6))) / (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (xy_d[..., 0] - dx) * icdist
            y = (xy_d[..., 1] - dy) * icdist
        out = np.stack([x, y], axis=-1)
        err = np.linalg.norm(brown_distort(out, coeffs) - xy_d, axis=-1)
    out[~(err < 1e-10)] = np.nan
    return out


def _fisheye_coeffs(coeffs: Sequence[float] | np.ndarray) -> np.ndarray:
    c = np.asarray(coeffs, dtype=float).ravel()
    if c.size != 4:
        raise ValueError(f"OpenCV fisheye distortion needs 4 coefficients, got {c.size}")
    return c


def fisheye_distort(xy: np.ndarray, coeffs: Sequence[float] | np.ndarray) -> np.ndarray:
    """OpenCV fisheye (equidistant) distortion of normalised coordinates ``(..., 2)``.

    ``theta = atan(r)``, ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
    k4 theta^8)``, distorted = ``theta_d / r * xy``.
    """
    k1, k2, k3, k4 = _fisheye_coeffs(coeffs)
    xy = np.asarray(xy, dtype=float)
    r = np.hypot(xy[..., 0], xy[..., 1])
    th = np.arctan(r)
    th2 = th * th
    thd = th * (1 + th2 * (k1 + th2 * (k2 + th2 * (k3 + th2 * k4))))
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 1e-12, thd / np.where(r > 1e-12, r, 1.0), 1.0)
    return xy * scale[..., None]


def fisheye_undistort(xy_d: np.ndarray, coeffs: Sequence[float] | np.ndarray) -> np.ndarray:
    """Invert :func:`fisheye_distort` (Newton on theta), ``(..., 2)`` to ``(..., 2)``.

    NaN where it fails or the ray would be at or beyond 90 degrees.
    """
    k1, k2, k3, k4 = _fisheye_coeffs(coeffs)
    xy_d = np.asarray(xy_d, dtype=float)
    thd = np.hypot(xy_d[..., 0], xy_d[..., 1])
    th = thd.copy()
    with np.errstate(all="ignore"):
        for _ in range(50):
            t2 = th * th
            g = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - thd
            dg = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            th = th - g / dg
        r = np.tan(th)
        scale = np.where(thd > 1e-12, r / np.where(thd > 1e-12, thd, 1.0), 1.0)
        out = xy_d * scale[..., None]
        err = np.abs(fisheye_distort(out, coeffs) - xy_d).max(-1)
        bad = ~((th >= 0) & (th < np.pi / 2 - 1e-6)) | ~(err < 1e-10)
    out[bad] = np.nan
    return out


def pixel_grid(size: tuple[int, int], n: int = 61) -> np.ndarray:
    """An ``n x n`` grid of raw pixels ``(n*n, 2)`` spanning the image (corners included)."""
    w, h = size
    gx, gy = np.meshgrid(np.linspace(0.0, w - 1.0, n), np.linspace(0.0, h - 1.0, n))
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def pixels_to_normalised(p: np.ndarray, intr: Intrinsics) -> np.ndarray:
    x0, y0 = intr.principal_point
    yn = (p[..., 1] - y0) * intr.aspect / intr.focal_length
    xn = (p[..., 0] - x0 - intr.skew * yn) / intr.focal_length
    return np.stack([xn, yn], axis=-1)


def normalised_to_pixels(xy: np.ndarray, intr: Intrinsics) -> np.ndarray:
    x0, y0 = intr.principal_point
    f = intr.focal_length
    return np.stack([f * xy[..., 0] + intr.skew * xy[..., 1] + x0,
                     f / intr.aspect * xy[..., 1] + y0], axis=-1)


def _radial_lstsq(p_r: np.ndarray, p_c: np.ndarray, centre: np.ndarray, aspect: float, f: float,
                  n_terms: int) -> tuple[np.ndarray, np.ndarray]:
    """Best ``k`` for a given distortion centre; returns ``(k (3,), residuals (N, 2) px)``."""
    d = np.stack([p_r[:, 0] - centre[0], aspect * (p_r[:, 1] - centre[1])], axis=1)
    e = np.stack([p_c[:, 0] - centre[0], aspect * (p_c[:, 1] - centre[1])], axis=1)
    scale = max(f, 1.0) ** 2  # conditioning: fit in powers of (r / f)^2
    u = (d * d).sum(axis=1) / scale
    cols = np.stack([u ** (j + 1) for j in range(n_terms)], axis=1)  # (N, n)
    A = (cols[:, None, :] * d[:, :, None]).reshape(-1, n_terms)
    b = (e - d).reshape(-1)
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    k = np.zeros(3)
    k[:n_terms] = coef / scale ** np.arange(1, n_terms + 1)
    res = (A @ coef - b).reshape(-1, 2)
    res[:, 1] /= aspect
    return k, res


def fit_radial_correction(linear: Intrinsics, undistort_normalised: Callable[[np.ndarray], np.ndarray],
                          *, n_terms: int = 3, fit_centre: bool = False,
                          grid: int = 61) -> tuple[Intrinsics, dict[str, Any]]:
    """Fit the XCP radial correction to another lens model, by least squares over the image.

    Raw pixels on a ``grid x grid`` lattice over ``linear.sensor_size`` are undistorted by
    the other model; the XCP correction ``p_c = c + s(r) (p_r - c)``,
    ``s = 1 + k1 r^2 + k2 r^4 + k3 r^6`` (``r`` in pixels) is fitted to those pairs (linear
    least squares on the displacement).

    Parameters
    ----------
    linear : Intrinsics
        Focal length, principal point, aspect, skew and sensor size (its radial terms are
        ignored). ``sensor_size`` must be positive.
    undistort_normalised : callable
        Maps distorted normalised coordinates ``(N, 2)`` to undistorted ones (NaN where the
        model cannot be inverted; such points are left out of the fit).
    n_terms : int
        Number of radial terms fitted (1 to 3).
    fit_centre : bool
        Also fit the distortion centre (``VICON_RADIAL2``'s own centre). A shifted centre
        absorbs most of a decentring (tangential) distortion, which the radial model
        cannot otherwise represent. Without it the centre is the principal point.

    Returns
    -------
    intrinsics : Intrinsics
        ``linear`` with ``radial`` set, and ``distortion_centre`` when ``fit_centre``.
    report : dict
        ``max_residual_px`` and ``rms_residual_px`` of the fit over the grid, ``n_points``
        used, and ``centre_shift_px`` (distortion centre minus principal point).

    Raises
    ------
    ValueError
        If the sensor size is unknown or fewer than 10 grid points could be undistorted.
    """
    if not (1 <= n_terms <= 3):
        raise ValueError(f"n_terms must be 1..3, got {n_terms}")
    w, h = linear.sensor_size
    if w <= 0 or h <= 0:
        raise ValueError("the image size is needed to convert the distortion model")
    base = linear.with_(radial=(0.0, 0.0, 0.0), distortion_centre=None)
    p_r = pixel_grid((w, h), grid)
    xu = undistort_normalised(pixels_to_normalised(p_r, base))
    ok = np.isfinite(xu).all(axis=1)
    if ok.sum() < 10:
        raise ValueError("the distortion model cannot be inverted over the image")
    p_r, p_c = p_r[ok], normalised_to_pixels(xu[ok], base)
    pp = np.asarray(base.principal_point, dtype=float)
    a, f = base.aspect, base.focal_length
    centre = pp
    if fit_centre:
        from scipy.optimize import least_squares

        def resid(delta: np.ndarray) -> np.ndarray:
            return _radial_lstsq(p_r, p_c, pp + delta, a, f, n_terms)[1].ravel()

        centre = pp + least_squares(resid, np.zeros(2), x_scale=10.0).x
    k, res = _radial_lstsq(p_r, p_c, centre, a, f, n_terms)
    rn = np.linalg.norm(res, axis=1)
    out = base.with_(radial=(float(k[0]), float(k[1]), float(k[2])),
                     distortion_centre=(float(centre[0]), float(centre[1])) if fit_centre else None)
    return out, {"max_residual_px": float(rn.max()), "rms_residual_px": float(np.sqrt(np.mean(rn ** 2))),
                 "n_points": int(ok.sum()), "centre_shift_px": [float(v) for v in centre - pp]}


def monotonic_radius(radial: Sequence[float] | np.ndarray) -> float:
    """Largest raw radius (px) up to which the XCP correction ``r s(r)`` keeps increasing.

    Beyond it the polynomial folds back (two raw radii map to one corrected radius) and the
    model is meaningless; Vicon calibrations reach this near the sensor corners of some
    cameras, where no wand data was seen. ``inf`` if it never folds.
    """
    k1, k2, k3 = (list(radial) + [0.0, 0.0, 0.0])[:3]
    # d(r s)/dr = 1 + 3 k1 u + 5 k2 u^2 + 7 k3 u^3 with u = r^2
    coeffs = np.trim_zeros(np.array([7 * k3, 5 * k2, 3 * k1, 1.0]), "f")
    if coeffs.size <= 1:
        return float("inf")
    roots = np.roots(coeffs)
    u = roots.real[(np.abs(roots.imag) <= 1e-9 * np.abs(roots)) & (roots.real > 0)]
    return float(np.sqrt(u.min())) if u.size else float("inf")


def fit_brown_distortion(intr: Intrinsics, *, rational: bool = False,
                         grid: int = 61) -> tuple[np.ndarray, dict[str, Any]]:
    """Fit OpenCV distortion coefficients to an XCP radial correction.

    Raw pixels over the image (within :func:`monotonic_radius`, where the XCP model is
    valid) are corrected with :func:`carapost.core.camera.undistort`, and the OpenCV
    forward model ``x_d = x_u (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``
    (normalised coordinates, ``r = |x_u|``) is fitted by linear least squares (the rational
    part linearised). ``K`` is exact; the distortion is approximate.

    Parameters
    ----------
    intr : Intrinsics
        Must have a positive ``sensor_size`` when it has distortion.
    rational : bool
        Also fit ``k4, k5, k6`` (OpenCV's rational model, 8 coefficients). Much closer
        near the corners of strongly distorting lenses (Vicon Vantage: tens of pixels with
        5 coefficients, a few with 8), but not every tool reads 8 coefficients.

    Returns
    -------
    coeffs : ndarray (5,) or (8,)
        OpenCV ``[k1, k2, p1, p2, k3(, k4, k5, k6)]`` with ``p1 = p2 = 0``.
    report : dict
        ``max_residual_px`` / ``rms_residual_px`` over the fitted region,
        ``max_residual_px_incircle`` within the circle inscribed in the image, and
        ``fitted_fraction`` of the image grid inside the valid region.
    """
    n = 8 if rational else 5
    if not intr.has_distortion:
        return np.zeros(n), {"max_residual_px": 0.0, "rms_residual_px": 0.0,
                             "max_residual_px_incircle": 0.0, "fitted_fraction": 1.0}
    w, h = intr.sensor_size
    if w <= 0 or h <= 0:
        raise ValueError("the image size is needed to convert the distortion model")
    p_r = pixel_grid((w, h), grid)
    rr = np.hypot(p_r[:, 0] - intr.centre[0], intr.aspect * (p_r[:, 1] - intr.centre[1]))
    keep = rr < 0.995 * monotonic_radius(intr.radial)
    p_r, rr = p_r[keep], rr[keep]
    if len(p_r) < 10:
        raise ValueError("the radial correction folds over almost the whole image")
    p_c = undistort(p_r, intr)
    xd = pixels_to_normalised(p_r, intr)
    xu = pixels_to_normalised(p_c, intr)
    r2 = (xu * xu).sum(axis=1)
    P = np.stack([r2, r2 ** 2, r2 ** 3], axis=1)
    cols = P[:, None, :] * xu[:, :, None]  # (N, 2, 3)
    if rational:
        cols = np.concatenate([cols, -P[:, None, :] * xd[:, :, None]], axis=2)
    A = cols.reshape(-1, cols.shape[2])
    b = (xd - xu).reshape(-1)
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    out = np.zeros(n)
    out[[0, 1, 4]] = coef[:3]
    if rational:
        out[5:] = coef[3:]
    res_px = normalised_to_pixels(brown_distort(xu, out), intr) - p_r
    rn = np.linalg.norm(res_px, axis=1)
    inc = rr <= min(w, h) / 2.0
    return out, {"max_residual_px": float(rn.max()), "rms_residual_px": float(np.sqrt(np.mean(rn ** 2))),
                 "max_residual_px_incircle": float(rn[inc].max()) if inc.any() else float("nan"),
                 "fitted_fraction": float(keep.mean())}
