"""Per-candidate stage of the blob detector: level search, local background, ellipse, centre.

All candidates of one patch size (whatever pyramid level they come from) are processed
together on a stack of square patches ``(N, S, S)`` (:func:`extract_patches`); nothing loops
over candidates in Python. Morphology and connectivity run on a "mosaic" of the patches
(stacked with blank rows between them) in single OpenCV calls. Steps 1-2 are
:func:`search_levels` (its :class:`LevelSearch` is kept), steps 3-5 :func:`fit_outlines`, so
that the detector can reject candidates after step 2 (the gate) and fit alternative outlines
(a core forced to a higher level) without repeating steps 1-2; :func:`fit_patches` runs both
on one image.

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

from .blob_patches import (K3, MONO, MONO_INDEX, SEP, Patches, box3, dilate, dilate_many, dot_rows,
                           extract_patches, mosaic, patch_grid)
from .blob_score import asymmetry, ellipse_distance, profile_rms, shape_residual

__all__ = ["PatchFit", "fit_patches", "patch_half_size", "LEVELS"]

#: Signed-image levels at or below / at or above which a pixel is black or clipped.
_FLAT_LO, _FLAT_HI = 4, 251
_FLOOD_ROUND = 4  # flood steps between convergence checks
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
#: Fixed-point scale of the flood levels (uint8, clipped at 255; the peak is ``_FP``: the
#: searched levels are exact multiples of 10, and 8-bit morphology is the fastest).
_FP = 200
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
    terms = MONO[:3]
    pairs = np.asarray([[MONO_INDEX[(a[0] + b[0], a[1] + b[1])] for b in terms] for a in terms])
    pf = p.reshape(n, s * s)
    bk = mono[:, :3]
    w = mask.reshape(n, s * s).astype(np.float32)
    resid = pf
    sigma = np.zeros(n)
    s0 = np.zeros(n)
    c = np.zeros((n, 3), np.float32)
    for it in range(iters + 1):
        m = dot_rows(w, mono[:, :6]).astype(np.float64)              # sums of w * (1, x, y, xx, xy, yy)
        s0 = m[:, 0]
        A = m[:, pairs]                                       # (N, 3, 3)
        A[:, [0, 1, 2], [0, 1, 2]] += 1e-6 * np.maximum(A[:, [0, 1, 2], [0, 1, 2]], 1e-6) + 1e-9
        rhs = dot_rows(w * pf, bk).astype(np.float64)
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


def _flood(level: np.ndarray, pky: np.ndarray, pkx: np.ndarray, iters: int, floor: int) -> np.ndarray:
    """Flood levels ``L`` (uint8 (N, S, S)) of each patch from its peak pixel, at least ``floor``.

    ``L(p)`` is the largest ``t >= floor`` such that ``p`` is 8-connected to the peak through
    pixels of ``level >= t`` (morphological reconstruction by dilation of the peak under
    ``level``), computed by up to ``iters`` rounds of 3x3 dilation clipped by ``level``: exact
    for pixels reached by such a path within ``iters`` steps, an under-estimate beyond. Only
    the region above ``floor`` has to be flooded, and a patch leaves the rounds as soon as a
    round of :data:`_FLOOD_ROUND` steps changes nothing in it (it has converged: exact).
    """
    n, s, _ = level.shape
    b = s + SEP
    lv = cv2.max(mosaic(level, floor), floor).reshape(n, b, s)
    marker = np.full((n, s, s), floor, np.uint8)
    marker[np.arange(n), pky, pkx] = np.maximum(level[np.arange(n), pky, pkx], floor)
    mk = mosaic(marker, floor).reshape(n, b, s)
    # Rounds of a few steps on the patches still changing (a patch that did not change during
    # a whole round has converged).
    act = np.arange(n)
    done = 0
    while len(act) and done < iters:
        steps = min(_FLOOD_ROUND, iters - done)
        whole = len(act) == n
        m0 = mk if whole else mk[act]
        lim = (lv if whole else lv[act]).reshape(-1, s)
        m = m0.reshape(-1, s)
        for _ in range(steps):
            m = cv2.min(cv2.dilate(m, K3), lim)
        m = m.reshape(len(act), b, s)
        changed = (m != m0).reshape(len(act), -1).any(axis=1)
        mk[act] = m
        act = act[changed]
        done += steps
    return mk[:, :s]


def _thresholds() -> np.ndarray:
    """The searched levels (:data:`LEVELS`) in the fixed point of the flood levels, int16 (K,)."""
    return np.rint(np.asarray(LEVELS) * _FP).astype(np.int16)


def _moments(q: np.ndarray, mono: np.ndarray) -> tuple:
    """Centroid ``mx, my``, second central moments ``cxx, cxy, cyy`` and mass ``m0`` (N,) of
    soft regions ``q (N, S, S)`` (offsets from the patch centre)."""
    n = q.shape[0]
    mom = dot_rows(q.reshape(n, -1), mono[:, :6]).astype(np.float64)
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
        Centres in level pixels.
    """
    n = len(cx)
    pat = extract_patches(img, cx, cy, half, bad=bad, saturated=saturated)
    st = search_levels(pat, radius, max_radius=np.full(n, float(max_radius)),
                       pixel_noise=np.full(n, float(pixel_noise)))
    res = fit_outlines(st, np.arange(n), polarity=polarity, min_core=np.full(n, float(min_core)))
    res.x += cx
    res.y += cy
    return res


