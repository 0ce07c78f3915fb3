"""Per-candidate stage of the blob detector: level search, local background, ellipse, centre.

All candidates of one group (same pyramid level and patch size) are processed together on a
stack of square patches ``(N, S, S)``; nothing loops over candidates in Python. Morphology
and connectivity run on a "mosaic" of the patches (stacked with blank rows between them) in
single OpenCV calls.

For each candidate (signed image: the blob is bright):

1. **Ring background.** A plane is fitted (robustly) to the ring of the patch outside the
   expected blob; ``d0 = patch - plane``. The peak ``P`` is the largest 3x3 mean of ``d0``
   near the candidate.
2. **Level search.** The flood level ``L`` of every pixel — the highest level ``t`` at which
   it is still connected to the peak through pixels of ``d0 >= t`` — is computed once by
   morphological reconstruction (repeated 3x3 dilation clipped by the smoothed patch). The
   component of the peak at level ``f P`` is ``L >= f P``, so all levels come for free. The
   *core* is the component at the lowest level ``f`` in 0.5 .. 0.9 that is still a blob:
   not touching the patch border, not bigger than the largest allowed blob, and not having
   just merged with something (its area more than doubles from the level above). At half
   contrast a dot on an eyebrow or a lip line joins the band; a few levels up it is alone.
3. **Local background.** A plane fitted (robustly) to a thin band 2-4 px around the core,
   leaving out other bright structures: the dot's own surround (skin, or the band it sits on,
   or both across the band's edge). ``d = patch - plane``; the contrast ``C`` is the peak of
   the 3x3 mean of ``d`` in the core.
4. **Ellipse and centre** from the soft half-contrast region ``q = clip(1.5 (d/C - 1/2) +
   1/2, 0, 1)`` around the core: its centroid is the centre (noise enters only through the
   edge pixels; blur is symmetric and does not move it); its second moments give the
   covariance ``Sigma``, and a uniform ellipse has ``Sigma = diag(a^2, b^2) / 4``, so the
   semi-axes are ``2 sqrt(eig(Sigma))``.
5. **Shape measurements** for the classifier (:mod:`carapost.core.blob_score`): mismatch with
   the moment ellipse, central asymmetry, residual around the elliptical radial profile.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .blob_score import asymmetry, ellipse_distance, profile_rms, shape_residual

__all__ = ["PatchFit", "fit_patches", "patch_half_size", "LEVELS"]

#: Signed-image levels at or below / at or above which a pixel is black or clipped.
_FLAT_LO, _FLAT_HI = 4, 251
_SEP = 5  # blank rows between patches in a mosaic (> the largest dilation radius)
#: Levels (fractions of the peak over the ring background) searched for the blob's core.
LEVELS = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95)
#: A level's component is a blob while its area is at least this fraction of its moment
#: ellipse's (1 for an ellipse; a dot that has started to flood a band is elongated or
#: irregular) ...
_MIN_FILL = 0.9
#: ... a test made only on components of at least this many pixels, and at levels at least
#: this many noise sigmas (of the 3x3 mean) below the peak.
_FILL_MIN_AREA = 20
_TOP_NOISE = 4.0
#: ... and not above this level (the top of a flat, clipped or JPEG-coded dot is ragged).
_MAX_SHAPED_LEVEL = 0.8
#: Inner and outer radius (px) of the band around the core used as local background.
_BAND = (2, 4)
#: Largest fraction of a white blob's surround (2 px) that may be clipped at 255.
_MAX_SATURATED_RIM = 0.3
#: Slope of the soft half-contrast region ``q = clip(RAMP (d/C - 1/2) + 1/2, 0, 1)``.
_RAMP = 1.5
#: Fixed-point scale of the flood levels (int16; the peak is ``_FP``).
_FP = 1000
#: Trimmed moments: iterations, and the distance (px) beyond the moment ellipse from which
#: the region is dropped.
_TRIM_ITERS = 3
_TRIM_MARGIN = 1.0
DEBUG: dict | None = None


@dataclass
class PatchFit:
    """Fit results in the coordinates of the pyramid level the patches came from.

    Attributes
    ----------
    x, y : float64 (N,)
        Centre (level px).
    major, minor : float64 (N,)
        Ellipse semi-axes (level px).
    angle : float64 (N,)
        Major-axis direction, radians from +x towards +y, in (-pi/2, pi/2].
    contrast : float64 (N,)
        Peak blob signal above the local background (grey levels).
    background : float64 (N,)
        Local background level of the (signed) level image at the centre (grey levels).
    rise : float64 (N,)
        Local background minus the ring background at the centre, over the contrast: how far
        the blob stands on a band brighter than its wider surround (an eyebrow, a lip line).
    noise : float64 (N,)
        Standard deviation of the local background residual (grey levels).
    ring_noise : float64 (N,)
        Standard deviation of the ring background residual (grey levels).
    core_level : float64 (N,)
        The level (fraction of the peak over the ring) of the core (:data:`LEVELS`).
    found_level : float64 (N,)
        The core level the search found (``core_level`` is higher for an alternative outline,
        ``min_core``).
    area_ratio : float64 (N,)
        Area of the core's component at the next level up over the core's area.
    shape_residual, asymmetry, profile_rms : float64 (N,)
        See :mod:`carapost.core.blob_score`.
    area : float64 (N,)
        Area of the soft half-contrast region (level px^2).
    ok : bool (N,)
        False where the candidate is rejected outright (no peak, no isolated core, masked or
        saturated pixels in or around it, degenerate background).
    border : bool (N,)
        Even the highest level's component reached the patch border or the size limit (the
        patch may be too small: a blob bigger than its candidate's scale).
    open : float64 (N,)
        The dot's contrast against its surround in its weakest direction, as a fraction of its
        full contrast (1 on clean skin, near 0 where it merges with something as dark).
    kept : float64 (N,)
        Fraction of the soft region kept by the trimming (1 for a clean ellipse).
    saturated : float64 (N,)
        Fraction of the blob's 2 px surround that is clipped (white blobs).
    """

    x: np.ndarray
    y: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    angle: np.ndarray
    contrast: np.ndarray
    background: np.ndarray
    rise: np.ndarray
    noise: np.ndarray
    ring_noise: np.ndarray
    core_level: np.ndarray
    found_level: np.ndarray
    area_ratio: np.ndarray
    shape_residual: np.ndarray
    asymmetry: np.ndarray
    profile_rms: np.ndarray
    area: np.ndarray
    ok: np.ndarray
    border: np.ndarray

    open: np.ndarray
    kept: np.ndarray
    saturated: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "PatchFit":
        f = {k: np.zeros(n) for k in cls.__dataclass_fields__ if k not in ("ok", "border")}
        return cls(**f, ok=np.zeros(n, bool), border=np.zeros(n, bool))


#: Patch half sizes: a few classes, so that candidates are fitted in few large batches.
_HALF_SIZES = np.array([8, 11, 14, 18, 25, 33, 49, 65])


def patch_half_size(radius: np.ndarray | float) -> np.ndarray:
    """Half side of the patches used for blobs of ``radius`` px (at the patch's level): at
    least ``1.5 radius + 5``, rounded up to one of a few classes."""
    need = np.ceil(1.5 * np.asarray(radius, float) + 5.0)
    k = np.searchsorted(_HALF_SIZES, need)
    return np.where(k < len(_HALF_SIZES), _HALF_SIZES[np.minimum(k, len(_HALF_SIZES) - 1)], need).astype(int)


#: Largest ``M * P * k`` of one product in :func:`_dot` (OpenBLAS runs GEMMs up to 4 x 65536
#: multiply-adds on the calling thread only).
_DOT_CHUNK = 200_000


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a tall ``a (M, P)`` and a thin ``b (P, k)``, in row blocks small enough
    that a multi-threaded BLAS keeps each product on the calling thread: waking its threads
    for these skinny products costs more CPU time than computing them, and competes with
    :func:`carapost.core.detect_range.detect_frames`' own threads."""
    m, p = a.shape
    rows = max(1, _DOT_CHUNK // max(p * b.shape[1], 1))
    if m <= rows:
        return a @ b
    out = np.empty((m, b.shape[1]), np.result_type(a, b))
    for i in range(0, m, rows):
        np.matmul(a[i:i + rows], b, out=out[i:i + rows])
    return out


def _mosaic(a: np.ndarray, fill: float = 0) -> np.ndarray:
    """Stack ``(N, S, S)`` patches vertically with ``_SEP`` rows of ``fill`` between them."""
    n, s, _ = a.shape
    mos = np.full((n, s + _SEP, s), fill, a.dtype if a.dtype != bool else np.uint8)
    mos[:, :s] = a
    return mos.reshape(n * (s + _SEP), s)


def _unmosaic(mos: np.ndarray, n: int, s: int) -> np.ndarray:
    return mos.reshape(n, s + _SEP, s)[:, :s]


_KERNELS = {r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)) for r in (1, 2, 3, 4)}
_K3 = np.ones((3, 3), np.uint8)


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """Dilate each ``(S, S)`` mask of a stack by a disc of radius ``r`` (1..4) px."""
    n, s, _ = mask.shape
    if n == 0:
        return mask.copy()
    return _unmosaic(cv2.dilate(_mosaic(mask), _KERNELS[r]), n, s).astype(bool)


