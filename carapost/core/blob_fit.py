"""Per-candidate stage of the blob detector: background, boundary, ellipse and centre.

All candidates of one group (same pyramid level and patch size) are processed together on a
stack of square patches ``(N, S, S)``; nothing loops over candidates in Python.

For each candidate:

1. **Background.** A plane is fitted to the ring of the patch outside the expected blob;
   ``d = patch - plane`` is the blob signal. Candidates whose peak is below 2 sigma of the
   ring's residual stop here.
2. **Boundary.** The contrast ``C`` is the peak of the 3x3-smoothed ``d`` near the candidate;
   the blob is the 8-connected component of ``d >= C/2`` (half contrast) containing the peak.
   Components of other blobs in the patch are excluded from everything that follows. If the
   component reaches the patch border, the level is walked down from ``0.9 C``: the region
   just before it merges with its surround (its area jumps) is the blob, and a thin ring
   around it is its background (a dot on an eyebrow or a lip line). Otherwise the blob is
   flagged ``border`` (the caller retries with a bigger patch) and rejected.
3. **Background again**: a robust quadratic surface (skin curvature, shading) fitted to every
   pixel at least 2 px away from the blob and from other components (black or clipped pixels
   left out when enough others remain); then the contrast and the boundary again.
4. **Ellipse and centre** from the soft half-contrast region
   ``q = clip(1.5 (d/C - 1/2) + 1/2, 0, 1)``: its centroid is the centre (noise enters only
   through the edge pixels; blur is symmetric and does not move it); its second moments give
   the covariance ``Sigma``, and a uniform ellipse has ``Sigma = diag(a^2, b^2) / 4``, so the
   semi-axes are ``2 sqrt(eig(Sigma))``.
5. **Shape measurements** for the classifier: area mismatch with the moment ellipse, central
   asymmetry, residual around the elliptical radial profile (a clean projected dot is a
   blurred ellipse; two merged dots, or a dot cut by an occluding edge, are not).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["PatchFit", "fit_patches", "patch_half_size"]

#: Signed-image levels at or below / at or above which a pixel is black or clipped.
_FLAT_LO, _FLAT_HI = 4, 251
#: Candidates whose peak (3x3 mean) is below this many ring noise sigmas are not fitted.
_EARLY_CNR = 2.0
_SEP = 5  # zero rows between patches in a mosaic (> the largest dilation radius)
#: Levels (fractions of the contrast over the surround, walked down) tried when the
#: half-contrast region runs into the patch border; the area growth between two levels that
#: means "merged with the surround"; the outer radius (px) of the thin ring then used as the
#: blob's local background.
_LOCAL_LEVELS = (0.9, 0.8, 0.7, 0.6, 0.5)
_JUMP = 1.6
_LOCAL_RING = 4
#: Slope of the soft half-contrast region ``q = clip(RAMP (d/C - 1/2) + 1/2, 0, 1)``: 1 is the
#: plain coverage fraction, large values a hard threshold. 1.5 gave the smallest centre errors
#: on rendered dots (noise enters only through the edge pixels; no pixelation).
_RAMP = 1.5


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
        Peak blob signal above the background (grey levels).
    background : float64 (N,)
        Background level of the (signed) level image at the centre (grey levels).
    noise : float64 (N,)
        Standard deviation of the background residual around the blob (grey levels).
    shape_residual : float64 (N,)
        Mismatch between the half-contrast region and its moment ellipse (fraction of area).
    offset : float64 (N,)
        Distance between the intensity centroid and the half-contrast region's centroid,
        divided by the major semi-axis.
    area : float64 (N,)
        Area of the soft half-contrast region (level px^2).
    asymmetry : float64 (N,)
        Mismatch between the half-contrast region and its point reflection about the centre,
        as a fraction of its area (0 for any centrally symmetric blob: an ellipse; high for a
        dot cut by an occluding edge or merged with a different one).
    profile_rms : float64 (N,)
        RMS (grey levels) of the blob signal around its elliptical profile: the mean of the
        signal over pixels at the same normalised elliptical radius, in 0.35 px bins, out to
        2.5 px beyond the boundary. A blurred ellipse is (nearly) a function of that radius,
        so only noise remains; a merged or cut blob leaves structure.
    ok : bool (N,)
        False where the candidate is rejected outright (no blob, touches the patch border,
        masked or saturated pixels in or around it, degenerate background).
    border : bool (N,)
        The blob's half-contrast region reached the patch border (the patch may be too small).
    """

    x: np.ndarray
    y: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    angle: np.ndarray
    contrast: np.ndarray
    background: np.ndarray
    noise: np.ndarray
    shape_residual: np.ndarray
    offset: np.ndarray
    area: np.ndarray
    asymmetry: np.ndarray
    profile_rms: np.ndarray
    ok: np.ndarray
    border: np.ndarray


