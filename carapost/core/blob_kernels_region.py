"""Compiled (numba) background and region steps of the blob outline
(:mod:`carapost.core.blob_kernels_outline` calls them per row): the core and its box, the
band around it (the core's disc dilations as 64-bit row masks), the peak contrast, the
saturation checks, the coverage and the per-sector background.

Each step is its own compiled function working on the boxes the caller gives (the core's box
grown by 5 px, 4 or 3); the work arrays are allocated by
:func:`carapost.core.blob_kernels_outline.outline_step`.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .blob_kernels import FLAT_HI as _FLAT_HI
from .blob_kernels import FLAT_LO as _FLAT_LO
from .blob_kernels import mean3

_JIT = dict(cache=True, nogil=True, error_model="numpy")
_INLINE = dict(_JIT, inline="always")

#: Inner and outer radius (px) of the band around the core used as local background, and
#: the radius of the fitted region's window around the core.
_BAND = (2, 4)
_BAND_IN, _BAND_OUT, _WIN = _BAND[0], _BAND[1], 3
#: Largest fraction of a white blob's surround (2 px) that may be clipped at 255.
_MAX_SATURATED_RIM = 0.3
#: Angular sectors of the local background, and the highest level (fraction of the dot's
#: full contrast) a sector's background may take.
_N_SECTORS = 8
_MAX_SECTOR_LEVEL = 0.7


def _disc_radii() -> np.ndarray:
    """``(9, 9)`` int64: for each offset ``(dy, dx)`` within 4 px, the smallest radius r (1..4)
    whose OpenCV elliptic disc kernel (``blob_patches.dilate``) holds it, 99 if none (the
    discs are nested)."""
    import cv2

    out = np.full((9, 9), 99, np.int64)
    for r in (4, 3, 2, 1):
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        out[4 - r:4 + r + 1, 4 - r:4 + r + 1][k > 0] = r
    return out


_DISC_R = _disc_radii()


def _disc_spans() -> np.ndarray:
    """``(5, 5)`` int64: the half-width of row ``dy`` (0..4) of the union of the discs of radius
    up to ``r`` (0..4) in :data:`_DISC_R` (each row is one centred run), -1 where empty."""
    out = np.full((5, 5), -1, np.int64)
    for r in range(1, 5):
        for dy in range(5):
            dx = np.flatnonzero(_DISC_R[4 + dy] <= r) - 4
            if len(dx):
                assert np.array_equal(dx, np.arange(-dx.max(), dx.max() + 1))
                out[r, dy] = dx.max()
    return out


_DISC_SPAN = _disc_spans()


@nb.njit(**_INLINE)
def _diamond(ux, uy):
    t = uy / max(abs(ux) + abs(uy), np.float32(1e-6))
    if ux >= 0:
        return t if uy >= 0 else np.float32(4.0) + t
    return np.float32(2.0) - t


@nb.njit(**_INLINE)
def _core_box(Lr, thr, core):
    """The core (flood level at least ``thr``) into ``core`` (whole patch); its box
    ``(y0, y1, x0, x1)`` (end exclusive)."""
    s = Lr.shape[0]
    y0, y1, x0, x1 = s, -1, s, -1
    for i in range(s):
        for j in range(s):
            c = Lr[i, j] >= thr
            core[i, j] = c
            if c:
                y0 = min(y0, i)
                y1 = max(y1, i)
                x0 = min(x0, j)
                x1 = max(x1, j)
    return y0, y1 + 1, x0, x1 + 1


@nb.njit(**_JIT)
def _band_and_region(core, lvlr, pur, badr, satr, thr, disc_r, others, grow, band, win, rowbits, dilbits,
                     cy0, cy1, cx0, cx1, y0, y1, x0, x1, by0, by1, bx0, bx1):
    """Step 3's band (2-4 px around the core, not bad or saturated, preferring pixels that
    are not black or clipped) into ``band`` (uint8) and the fitted region's window (3 px)
    into ``win``, both leaving out other bright structures (pixels above the core level not
    connected to it, grown by the 3x3 cross). ``grow (S, S)``, ``rowbits (S, 5)`` and
    ``dilbits (S, 3)`` (uint64) are work space."""
    for i in range(y0, y1):
        for j in range(x0, x1):
            others[i, j] = lvlr[i, j] >= thr and not core[i, j]
    # The core's dilations by the discs of radius 2, 3, 4: as bit masks of the band box's
    # columns when it has at most 64, else stamped as the smallest radius reaching each pixel.
    bits = bx1 - bx0 <= 64
    if bits:
        _grow_bits(core, rowbits, dilbits, cy0, cy1, cx0, cx1, by0, by1, bx0)
    else:
        _grow_stamped(core, disc_r, grow, cy0, cy1, cx0, cx1, y0, y1, x0, x1)
    n_band = 0
    n_info = 0
    for i in range(by0, by1):
        d2, d3, d4 = dilbits[i, 0], dilbits[i, 1], dilbits[i, 2]
        for j in range(bx0, bx1):
            o1 = others[i, j] or (i > y0 and others[i - 1, j]) or (i < y1 - 1 and others[i + 1, j]) \
                or (j > x0 and others[i, j - 1]) or (j < x1 - 1 and others[i, j + 1])
            if bits:
                bit = np.uint64(1) << np.uint64(j - bx0)
                in2, in3, in4 = (d2 & bit) != 0, (d3 & bit) != 0, (d4 & bit) != 0
            else:
                g = grow[i, j]
                in2, in3, in4 = g <= _BAND_IN, g <= _WIN, g <= _BAND_OUT
            bd = in4 and not in2 and not o1 and not badr[i, j] and not satr[i, j]
            band[i, j] = 1 if bd else 0
            win[i, j] = in3 and not o1
            if bd:
                n_band += 1
                if _FLAT_LO < pur[i, j] < _FLAT_HI:
                    n_info += 1
    if n_info >= 10 and 3 * n_info >= n_band:
        for i in range(by0, by1):
            for j in range(bx0, bx1):
                if band[i, j] and not (_FLAT_LO < pur[i, j] < _FLAT_HI):
                    band[i, j] = 0


@nb.njit(**_INLINE)
def _grow_bits(core, rowbits, dilbits, cy0, cy1, cx0, cx1, by0, by1, bx0):
    """The core's dilations by the discs of radius 2, 3 and 4 (:data:`_DISC_R`) on the rows
    ``by0:by1``, as bit masks of the columns ``bx0 ..`` into ``dilbits[:, 0..2]``: per core row
    its horizontal dilations by 0..4 px (``rowbits``), then per row the union of those that
    the discs' rows ask of the core rows within reach (:data:`_DISC_SPAN`)."""
    one = np.uint64(1)
    for i in range(cy0, cy1):
        m = np.uint64(0)
        for j in range(cx0, cx1):
            if core[i, j]:
                m |= one << np.uint64(j - bx0)
        h = m
        rowbits[i, 0] = m
        for w in range(1, 5):
            h = h | (m << np.uint64(w)) | (m >> np.uint64(w))
            rowbits[i, w] = h
    for a in range(by0, by1):
        for rr in range(3):
            r = rr + 2
            acc = np.uint64(0)
            for i in range(max(a - r, cy0), min(a + r + 1, cy1)):
                w = _DISC_SPAN[r, abs(i - a)]
                if w >= 0:
                    acc |= rowbits[i, w]
            dilbits[a, rr] = acc


