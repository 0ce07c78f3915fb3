"""Detection of small shaded marker spheres (retro-reflective body markers seen in room light).

Such a marker, 5-10 px across, is neither a white nor a black dot: a bright highlight on one
side, a dark crescent on the other, its middle often darker than the skin around it (the
Pose2Sim demo's body markers in room light). What singles it out is a compact disc of strong
contrast of both signs on a smooth surround. Steps:

1. *Candidates* (:func:`sphere_candidates`): local maxima (7 x 7) of the difference of
   Gaussians (sigma 2 and 5 px) of the absolute departure from the local background (a 15 px
   median), above ``min_contrast`` grey levels, not line-like (the Hessian's smaller
   curvature at least 0.1 x the larger: a highlight beside a crescent makes an elongated
   spot). :func:`detect_spheres` then keeps those with a highlight and a shadow
   (``min_highlight``, ``min_shadow`` above and below the background) within reach.
2. *Model fit* (:func:`fit_spheres`): in a circular window around each candidate the image is
   fitted by linear least squares, for every hypothesis of centre ``(cx, cy)`` and radius
   ``r``, with a shaded sphere on a plane: inside the soft-edged disc (``edge_blur`` px) a
   quadratic in the sphere's unit normal ``n`` (``1, nx, ny, nz, nx^2, nx ny, ny^2``: any
   direction of light, the shadow side included), outside ``e + f u + g v``. The residual of a
   hypothesis is ``|y|^2 - |Q_k^T y|^2`` (``Q_k`` an orthonormal basis of its design): one
   matrix product for all candidates and hypotheses, since the hypotheses are sub-pixel offsets
   from the candidate's integer pixel and share their designs. A coarse grid (0.5 px, radii in
   0.5 px steps) then a fine one (0.125 px, +-0.25 px in radius) around the best, with a
   parabolic refinement of the residual, give the centre of the *sphere* (its silhouette), not
   of its highlight: median 0.18 px, at most 0.45 px from the truth on rendered spheres whose
   highlight lies 1-3 px off centre (``tests/core/test_sphere_markers.py``).
3. *Score*: the fraction of the window's variance about a plane that the sphere explains
   (``1 - RSS_sphere / RSS_plane``, 0..1): straight edges and texture leave residuals and
   score low; the demo's markers score 0.5-0.85, rendered ones 0.9+. Detections within the
   radius of a better one are dropped.

The result has the layout of :func:`carapost.core.blobs.detect_blobs` (the fields of
:data:`carapost.model.detections.DETECTION_FIELDS`), ``major = minor =`` the fitted radius,
``polarity`` +1 (white: the markers are retro-reflective), so automatic initialization and
matching take it unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from ..model.detections import DETECTION_FIELDS, WHITE

__all__ = ["SphereParameters", "detect_spheres", "fit_spheres", "sphere_candidates"]


@dataclass(frozen=True)
class SphereParameters:
    """Settings of :func:`detect_spheres`.

    min_radius, max_radius : float
        Range of sphere radii searched, px (silhouette radius).
    threshold : float
        Minimum score (fraction of the window's variance about a plane explained by the
        sphere, 0..1).
    min_contrast : float
        Minimum band-pass response of a candidate (difference of Gaussians of the absolute
        departure from the local background), grey levels.
    min_highlight, min_shadow : float
        The brightest pixel of the sphere must lie this much above the local background, its
        darkest this much below, grey levels (a lit sphere in room light shows both; set
        ``min_shadow=0`` for spheres brighter than everything around them).
    max_candidates : int
        At most this many candidates (strongest band-pass energy first) are fitted.
    edge_blur : float
        Width of the disc's soft edge, px (the optics' and the codec's blur).
    """

    min_radius: float = 2.5
    max_radius: float = 5.5
    threshold: float = 0.5
    min_contrast: float = 8.0
    min_highlight: float = 30.0
    min_shadow: float = 30.0
    max_candidates: int = 3000
    edge_blur: float = 2.0

    def __post_init__(self) -> None:
        if not 1.0 <= self.min_radius <= self.max_radius <= 12.0:
            raise ValueError(f"sphere radii must satisfy 1 <= min_radius <= max_radius <= 12 px, "
                             f"got {self.min_radius}, {self.max_radius}")
        if not 0.0 <= self.threshold < 1.0:
            raise ValueError(f"sphere threshold must be in [0, 1), got {self.threshold}")
        if self.max_candidates < 1 or self.edge_blur <= 0 or min(self.min_contrast, self.min_highlight,
                                                                                   self.min_shadow) < 0:
            raise ValueError("max_candidates must be >= 1, edge_blur > 0, min_contrast, min_highlight and "
                             "min_shadow >= 0")

    @property
    def radii(self) -> np.ndarray:
        """Radii of the coarse search, px (0.5 px steps)."""
        n = int(np.floor((self.max_radius - self.min_radius) / 0.5 + 1e-9)) + 1
        return self.min_radius + 0.5 * np.arange(n)

    @property
    def half_window(self) -> int:
        """Half side of the fitting window, px (radius, soft edge and a 2 px surround)."""
        return int(np.ceil(self.max_radius + 0.5 * self.edge_blur + 2.5))


#: Coarse search: sub-pixel offsets of the centre from the candidate pixel, px.
_COARSE = np.arange(-1.5, 1.51, 0.5)
#: Fine search around the coarse optimum, px (offsets and radius steps).
_FINE = np.arange(-0.375, 0.376, 0.125)
_FINE_R = np.array([-0.25, 0.0, 0.25])
#: Terms of the sphere-on-plane model (:func:`_designs`).
_TERMS = 10
#: Side of the median filter giving the local background, px (odd; larger than a marker).
_BACKGROUND_PX = 15
#: Candidates' smaller principal curvature must be at least this fraction of the larger.
_MIN_ROUNDNESS = 0.1


def _check(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"sphere detection needs a 2-D uint8 grayscale image, got {image.dtype} {image.shape}")
    return image


def _deviation(image: np.ndarray) -> np.ndarray:
    """Signed departure of each pixel from its local background (15 px median), float32 (H, W)."""
    return image.astype(np.float32) - cv2.medianBlur(image, _BACKGROUND_PX).astype(np.float32)


def sphere_candidates(image: np.ndarray, params: SphereParameters) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel positions of candidate spheres.

    Local maxima (7 x 7) of the difference of Gaussians (sigma 2 and 5 px) of the absolute
    departure from the local background: compact spots of contrast of either sign (highlight,
    shadow crescent or both), above ``params.min_contrast``, roughly round (the smaller
    principal curvature at least 0.1 x the larger: straight edges are left out).

    Returns ``(x, y)`` int arrays (n,), strongest first, at most ``params.max_candidates``,
    at least ``params.half_window + 1`` px from the image border.
    """
    dev = np.abs(_deviation(_check(image)))
    g1 = cv2.GaussianBlur(dev, (0, 0), 2.0)
    resp = g1 - cv2.GaussianBlur(dev, (0, 0), 5.0)
    h = params.half_window
    peak = cv2.dilate(resp, np.ones((7, 7), np.uint8))
    ok = (resp >= peak) & (resp > params.min_contrast)
    ok[:h + 1], ok[-h - 1:], ok[:, :h + 1], ok[:, -h - 1:] = False, False, False, False
    y, x = np.nonzero(ok)
    gxx = cv2.Sobel(g1, cv2.CV_32F, 2, 0, ksize=5)[y, x]
    gyy = cv2.Sobel(g1, cv2.CV_32F, 0, 2, ksize=5)[y, x]
    gxy = cv2.Sobel(g1, cv2.CV_32F, 1, 1, ksize=5)[y, x]
    mean, half = -(gxx + gyy) / 2, np.sqrt(((gxx - gyy) / 2) ** 2 + gxy ** 2)
    round_ = (mean - half) >= _MIN_ROUNDNESS * (mean + half)
    x, y = x[round_], y[round_]
    order = np.argsort(-resp[y, x], kind="stable")[:params.max_candidates]
    return x[order], y[order]