def _box3(d: np.ndarray) -> np.ndarray:
    """3x3 mean of each ``(S, S)`` float32 patch of a stack (edge values approximate)."""
    n, s, _ = d.shape
    if n == 0:
        return d.copy()
    out = cv2.blur(_mosaic(d), (3, 3), borderType=cv2.BORDER_CONSTANT)
    return _unmosaic(out, n, s)


_GRIDS: dict[int, tuple] = {}


def _grid(half: int) -> tuple:
    """Offsets ``dy, dx`` (int), their float32 copies, monomials and border mask (cached)."""
    g = _GRIDS.get(half)
    if g is None:
        off = np.arange(-half, half + 1)
        dy, dx = np.meshgrid(off, off, indexing="ij")
        dxf, dyf = dx.astype(np.float32), dy.astype(np.float32)
        edge = (np.abs(dx) == half) | (np.abs(dy) == half)
        g = (dy, dx, dxf, dyf, _monomials(dxf, dyf), edge)
        for a in g:
            a.flags.writeable = False
        _GRIDS[half] = g
    return g


#: Exponents (i, j) of the monomials; the first six are the quadratic basis 1, x, y, xx, xy, yy.
_MONO = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3),
         (4, 0), (3, 1), (2, 2), (1, 3), (0, 4)]
