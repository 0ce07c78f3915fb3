"""Compiled (numba) steps 3-6 of the blob fit (:mod:`carapost.core.blob_outline`): the
outline of each core found by the level search — local background, coverage, sector
background, trimmed moments, shape — in one call per level search. The background and region
steps (band, peak, saturation, coverage, sectors) are in
:mod:`carapost.core.blob_kernels_region`; the soft region, the trimmed moments (the ellipse)
and the shape measurements here.

:func:`outline_step` loops over the requested rows of a
:class:`~carapost.core.blob_fit.LevelSearch` and, for each, over the pixels within 5 px of its
core's bounding box (the band reaches 4 px beyond the core, the 3x3 means one more), with the
arithmetic of the numpy version (:func:`carapost.core.blob_outline._outline`, kept as the
reference: ``fit_outline_parts(..., compiled=False)``) — float32 per pixel, sums in float64.
Each step is its own compiled function (one job each; typing one big function takes longer
than its parts), called per row with the boxes it needs: the core's box grown by 5 px
(read), 4 (the band) or 3 (the fitted region). :func:`outline_step` allocates the outputs
and the work arrays; the row loop leaves the work arrays clean for the next row.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .blob_kernels import LEVEL_THRESHOLDS, LEVELS, plane_fit
from .blob_kernels_region import (_DISC_R, _MAX_SATURATED_RIM, _N_SECTORS, _band_and_region, _core_box, _coverage,
                                  _diamond, _peak_mean, _saturation, _sector_levels)
from .blob_score import _PROFILE_BIN, _PROFILE_MARGIN

__all__ = ["outline_step", "N_OUTPUTS", "OUTPUT_FIELDS"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")
_INLINE = dict(_JIT, inline="always")
#: Slope of the soft half-contrast region ``q = clip(RAMP (d/C - 1/2) + 1/2, 0, 1)``.
_RAMP = 1.5
#: Trimmed moments: iterations, and the distance (px) beyond the moment ellipse from which
#: the region is dropped.
_TRIM_ITERS = 3
_TRIM_MARGIN = 1.0
_LEVELS = np.asarray(LEVELS)
#: The float64 outputs of :func:`outline_step`, in its column order (``ok`` and ``border``
#: are returned apart).
OUTPUT_FIELDS = ("x", "y", "major", "minor", "angle", "contrast", "background", "rise", "noise", "ring_noise",
                 "core_level", "found_level", "area_ratio", "shape_residual", "asymmetry", "profile_rms", "area",
                 "open", "kept", "saturated")
N_OUTPUTS = len(OUTPUT_FIELDS)


@nb.njit(**_INLINE)
def _moment_stats(m0, m1, m2, m3, m4, m5):
    """Mass, centroid and second central moments ``(m0, mx, my, cxx, cxy, cyy)`` (float64)
    from the sums of ``q``, ``q x``, ``q y``, ``q x^2``, ``q x y``, ``q y^2`` over a region
    (offsets from the patch centre)."""
    m0s = max(m0, 1e-9)
    mx, my = m1 / m0s, m2 / m0s
    cxx = max(m3 / m0s - mx * mx, 1e-6)
    cxy = m4 / m0s - mx * my
    cyy = max(m5 / m0s - my * my, 1e-6)
    return m0, mx, my, cxx, cxy, cyy


@nb.njit(**_INLINE)
def _ellipse_coef(mx, my, cxx, cxy, cyy):
    det = max(cxx * cyy - cxy * cxy, 1e-9)
    return (np.float32(cyy / (4 * det)), np.float32(-cxy / (4 * det)), np.float32(cxx / (4 * det)),
            np.float32(mx), np.float32(my))


@nb.njit(**_INLINE)
def _ellipse_dist(i, j, half, ia, ib, ic, fx, fy):
    """Signed distance from the ellipse and the squared normalised radius of pixel ``(i, j)``
    (as :func:`carapost.core.blob_score.ellipse_distance`, float32)."""
    ux = np.float32(j - half) - fx
    uy = np.float32(i - half) - fy
    r2 = ux * ux + uy * uy
    rho2 = max(ia * ux * ux + np.float32(2.0) * ib * ux * uy + ic * uy * uy, np.float32(1e-12))
    return np.float32(math.sqrt(r2)) - np.float32(math.sqrt(r2 / rho2)), rho2


@nb.njit(**_JIT)
def _soft_region(cov, win, lv32, fcx, fcy, half, q, qf, cut, wy0, wy1, wx0, wx1):
    """The soft half-contrast region ``q`` between the sector background (interpolated
    linearly in angle) and the dot's top, in the window; a copy in ``qf`` and ``cut`` cleared
    for :func:`_trimmed_moments`. Returns the region's :func:`_moment_stats`."""
    K = _N_SECTORS
    m0 = m1 = m2 = m3 = m4 = m5 = 0.0
    for i in range(wy0, wy1):
        y = float(i - half)
        for j in range(wx0, wx1):
            q[i, j] = 0.0
            qf[i, j] = 0.0
            cut[i, j] = False
            if not win[i, j]:
                continue
            ang = _diamond(np.float32(j - half) - fcx, np.float32(i - half) - fcy) * np.float32(2.0)
            sa = ang - np.float32(0.5)
            k0 = int(math.floor(sa))
            f = np.float32(float(sa) - k0)
            k0 %= K
            bpix = (np.float32(1.0) - f) * lv32[k0] + f * lv32[(k0 + 1) % K]
            v = np.float32(_RAMP) * (cov[i, j] - bpix) / max(np.float32(1.0) - bpix, np.float32(1e-3)) \
                + np.float32(0.5 - 0.5 * _RAMP)
            qv = min(max(v, np.float32(0.0)), np.float32(1.0))
            q[i, j] = qv
            qf[i, j] = qv
            vv = float(qv)
            if vv != 0.0:
                x = float(j - half)
                m0 += vv
                m1 += vv * x
                m2 += vv * y
                m3 += vv * x * x
                m4 += vv * x * y
                m5 += vv * y * y
    return _moment_stats(m0, m1, m2, m3, m4, m5)


