"""Compiled (numba) kernels of the blob fit's level search (steps 1-2 of
:mod:`carapost.core.blob_fit`) and of its patch stacks: one call per patch stack instead of
dozens of numpy passes.

Each kernel loops over the candidates of a stack ``(N, S, S)`` (``S = 2 half + 1``) and over
their pixels, and computes what the vectorised numpy steps it replaces computed (sums in
float64, per-pixel arithmetic in the same float32 order): the ring plane and peak
(:func:`ring_step`), the flood levels and the level search (:func:`level_step`), the patch
stacks (:func:`patch_step`); the candidate stage's kernels are in
:mod:`carapost.core.blob_kernels_dense`. The plane fit and the
3x3 mean are shared with the outline kernels (:mod:`carapost.core.blob_kernels_outline`,
:mod:`carapost.core.blob_kernels_region`).

The public functions are thin Python wrappers that allocate the outputs and work arrays (an
allocation inside a kernel costs compile time) and call the compiled ``_name``; small
helpers are inlined into their callers. Compiled with ``cache=True`` (the first call in a
fresh clone compiles them once, ~10 s for all kernels; later processes load the cache from
``__pycache__``) and ``nogil=True`` (Detect Blobs [Active Range] fits frames on two threads).
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["plane_fit", "box3", "mean3", "ring_step", "level_step", "patch_step", "LEVEL_THRESHOLDS", "LEVELS", "FP", "FLAT_LO", "FLAT_HI"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")
#: Small helpers are inlined into their callers (compiling them apart costs more time).
_INLINE = dict(_JIT, inline="always")

#: Signed-image levels at or below / at or above which a pixel is black or clipped.
FLAT_LO, FLAT_HI = 4, 251
#: Levels (fractions of the peak over the ring background) searched for the blob's core.
LEVELS = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95)
#: Fixed-point scale of the flood levels (uint8, clipped at 255; the peak is ``FP``: the
#: searched levels are exact multiples of 10) ...
FP = 200
#: ... and the searched levels in it.
LEVEL_THRESHOLDS = np.rint(np.asarray(LEVELS) * FP).astype(np.int64)
_LEVELS = np.asarray(LEVELS)
#: For each fixed-point level 0..255, the index of the highest searched level at or below it
#: (-1: none).
_LEVEL_INDEX = np.searchsorted(LEVEL_THRESHOLDS, np.arange(256), side="right") - 1
#: A level's component is a blob while its area is at least this fraction of its moment
#: ellipse's (1 for an ellipse; a dot that has started to flood a band is elongated or
#: irregular) ...
_MIN_FILL = 0.9
#: ... a test made only on components of at least this many pixels, and at levels at least
#: this many noise sigmas (of the 3x3 mean) below the peak: the peak is the largest of many
#: 3x3 means, ~2.5 sigmas above the top of a flat dot, and the component is ragged down to
#: ~2.5 sigmas below it (4 sigmas made the noisy top of a big white dot in low light look
#: like a merge, and the core a fragment of it) ...
_FILL_MIN_AREA = 20
_TOP_NOISE = 5.0
#: ... and not above this level (the top of a flat, clipped or JPEG-coded dot is ragged).
_MAX_SHAPED_LEVEL = 0.8


@nb.njit(**_INLINE)
def solve3(a00, a01, a02, a11, a12, a22, r0, r1, r2):
    """Solution of the symmetric 3x3 system ``A c = r`` (Gaussian elimination, float64)."""
    # Row reduction with partial pivoting on the first column is not needed: A is a
    # regularised Gram matrix (positive definite).
    l10 = a01 / a00
    l20 = a02 / a00
    b11 = a11 - l10 * a01
    b12 = a12 - l10 * a02
    b22 = a22 - l20 * a02
    s1 = r1 - l10 * r0
    s2 = r2 - l20 * r0
    l21 = b12 / b11
    c22 = b22 - l21 * b12
    t2 = s2 - l21 * s1
    c2 = t2 / c22
    c1 = (s1 - b12 * c2) / b11
    c0 = (r0 - a01 * c1 - a02 * c2) / a00
    return c0, c1, c2


@nb.njit(**_JIT)
def plane_fit(p, w, half, iters, y0, y1, x0, x1, resid, uy0, uy1, ux0, ux1):
    """Robust plane of one patch ``p (S, S)`` (uint8 or float32) over the pixels ``w`` (uint8
    (S, S), 1 = used; changed in place by the reweighting), as
    :func:`carapost.core.blob_fit._plane_fit`: ``iters`` passes dropping pixels beyond 2.5
    sigma. Only rows ``y0:y1`` and columns ``x0:x1`` are read (``w`` is 0 elsewhere; its
    non-zero pixels are within rows ``uy0:uy1`` and columns ``ux0:ux1``, the box the passes
    before the last visit), and ``resid (S, S)`` float32 receives ``p - plane`` there. Returns
    ``(sigma, n_used, c0, c1, c2)`` (sigma corrected for the clipping as there; ``c`` float32
    values)."""
    sigma = 0.0
    s0 = 0.0
    c0 = np.float32(0.0)
    c1 = np.float32(0.0)
    c2 = np.float32(0.0)
    lim = np.float32(np.inf)
    for it in range(iters + 1):
        m0 = m1 = m2 = m3 = m4 = m5 = 0.0
        r0 = r1 = r2 = 0.0
        for i in range(uy0, uy1):
            y = float(i - half)
            for j in range(ux0, ux1):
                if w[i, j] and it > 0 and not (abs(resid[i, j]) < lim):
                    w[i, j] = 0                # the previous pass's reweighting
                if w[i, j]:
                    x = float(j - half)
                    v = float(p[i, j])
                    m0 += 1.0
                    m1 += x
                    m2 += y
                    m3 += x * x
                    m4 += x * y
                    m5 += y * y
                    r0 += v
                    r1 += v * x
                    r2 += v * y
        s0 = m0
        a00 = m0 + 1e-6 * max(m0, 1e-6) + 1e-9
        a11 = m3 + 1e-6 * max(m3, 1e-6) + 1e-9
        a22 = m5 + 1e-6 * max(m5, 1e-6) + 1e-9
        e0, e1, e2 = solve3(a00, m1, m2, a11, m4, a22, r0, r1, r2)
        c0 = np.float32(e0)
        c1 = np.float32(e1)
        c2 = np.float32(e2)
        e2s = 0.0
        last = it == iters
        by0, by1, bx0, bx1 = (y0, y1, x0, x1) if last else (uy0, uy1, ux0, ux1)
        for i in range(by0, by1):
            yf = np.float32(i - half)
            for j in range(bx0, bx1):
                if last or w[i, j]:        # before the last pass only the used pixels
                    xf = np.float32(j - half)
                    r = np.float32(p[i, j]) - (c0 + c1 * xf + c2 * yf)
                    resid[i, j] = r
                    if w[i, j]:
                        e2s += float(r) * float(r)
        sigma = np.sqrt(e2s / max(s0 - 3.0, 1.0))
        lim = np.float32(2.5 * max(sigma, 0.3))
    scale = 0.94 if iters > 0 else 1.0
    return sigma / scale, s0, c0, c1, c2


@nb.njit(**_JIT)
def box3(d, out, y0, y1, x0, x1, rs):
    """3x3 mean of ``d (S, S)`` float32 into ``out`` at rows ``y0:y1``, columns ``x0:x1``
    (pixels outside the patch count as 0, as ``cv2.blur`` with a constant border; sums in
    float64 as OpenCV's). ``rs`` (float64, at least ``(S + 2, S)``) is work space: the
    horizontal sums of 3 of rows ``y0 - 1 .. y1``."""
    s = d.shape[0]
    for i in range(y0 - 1, y1 + 1):
        for j in range(x0, x1):
            acc = 0.0
            if 0 <= i < s:
                acc = float(d[i, j])
                if j > 0:
                    acc += float(d[i, j - 1])
                if j < s - 1:
                    acc += float(d[i, j + 1])
            rs[i - y0 + 1, j - x0] = acc
    for i in range(y0, y1):
        for j in range(x0, x1):
            a = i - y0 + 1
            out[i, j] = np.float32((rs[a - 1, j - x0] + rs[a, j - x0] + rs[a + 1, j - x0]) * (1.0 / 9.0))


@nb.njit(**_INLINE)
def mean3(d, i, j):
    """:func:`box3` of ``d`` at one pixel."""
    s = d.shape[0]
    acc = 0.0
    for a in range(max(i - 1, 0), min(i + 2, s)):
        for b in range(max(j - 1, 0), min(j + 2, s)):
            acc += float(d[a, b])
    return np.float32(acc * (1.0 / 9.0))


def ring_step(pu: np.ndarray, bad: np.ndarray, sat: np.ndarray, radius: np.ndarray, half: int) -> tuple:
    """Step 1 of the fit for a stack: the ring plane (pixels outside ``1.5 r + 1.5`` px inside
    the patch's disc, not bad or saturated, preferring pixels that are not black or clipped),
    the signal over it ``d0`` and the peak (largest 3x3 mean of ``d0`` within ``max(1.5, r /
    2)`` px of the centre; the 3x3 mean of the whole patch is left to :func:`level_step`, for
    the patches that get there).

    Parameters: ``pu`` uint8 (N, S, S), ``bad``/``sat`` bool (N, S, S), ``radius`` float32 (N,).
    Returns ``d0`` float32 (N, S, S), ``sig0, n0`` float64 (N,), ``c0`` float32 (N, 3),
    ``pk`` int64 (N,) flat index of the peak, ``peak`` float64 (N,).
    """
    n, s = pu.shape[0], pu.shape[1]
    out = (np.empty((n, s, s), np.float32), np.zeros(n), np.zeros(n), np.zeros((n, 3), np.float32),
           np.zeros(n, np.int64), np.zeros(n))
    _ring_step(pu, bad, sat, np.asarray(radius, np.float32), int(half), *out, np.empty((s, s), np.uint8),
               np.empty((s + 2, s)), np.empty((s, s), np.float32))
    return out


@nb.njit(**_JIT)
def _ring_step(pu, bad, sat, radius, half, d0, sig0, n0, c0, pk, peak, w, rs, ds):
    """:func:`ring_step` into its outputs (``w``, ``rs``, ``ds``: work space)."""
    n = pu.shape[0]
    s = pu.shape[1]
    hd = np.float32(half * half)
    for k in range(n):
        r0 = radius[k]
        r_in = min(np.float32(1.5) * r0 + np.float32(1.5), np.float32(half - 1.5))
        r_in2 = r_in * r_in
        n_mask = 0
        n_info = 0
        for i in range(s):
            for j in range(s):
                xf = np.float32(j - half)
                yf = np.float32(i - half)
                rho2 = xf * xf + yf * yf
                m = rho2 >= r_in2 and rho2 <= hd and not bad[k, i, j] and not sat[k, i, j]
                w[i, j] = 1 if m else 0
                if m:
                    n_mask += 1
                    v = pu[k, i, j]
                    if v > FLAT_LO and v < FLAT_HI:
                        n_info += 1
        if n_info >= 20 and 3 * n_info >= n_mask:
            for i in range(s):
                for j in range(s):
                    v = pu[k, i, j]
                    if v <= FLAT_LO or v >= FLAT_HI:
                        w[i, j] = 0
        sg, su, a, b, c = plane_fit(pu[k], w, half, 1, 0, s, 0, s, d0[k], 0, s, 0, s)
        sig0[k] = sg
        n0[k] = su
        c0[k, 0] = a
        c0[k, 1] = b
        c0[k, 2] = c
        rn = max(np.float32(1.5), np.float32(0.5) * r0)
        rn2 = rn * rn
        best = -np.inf
        bi = 0
        ext = min(int(np.ceil(rn)), half)
        box3(d0[k], ds, half - ext, half + ext + 1, half - ext, half + ext + 1, rs)   # only where the peak may be
        for i in range(half - ext, half + ext + 1):
            for j in range(half - ext, half + ext + 1):
                xf = np.float32(j - half)
                yf = np.float32(i - half)
                if xf * xf + yf * yf <= rn2 and ds[i, j] > best:
                    best = ds[i, j]
                    bi = i * s + j
        pk[k] = bi
        peak[k] = best
    return d0, sig0, n0, c0, pk, peak


@nb.njit(**_JIT)
def _flood_one(lv, py, px, floor, out, heads, nxt):
    """Flood levels of one patch: ``out[p]`` = the largest ``t >= floor`` such that ``p`` is
    8-connected to ``(py, px)`` through pixels of ``lv >= t`` (morphological reconstruction of
    the peak under ``max(lv, floor)``), by a priority flood over the levels above the floor
    (exact; ``lv`` below the floor needs no clipping: such a pixel is never raised)."""
    s = lv.shape[0]
    for i in range(s):
        for j in range(s):
            out[i, j] = floor
    for v in range(floor + 1, 256):     # levels at or below the floor are never queued
        heads[v] = -1
    top = max(int(lv[py, px]), floor)
    out[py, px] = top
    if top <= floor:
        return
    # Bucket queue: linked lists of pixel indices per level (``nxt`` holds the links).
    heads[top] = py * s + px
    nxt[py * s + px] = -1
    v = top
    while v > floor:
        e = heads[v]
        if e < 0:
            v -= 1
            continue
        heads[v] = nxt[e]
        i, j = e // s, e % s
        if out[i, j] != v:          # a stale entry (raised later)
            continue
        for a in range(max(i - 1, 0), min(i + 2, s)):
            for b in range(max(j - 1, 0), min(j + 2, s)):
                t = min(v, int(lv[a, b]))
                if t > out[a, b]:
                    out[a, b] = t
                    q = a * s + b
                    nxt[q] = heads[t]
                    heads[t] = q


def level_step(d0: np.ndarray, peak: np.ndarray, pk: np.ndarray, half: int, max_radius: np.ndarray,
               pixel_noise: np.ndarray) -> tuple:
    """Step 2 of the fit for a stack (see :func:`carapost.core.blob_fit.search_levels`): the
    smoothed signal (the 3x3 mean of the signal over the ring plane ``d0``, :func:`box3`) in
    fixed point (the peak is :data:`FP`) ``lvl``, the flood levels ``L`` (uint8,
    at least 99), per level of :data:`LEVEL_THRESHOLDS` the area and fill (area over its
    moment ellipse's) of the peak's component, the largest flood level on the patch border,
    whether each level is a blob (``valid``), the core level found ``k_found`` and whether
    an isolated core exists ``has``.

    Parameters: ``d0`` float32 (N, S, S), ``peak`` float64 (N,), ``pk`` int64 (N,) flat peak
    index, ``max_radius``, ``pixel_noise`` float64 (N,).
    """
    n, s = d0.shape[0], d0.shape[1]
    K = len(LEVELS)
    out = (np.empty((n, s, s), np.uint8), np.empty((n, s, s), np.uint8), np.zeros((n, K)), np.zeros((n, K)),
           np.zeros(n, np.int64), np.zeros((n, K), bool), np.zeros(n, np.int64), np.zeros(n, bool))
    _level_step(d0, np.asarray(peak, float), np.asarray(pk, np.int64), int(half), np.asarray(max_radius, float),
                np.asarray(pixel_noise, float), *out, np.empty(256, np.int64), np.empty(s * s, np.int64),
                np.zeros((K, 6)), np.empty((s, s), np.float32), np.empty((s + 2, s)))
    return out


@nb.njit(**_JIT)
def _level_step(d0, peak, pk, half, max_radius, pixel_noise, lvl, L, area, fill, edge_max, valid, k_found, has,
                heads, nxt, mom, ds, rs):
    """:func:`level_step` into its outputs (the last five: work space)."""
    n = d0.shape[0]
    s = d0.shape[1]
    K = LEVEL_THRESHOLDS.shape[0]
    floor = int(LEVEL_THRESHOLDS[0]) - 1
    for k in range(n):
        scale = np.float32(FP / peak[k])
        box3(d0[k], ds, 0, s, 0, s, rs)
        for i in range(s):
            for j in range(s):
                v = ds[i, j] * scale
                v = min(max(v, np.float32(0.0)), np.float32(255.0))
                lvl[k, i, j] = np.uint8(int(v))
        Lk = L[k]
        _flood_one(lvl[k], pk[k] // s, pk[k] % s, floor, Lk, heads, nxt)     # straight into L
        for q in range(K):
            for c in range(6):
                mom[q, c] = 0.0
        em = 0
        for i in range(s):
            y = float(i - half)
            for j in range(s):
                t = int(Lk[i, j])
                if i == 0 or j == 0 or i == s - 1 or j == s - 1:
                    em = max(em, t)
                if t < LEVEL_THRESHOLDS[0]:
                    continue
                x = float(j - half)
                q = _LEVEL_INDEX[t]                 # the highest level the pixel reaches
                mom[q, 0] += 1.0
                mom[q, 1] += x
                mom[q, 2] += y
                mom[q, 3] += x * x
                mom[q, 4] += x * y
                mom[q, 5] += y * y
        # A level's component is every pixel reaching it or a higher one (integer sums: exact
        # in any order).
        for q in range(K - 2, -1, -1):
            for c in range(6):
                mom[q, c] += mom[q + 1, c]
        edge_max[k] = em
        a_max = np.pi * (1.3 * max_radius[k] + 2.0) ** 2
        noise_band = 1.0 - _TOP_NOISE * (pixel_noise[k] / 3.0) / peak[k]
        shaped_top = min(noise_band, _MAX_SHAPED_LEVEL)
        for q in range(K):
            a = mom[q, 0]
            a_s = max(a, 1.0)
            vx = mom[q, 3] / a_s - (mom[q, 1] / a_s) ** 2 + 1.0 / 12.0
            vy = mom[q, 5] / a_s - (mom[q, 2] / a_s) ** 2 + 1.0 / 12.0
            vxy = mom[q, 4] / a_s - mom[q, 1] * mom[q, 2] / (a_s * a_s)
            f = a / (4.0 * np.pi * np.sqrt(max(vx * vy - vxy * vxy, 1e-6)))
            area[k, q] = a
            fill[k, q] = f
            ok = em < LEVEL_THRESHOLDS[q] and a <= a_max
            shaped = _LEVELS[q] <= shaped_top
            valid[k, q] = ok and (f >= _MIN_FILL or a < _FILL_MIN_AREA or not shaped)
        # The core is the lowest level from which every higher level is valid.
        kf = K
        for q in range(K - 1, -1, -1):
            if not valid[k, q]:
                break
            kf = q
        has[k] = kf < K
        k_found[k] = kf if kf < K else K - 1
    return lvl, L, area, fill, edge_max, valid, k_found, has


def patch_step(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, half: int, mask: np.ndarray, sat_lo: int,
               sat_hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_patch_step` (see there): returns ``pu``, ``bad``, ``sat``."""
    n, s = len(cx), 2 * int(half) + 1
    out = (np.empty((n, s, s), np.uint8), np.empty((n, s, s), bool), np.empty((n, s, s), bool))
    _patch_step(img, cx, cy, int(half), mask, int(sat_lo), int(sat_hi), *out)
    return out


@nb.njit(**_JIT)
def _patch_step(img, cx, cy, half, mask, sat_lo, sat_hi, pu, bad, sat):
    """:func:`carapost.core.blob_patches.extract_patches` compiled: the ``(2 half + 1)^2``
    patches of ``img`` (uint8 (H, W)) around ``cx, cy`` (int64 (N,)), pixels beyond the image
    clamped to its border and marked bad, ``mask`` (bool (H, W); ``(0, 0)`` for none) marked
    bad, values in ``sat_lo..sat_hi`` inside the image marked saturated (``sat_lo > sat_hi``:
    none), into ``pu`` uint8, ``bad``, ``sat`` bool (N, S, S)."""
    H, W = img.shape
    n = cx.shape[0]
    s = 2 * half + 1
    has_mask = mask.shape[0] > 0
    for k in range(n):
        y0, x0 = cy[k] - half, cx[k] - half
        if not has_mask and y0 >= 0 and x0 >= 0 and y0 + s <= H and x0 + s <= W:
            # Inside the image, no mask: row copies (nothing clamped, nothing bad).
            for i in range(s):
                src, pk, bk, sk = img[y0 + i, x0:x0 + s], pu[k, i], bad[k, i], sat[k, i]
                for j in range(s):
                    v = src[j]
                    pk[j] = v
                    bk[j] = False
                    sk[j] = v >= sat_lo and v <= sat_hi
            continue
        for i in range(s):
            y = cy[k] + i - half
            yc = min(max(y, 0), H - 1)
            for j in range(s):
                x = cx[k] + j - half
                xc = min(max(x, 0), W - 1)
                v = img[yc, xc]
                out = y != yc or x != xc
                pu[k, i, j] = v
                b = out
                if has_mask and mask[yc, xc]:
                    b = True
                bad[k, i, j] = b
                sat[k, i, j] = (not out) and v >= sat_lo and v <= sat_hi