@nb.njit(**_JIT)
def _grow_stamped(core, disc_r, grow, cy0, cy1, cx0, cx1, y0, y1, x0, x1):
    """The smallest disc radius (1..4, :data:`_DISC_R`; 99: none) whose dilation of the core
    reaches each pixel, into ``grow`` (stamped from the core's boundary pixels only: a pixel
    of the dilation by an orthogonally convex disc is within the disc of a core pixel that
    has a 4-neighbour outside the core)."""
    s = core.shape[0]
    for i in range(y0, y1):
        for j in range(x0, x1):
            grow[i, j] = 99
    for i in range(cy0, cy1):
        for j in range(cx0, cx1):
            if core[i, j]:
                grow[i, j] = 1
                if (i > 0 and core[i - 1, j]) and (i < s - 1 and core[i + 1, j]) \
                        and (j > 0 and core[i, j - 1]) and (j < s - 1 and core[i, j + 1]):
                    continue
                for a in range(max(i - 4, 0), min(i + 5, s)):
                    for b in range(max(j - 4, 0), min(j + 5, s)):
                        rr = disc_r[a - i + 4, b - j + 4]
                        if rr < grow[a, b]:
                            grow[a, b] = rr


@nb.njit(**_INLINE)
def _peak_mean(d, core, cy0, cy1, cx0, cx1):
    """``max(largest 3x3 mean of d in the core, 0.9 x largest d in the core)`` (float32)."""
    c_box = np.float32(-np.inf)
    c_raw = np.float32(-np.inf)
    for i in range(cy0, cy1):
        for j in range(cx0, cx1):
            if core[i, j]:
                c_box = max(c_box, mean3(d, i, j))
                c_raw = max(c_raw, d[i, j])
    return max(c_box, np.float32(0.9) * c_raw)