@nb.njit(**_JIT)
def _trimmed_moments(q, qf, cut, half, m0, mx, my, cxx, cxy, cyy, wy0, wy1, wx0, wx1):
    """Step 5: moments of ``q`` (given untrimmed: ``m0 .. cyy``; ``qf`` its copy, ``cut``
    clear), trimmed up to :data:`_TRIM_ITERS` times of the parts more than
    :data:`_TRIM_MARGIN` px outside the moment ellipse (``q`` is left trimmed). Returns the
    untrimmed mass and the trimmed ``(m0, mx, my, cxx, cxy, cyy)``."""
    m0_full = max(m0, 1e-9)
    for _ in range(_TRIM_ITERS):
        ia, ib, ic, fx, fy = _ellipse_coef(mx, my, cxx, cxy, cyy)
        changed = False
        for i in range(wy0, wy1):
            for j in range(wx0, wx1):
                c = False
                if qf[i, j] > 0:
                    dist, _r = _ellipse_dist(i, j, half, ia, ib, ic, fx, fy)
                    c = dist > _TRIM_MARGIN
                if c != cut[i, j]:
                    changed = True
                    cut[i, j] = c
        if not changed:
            break
        # The trimmed region and its moments in one pass.
        s0 = s1 = s2 = s3 = s4 = s5 = 0.0
        for i in range(wy0, wy1):
            y = float(i - half)
            for j in range(wx0, wx1):
                qv = np.float32(0.0) if cut[i, j] else qf[i, j]
                q[i, j] = qv
                v = float(qv)
                if v != 0.0:
                    x = float(j - half)
                    s0 += v
                    s1 += v * x
                    s2 += v * y
                    s3 += v * x * x
                    s4 += v * x * y
                    s5 += v * y * y
        m0, mx, my, cxx, cxy, cyy = _moment_stats(s0, s1, s2, s3, s4, s5)
    return m0_full, m0, mx, my, cxx, cxy, cyy