#: Patch half sizes: a few classes, so that candidates are fitted in few large batches.
_HALF_SIZES = np.array([9, 13, 17, 25, 33, 49, 65])


def patch_half_size(radius: np.ndarray | float) -> np.ndarray:
    """Half side of the patches used for blobs of ``radius`` px (at the patch's level): at
    least ``1.6 radius + 4``, rounded up to one of a few classes."""
    need = np.ceil(1.6 * np.asarray(radius, float) + 4.0)
    k = np.searchsorted(_HALF_SIZES, need)
    return np.where(k < len(_HALF_SIZES), _HALF_SIZES[np.minimum(k, len(_HALF_SIZES) - 1)], need).astype(int)


def _mosaic(mask: np.ndarray) -> np.ndarray:
    """Stack ``(N, S, S)`` masks vertically with ``_SEP`` zero rows between them (uint8)."""
    n, s, _ = mask.shape
    mos = np.zeros((n, s + _SEP, s), np.uint8)
    mos[:, :s] = mask
    return mos.reshape(n * (s + _SEP), s)


def _unmosaic(mos: np.ndarray, n: int, s: int) -> np.ndarray:
    return mos.reshape(n, s + _SEP, s)[:, :s]


_KERNELS = {r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)) for r in (1, 2, 4)}


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """Dilate each ``(S, S)`` mask of a stack by a disc of radius ``r`` (1, 2 or 4) px."""
    n, s, _ = mask.shape
    if n == 0:
        return mask.copy()
    return _unmosaic(cv2.dilate(_mosaic(mask), _KERNELS[r]), n, s).astype(bool)


def _box3(d: np.ndarray) -> np.ndarray:
    """3x3 mean of each ``(S, S)`` patch of a stack (values on the patch edge are approximate:
    they are never used as peaks)."""
    n, s, _ = d.shape
    if n == 0:
        return d.copy()
    mos = np.zeros((n, s + _SEP, s), np.float32)
    mos[:, :s] = d
    out = cv2.blur(mos.reshape(n * (s + _SEP), s), (3, 3), borderType=cv2.BORDER_CONSTANT)
    return out.reshape(n, s + _SEP, s)[:, :s]


_GRIDS: dict[int, tuple] = {}


def _grid(half: int) -> tuple:
    """Offsets ``dy, dx`` (int), their float32 copies and monomials of a patch (cached)."""
    g = _GRIDS.get(half)
    if g is None:
        off = np.arange(-half, half + 1)
        dy, dx = np.meshgrid(off, off, indexing="ij")
        dxf, dyf = dx.astype(np.float32), dy.astype(np.float32)
        g = (dy, dx, dxf, dyf, _monomials(dxf, dyf))
        for a in g:
            a.flags.writeable = False
        _GRIDS[half] = g
    return g


def _monomials(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """``(S*S, 15)`` float32: ``x^i y^j`` for ``i + j <= 4`` in the order of :data:`_MONO`."""
    x, y = dx.ravel().astype(np.float64), dy.ravel().astype(np.float64)
    return np.stack([x ** i * y ** j for i, j in _MONO], axis=1).astype(np.float32)


#: Exponents (i, j) of the monomials; the first six are the quadratic basis 1, x, y, xx, xy, yy.
_MONO = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3),
         (4, 0), (3, 1), (2, 2), (1, 3), (0, 4)]