@dataclass
class LevelSearch:
    """Steps 1-2 of the fit for a stack of patches (:func:`search_levels`), kept so that
    outlines at several core levels (:func:`fit_outlines`) share them. Arrays are over the
    ``alive`` patches (those with a peak) unless noted."""

    n: int                   # patches in the stack
    half: int
    alive: np.ndarray        # int (A,): patches with a peak above the ring noise
    p: np.ndarray            # float32 (A, S, S)
    pu: np.ndarray           # uint8 (A, S, S)
    bad: np.ndarray          # bool (A, S, S)
    sat: np.ndarray          # bool (A, S, S)
    dead: np.ndarray         # bool (A, S, S): black or clipped
    d0: np.ndarray           # float32 (A, S, S): patch minus ring plane
    sig0: np.ndarray         # (A,) ring residual std
    c0: np.ndarray           # float32 (A, 3) ring plane
    L: np.ndarray            # uint8 (A, S, S) flood levels
    lvl: np.ndarray          # uint8 (A, S, S) smoothed signal in fixed point
    area: np.ndarray         # (A, K) area of the peak's component per level
    k_found: np.ndarray      # int (A,) core level index found by the search
    has: np.ndarray          # bool (A,) an isolated core exists
    peak: np.ndarray         # (A,) peak of the 3x3 mean over the ring plane (grey levels)
    fill: np.ndarray         # (A,) core area over its moment ellipse's, at the found level

    @classmethod
    def gather(cls, parts: list[tuple["LevelSearch", np.ndarray]]) -> tuple["LevelSearch", np.ndarray]:
        """One level search made of patches ``sel`` (stack indices) of several searches of
        equal half size; returns it and, for every requested patch, its index in it (-1:
        not alive)."""
        names = ("p", "pu", "bad", "sat", "dead", "d0", "sig0", "c0", "L", "lvl", "area", "k_found", "has", "peak",
                 "fill")
        got = {k: [] for k in names}
        index, base = [], 0
        for st, sel in parts:
            keep, rows = st.rows(np.asarray(sel, np.int64))
            for k in names:
                got[k].append(getattr(st, k)[rows])
            ix = np.full(len(sel), -1)
            ix[keep] = base + np.arange(len(keep))
            index.append(ix)
            base += len(keep)
        merged = cls(base, parts[0][0].half, np.arange(base), **{k: np.concatenate(v) for k, v in got.items()})
        return merged, np.concatenate(index)

    def rows(self, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For patch indices ``sel`` (into the stack), the positions in ``sel`` of those
        alive and their rows in the alive arrays."""
        pos = np.full(self.n, -1)
        pos[self.alive] = np.arange(len(self.alive))
        r = pos[sel]
        keep = np.flatnonzero(r >= 0)
        return keep, r[keep]


def search_levels(pat: Patches, radius: np.ndarray, *, max_radius: np.ndarray,
                  pixel_noise: np.ndarray) -> LevelSearch:
    """Steps 1 (ring background, peak) and 2 (flood levels, core level) of the fit.

    ``radius``, ``max_radius`` and ``pixel_noise`` are per patch (level px / grey levels of
    the level each patch came from).
    """
    half = pat.half
    n = len(pat)
    S = 2 * half + 1
    dy, dx, dxf, dyf, mono, edge = patch_grid(half)
    pu = pat.pu
    p = pu.astype(np.float32)
    badp, satp = pat.bad, pat.sat
    # Black or clipped pixels (a dark background beyond the face's silhouette, a clipped
    # card) carry no shading information: left out of backgrounds when enough others remain.
    dead = (pu <= _FLAT_LO) | (pu >= _FLAT_HI)
    rho2 = (dxf * dxf + dyf * dyf)[None]
    r0 = np.asarray(radius, np.float32)[:, None, None]
    in_disc = rho2 <= float(half * half)
    idx = np.arange(n)

    # 1. Ring background and peak.
    r_in = np.minimum(1.5 * r0 + 1.5, half - 1.5)
    ring = _prefer_informative((rho2 >= r_in * r_in) & in_disc & ~badp & ~satp, dead)
    d0, sig0, n0, c0 = _plane_fit(p, ring, mono, iters=1)
    ds = box3(d0)
    near = rho2 <= np.maximum(1.5, 0.5 * r0) ** 2
    flat = np.where(near, ds, -np.inf).reshape(n, -1)
    pk = np.argmax(flat, axis=1) if n else np.zeros(0, np.int64)
    peak = flat[idx, pk].astype(np.float64)
    pky, pkx = np.divmod(pk, S)
    ok = (peak > 1.0 * sig0) & (peak > 0.5) & (n0 >= 8)
    alive = np.flatnonzero(ok)

    # 2. Level search on the flood levels (fixed point: the peak is _FP).
    n = len(alive)
    idx = np.arange(n)
    p, pu, badp, satp, dead, ds, d0 = p[alive], pu[alive], badp[alive], satp[alive], dead[alive], ds[alive], d0[alive]
    pky, pkx, peak, r0 = pky[alive], pkx[alive], peak[alive], r0[alive]
    max_radius, pixel_noise = np.asarray(max_radius, float)[alive], np.asarray(pixel_noise, float)[alive]
    K = len(LEVELS)
    if n == 0:
        z = np.zeros((0, S, S), np.uint8)
        return LevelSearch(len(pat), half, alive, p, pu, badp, satp, dead, d0, sig0[alive], c0[alive], z, z,
                           np.zeros((0, K)), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0), np.zeros(0))
    scale = (_FP / peak).astype(np.float32)[:, None, None]
    lvl = np.clip(ds * scale, 0, 255).astype(np.uint8)
    thr = _thresholds()                                                    # (K,)
    # Flood levels below the lowest searched level are never used: they are all ``thr[0] - 1``.
    L = _flood(lvl, pky, pkx, half + 4, int(thr[0]) - 1)
    Lf = L.reshape(n, -1)
    masks = (Lf[:, None, :] >= thr[None, :, None]).astype(np.float32)      # (n, K, S*S)
    m = dot_rows(masks.reshape(n * K, -1), mono[:, :6]).reshape(n, K, 6).astype(np.float64)
    area = m[..., 0]
    a_s = np.maximum(area, 1.0)
    vx = m[..., 3] / a_s - (m[..., 1] / a_s) ** 2 + 1.0 / 12.0
    vy = m[..., 5] / a_s - (m[..., 2] / a_s) ** 2 + 1.0 / 12.0
    vxy = m[..., 4] / a_s - m[..., 1] * m[..., 2] / (a_s * a_s)
    # Area over the area of the moment ellipse (a uniform ellipse has Sigma = diag(a^2, b^2)/4).
    fill = area / (4.0 * np.pi * np.sqrt(np.maximum(vx * vy - vxy * vxy, 1e-6)))
    edge_max = Lf[:, edge.ravel()].max(axis=1)                             # (n,)
    a_max = np.pi * (1.3 * max_radius + 2.0) ** 2
    valid = (edge_max[:, None] < thr[None]) & (area <= a_max[:, None])
    # The shape test only below the peak's noise band (a flat, noisy top is ragged).
    noise_band = 1.0 - _TOP_NOISE * (pixel_noise / 3.0) / peak                # 3x3 mean: sigma / 3
    shaped = np.asarray(LEVELS)[None] <= np.minimum(noise_band, _MAX_SHAPED_LEVEL)[:, None]
    valid &= (fill >= _MIN_FILL) | (area < _FILL_MIN_AREA) | ~shaped
    # The core is the lowest level from which every higher level is valid.
    run = np.cumprod(valid[:, ::-1], axis=1)[:, ::-1].astype(bool)         # valid and all above
    has = run[:, -1]
    k_found = np.where(has, np.argmax(run, axis=1), K - 1)
    if DEBUG is not None:
        DEBUG.update(dict(alive=alive, L=L, area=area, fill=fill, edge_max=edge_max, valid=valid, kc=k_found, lvl=lvl,
                          p=p, peak=peak, pky=pky, pkx=pkx, sig0=sig0[alive], half=half))
    return LevelSearch(len(pat), half, alive, p, pu, badp, satp, dead, d0, sig0[alive], c0[alive], L, lvl, area,
                       k_found, has, peak, fill[np.arange(n), k_found])


def fit_outlines(st: LevelSearch, sel: np.ndarray, *, polarity: int, min_core: np.ndarray) -> PatchFit:
    """Steps 3-6 of the fit (local background, coverage, ellipse, shape) for patches ``sel``
    (indices into the stack of ``st``; repeats allowed) with their core at least at level
    ``min_core (len(sel),)`` (fraction of the peak; 0: the level the search found).

    Returns a :class:`PatchFit` of ``len(sel)`` rows with centres relative to the patch
    centre (level px); patches without a peak are not ok.
    """
    half = st.half
    dy, dx, dxf, dyf, mono, edge = patch_grid(half)
    res = PatchFit.empty(len(sel))
    keep, rows = st.rows(np.asarray(sel, np.int64))
    n = len(rows)
    if n == 0:
        return res
    idx = np.arange(n)
    K = len(LEVELS)
    thr = _thresholds()
    if n == len(st.alive) and (rows == idx).all():
        rows = slice(None)                                                # all, in order: no copies
    p, badp, satp, dead, d0 = st.p[rows], st.bad[rows], st.sat[rows], st.dead[rows], st.d0[rows]
    L, lvl, area = st.L[rows], st.lvl[rows], st.area[rows]
    sig0, c0 = st.sig0[rows], st.c0[rows]
    k_found = st.k_found[rows]
    kc = k_found
    mc = np.asarray(min_core, float)[keep]
    if (mc > 0).any():
        kmin = np.minimum(np.searchsorted(np.asarray(LEVELS), mc - 1e-9), K - 1)
        kc = np.where(mc > 0, np.maximum(kc, kmin), kc)
    core = L >= thr[kc][:, None, None]
    core_area = area[idx, kc]
    above = np.minimum(kc + 1, K - 1)
    area_ratio = np.where(kc < K - 1, area[idx, above] / np.maximum(core_area, 1.0), 1.0)
    border = ~st.has[rows]
    ok = st.has[rows].copy()

    # 3. Local background: a plane on a thin band around the core, away from other bright
    # structures (pixels above the core level not connected to it).
    others = (lvl >= thr[kc][:, None, None]) & ~core
    oth1 = dilate(others, 1)
    grown_in, grown_out, grown_win = dilate_many(core, (_BAND[0], _BAND[1], 3))
    band = grown_out & ~grown_in & ~oth1 & ~badp & ~satp
    band = _prefer_informative(band, dead, min_count=10)
    d, sigma, n_band, cb = _plane_fit(p, band, mono, iters=1)
    few = n_band < 10
    if few.any():
        d[few], sigma[few], cb[few] = d0[few], sig0[few], c0[few]
    dsb = box3(d)
    c_box = np.where(core, dsb, -np.inf).reshape(n, -1).max(axis=1)
    c_raw = np.where(core, d, -np.inf).reshape(n, -1).max(axis=1)
    C = np.maximum(c_box, 0.9 * c_raw).astype(np.float64)
    ok &= C > 0
    Cs = np.where(C > 0, C, 1.0).astype(np.float32)[:, None, None]

    # Rejections: masked pixels near the blob, saturation around it.
    win = grown_win & ~oth1
    ok &= ~(win & badp).any(axis=(1, 2))
    # Saturated pixels next to a white blob: the fraction of its surround (2 px) that is
    # clipped. A dot merging with a clipped region cannot be measured.
    sat_near = np.zeros(n)
    has_sat = satp.reshape(n, -1).any(axis=1)
    if has_sat.any():
        hs = np.flatnonzero(has_sat)
        half_region = win[hs] & (d[hs] >= 0.5 * Cs[hs])
        rim = dilate(half_region, 2) & ~half_region
        sat_near[hs] = (satp[hs] & rim).sum(axis=(1, 2)) / np.maximum(rim.sum(axis=(1, 2)), 1)
    ok &= sat_near <= _MAX_SATURATED_RIM

    # 4. Coverage: the signal over the dot's full contrast at each pixel. Paint multiplies the
    # light, so the full contrast is a fixed fraction ``Ce`` of the local background's grey
    # level in the original image (shading across the dot cancels); a white dot cannot rise
    # above 255 (a clipped dot's top is 255 everywhere).
    bg_grey = np.maximum(p - d if polarity > 0 else 255.0 - (p - d), 1.0)
    e = d / bg_grey
    Ce = np.maximum(np.where(core, box3(e), -np.inf).reshape(n, -1).max(axis=1),
                    0.9 * np.where(core, e, -np.inf).reshape(n, -1).max(axis=1))
    full = bg_grey * np.where(Ce > 0, Ce, 1.0).astype(np.float32)[:, None, None]
    if polarity > 0:
        full = np.minimum(full, 255.0 - bg_grey)
    cov = d / np.maximum(full, 1e-3)
    # Per-direction local background (a band or a line on one side only), then the soft
    # half-contrast region between it and the dot's top.
    mcx, mcy, _, _, _, _ = _moments(core.astype(np.float32), mono)
    b_pix, b_sec = _sector_background(box3(cov), band, win, mcx, mcy, dxf, dyf)
    q = np.clip(_RAMP * (cov - b_pix) / np.maximum(1.0 - b_pix, 1e-3) + (0.5 - 0.5 * _RAMP), 0.0, 1.0) * win
    if DEBUG is not None:
        DEBUG.update(q=q, d=d, win=win, core=core, band=band, C=C)
    # 5. Ellipse and centre: moments of the region, trimmed a few times of the parts beyond
    # the moment ellipse (a line or a shadow touching the dot).
    mx, my, cxx, cxy, cyy, m0 = _moments(q, mono)
    m0_full = np.maximum(m0, 1e-9)
    q_full = q
    q = q_full.copy()
    # Only regions whose trimmed part changed are iterated again (the others have converged:
    # the same region gives the same moments).
    cut_prev = np.zeros(q.shape, bool)
    act = np.arange(n)
    for _ in range(_TRIM_ITERS):
        dist = ellipse_distance(mx[act], my[act], (cxx[act], cxy[act], cyy[act]), dxf, dyf)[0]
        qa = q_full[act]
        cut = (dist > _TRIM_MARGIN) & (qa > 0)
        changed = (cut != cut_prev[act]).reshape(len(act), -1).any(axis=1)
        act, cut, qa = act[changed], cut[changed], qa[changed]
        if len(act) == 0:
            break
        cut_prev[act] = cut
        qa = np.where(cut, np.float32(0.0), qa)
        q[act] = qa
        mx[act], my[act], cxx[act], cxy[act], cyy[act], m0[act] = _moments(qa, mono)
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
    bg_ring = c0[:, 0] + c0[:, 1] * mx + c0[:, 2] * my
    for name, val in (("x", mx), ("y", my), ("major", major), ("minor", minor),
                      ("angle", angle), ("contrast", C), ("background", bg_band),
                      ("rise", (bg_band - bg_ring) / np.maximum(C, 1e-6)), ("noise", sigma),
                      ("ring_noise", sig0), ("core_level", np.asarray(LEVELS)[kc]),
                      ("found_level", np.asarray(LEVELS)[k_found]),
                      ("area_ratio", area_ratio), ("shape_residual", shape), ("asymmetry", asym),
                      ("profile_rms", prms), ("area", m0), ("ok", ok), ("border", border),
                      ("open", 1.0 - b_sec.max(axis=1)), ("kept", m0 / m0_full), ("saturated", sat_near)):
        getattr(res, name)[keep] = val
    return res