@nb.njit(**_JIT)
def _shape_profile(q, d, win, badr, binned, pc, ps, mx, my, cxx, cxy, cyy, radius, m0s, half, wy0, wy1, wx0, wx1):
    """Step 6: ``sum |q - ellipse| / m0`` over the window and the RMS of ``d`` around its mean
    profile over the elliptical radius — :func:`carapost.core.blob_score.shape_residual` and
    ``profile_rms`` (``binned`` float32 (S, S), the profile's counts ``pc`` int64 and sums
    ``ps`` float64 (at least the number of bins): work space)."""
    ia, ib, ic, fx, fy = _ellipse_coef(mx, my, cxx, cxy, cyy)
    nbins = min(int(math.ceil((float(radius) + _PROFILE_MARGIN) / _PROFILE_BIN)) + 1, pc.shape[0])
    for kb in range(nbins):
        pc[kb] = 0
        ps[kb] = 0.0
    shape = 0.0
    for i in range(wy0, wy1):
        for j in range(wx0, wx1):
            if not win[i, j]:
                continue
            dist, rho2 = _ellipse_dist(i, j, half, ia, ib, ic, fx, fy)
            qe = min(max(np.float32(0.5) - dist, np.float32(0.0)), np.float32(1.0))
            shape += float(abs(q[i, j] - qe))
            if badr[i, j]:
                continue
            tt = np.float32(math.sqrt(rho2)) * radius
            binned[i, j] = -1.0
            if tt <= radius + np.float32(_PROFILE_MARGIN):
                kb = min(int(tt * np.float32(1.0 / _PROFILE_BIN)), nbins - 1)
                binned[i, j] = kb
                pc[kb] += 1
                ps[kb] += float(d[i, j])
    rss = 0.0
    npix = 0
    for i in range(wy0, wy1):
        for j in range(wx0, wx1):
            if win[i, j] and not badr[i, j] and binned[i, j] >= 0:
                kb = int(binned[i, j])
                res = float(d[i, j]) - ps[kb] / max(pc[kb], 1)
                rss += res * res
                npix += 1
    nb_used = 0
    for kb in range(nbins):
        if pc[kb] > 0:
            nb_used += 1
    return shape / m0s, math.sqrt(rss / max(npix - nb_used, 1))


def outline_step(pu: np.ndarray, bad: np.ndarray, sat: np.ndarray, d0: np.ndarray, lvl: np.ndarray, L: np.ndarray,
                 area: np.ndarray, sig0: np.ndarray, c0: np.ndarray, k_found: np.ndarray, has: np.ndarray,
                 rows: np.ndarray, kc: np.ndarray, polarity: int, half: int) -> tuple:
    """Steps 3-6 for rows ``rows`` (int (M,)) of a level search's arrays (``pu`` uint8, ``d0``
    float32 (A, S, S); ``bad``, ``sat`` bool; ``lvl``, ``L`` uint8; ``area`` (A, K); ``sig0``
    (A,); ``c0`` float32 (A, 3); ``k_found`` int; ``has`` bool) with core level indices ``kc``
    (M,). Returns ``(out float64 (M, N_OUTPUTS), ok, border)`` (columns:
    :data:`OUTPUT_FIELDS`)."""
    m, s, K = len(rows), pu.shape[1], _N_SECTORS
    out = (np.zeros((m, N_OUTPUTS)), np.zeros(m, bool), np.zeros(m, bool))
    nb_max = 8 * s + 16                   # profile bins: the radius is at most the patch diagonal
    _outline_step(pu, bad, sat, d0, lvl, L, area, np.asarray(sig0, float), c0, np.asarray(k_found, np.int64), has,
                  np.asarray(rows, np.int64), np.asarray(kc, np.int64), int(polarity), int(half), _DISC_R, *out,
                  np.zeros((6, s, s), bool), np.zeros((2, s, s), np.uint8), np.zeros((s, s), np.int64),
                  np.zeros((6, s, s), np.float32), np.zeros((s + 2, s + 2), np.float32), np.zeros(K, np.float32),
                  np.zeros(K), np.zeros(K, np.int64), np.zeros(K, bool), np.zeros(K), np.zeros(K, bool),
                  np.zeros(nb_max, np.int64), np.zeros(nb_max), np.zeros((s, 5), np.uint64),
                  np.zeros((s, 3), np.uint64))
    return out