@nb.njit(**_JIT)
def _saturation(d, win, badr, satr, half_c, hr, h2, rowbits, wy0, wy1, wx0, wx1):
    """Whether a pixel of the window is bad, and the fraction of the half-contrast region's
    rim (its dilation by the radius-2 disc, less itself) that is saturated (0 when no
    saturated pixel is near it). Fills ``hr`` (the region) in the window box; ``h2 (S, S)``
    and ``rowbits (S, >= 2)`` are work space."""
    s = d.shape[0]
    masked = False
    hy0, hy1, hx0, hx1 = s, -1, s, -1
    for i in range(wy0, wy1):
        for j in range(wx0, wx1):
            h = False
            if win[i, j]:
                if badr[i, j]:
                    masked = True
                h = d[i, j] >= half_c
            hr[i, j] = h
            if h:
                hy0 = min(hy0, i)
                hy1 = max(hy1, i)
                hx0 = min(hx0, j)
                hx1 = max(hx1, j)
    if hy1 < 0:
        return masked, 0.0
    ry0, ry1, rx0, rx1 = max(hy0 - 2, 0), min(hy1 + 3, s), max(hx0 - 2, 0), min(hx1 + 3, s)
    any_sat = False
    for i in range(ry0, ry1):
        for j in range(rx0, rx1):
            if satr[i, j]:
                any_sat = True
    if not any_sat:
        return masked, 0.0
    if rx1 - rx0 <= 64:
        return masked, _rim_bits(hr, satr, rowbits, ry0, ry1, rx0, rx1)
    # The disc: rows -1..1 span 5 columns, rows -2 and 2 one (from the horizontal dilation).
    for i in range(ry0, ry1):
        for j in range(rx0, rx1):
            h = False
            for b in range(max(j - 2, 0), min(j + 3, s)):
                h = h or hr[i, b]
            h2[i, j] = h
    n_rim = 0
    n_sat = 0
    for i in range(ry0, ry1):
        for j in range(rx0, rx1):
            if hr[i, j]:
                continue
            hit = h2[i, j] or (i > ry0 and h2[i - 1, j]) or (i < ry1 - 1 and h2[i + 1, j]) \
                or (i > 1 and hr[i - 2, j]) or (i < s - 2 and hr[i + 2, j])
            if hit:
                n_rim += 1
                if satr[i, j]:
                    n_sat += 1
    return masked, n_sat / max(n_rim, 1)


@nb.njit(**_INLINE)
def _grey_level(pur, d, polarity, i, j):
    """The local background's grey level at pixel ``(i, j)`` (at least 1; for black dots its
    distance from white), float32."""
    g = np.float32(pur[i, j]) - d[i, j]
    if polarity <= 0:
        g = np.float32(255.0) - g
    return max(g, np.float32(1.0))


@nb.njit(**_INLINE)
def _rim_bits(hr, satr, rowbits, ry0, ry1, rx0, rx1):
    """:func:`_saturation`'s rim fraction with the rows of the region ``hr`` as bit masks of
    the rim box's columns (at most 64): each row's horizontal dilation by 2 px, OR-ed over the
    disc's rows (-1..1 that, -2 and 2 the row itself)."""
    one = np.uint64(1)
    for i in range(ry0, ry1):
        m = np.uint64(0)
        for j in range(rx0, rx1):
            if hr[i, j]:
                m |= one << np.uint64(j - rx0)
        rowbits[i, 0] = m
        rowbits[i, 1] = m | (m << one) | (m >> one) | (m << np.uint64(2)) | (m >> np.uint64(2))
    n_rim = 0
    n_sat = 0
    for i in range(ry0, ry1):
        rim = rowbits[i, 1]
        if i > ry0:
            rim |= rowbits[i - 1, 1]
        if i < ry1 - 1:
            rim |= rowbits[i + 1, 1]
        if i - 2 >= ry0:
            rim |= rowbits[i - 2, 0]
        if i + 2 < ry1:
            rim |= rowbits[i + 2, 0]
        rim &= ~rowbits[i, 0]
        if rim == 0:
            continue
        for j in range(rx0, rx1):
            if rim & (one << np.uint64(j - rx0)):
                n_rim += 1
                if satr[i, j]:
                    n_sat += 1
    return n_sat / max(n_rim, 1)