_MONO_INDEX = {e: k for k, e in enumerate(_MONO)}


def _monomials(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """``(S*S, 15)`` float32: ``x^i y^j`` for ``i + j <= 4`` in the order of :data:`_MONO`."""
    x, y = dx.ravel().astype(np.float64), dy.ravel().astype(np.float64)
    return np.stack([x ** i * y ** j for i, j in _MONO], axis=1).astype(np.float32)


def _plane_fit(p: np.ndarray, mask: np.ndarray, mono: np.ndarray,
               iters: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust least-squares plane per patch.

    Parameters
    ----------
    p : float32 (N, S, S)
    mask : bool (N, S, S)
        Pixels allowed in the fit.
    mono : float32 (S*S, 15)
        Monomials of the patch offsets.
    iters : int
        Reweighting passes: pixels beyond 2.5 sigma of the previous fit are dropped (lines,
        edges, unresolved neighbours).

    Returns
    -------
    resid : float32 (N, S, S)
        ``p - plane`` everywhere in the patch.
    sigma : float64 (N,)
        Standard deviation of the residual over the finally used pixels.
    n_used : float64 (N,)
        Number of pixels used in the final fit.
    coef : float32 (N, 3)
        Coefficients of ``1, x, y``.
    """
    n, s, _ = p.shape
    terms = _MONO[:3]
    pairs = np.asarray([[_MONO_INDEX[(a[0] + b[0], a[1] + b[1])] for b in terms] for a in terms])
    pf = p.reshape(n, s * s)
    bk = mono[:, :3]
    w = mask.reshape(n, s * s).astype(np.float32)
    resid = pf
    sigma = np.zeros(n)
    s0 = np.zeros(n)
    c = np.zeros((n, 3), np.float32)
    for it in range(iters + 1):
        m = _dot(w, mono[:, :6]).astype(np.float64)              # sums of w * (1, x, y, xx, xy, yy)
        s0 = m[:, 0]
        A = m[:, pairs]                                       # (N, 3, 3)
        A[:, [0, 1, 2], [0, 1, 2]] += 1e-6 * np.maximum(A[:, [0, 1, 2], [0, 1, 2]], 1e-6) + 1e-9
        rhs = _dot(w * pf, bk).astype(np.float64)
        c = np.linalg.solve(A, rhs[..., None])[..., 0].astype(np.float32)
        resid = pf - (c[:, 0:1] * bk[:, 0] + c[:, 1:2] * bk[:, 1] + c[:, 2:3] * bk[:, 2])  # c @ bk.T, no BLAS
        e2 = np.einsum("ij,ij->i", w * resid, resid, dtype=np.float64)
        sigma = np.sqrt(e2 / np.maximum(s0 - 3, 1.0))
        if it < iters:
            lim = (2.5 * np.maximum(sigma, 0.3)).astype(np.float32)[:, None]
            w = w * (np.abs(resid) < lim)
    # Clipping at 2.5 sigma shrinks a Gaussian's std by ~0.94: undo that.
    scale = 0.94 if iters > 0 else 1.0
    return resid.reshape(n, s, s), sigma / scale, s0, c


def _prefer_informative(mask: np.ndarray, dead: np.ndarray, min_count: int = 20) -> np.ndarray:
    """``mask & ~dead`` for patches where that leaves at least ``min_count`` pixels and a third
    of ``mask`` (a face next to a black background), else ``mask`` (a dot on a clipped card)."""
    info = mask & ~dead
    n_info = info.reshape(len(mask), -1).sum(axis=1)
    enough = (n_info >= min_count) & (3 * n_info >= mask.reshape(len(mask), -1).sum(axis=1))
    return np.where(enough[:, None, None], info, mask)


def _flood(level: np.ndarray, pky: np.ndarray, pkx: np.ndarray, iters: int) -> np.ndarray:
    """Flood levels ``L`` (int16 (N, S, S)) of each patch from its peak pixel.

    ``L(p)`` is the largest ``t`` such that ``p`` is 8-connected to the peak through pixels of
    ``level >= t`` (morphological reconstruction by dilation of the peak under ``level``),
    computed by ``iters`` rounds of 3x3 dilation clipped by ``level``: exact for pixels
    reached by such a path within ``iters`` steps, an under-estimate beyond.
    """
    n, s, _ = level.shape
    lo = np.iinfo(np.int16).min
    mos_lvl = _mosaic(level, lo)
    marker = np.full((n, s, s), lo, np.int16)
    marker[np.arange(n), pky, pkx] = level[np.arange(n), pky, pkx]
    mk = _mosaic(marker, lo)
    for _ in range(iters):
        mk = cv2.min(cv2.dilate(mk, _K3), mos_lvl)
    return _unmosaic(mk, n, s)


def _moments(q: np.ndarray, mono: np.ndarray) -> tuple:
    """Centroid ``mx, my``, second central moments ``cxx, cxy, cyy`` and mass ``m0`` (N,) of
    soft regions ``q (N, S, S)`` (offsets from the patch centre)."""
    n = q.shape[0]
    mom = _dot(q.reshape(n, -1), mono[:, :6]).astype(np.float64)
    m0 = mom[:, 0]
    m0s = np.maximum(m0, 1e-9)
    mx, my = mom[:, 1] / m0s, mom[:, 2] / m0s
    cxx = np.maximum(mom[:, 3] / m0s - mx * mx, 1e-6)
    cxy = mom[:, 4] / m0s - mx * my
    cyy = np.maximum(mom[:, 5] / m0s - my * my, 1e-6)
    return mx, my, cxx, cxy, cyy, m0


#: Angular sectors of the local background, and the highest level (fraction of the dot's
#: full contrast) a sector's background may take.
_N_SECTORS = 8
_MAX_SECTOR_LEVEL = 0.7


def _diamond_angle(ux: np.ndarray, uy: np.ndarray) -> np.ndarray:
    """A monotonic stand-in for the polar angle, in [0, 4) (0 along +x, 1 along +y, ...)."""
    t = uy / np.maximum(np.abs(ux) + np.abs(uy), 1e-6)
    return np.where(ux >= 0, np.where(uy >= 0, t, 4.0 + t), 2.0 - t)


def _sector_background(d: np.ndarray, band: np.ndarray, need: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                       dxf: np.ndarray, dyf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Background of each patch as a function of the direction from ``cx, cy``.

    ``d`` is the (smoothed) signal in units of the dot's full contrast. The ``band`` pixels
    are split into :data:`_N_SECTORS` angular sectors; each sector's level is the highest
    value of its band pixels (the structure right next to the dot on that side: a line
    touching it rather than the skin beyond); sectors without band pixels take their
    neighbours' value; levels are capped at :data:`_MAX_SECTOR_LEVEL`. Returns the background
    ``(N, S, S)`` at the ``need`` pixels (interpolated linearly in angle; 0 elsewhere) and the
    sector levels ``(N, K)``.
    """
    n = d.shape[0]
    K = _N_SECTORS
    b = np.zeros(d.shape, np.float32)
    if n == 0:
        return b, np.zeros((0, K))
    S2 = d.shape[1] * d.shape[2]
    sel = np.flatnonzero((band | need).ravel())
    patch, pix = np.divmod(sel, S2)
    ux = dxf.ravel()[pix] - cx.astype(np.float32)[patch]
    uy = dyf.ravel()[pix] - cy.astype(np.float32)[patch]
    ang = _diamond_angle(ux, uy) * (K / 4.0)                               # [0, K)
    is_band = band.ravel()[sel]
    key = patch[is_band] * K + np.minimum(ang[is_band].astype(np.int64), K - 1)
    cnt = np.bincount(key, minlength=n * K)
    level = np.full(n * K, -np.inf)
    np.maximum.at(level, key, d.ravel()[sel[is_band]].astype(np.float64))
    valid = (cnt >= 2).reshape(n, K)
    level = np.where(valid, level.reshape(n, K), 0.0)
    # Fill empty sectors from their neighbours (a few passes around the circle).
    for _ in range(K // 2):
        if valid.all():
            break
        left, right = np.roll(level, 1, axis=1), np.roll(level, -1, axis=1)
        vl, vr = np.roll(valid, 1, axis=1), np.roll(valid, -1, axis=1)
        fill = (left * vl + right * vr) / np.maximum(vl.astype(float) + vr, 1.0)
        newly = ~valid & (vl | vr)
        level = np.where(newly, fill, level)
        valid = valid | newly
    level = np.minimum(np.where(valid, level, 0.0), _MAX_SECTOR_LEVEL)
    # Linear interpolation between sector centres.
    is_need = need.ravel()[sel]
    s = ang[is_need] - 0.5
    k0 = np.floor(s).astype(np.int64)
    f = (s - k0).astype(np.float32)
    k0 %= K
    lv = level.astype(np.float32).ravel()
    base = patch[is_need] * K
    b.ravel()[sel[is_need]] = (1.0 - f) * lv[base + k0] + f * lv[base + (k0 + 1) % K]
    return b, level


def fit_patches(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, radius: np.ndarray, half: int, *,
                polarity: int, max_radius: float, pixel_noise: float, bad: np.ndarray | None, saturated: tuple[int, int] | None,
                min_core: float = 0.0) -> PatchFit:
    """Fit blobs around candidate pixels of one pyramid level image.

    Parameters
    ----------
    img : uint8 (H, W)
        Signed image at the level (blobs bright).
    cx, cy : int arrays (N,)
        Candidate pixels (level px).
    radius : float64 (N,)
        Candidate radius estimates (level px).
    half : int
        Patch half size; patches are ``(2 half + 1)`` square.
    polarity : int
        +1 (white blobs: ``img`` is the image) or -1 (black: ``img`` is ``255 - image``).
    max_radius : float
        Largest allowed blob radius (level px): bigger cores are not blobs.
    pixel_noise : float
        Pixel noise of ``img`` (grey levels).
    bad : bool (H, W) or None
        Pixels to ignore (user mask). A blob touching them is rejected.
    saturated : (lo, hi) or None
        Pixels of ``img`` with values in ``lo..hi`` are saturated pixels of the original
        image (give it for white blobs). They are left out of the background and may only be
        inside the blob itself (an over-exposed white dot); a blob next to a saturated region
        is rejected. Black blobs do not need it: a black dot on a clipped white card is fine.
    min_core : float
        Lowest level (fraction of the peak, one of :data:`LEVELS`) allowed for the core: an
        alternative, tighter outline for a dot that merges with a dark band at the level the
        search picks (the detector fits both and keeps the more probable).

    Returns
    -------
    PatchFit
    """
    H, W = img.shape
    n = len(cx)
    S = 2 * half + 1
    dy, dx, dxf, dyf, mono, edge = _grid(half)
    res = PatchFit.empty(n)
    if n == 0:
        return res
    # Flat pixel indices; patches crossing the image border are clamped (and marked outside).
    inside = (cx >= half) & (cx < W - half) & (cy >= half) & (cy < H - half)
    flat_idx = ((cy * W + cx)[:, None, None] + (dy * W + dx)[None]).astype(np.intp)
    outside = np.zeros((n, S, S), bool)
    if not inside.all():
        e = np.flatnonzero(~inside)
        rows = cy[e, None, None] + dy[None]
        cols = cx[e, None, None] + dx[None]
        outside[e] = (rows < 0) | (rows >= H) | (cols < 0) | (cols >= W)
        flat_idx[e] = np.clip(rows, 0, H - 1) * W + np.clip(cols, 0, W - 1)
    pu = img.ravel()[flat_idx]
    p = pu.astype(np.float32)
    badp = outside if bad is None else outside | bad.ravel()[flat_idx]
    if saturated is None:
        satp = np.zeros_like(outside)
    else:
        satp = (pu >= saturated[0]) & (pu <= saturated[1]) & ~outside
    # Black or clipped pixels (a dark background beyond the face's silhouette, a clipped
    # card) carry no shading information: left out of backgrounds when enough others remain.
    dead = (pu <= _FLAT_LO) | (pu >= _FLAT_HI)
    rho2 = (dxf * dxf + dyf * dyf)[None]
    r0 = radius.astype(np.float32)[:, None, None]
    in_disc = rho2 <= float(half * half)
    idx = np.arange(n)

    # 1. Ring background and peak.
    r_in = np.minimum(1.5 * r0 + 1.5, half - 1.5)
    ring = _prefer_informative((rho2 >= r_in * r_in) & in_disc & ~badp & ~satp, dead)
    d0, sig0, n0, c0 = _plane_fit(p, ring, mono, iters=1)
    ds = _box3(d0)
    near = rho2 <= np.maximum(1.5, 0.5 * r0) ** 2
    flat = np.where(near, ds, -np.inf).reshape(n, -1)
    pk = np.argmax(flat, axis=1)
    peak = flat[idx, pk].astype(np.float64)
    pky, pkx = np.divmod(pk, S)
    ok = (peak > 1.0 * sig0) & (peak > 0.5) & (n0 >= 8)
    alive = np.flatnonzero(ok)
    if len(alive) == 0:
        return res

    # 2. Level search on the flood levels (fixed point: the peak is _FP).
    n = len(alive)
    idx = np.arange(n)
    p, pu, badp, satp, dead, ds, d0 = p[alive], pu[alive], badp[alive], satp[alive], dead[alive], ds[alive], d0[alive]
    pky, pkx, peak, r0 = pky[alive], pkx[alive], peak[alive], r0[alive]
    scale = (_FP / peak).astype(np.float32)[:, None, None]
    lvl = np.clip(ds * scale, -30000, 30000).astype(np.int16)
    L = _flood(lvl, pky, pkx, half + 4)
    thr = (np.asarray(LEVELS) * _FP).astype(np.int16)                     # (K,)
    K = len(LEVELS)
    Lf = L.reshape(n, -1)
    masks = (Lf[:, None, :] >= thr[None, :, None]).astype(np.float32)      # (n, K, S*S)
    m = _dot(masks.reshape(n * K, -1), mono[:, :6]).reshape(n, K, 6).astype(np.float64)
    area = m[..., 0]
    a_s = np.maximum(area, 1.0)
    vx = m[..., 3] / a_s - (m[..., 1] / a_s) ** 2 + 1.0 / 12.0
    vy = m[..., 5] / a_s - (m[..., 2] / a_s) ** 2 + 1.0 / 12.0
    vxy = m[..., 4] / a_s - m[..., 1] * m[..., 2] / (a_s * a_s)
    # Area over the area of the moment ellipse (a uniform ellipse has Sigma = diag(a^2, b^2)/4).
    fill = area / (4.0 * np.pi * np.sqrt(np.maximum(vx * vy - vxy * vxy, 1e-6)))
    edge_max = Lf[:, edge.ravel()].max(axis=1)                             # (n,)
    a_max = np.pi * (1.3 * max_radius + 2.0) ** 2
    valid = (edge_max[:, None] < thr[None]) & (area <= a_max)
    # The shape test only below the peak's noise band (a flat, noisy top is ragged).
    noise_band = 1.0 - _TOP_NOISE * (pixel_noise / 3.0) / peak                # 3x3 mean: sigma / 3
    shaped = np.asarray(LEVELS)[None] <= np.minimum(noise_band, _MAX_SHAPED_LEVEL)[:, None]
    valid &= (fill >= _MIN_FILL) | (area < _FILL_MIN_AREA) | ~shaped
    # The core is the lowest level from which every higher level is valid.
    run = np.cumprod(valid[:, ::-1], axis=1)[:, ::-1].astype(bool)         # valid and all above
    has = run[:, -1]
    kc = np.where(has, np.argmax(run, axis=1), K - 1)
    k_found = kc
    if min_core > 0:
        kc = np.maximum(kc, min(int(np.searchsorted(np.asarray(LEVELS), min_core - 1e-9)), K - 1))
    core = L >= thr[kc][:, None, None]
    core_area = area[idx, kc]
    above = np.minimum(kc + 1, K - 1)
    area_ratio = np.where(kc < K - 1, area[idx, above] / np.maximum(core_area, 1.0), 1.0)
    border = ~has
    ok = has.copy()

    if DEBUG is not None:
        DEBUG.update(dict(alive=alive, L=L, area=area, fill=fill, edge_max=edge_max, valid=valid, kc=kc, lvl=lvl, p=p, peak=peak,
                          pky=pky, pkx=pkx, sig0=sig0[alive], half=half))
    # 3. Local background: a plane on a thin band around the core, away from other bright
    # structures (pixels above the core level not connected to it).
    others = (lvl >= thr[kc][:, None, None]) & ~core
    oth1 = _dilate(others, 1)
    grown_in = _dilate(core, _BAND[0])
    band = _dilate(core, _BAND[1]) & ~grown_in & ~oth1 & ~badp & ~satp
    band = _prefer_informative(band, dead, min_count=10)
    d, sigma, n_band, cb = _plane_fit(p, band, mono, iters=1)
    few = n_band < 10
    if few.any():
        d[few], sigma[few], cb[few] = d0[few], sig0[alive][few], c0[alive][few]
    dsb = _box3(d)
    c_box = np.where(core, dsb, -np.inf).reshape(n, -1).max(axis=1)
    c_raw = np.where(core, d, -np.inf).reshape(n, -1).max(axis=1)
    C = np.maximum(c_box, 0.9 * c_raw).astype(np.float64)
    ok &= C > 0
    Cs = np.where(C > 0, C, 1.0).astype(np.float32)[:, None, None]

    # Rejections: masked pixels near the blob, saturation around it.
    win = _dilate(core, 3) & ~oth1
    ok &= ~(win & badp).any(axis=(1, 2))
    # Saturated pixels next to a white blob: the fraction of its surround (2 px) that is
    # clipped. A dot merging with a clipped region cannot be measured.
    half_region = win & (d >= 0.5 * Cs)
    rim = _dilate(half_region, 2) & ~half_region
    sat_near = (satp & rim).sum(axis=(1, 2)) / np.maximum(rim.sum(axis=(1, 2)), 1)
    ok &= sat_near <= _MAX_SATURATED_RIM

    # 4. Coverage: the signal over the dot's full contrast at each pixel. Paint multiplies the
    # light, so the full contrast is a fixed fraction ``Ce`` of the local background's grey
    # level in the original image (shading across the dot cancels); a white dot cannot rise
    # above 255 (a clipped dot's top is 255 everywhere).
    bg_grey = np.maximum(p - d if polarity > 0 else 255.0 - (p - d), 1.0)
    e = d / bg_grey
    Ce = np.maximum(np.where(core, _box3(e), -np.inf).reshape(n, -1).max(axis=1),
                    0.9 * np.where(core, e, -np.inf).reshape(n, -1).max(axis=1))
    full = bg_grey * np.where(Ce > 0, Ce, 1.0).astype(np.float32)[:, None, None]
    if polarity > 0:
        full = np.minimum(full, 255.0 - bg_grey)
    cov = d / np.maximum(full, 1e-3)
    # Per-direction local background (a band or a line on one side only), then the soft
    # half-contrast region between it and the dot's top.
    mcx, mcy, _, _, _, _ = _moments(core.astype(np.float32), mono)
    b_pix, b_sec = _sector_background(_box3(cov), band, win, mcx, mcy, dxf, dyf)
    q = np.clip(_RAMP * (cov - b_pix) / np.maximum(1.0 - b_pix, 1e-3) + (0.5 - 0.5 * _RAMP), 0.0, 1.0) * win
    if DEBUG is not None:
        DEBUG.update(q=q, d=d, win=win, core=core, band=band, C=C)
    # 5. Ellipse and centre: moments of the region, trimmed a few times of the parts beyond
    # the moment ellipse (a line or a shadow touching the dot).
    mx, my, cxx, cxy, cyy, m0 = _moments(q, mono)
    m0_full = np.maximum(m0, 1e-9)
    q_full = q
    for _ in range(_TRIM_ITERS):
        dist = ellipse_distance(mx, my, (cxx, cxy, cyy), dxf, dyf)[0]
        q = np.where(dist > _TRIM_MARGIN, 0.0, q_full)
        mx, my, cxx, cxy, cyy, m0 = _moments(q, mono)
    m0s = np.maximum(m0, 1e-9)
    tr = 0.5 * (cxx + cyy)
    disc = np.sqrt(np.maximum(0.25 * (cxx - cyy) ** 2 + cxy ** 2, 0.0))
    major = 2.0 * np.sqrt(np.maximum(tr + disc, 1e-6))
    minor = 2.0 * np.sqrt(np.maximum(tr - disc, 1e-6))
    angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    ok &= m0 >= 1.5

    # 6. Shape measurements.
    shape, rho_e2 = shape_residual(q, mx, my, (cxx, cxy, cyy), dxf, dyf, win, m0s)
    asym = asymmetry(q, mx, my, half)
    prms = profile_rms(d, rho_e2, np.sqrt(major * minor), win & ~badp)
    bg_band = cb[:, 0] + cb[:, 1] * mx + cb[:, 2] * my
    bg_ring = c0[alive][:, 0] + c0[alive][:, 1] * mx + c0[alive][:, 2] * my
    for name, val in (("x", cx[alive] + mx), ("y", cy[alive] + my), ("major", major), ("minor", minor),
                      ("angle", angle), ("contrast", C), ("background", bg_band),
                      ("rise", (bg_band - bg_ring) / np.maximum(C, 1e-6)), ("noise", sigma),
                      ("ring_noise", sig0[alive]), ("core_level", np.asarray(LEVELS)[kc]),
                      ("found_level", np.asarray(LEVELS)[k_found]),
                      ("area_ratio", area_ratio), ("shape_residual", shape), ("asymmetry", asym),
                      ("profile_rms", prms), ("area", m0), ("ok", ok), ("border", border),
                      ("open", 1.0 - b_sec.max(axis=1)), ("kept", m0 / m0_full), ("saturated", sat_near)):
        getattr(res, name)[alive] = val
    return res