@nb.njit(**_JIT)
def _outline_step(pu, bad, sat, d0, lvl, L, area, sig0, c0, k_found, has, rows, kc, polarity, half, disc_r,
                  out, oks, border, wbool, wu8, grow, wf, q1, lv32, lev, cnt, valid, nl, nv, pc, ps, rowbits, dilbits):
    """:func:`outline_step` into ``out``, ``oks``, ``border``; the other arrays after them are
    work space (zero on entry; left zero where it matters: the row loop cleans what it
    reads)."""
    m = rows.shape[0]
    s = pu.shape[1]
    K = LEVEL_THRESHOLDS.shape[0]
    core, others, win, cut, hr, h2 = wbool[0], wbool[1], wbool[2], wbool[3], wbool[4], wbool[5]
    band, wb = wu8[0], wu8[1]
    d, tmp, e, cov, q, qf = wf[0], wf[1], wf[2], wf[3], wf[4], wf[5]
    for t in range(m):
        r = rows[t]
        k = kc[t]
        thr = LEVEL_THRESHOLDS[k]
        pur, badr, satr, d0r = pu[r], bad[r], sat[r], d0[r]
        cy0, cy1, cx0, cx1 = _core_box(L[r], thr, core)
        # Boxes of the core grown by 5 px (what is read), 4 (the band) and 3 (the region).
        y0, y1, x0, x1 = max(cy0 - 5, 0), min(cy1 + 5, s), max(cx0 - 5, 0), min(cx1 + 5, s)
        by0, by1, bx0, bx1 = max(cy0 - 4, 0), min(cy1 + 4, s), max(cx0 - 4, 0), min(cx1 + 4, s)
        wy0, wy1, wx0, wx1 = max(cy0 - 3, 0), min(cy1 + 3, s), max(cx0 - 3, 0), min(cx1 + 3, s)
        area_ratio = area[r, k + 1] / max(area[r, k], 1.0) if k < K - 1 else 1.0
        ok = has[r]
        border[t] = not has[r]
        # 3. Local background: a plane on the band.
        _band_and_region(core, lvl[r], pur, badr, satr, thr, disc_r, others, grow, band, win, rowbits, dilbits,
                         cy0, cy1, cx0, cx1, y0, y1, x0, x1, by0, by1, bx0, bx1)
        for i in range(by0, by1):
            for j in range(bx0, bx1):
                wb[i, j] = band[i, j]
        sigma, n_used, cb0, cb1, cb2 = plane_fit(pur, wb, half, 1, y0, y1, x0, x1, d, by0, by1, bx0, bx1)
        if n_used < 10:
            for i in range(y0, y1):
                for j in range(x0, x1):
                    d[i, j] = d0r[i, j]
            sigma = sig0[r]
            cb0, cb1, cb2 = c0[r, 0], c0[r, 1], c0[r, 2]
        C = float(_peak_mean(d, core, cy0, cy1, cx0, cx1))
        ok = ok and C > 0
        Cs = np.float32(C if C > 0 else 1.0)
        # Rejections: masked pixels near the blob, saturation around it.
        masked, sat_near = _saturation(d, win, badr, satr, np.float32(0.5) * Cs, hr, h2, rowbits, wy0, wy1,
                                      wx0, wx1)
        ok = ok and not masked and sat_near <= _MAX_SATURATED_RIM
        # 4. Coverage, per-direction background, soft half-contrast region.
        fcx, fcy = _coverage(pur, d, core, polarity, half, e, cov, cy0, cy1, cx0, cx1, y0, y1, x0, x1)
        sec_max = _sector_levels(cov, band, fcx, fcy, half, lv32, lev, cnt, valid, nl, nv, by0, by1, bx0, bx1)
        m0, mx, my, cxx, cxy, cyy = _soft_region(cov, win, lv32, fcx, fcy, half, q, qf, cut, wy0, wy1, wx0, wx1)
        # 5. Ellipse and centre from the trimmed moments.
        m0_full, m0, mx, my, cxx, cxy, cyy = _trimmed_moments(q, qf, cut, half, m0, mx, my, cxx, cxy, cyy,
                                                              wy0, wy1, wx0, wx1)
        m0s = max(m0, 1e-9)
        tr = 0.5 * (cxx + cyy)
        disc = math.sqrt(max(0.25 * (cxx - cyy) ** 2 + cxy ** 2, 0.0))
        major = 2.0 * math.sqrt(max(tr + disc, 1e-6))
        minor = 2.0 * math.sqrt(max(tr - disc, 1e-6))
        angle = 0.5 * math.atan2(2.0 * cxy, cxx - cyy)
        ok = ok and m0 >= 1.5
        # 6. Shape measurements.
        shape, prms = _shape_profile(q, d, win, badr, tmp, pc, ps, mx, my, cxx, cxy, cyy, np.float32(math.sqrt(major * minor)),
                                     m0s, half, wy0, wy1, wx0, wx1)
        asym = _asymmetry(q, q1, mx, my, half, wy0, wy1, wx0, wx1)
        bg_band = float(cb0) + float(cb1) * mx + float(cb2) * my
        bg_ring = float(c0[r, 0]) + float(c0[r, 1]) * mx + float(c0[r, 2]) * my
        o = out[t]
        o[0], o[1], o[2], o[3], o[4], o[5] = mx, my, major, minor, angle, C
        o[6], o[7], o[8], o[9] = bg_band, (bg_band - bg_ring) / max(C, 1e-6), sigma, sig0[r]
        o[10], o[11], o[12], o[13], o[14], o[15] = _LEVELS[k], _LEVELS[k_found[r]], area_ratio, shape, asym, prms
        o[16], o[17], o[18], o[19] = m0, 1.0 - sec_max, m0 / m0_full, sat_near
        oks[t] = ok
        # Leave the work arrays clean for the next row's boxes (``band`` and ``win`` need not
        # be: every step reads them only in the band's box, where each row rewrites them).
        for i in range(by0, by1):
            for j in range(bx0, bx1):
                wb[i, j] = 0
        for i in range(wy0, wy1):
            for j in range(wx0, wx1):
                q[i, j] = 0.0
                hr[i, j] = False
        for i in range(wy0, wy1 + 1):
            for j in range(wx0, wx1 + 1):
                q1[i, j] = 0.0
    return out, oks, border