@nb.njit(**_JIT)
def _coverage(pur, d, core, polarity, half, e, cov, cy0, cy1, cx0, cx1, y0, y1, x0, x1):
    """Step 4: the signal over the dot's full contrast ``cov`` (a fraction of the local
    background's grey level; a white dot cannot rise above 255). Returns the core's centroid
    (float32 offsets from the patch centre)."""
    s = d.shape[0]
    # The peak of d over the background level: only the core's 3x3 means read it.
    for i in range(max(cy0 - 1, 0), min(cy1 + 1, s)):
        for j in range(max(cx0 - 1, 0), min(cx1 + 1, s)):
            e[i, j] = d[i, j] / _grey_level(pur, d, polarity, i, j)
    Ce = _peak_mean(e, core, cy0, cy1, cx0, cx1)
    Cef = Ce if Ce > 0 else np.float32(1.0)
    mc0 = 0.0
    mcx = 0.0
    mcy = 0.0
    for i in range(y0, y1):
        for j in range(x0, x1):
            g = _grey_level(pur, d, polarity, i, j)
            full = g * Cef
            if polarity > 0:
                full = min(full, np.float32(255.0) - g)
            cov[i, j] = d[i, j] / max(full, np.float32(1e-3))
            if core[i, j]:
                mc0 += 1.0
                mcx += float(j - half)
                mcy += float(i - half)
    mc0 = max(mc0, 1e-9)
    return np.float32(mcx / mc0), np.float32(mcy / mc0)


@nb.njit(**_JIT)
def _sector_levels(cov, band, fcx, fcy, half, lv32, lev, cnt, valid, nl, nv, by0, by1, bx0, bx1):
    """The per-direction background (:func:`carapost.core.blob_outline._sector_background`):
    the highest 3x3 mean of ``cov`` over the band pixels of each of the angular sectors around
    ``(fcx, fcy)`` (at least 2 pixels; empty sectors from their neighbours), capped; into
    ``lv32`` (float32 (K,); ``lev``, ``nl`` float64, ``cnt`` int64, ``valid``, ``nv`` bool (K,)
    are work space). Returns the largest sector level."""
    K = _N_SECTORS
    for kk in range(K):
        lev[kk] = -np.inf
        cnt[kk] = 0
    for i in range(by0, by1):
        for j in range(bx0, bx1):
            if band[i, j]:
                ang = _diamond(np.float32(j - half) - fcx, np.float32(i - half) - fcy) * np.float32(2.0)
                kk = min(int(ang), K - 1)
                cnt[kk] += 1
                lev[kk] = max(lev[kk], float(mean3(cov, i, j)))
    n_valid = 0
    for kk in range(K):
        valid[kk] = cnt[kk] >= 2
        if valid[kk]:
            n_valid += 1
        else:
            lev[kk] = 0.0
    for _ in range(K // 2):
        if n_valid == K:
            break
        for kk in range(K):
            nl[kk] = lev[kk]
            nv[kk] = valid[kk]
            if valid[kk]:
                continue
            kl, kr = (kk - 1) % K, (kk + 1) % K
            vl, vr = valid[kl], valid[kr]
            if vl or vr:
                sl = lev[kl] if vl else 0.0
                sr = lev[kr] if vr else 0.0
                nl[kk] = (sl + sr) / ((1.0 if vl else 0.0) + (1.0 if vr else 0.0))
                nv[kk] = True
        n_valid = 0
        for kk in range(K):
            lev[kk] = nl[kk]
            valid[kk] = nv[kk]
            if nv[kk]:
                n_valid += 1
    sec_max = -np.inf
    for kk in range(K):
        v = min(lev[kk] if valid[kk] else 0.0, _MAX_SECTOR_LEVEL)
        lv32[kk] = np.float32(v)
        sec_max = max(sec_max, v)
    return sec_max