def _designs(params: SphereParameters, offsets: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Design matrices of the sphere-on-plane model for each hypothesis.

    offsets : (K, 2) centre offsets from the window centre, px; radii : (K,) px.
    Returns ``A (K, P, 7)`` over the window's P pixels and the window's pixel offsets (P, 2).
    """
    h = params.half_window
    g = np.arange(-h, h + 1, dtype=float)
    u, v = np.meshgrid(g, g)
    win = u ** 2 + v ** 2 <= (h + 0.5) ** 2
    u, v = u[win], v[win]
    du = u[None] - offsets[:, 0:1]
    dv = v[None] - offsets[:, 1:2]
    r = radii[:, None]
    d = np.hypot(du, dv)
    w = np.clip(0.5 + (r - d) / params.edge_blur, 0.0, 1.0)
    nx, ny = np.clip(du / r, -1, 1), np.clip(dv / r, -1, 1)
    nz = np.sqrt(np.clip(1.0 - (d / r) ** 2, 0.0, 1.0))
    A = np.stack([w, w * nx, w * ny, w * nz, w * nx * nx, w * nx * ny, w * ny * ny,
                  1 - w, (1 - w) * u[None] / h, (1 - w) * v[None] / h], axis=-1)
    return A, np.c_[u, v]


def _basis(A: np.ndarray) -> np.ndarray:
    """Orthonormal bases of the designs ``A (K, P, m)``, side by side: (P, K * m)."""
    K, P, m = A.shape
    Q, _ = np.linalg.qr(A)
    return np.ascontiguousarray(Q.transpose(1, 0, 2).reshape(P, K * m))


@lru_cache(maxsize=4)
def _coarse(params: SphereParameters) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The coarse hypotheses (offsets (K, 2), radii (K,)), their bases and the window's offsets."""
    ox, oy, rr = np.meshgrid(_COARSE, _COARSE, params.radii, indexing="ij")
    offs, rads = np.c_[ox.ravel(), oy.ravel()], rr.ravel()
    A, uv = _designs(params, offs, rads)
    return offs, rads, _basis(A).astype(np.float32), uv


def _rss(Y: np.ndarray, yy: np.ndarray, Q: np.ndarray, m: int = _TERMS) -> np.ndarray:
    """Residual sum of squares of every window ``Y (N, P)`` under every design whose
    orthonormal basis is a block of ``m`` columns of ``Q (P, K * m)``: (N, K)."""
    B = Y @ Q
    return yy[:, None] - np.einsum("nkm,nkm->nk", *(2 * (B.reshape(len(Y), -1, m),)))


def _windows(img: np.ndarray, x: np.ndarray, y: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixel values (N, P) of the windows centred on integer ``(x, y)``; ``uv (P, 2)`` offsets."""
    return img[y[:, None] + uv[None, :, 1].astype(int), x[:, None] + uv[None, :, 0].astype(int)]


def _parabolic(f_m: np.ndarray, f_0: np.ndarray, f_p: np.ndarray) -> np.ndarray:
    """Vertex offset (in steps, within +-0.5) of the parabola through three values."""
    den = f_m - 2 * f_0 + f_p
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(den > 0, 0.5 * (f_m - f_p) / den, 0.0)
    return np.clip(s, -0.5, 0.5)


def fit_spheres(image: np.ndarray, x: np.ndarray, y: np.ndarray, params: SphereParameters) -> dict[str, np.ndarray]:
    """Fit the shaded-sphere model around integer candidate positions.

    Parameters
    ----------
    image : uint8 (H, W)
    x, y : int (N,)
        Candidate pixels, at least ``params.half_window + 1`` from the border.

    Returns
    -------
    dict with float64 (N,) arrays ``x, y`` (sphere centre, px), ``radius`` (px), ``score``
    (fraction of the variance about a plane explained, 0..1), ``contrast`` (RMS of the
    fitted sphere's departure from the plane over the disc, grey levels), ``bright`` and
    ``dark`` (the largest departure above and below the local background within the disc
    and 1 px around it, grey levels: the highlight and the shadow side).
    """
    img = _check(image).astype(np.float64)
    x, y = np.asarray(x, int), np.asarray(y, int)
    n = len(x)
    if n == 0:
        return {k: np.zeros(0) for k in ("x", "y", "radius", "score", "contrast", "bright", "dark")}
    # coarse: every radius, 0.5 px offsets
    offs, rads, Qc, uv = _coarse(params)
    Y = _windows(img, x, y, uv)
    Y = (Y - Y.mean(axis=1, keepdims=True)).astype(np.float32)  # the coarse optimum only: float32 will do
    yy = np.einsum("np,np->n", Y, Y)
    best = np.argmin(_rss(Y, yy, Qc), axis=1)
    cx, cy, cr = x + offs[best, 0], y + offs[best, 1], rads[best]
    # fine: re-centre on the nearest pixel, 0.125 px offsets around the coarse optimum
    ix, iy = np.rint(cx).astype(int), np.rint(cy).astype(int)
    h = params.half_window
    H, W = img.shape
    ix, iy = np.clip(ix, h, W - 1 - h), np.clip(iy, h, H - 1 - h)
    fx, fy = cx - ix, cy - iy
    Y = _windows(img, ix, iy, uv)
    Y = Y - Y.mean(axis=1, keepdims=True)
    yy = np.einsum("np,np->n", Y, Y)
    nf = len(_FINE)
    gx, gy, gr = np.meshgrid(_FINE, _FINE, _FINE_R, indexing="ij")
    gx, gy, gr = gx.ravel(), gy.ravel(), gr.ravel()
    # the fine grid is relative to each candidate's coarse optimum: group by that optimum
    rss = np.empty((n, len(gx)))
    key = np.round(np.c_[fx, fy, cr] * 8).astype(int)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    for j, kk in enumerate(uniq):
        sel = np.flatnonzero(inv == j)
        o = np.c_[kk[0] / 8 + gx, kk[1] / 8 + gy]
        rad = np.maximum(kk[2] / 8 + gr, 1.0)
        Aj, _ = _designs(params, o, rad)
        rss[sel] = _rss(Y[sel], yy[sel], _basis(Aj))
    cube = rss.reshape(n, nf, nf, len(_FINE_R))
    flat = np.argmin(rss, axis=1)
    i, j, k = np.unravel_index(flat, cube.shape[1:])
    ar = np.arange(n)
    im, ip = np.clip(i - 1, 0, nf - 1), np.clip(i + 1, 0, nf - 1)
    jm, jp = np.clip(j - 1, 0, nf - 1), np.clip(j + 1, 0, nf - 1)
    km, kp = np.clip(k - 1, 0, len(_FINE_R) - 1), np.clip(k + 1, 0, len(_FINE_R) - 1)
    f0 = cube[ar, i, j, k]
    sx = np.where((i > 0) & (i < nf - 1), _parabolic(cube[ar, im, j, k], f0, cube[ar, ip, j, k]), 0.0)
    sy = np.where((j > 0) & (j < nf - 1), _parabolic(cube[ar, i, jm, k], f0, cube[ar, i, jp, k]), 0.0)
    sr = np.where((k > 0) & (k < len(_FINE_R) - 1), _parabolic(cube[ar, i, j, km], f0, cube[ar, i, j, kp]), 0.0)
    step, rstep = _FINE[1] - _FINE[0], _FINE_R[1] - _FINE_R[0]
    out_x = ix + fx + _FINE[i] + sx * step
    out_y = iy + fy + _FINE[j] + sy * step
    out_r = np.maximum(cr + _FINE_R[k] + sr * rstep, 1.0)
    # score against a plane over the same window
    rss0 = _rss(Y, yy, _basis(np.c_[np.ones(len(uv)), uv / h][None]), 3)[:, 0]
    score = np.where(rss0 > 0, 1.0 - f0 / np.maximum(rss0, 1e-12), 0.0)
    area = np.pi * out_r ** 2
    contrast = np.sqrt(np.maximum(rss0 - f0, 0.0) / area)
    # the brightest and darkest departures from the local background within the disc (+1 px)
    dev = _windows(_deviation(image), ix, iy, uv)
    inside = np.hypot(uv[None, :, 0] - (out_x - ix)[:, None], uv[None, :, 1] - (out_y - iy)[:, None]) \
        <= out_r[:, None] + 1.0
    bright = np.max(np.where(inside, dev, -np.inf), axis=1)
    dark = -np.min(np.where(inside, dev, np.inf), axis=1)
    return {"x": out_x, "y": out_y, "radius": out_r, "score": np.clip(score, 0.0, 1.0), "contrast": contrast,
            "bright": bright, "dark": dark}


def _suppress(x: np.ndarray, y: np.ndarray, r: np.ndarray, score: np.ndarray) -> np.ndarray:
    """bool (N,): keep each detection unless a better one that is kept lies within its radius
    (greedy, best score first; only neighbours within the largest radius are looked at)."""
    from scipy.spatial import cKDTree

    n = len(x)
    keep = np.zeros(n, bool)
    if n == 0:
        return keep
    pairs = cKDTree(np.c_[x, y]).query_pairs(r=float(r.max()), output_type="ndarray")
    a, b = np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]]
    close = (x[a] - x[b]) ** 2 + (y[a] - y[b]) ** 2 < r[a] ** 2   # b would hide a
    a, b = a[close], b[close]
    by_a = np.argsort(a, kind="stable")
    a, b = a[by_a], b[by_a]
    start = np.searchsorted(a, np.arange(n + 1))
    for i in np.argsort(-score, kind="stable"):
        if not keep[b[start[i]:start[i + 1]]].any():
            keep[i] = True
    return keep


def detect_spheres(image: np.ndarray, params: SphereParameters | None = None, *,
                   mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Detect shaded marker spheres in one image.

    Parameters
    ----------
    image : uint8 (H, W)
        Grayscale frame.
    params : SphereParameters, optional
        Radius range, score threshold, candidate limits (defaults: radius 2.5-5.5 px, score 0.5,
        highlight and shadow 30 grey levels).
    mask : bool (H, W), optional
        True where pixels must be ignored (detections whose centre falls there are dropped).

    Returns
    -------
    dict of str to array
        The fields of :data:`carapost.model.detections.DETECTION_FIELDS`, one row per sphere
        (sorted by y then x): centre ``x, y`` (raw px, sub-pixel: the sphere's centre),
        ``major = minor`` (its radius, px), ``angle`` 0, ``polarity`` +1, ``score`` (0..1).

    Raises
    ------
    ValueError
        If the image is not a 2-D uint8 array or the mask does not match it.
    """
    params = params or SphereParameters()
    image = _check(image)
    if mask is not None and np.shape(mask) != image.shape:
        raise ValueError(f"sphere detection: mask shape {np.shape(mask)} does not match image {image.shape}")
    cx, cy = sphere_candidates(image, params)
    # a sphere's highlight and shadow lie within its radius + 1 px of its centre, the centre
    # within 2.5 px (each axis) of the candidate: candidates without both that close are not fitted
    if len(cx) and (params.min_highlight > 0 or params.min_shadow > 0):
        dev = _deviation(image)
        reach = int(np.ceil(params.max_radius + 1.5 + 2.5 * np.sqrt(2.0)))
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
        near = (cv2.dilate(dev, disc)[cy, cx] >= params.min_highlight) \
            & (-cv2.erode(dev, disc)[cy, cx] >= params.min_shadow)
        cx, cy = cx[near], cy[near]
    fit = fit_spheres(image, cx, cy, params)
    ok = (fit["score"] > params.threshold) & (fit["radius"] >= params.min_radius - 0.5) \
        & (fit["radius"] <= params.max_radius + 0.5) \
        & (fit["bright"] >= params.min_highlight) & (fit["dark"] >= params.min_shadow)
    ok &= (np.abs(fit["x"] - cx) <= 2.5) & (np.abs(fit["y"] - cy) <= 2.5)
    if mask is not None and ok.any():
        m = np.asarray(mask, bool)
        H, W = image.shape
        px = np.clip(np.rint(fit["x"]).astype(int), 0, W - 1)
        py = np.clip(np.rint(fit["y"]).astype(int), 0, H - 1)
        ok &= ~m[py, px]
    sel = np.flatnonzero(ok)
    keep = sel[_suppress(fit["x"][sel], fit["y"][sel], fit["radius"][sel], fit["score"][sel])]
    keep = keep[np.lexsort((fit["x"][keep], fit["y"][keep]))]
    n = len(keep)
    out = {"x": fit["x"][keep], "y": fit["y"][keep], "major": fit["radius"][keep], "minor": fit["radius"][keep],
           "angle": np.zeros(n), "polarity": np.full(n, WHITE), "score": fit["score"][keep]}
    return {k: np.asarray(out[k]).astype(dt, copy=False) for k, dt in DETECTION_FIELDS.items()}