@nb.njit(**_INLINE)
def _reflected_range(k, lo, hi, half, s):
    """Indices ``i`` (0..s-1) whose own bilinear index ``i + 1`` or reflected one
    ``clip(k - i + 2 half + 1, 0, s + 1)`` lies in ``lo..hi``: ``(first, last)``."""
    first, last = s, -1
    for i in range(s):
        r = min(max(k - i + 2 * half + 1, 0), s + 1)
        if (lo <= i + 1 <= hi) or (lo <= r <= hi):
            first = min(first, i)
            last = max(last, i)
    return first, last


@nb.njit(**_JIT)
def _asymmetry(q, q1, mx, my, half, y0, y1, x0, x1):
    """:func:`carapost.core.blob_score.asymmetry` of one region ``q (S, S)`` (zero outside the
    box ``y0:y1, x0:x1``) on the whole patch; ``q1 (S + 2, S + 2)`` is work space, zero
    outside the box grown by one (it is filled there)."""
    s = q.shape[0]
    ty2, tx2 = 2.0 * my, 2.0 * mx
    ky, kx = int(math.floor(ty2)), int(math.floor(tx2))
    ty = np.float32((ty2 - ky) / 2.0)
    tx = np.float32((tx2 - kx) / 2.0)
    w00 = (np.float32(1.0) - ty) * (np.float32(1.0) - tx)
    w01 = (np.float32(1.0) - ty) * tx
    w10 = ty * (np.float32(1.0) - tx)
    w11 = ty * tx
    # q1[a, b] = q'(offset (a - half - 1, b - half - 1)) = bilinear of q at (a - 1 + ty, b - 1 + tx):
    # non-zero only for a in y0..y1, b in x0..x1.
    tot = 0.0
    if y0 > 0 and x0 > 0 and y1 < s and x1 < s:      # inside the patch: q is 0 around the box
        for a in range(y0, y1 + 1):
            for b in range(x0, x1 + 1):
                q1[a, b] = w00 * q[a - 1, b - 1] + w01 * q[a - 1, b] + w10 * q[a, b - 1] + w11 * q[a, b]
    else:
        _bilinear_edge(q, q1, w00, w01, w10, w11, y0, y1, x0, x1)
    for i in range(y0, y1):
        for j in range(x0, x1):
            tot += float(q[i, j])
    # Only pixels whose own or reflected q1 can be non-zero contribute.
    i0, i1 = _reflected_range(ky, y0, y1, half, s)
    j0, j1 = _reflected_range(kx, x0, x1, half, s)
    num = 0.0
    for i in range(i0, i1 + 1):
        iy = min(max(ky - (i - half) + half + 1, 0), s + 1)
        for j in range(j0, j1 + 1):
            ix = min(max(kx - (j - half) + half + 1, 0), s + 1)
            num += float(abs(q1[i + 1, j + 1] - q1[iy, ix]))
    return num / max(2.0 * tot, 1e-9)


@nb.njit(**_INLINE)
def _bilinear_edge(q, q1, w00, w01, w10, w11, y0, y1, x0, x1):
    """The bilinear ``q1`` of :func:`_asymmetry` for a box at the patch border."""
    s = q.shape[0]
    for a in range(y0, y1 + 1):
        for b in range(x0, x1 + 1):
            v00 = q[a - 1, b - 1] if (a >= 1 and b >= 1 and a - 1 < s and b - 1 < s) else np.float32(0.0)
            v01 = q[a - 1, b] if (a >= 1 and a - 1 < s and b < s) else np.float32(0.0)
            v10 = q[a, b - 1] if (a < s and b >= 1 and b - 1 < s) else np.float32(0.0)
            v11 = q[a, b] if (a < s and b < s) else np.float32(0.0)
            q1[a, b] = w00 * v00 + w01 * v01 + w10 * v10 + w11 * v11