_MONO_INDEX = {e: k for k, e in enumerate(_MONO)}
_QUAD = _MONO[:6]


def _background_fit(p: np.ndarray, mask: np.ndarray, mono: np.ndarray, *, quadratic: bool,
                    iters: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust least-squares background (plane or quadratic surface) per patch.

    Parameters
    ----------
    p : float32 (N, S, S)
    mask : bool (N, S, S)
        Pixels allowed in the fit.
    mono : float32 (S*S, 15)
        Monomials of the patch offsets (:func:`_monomials`).
    quadratic : bool
        Fit ``1, x, y, x^2, xy, y^2`` (skin curvature, shading fall-off) instead of a plane;
        the quadratic terms get a mild ridge so that a one-sided surround cannot make them
        extrapolate wildly under the blob.
    iters : int
        Reweighting passes: pixels beyond 2.5 sigma of the previous fit are dropped (lines,
        edges, unresolved neighbours in the surround).

    Returns
    -------
    resid : float32 (N, S, S)
        ``p - background`` everywhere in the patch.
    sigma : float64 (N,)
        Standard deviation of the residual over the finally used pixels.
    n_used : float64 (N,)
        Number of pixels used in the final fit.
    coef : float32 (N, 6)
        Coefficients of ``1, x, y, x^2, xy, y^2`` (zeros for the quadratic terms of a plane).
    """
    n, s, _ = p.shape
    k = 6 if quadratic else 3
    terms = _QUAD[:k]
    pairs = [[_MONO_INDEX[(a[0] + b[0], a[1] + b[1])] for b in terms] for a in terms]
    pf = p.reshape(n, s * s)
    bk = mono[:, :k]
    w = mask.reshape(n, s * s).astype(np.float32)
    resid = pf
    sigma = np.zeros(n)
    s0 = np.zeros(n)
    coef = np.zeros((n, 6), np.float32)
    for it in range(iters + 1):
        m = (w @ mono).astype(np.float64)                      # (N, 15): sums of w * x^i y^j
        s0 = m[:, 0]
        A = m[:, np.asarray(pairs)]                            # (N, k, k)
        diag = np.arange(k)
        ridge = np.full(k, 1e-6)
        if quadratic:
            ridge[3:] = 0.05
        A[:, diag, diag] += ridge[None] * np.maximum(A[:, diag, diag], 1e-6)
        rhs = ((w * pf) @ bk).astype(np.float64)
        c = np.linalg.solve(A, rhs[..., None])[..., 0].astype(np.float32)
        resid = pf - c @ bk.T
        e2 = np.einsum("ij,ij->i", w * resid, resid, dtype=np.float64)
        sigma = np.sqrt(e2 / np.maximum(s0 - k, 1.0))
        coef[:, :k] = c
        if it < iters:
            lim = (2.5 * np.maximum(sigma, 0.3)).astype(np.float32)[:, None]
            w = w * (np.abs(resid) < lim)
    # Clipping at 2.5 sigma shrinks a Gaussian's std by ~0.94: undo that.
    scale = 0.94 if iters > 0 else 1.0
    return resid.reshape(n, s, s), sigma / scale, s0, coef


def fit_patches(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, radius: np.ndarray, half: int, *,
                bad: np.ndarray | None, saturated: tuple[int, int] | None) -> PatchFit:
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
    bad : bool (H, W) or None
        Pixels to ignore (user mask). A blob touching them is rejected.
    saturated : (lo, hi) or None
        Pixels of ``img`` with values in ``lo..hi`` are saturated pixels of the original
        image (give it for white blobs). They carry no information: they are left out of the
        background, and may only be inside the blob itself (an over-exposed white dot); a
        blob next to a saturated region is rejected. Black blobs do not need it: a black dot
        on a clipped white card is a perfectly good blob.

    Returns
    -------
    PatchFit
    """
    H, W = img.shape
    n = len(cx)
    S = 2 * half + 1
    dy, dx, dxf, dyf, mono = _grid(half)
    basis = mono[:, :6]
    # Flat pixel indices; patches crossing the image border are clamped (and marked outside).
    inside = (cx >= half) & (cx < W - half) & (cy >= half) & (cy < H - half)
    flat_idx = ((cy * W + cx)[:, None, None] + (dy * W + dx)[None]).astype(np.intp)
    outside = np.zeros((n, S, S), bool)
    if not inside.all():
        edge = np.flatnonzero(~inside)
        rows = cy[edge, None, None] + dy[None]
        cols = cx[edge, None, None] + dx[None]
        outside[edge] = (rows < 0) | (rows >= H) | (cols < 0) | (cols >= W)
        flat_idx[edge] = np.clip(rows, 0, H - 1) * W + np.clip(cols, 0, W - 1)
    pu = img.ravel()[flat_idx]
    p = pu.astype(np.float32)
    badp = outside if bad is None else outside | bad.ravel()[flat_idx]
    if saturated is None:
        satp = np.zeros_like(outside)
    else:
        lo, hi = saturated
        satp = ((pu >= lo) & (pu <= hi)) & ~outside
    # Black or clipped pixels (a dark background beyond the face's silhouette, a clipped
    # card) carry no shading information: left out of the background when enough others remain.
    dead = (pu <= _FLAT_LO) | (pu >= _FLAT_HI)
    rho2 = (dxf * dxf + dyf * dyf)[None]
    r0 = radius.astype(np.float32)[:, None, None]
    in_disc = rho2 <= float(half * half)
    idx = np.arange(n)

    # 1. Background from the ring outside the expected blob.
    r_in = np.minimum(1.5 * r0 + 1.5, half - 1.5)
    ring = _prefer_informative((rho2 >= r_in * r_in) & in_disc & ~badp & ~satp, dead)
    d, sig1, n1, _ = _background_fit(p, ring, mono, quadratic=False, iters=0)

    # 2. Peak, contrast, half-contrast component.
    ds = _box3(d)
    near = rho2 <= np.maximum(1.5, 0.6 * r0) ** 2
    flat = np.where(near, ds, -np.inf).reshape(n, -1)
    pk = np.argmax(flat, axis=1)
    c1 = flat[idx, pk].astype(np.float64)
    pky, pkx = np.divmod(pk, S)
    ok = (c1 > 0) & (n1 >= 8)
    c1s = np.where(c1 > 0, c1, 1.0).astype(np.float32)[:, None, None]
    ok0 = ok
    M, others, ok, border = _component(d >= 0.5 * c1s, pky, pkx, ok0)
    # A dot inside a darker band (an eyebrow, a lip line): at half contrast over the skin the
    # band joins the dot. Walk the level down from near the peak; the dot's own region grows
    # slowly (blur) until it merges with the band (the area jumps, or reaches the border). The
    # region just above that level is the dot; its background is then the band around it,
    # measured on a thin ring (``local``).
    local = np.zeros(n, bool)
    sel = np.flatnonzero(border & ok0)
    if len(sel):
        best = np.zeros((len(sel),) + M.shape[1:], bool)
        best_o = np.zeros_like(best)
        found = np.zeros(len(sel), bool)
        prev_area = np.zeros(len(sel))
        alive_w = np.ones(len(sel), bool)
        for level in _LOCAL_LEVELS:
            m2, o2, ok2, b2 = _component(d[sel] >= level * c1s[sel], pky[sel], pkx[sel], ok0[sel])
            area = m2.reshape(len(sel), -1).sum(axis=1)
            jump = b2 | ~ok2 | ((prev_area > 0) & (area > _JUMP * prev_area + 2))
            take = alive_w & ~jump
            best[take], best_o[take] = m2[take], o2[take]
            found |= take
            alive_w &= ~jump
            prev_area = np.where(take, area, prev_area)
        g = sel[found]
        M[g], others[g], ok[g], border[g], local[g] = best[found], best_o[found], True, False, True

    # Candidates without a clear peak above the ring's noise stop here (most texture maxima,
    # the skin next to a blob of the other polarity).
    res = PatchFit(**{k: np.zeros(n) for k in ("x", "y", "major", "minor", "angle", "contrast",
                                              "background", "noise", "shape_residual", "offset",
                                              "area", "asymmetry", "profile_rms")},
                   ok=np.zeros(n, bool), border=np.zeros(n, bool))
    alive = np.flatnonzero(ok & (c1 > _EARLY_CNR * sig1))
    res.border[alive] = border[alive]
    if len(alive) == 0:
        return res
    n = len(alive)
    idx = np.arange(n)
    p, badp, satp, dead, r0, M, others, ok, local = (
        p[alive], badp[alive], satp[alive], dead[alive], r0[alive], M[alive], others[alive], ok[alive],
        local[alive])
    cx, cy = cx[alive], cy[alive]

    # 3. Background from everything away from the blob and other blobs.
    grown = _dilate(M, 2)
    oth1 = _dilate(others, 1)
    bgmask = _prefer_informative(~grown & ~oth1 & ~badp & ~satp & in_disc, dead)
    if local.any():
        band = _dilate(M[local], _LOCAL_RING) & ~_dilate(M[local], 1)
        bgmask[local] = band & ~oth1[local] & ~badp[local] & ~satp[local]
    d, sigma, n2, plane = _background_fit(p, bgmask, mono, quadratic=True, iters=1)
    ok &= n2 >= 12
    ds = _box3(d)
    flat = np.where(M, ds, -np.inf).reshape(n, -1)
    pk2 = np.argmax(flat, axis=1)
    c2 = flat[idx, pk2].astype(np.float64)
    # A blob narrower than the 3x3 smoothing: use the raw peak if it is higher.
    c2 = np.maximum(c2, np.where(M, d, -np.inf).reshape(n, -1).max(axis=1) * 0.9)
    ok &= c2 > 0
    c2s = np.where(c2 > 0, c2, 1.0).astype(np.float32)[:, None, None]
    pky2, pkx2 = np.divmod(pk2, S)
    M, others2, ok, border2 = _component(d >= 0.5 * c2s, pky2, pkx2, ok)
    border2 |= res.border[alive]
    others = others | others2
    grown = _dilate(M, 2)
    oth1 = _dilate(others, 1)

    # Rejections: masked pixels near the blob, saturation around it.
    ok &= ~(grown & badp).any(axis=(1, 2))
    sat_bad = satp & grown & ~M
    ok &= ~sat_bad.any(axis=(1, 2))
    ring_sat = (satp & in_disc & ~grown).sum(axis=(1, 2)) / max(int(in_disc.sum()), 1)
    ok &= ring_sat < 0.05

    # 4. Ellipse and centre from the soft half-contrast region: moments by one matrix product.
    q = np.clip(d * (_RAMP / c2s) + (0.5 - 0.5 * _RAMP), 0.0, 1.0) * _dilate(M, 1)
    mom = (q.reshape(n, -1) @ basis).astype(np.float64)     # sums of q * (1, x, y, xx, xy, yy)
    m0 = mom[:, 0]
    m0s = np.maximum(m0, 1e-9)
    mx, my = mom[:, 1] / m0s, mom[:, 2] / m0s
    cxx = np.maximum(mom[:, 3] / m0s - mx * mx, 1e-6)
    cxy = mom[:, 4] / m0s - mx * my
    cyy = np.maximum(mom[:, 5] / m0s - my * my, 1e-6)
    tr = 0.5 * (cxx + cyy)
    disc = np.sqrt(np.maximum(0.25 * (cxx - cyy) ** 2 + cxy ** 2, 0.0))
    major = 2.0 * np.sqrt(np.maximum(tr + disc, 1e-6))
    minor = 2.0 * np.sqrt(np.maximum(tr - disc, 1e-6))
    angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    ok &= m0 >= 1.5

    # 5. Intensity-weighted centroid over the grown blob: only for the asymmetry feature.
    win = grown & ~oth1 & ~badp
    wd = (d * win).reshape(n, -1)
    mw = (wd @ basis[:, :3]).astype(np.float64)
    sw = mw[:, 0]
    sws = np.where(sw > 0, sw, 1.0)
    ix, iy = mw[:, 1] / sws, mw[:, 2] / sws
    ok &= sw > 0

    # 6. Shape residual against the soft moment ellipse (boundary covariance = 4 Sigma).
    det = np.maximum(cxx * cyy - cxy * cxy, 1e-9)
    ia = (cyy / (4 * det)).astype(np.float32)[:, None, None]
    ib = (-cxy / (4 * det)).astype(np.float32)[:, None, None]
    ic = (cxx / (4 * det)).astype(np.float32)[:, None, None]
    ux = dxf[None] - mx.astype(np.float32)[:, None, None]
    uy = dyf[None] - my.astype(np.float32)[:, None, None]
    r2 = ux * ux + uy * uy
    rho_e2 = np.maximum(ia * ux * ux + 2 * ib * ux * uy + ic * uy * uy, 1e-12)
    dist = np.sqrt(r2) - np.sqrt(r2 / rho_e2)       # = |u| (1 - 1/rho): negative inside
    cmp_win = grown & ~oth1
    q_ell = np.clip(0.5 - dist, 0.0, 1.0)
    shape = np.einsum("ij,ij->i", np.abs(q - q_ell).reshape(n, -1), cmp_win.reshape(n, -1),
                      dtype=np.float64) / m0s
    offset = np.hypot(ix - mx, iy - my) / np.maximum(major, 0.5)
    asym = _asymmetry(q, mx, my, half)
    prms = _profile_rms(d, rho_e2, np.sqrt(major * minor), cmp_win & ~badp)

    background = (plane[:, 0] + plane[:, 1] * mx + plane[:, 2] * my + plane[:, 3] * mx * mx
                  + plane[:, 4] * mx * my + plane[:, 5] * my * my)
    for name, val in (("x", cx + mx), ("y", cy + my), ("major", major), ("minor", minor),
                      ("angle", angle), ("contrast", c2), ("background", background),
                      ("noise", sigma), ("shape_residual", shape), ("offset", offset),
                      ("area", m0), ("asymmetry", asym), ("profile_rms", prms), ("ok", ok),
                      ("border", border2)):
        getattr(res, name)[alive] = val
    return res


_PROFILE_BIN = 0.35
_PROFILE_MARGIN = 2.5


def _profile_rms(d: np.ndarray, rho2: np.ndarray, radius: np.ndarray, win: np.ndarray) -> np.ndarray:
    """RMS of ``d`` around its mean profile over elliptical radius ``sqrt(rho2) * radius``."""
    n = d.shape[0]
    if n == 0:
        return np.zeros(0)
    rad = radius.astype(np.float32)[:, None, None]
    t = np.sqrt(rho2) * rad
    w = win & (t <= rad + _PROFILE_MARGIN)
    nb = int(np.ceil((float(radius.max()) + _PROFILE_MARGIN) / _PROFILE_BIN)) + 2
    # Pixels outside the window go to a last, ignored bin of their patch.
    b = np.minimum(t * (1.0 / _PROFILE_BIN), nb - 2).astype(np.int64)
    b[~w] = nb - 1
    key = (np.arange(n) * nb)[:, None, None] + b
    kf = key.ravel()
    df = d.ravel()
    cnt = np.bincount(kf, minlength=n * nb)
    prof = (np.bincount(kf, weights=df, minlength=n * nb) / np.maximum(cnt, 1)).astype(np.float32)
    r = (df - prof[kf]).reshape(n, -1)
    wf = w.reshape(n, -1)
    rss = np.einsum("ij,ij->i", r * wf, r, dtype=np.float64)
    npix = wf.sum(axis=1)
    nbins = (cnt.reshape(n, nb)[:, :-1] > 0).sum(axis=1)
    return np.sqrt(rss / np.maximum(npix - nbins, 1))


def _asymmetry(q: np.ndarray, mx: np.ndarray, my: np.ndarray, half: int) -> np.ndarray:
    """``sum |q'(p) - q'(2c - p)| / (2 sum q)`` per patch, ``c = (mx, my)`` (offsets from the
    patch centre).

    ``2c = k + f`` with integer ``k``; ``q'`` is ``q`` shifted by ``f/2`` (bilinear), whose
    reflection about ``c - f/2 = k/2`` is an exact index flip, so both sides of the comparison
    carry the same interpolation blur and a centrally symmetric blob scores ~0.
    """
    n, s, _ = q.shape
    if n == 0:
        return np.zeros(0)
    pad = 2
    sp = s + 2 * pad
    qp = np.zeros((n, sp, sp), np.float32)
    qp[:, pad:pad + s, pad:pad + s] = q
    ty_all, tx_all, k_all = [], [], []
    for m in (my, mx):
        t = 2.0 * m
        k = np.floor(t)
        k_all.append(k.astype(np.int64))
        (ty_all if not ty_all else tx_all).append(((t - k) / 2.0).astype(np.float32)[:, None, None])
    ty, tx = ty_all[0], tx_all[0]
    ky, kx = k_all
    # q'(p) = q(p + t): bilinear with offsets 0/1 (same integer offsets for all patches).
    q1 = ((1 - ty) * (1 - tx) * qp[:, 1:-1, 1:-1] + (1 - ty) * tx * qp[:, 1:-1, 2:]
          + ty * (1 - tx) * qp[:, 2:, 1:-1] + ty * tx * qp[:, 2:, 2:])      # (n, s+2, s+2), offset -1
    # Reflection about k/2: q'(k - o); q1 index of offset o is o + half + 1.
    s1 = s + 2
    off = np.arange(-half, half + 1)
    iy = np.clip(ky[:, None] - off[None] + half + 1, 0, s1 - 1)
    ix = np.clip(kx[:, None] - off[None] + half + 1, 0, s1 - 1)
    flat = q1.reshape(-1)
    base = (np.arange(n) * s1 * s1)[:, None, None]
    qr = flat[base + iy[:, :, None] * s1 + ix[:, None, :]]
    num = np.abs(q1[:, 1:-1, 1:-1] - qr).reshape(n, -1).sum(axis=1, dtype=np.float64)
    return num / np.maximum(2.0 * q.reshape(n, -1).sum(axis=1, dtype=np.float64), 1e-9)


def _prefer_informative(mask: np.ndarray, dead: np.ndarray, min_count: int = 20) -> np.ndarray:
    """``mask & ~dead`` for patches where that leaves at least ``min_count`` pixels and a third
    of ``mask`` (a face next to a black background), else ``mask`` (a dot on a clipped card)."""
    info = mask & ~dead
    n_info = info.reshape(len(mask), -1).sum(axis=1)
    enough = (n_info >= min_count) & (3 * n_info >= mask.reshape(len(mask), -1).sum(axis=1))
    return np.where(enough[:, None, None], info, mask)


def _component(binary: np.ndarray, pky: np.ndarray, pkx: np.ndarray,
               ok: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 8-connected component of each patch's ``binary`` containing its peak.

    Returns the component ``(N, S, S)``, the other components, ``ok`` updated (False when
    the peak is not in ``binary`` or the component touches the patch border) and whether the
    component touches the border ``(N,)``.
    """
    n, s, _ = binary.shape
    if n == 0:
        return binary.copy(), binary.copy(), ok.copy(), np.zeros(0, bool)
    _, lab = cv2.connectedComponents(_mosaic(binary), connectivity=8, ltype=cv2.CV_32S)
    lab = _unmosaic(lab, n, s)
    own = lab[np.arange(n), pky, pkx]
    comp = (lab == own[:, None, None]) & (own[:, None, None] > 0)
    others = binary & ~comp
    border = comp[:, 0, :].any(1) | comp[:, -1, :].any(1) | comp[:, :, 0].any(1) | comp[:, :, -1].any(1)
    return comp, others, ok & (own > 0) & ~border, border & (own > 0)
