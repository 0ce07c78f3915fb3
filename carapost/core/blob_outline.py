"""Steps 3-6 of the per-candidate blob fit (:mod:`carapost.core.blob_fit`): the outline of a
core found by the level search — local background, coverage, ellipse, centre and shape.

:func:`fit_outlines` works on a kept :class:`~carapost.core.blob_fit.LevelSearch` (any rows,
any forced core level). Everything it computes lies within a few pixels of the core (the
background band reaches 4 px beyond it, the fitted region 3 px, the 3x3 means one more). The
compiled kernel (:func:`carapost.core.blob_kernels_outline.outline_step`, the default) visits
only that box of each patch; the numpy reference (``compiled=False``, :func:`_outline`) crops
each patch to a centred square of half size ``core extent + 5`` (rounded up to a few size
classes, :data:`_CROP_HALVES`) and fits one vectorised batch per window size. Either way a
small core in a big patch (a dot whose candidate scale was too large, a texture spot) costs
what its neighbourhood costs, and the results are those of the whole patch.
"""

from __future__ import annotations

import numpy as np

from . import blob_fit
from .blob_fit import LEVELS, LevelSearch, PatchFit, _moments, _plane_fit, _prefer_informative, _thresholds
from .blob_kernels_outline import _RAMP, _TRIM_ITERS, _TRIM_MARGIN, OUTPUT_FIELDS, outline_step
from .blob_kernels_region import _BAND, _MAX_SATURATED_RIM, _MAX_SECTOR_LEVEL, _N_SECTORS
from .blob_patches import box3, dilate, dilate_many, patch_grid
from .blob_score import asymmetry, ellipse_distance, profile_rms, shape_residual

__all__ = ["fit_outlines", "fit_outline_parts", "outline_tables", "crop_need"]

#: Pixels beyond the core that steps 3-6 read: the band's outer radius and the 3x3 mean
#: around it.
_CROP_MARGIN = _BAND[1] + 1
#: Half sizes of the windows (a few classes: each is one batch, whatever the patches' own
#: sizes) ...
_CROP_HALVES = np.array([8, 11, 14, 18, 25, 33, 49, 65])
#: ... and the most pixels merging a class into the next bigger one may add (see
#: :func:`_batch_sizes`).
_MERGE_PIXELS = 6000


def crop_need(core: np.ndarray, half: int) -> np.ndarray:
    """Half size (int (N,)) of the smallest centred window of each ``(S, S)`` patch of ``core``
    (bool (N, S, S), ``S = 2 half + 1``) that holds the core and :data:`_CROP_MARGIN` px
    around it (it may exceed ``half``: a core near the patch border)."""
    n = len(core)
    if n == 0:
        return np.zeros(0, np.int64)
    off = np.abs(np.arange(-half, half + 1))
    ext_y = np.where(core.any(axis=2), off[None], 0).max(axis=1)
    ext_x = np.where(core.any(axis=1), off[None], 0).max(axis=1)
    return np.maximum(ext_x, ext_y) + _CROP_MARGIN


def _window(v: np.ndarray, half: int, c: int, fill) -> np.ndarray:
    """The centred ``(2c+1)^2`` window of a stack of ``(2 half + 1)^2`` patches (cropped, or
    padded with ``fill``)."""
    if c == half:
        return v
    if c < half:
        a = half - c
        return v[:, a:a + 2 * c + 1, a:a + 2 * c + 1]
    out = np.full((len(v), 2 * c + 1, 2 * c + 1), fill, v.dtype)
    a = c - half
    out[:, a:a + 2 * half + 1, a:a + 2 * half + 1] = v
    return out


def _batch_sizes(need: np.ndarray, full_half: np.ndarray) -> np.ndarray:
    """Window half size of every patch (one batch per size): the smallest of
    :data:`_CROP_HALVES` that holds its core's neighbourhood (``need``), at most its own half
    size where it does not fit in the patch (those patches stay as they are). A size class
    whose patches all fit is merged into the next bigger one when that adds fewer than
    :data:`_MERGE_PIXELS` pixels (a batch has a fixed cost of many small array operations)."""
    cls = _CROP_HALVES[np.minimum(np.searchsorted(_CROP_HALVES, need), len(_CROP_HALVES) - 1)]
    cls = np.minimum(np.maximum(cls, need), full_half)
    fits = need <= full_half
    classes = np.unique(cls)
    for c, nxt in zip(classes[:-1], classes[1:]):
        m = cls == c
        if fits[m].all() and m.sum() * ((2 * nxt + 1) ** 2 - (2 * c + 1) ** 2) <= _MERGE_PIXELS:
            cls[m] = nxt
    return cls


def fit_outlines(st: LevelSearch, sel: np.ndarray, *, polarity: int, min_core: np.ndarray) -> PatchFit:
    """Steps 3-6 of the fit (local background, coverage, ellipse, shape) for patches ``sel``
    (indices into the stack of ``st``; repeats allowed) with their core at least at level
    ``min_core (len(sel),)`` (fraction of the peak; 0: the level the search found).

    Returns a :class:`PatchFit` of ``len(sel)`` rows with centres relative to the patch
    centre (level px); patches without a peak are not ok.
    """
    return fit_outline_parts([(st, sel, min_core)], polarity=polarity)[0]


def _core_levels(st: LevelSearch, sel: np.ndarray, min_core: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For patches ``sel`` of ``st`` with lowest core levels ``min_core``: the positions in
    ``sel`` of those with a peak, their rows in the search and their core level indices."""
    keep, rows = st.rows(np.asarray(sel, np.int64))
    kc = st.k_found[rows]
    mc = np.asarray(min_core, float)[keep]
    if (mc > 0).any():
        kmin = np.minimum(np.searchsorted(np.asarray(LEVELS), mc - 1e-9), len(LEVELS) - 1)
        kc = np.where(mc > 0, np.maximum(kc, kmin), kc)
    return keep, rows, kc


def outline_tables(parts: list[tuple[LevelSearch, np.ndarray, np.ndarray]], *, polarity: int
                   ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`fit_outline_parts` (compiled) as the kernel's tables: per part ``(keep, out, ok,
    border)``, the positions in ``sel`` of the patches with a peak (int (M,)) and their
    outputs ``out`` float64 (M, len(OUTPUT_FIELDS)) (columns
    :data:`~carapost.core.blob_kernels_outline.OUTPUT_FIELDS`), ``ok``, ``border`` bool (M,)."""
    res = []
    for st, sel, min_core in parts:
        keep, rows, kc = _core_levels(st, sel, min_core)
        if len(rows):
            res.append((keep, *outline_step(st.pu, st.bad, st.sat, st.d0, st.lvl, st.L, st.area, st.sig0, st.c0,
                                            st.k_found, st.has, rows, kc, polarity, st.half)))
        else:
            res.append((keep, np.zeros((0, len(OUTPUT_FIELDS))), np.zeros(0, bool), np.zeros(0, bool)))
    return res


def fit_outline_parts(parts: list[tuple[LevelSearch, np.ndarray, np.ndarray]], *, polarity: int,
                      compiled: bool = True) -> list[PatchFit]:
    """:func:`fit_outlines` of several ``(search, sel, min_core)`` at once (searches of any
    patch sizes). Returns one :class:`PatchFit` per part.

    ``compiled``: one call of the compiled kernel
    (:func:`~carapost.core.blob_kernels_outline.outline_step`) per part, which visits only
    each core's neighbourhood; else the numpy reference: the patches of all parts, cropped to
    their cores' neighbourhoods, fitted in one vectorised batch per window size."""
    thr = _thresholds()
    res, rows_of, kc_of, core_of, need_of = [], [], [], [], []
    for st, sel, min_core in parts:
        res.append(PatchFit.empty(len(sel)))
        keep, rows, kc = _core_levels(st, sel, min_core)
        if compiled:
            if len(rows):
                out, ok, border = outline_step(st.pu, st.bad, st.sat, st.d0, st.lvl, st.L, st.area, st.sig0,
                                               st.c0, st.k_found, st.has, rows, kc, polarity, st.half)
                cols = np.ascontiguousarray(out.T)
                if len(keep) == len(sel):                 # every patch has a peak: the kernel's rows
                    res[-1] = PatchFit(**dict(zip(OUTPUT_FIELDS, cols)), ok=ok, border=border)
                else:
                    r = res[-1]
                    for name, col in zip(OUTPUT_FIELDS, cols):
                        getattr(r, name)[keep] = col
                    r.ok[keep] = ok
                    r.border[keep] = border
            continue
        core = st.L[rows] >= thr[kc][:, None, None]
        rows_of.append((keep, rows))
        kc_of.append(kc)
        core_of.append(core)
        need_of.append(crop_need(core, st.half))
    if compiled or not any(len(v) for v in need_of):
        return res
    part = np.concatenate([np.full(len(v), i) for i, v in enumerate(need_of)])
    pos = np.concatenate([np.arange(len(v)) for v in need_of])
    full_half = np.array([st.half for st, _, _ in parts])[part]
    win_half = _batch_sizes(np.concatenate(need_of), full_half)
    for c in np.unique(win_half):
        c = int(c)
        got: dict[str, list] = {k: [] for k in _STACK + ("core", "kc", "full_half")}
        where = []
        for i in np.unique(part[win_half == c]):
            st = parts[i][0]
            g = pos[(part == i) & (win_half == c)]
            keep, rows = rows_of[i]
            r = rows[g]
            whole = c == st.half and len(r) == len(st.alive) and (r == np.arange(len(r))).all()
            for k in _STACK:
                v = getattr(st, k)
                got[k].append(v if whole else (v[r] if v.ndim < 3 else _window(v[r], st.half, c, _PAD[k])))
            got["core"].append(_window(core_of[i][g], st.half, c, False))
            got["kc"].append(kc_of[i][g])
            got["full_half"].append(np.full(len(g), st.half))
            where.append((i, keep[g]))
        arr = {k: v[0] if len(v) == 1 else np.concatenate(v) for k, v in got.items()}
        out = _outline(arr, c, polarity)
        off = 0
        for i, dest in where:
            for name, val in out.items():
                getattr(res[i], name)[dest] = val[off:off + len(dest)]
            off += len(dest)
    return res


#: The :class:`LevelSearch` arrays steps 3-6 read (windowed with the patches where 3-D), and
#: the values of padded pixels (never read: they are beyond every core's neighbourhood).
_STACK = ("p", "bad", "sat", "dead", "d0", "lvl", "area", "sig0", "c0", "k_found", "has")
_PAD = {"p": 0.0, "bad": True, "sat": False, "dead": True, "d0": 0.0, "lvl": 0}


def _asymmetry(q: np.ndarray, win: np.ndarray, mx: np.ndarray, my: np.ndarray, half: int,
               full_half: np.ndarray) -> np.ndarray:
    """:func:`~carapost.core.blob_score.asymmetry` of soft regions ``q`` (inside ``win``) on
    windows of half size ``half`` of patches of half size ``full_half (N,)``, as on the whole
    patches: where the reflection of the region about its centre leaves the smaller of the
    two, it is computed on the region placed back in its whole patch."""
    asym = asymmetry(q, mx, my, half)
    moved = full_half != half
    if not moved.any():
        return asym
    lim = np.minimum(full_half, half)
    off = np.arange(-half, half + 1)
    big = np.iinfo(np.int64).max // 4
    out = np.zeros(len(q), bool)
    for axis, m in ((1, mx), (2, my)):             # any over rows: columns (x); over columns: rows (y)
        has = win.any(axis=axis)                                             # (n, S)
        lo = np.where(has, off[None], big).min(axis=1)
        hi = np.where(has, off[None], -big).max(axis=1)
        k = np.floor(2.0 * m).astype(np.int64)
        out |= (k - hi - 1 < -lim) | (k - lo + 1 > lim)
    out &= moved
    for fh in np.unique(full_half[out]):
        o = np.flatnonzero(out & (full_half == fh))
        asym[o] = asymmetry(_window(q[o], half, int(fh), 0.0), mx[o], my[o], int(fh))
    return asym


def _outline(arr: dict[str, np.ndarray], half: int, polarity: int) -> dict[str, np.ndarray]:
    """Steps 3-6 on the :data:`_STACK` arrays of a level search's rows (patches cropped to a
    centred square of half size ``half``) with their cores ``arr["core"]`` (bool (n, S, S)) at
    level indices ``arr["kc"]`` (into :data:`LEVELS`); ``arr["full_half"]`` is each patch's
    uncropped half size. Returns the :class:`PatchFit` fields (n,)."""
    p, badp, satp, dead, d0, lvl = arr["p"], arr["bad"], arr["sat"], arr["dead"], arr["d0"], arr["lvl"]
    area, sig0, c0, k_found, core, kc = arr["area"], arr["sig0"], arr["c0"], arr["k_found"], arr["core"], arr["kc"]
    full_half = arr["full_half"]
    n = len(p)
    idx = np.arange(n)
    K = len(LEVELS)
    thr = _thresholds()
    dy, dx, dxf, dyf, mono, edge = patch_grid(half)
    core_area = area[idx, kc]
    above = np.minimum(kc + 1, K - 1)
    area_ratio = np.where(kc < K - 1, area[idx, above] / np.maximum(core_area, 1.0), 1.0)
    border = ~arr["has"]
    ok = arr["has"].copy()

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
    if blob_fit.DEBUG is not None:
        blob_fit.DEBUG.update(q=q, d=d, win=win, core=core, band=band, C=C)
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
    asym = _asymmetry(q, win, mx, my, half, full_half)
    prms = profile_rms(d, rho_e2, np.sqrt(major * minor), win & ~badp)
    bg_band = cb[:, 0] + cb[:, 1] * mx + cb[:, 2] * my
    bg_ring = c0[:, 0] + c0[:, 1] * mx + c0[:, 2] * my
    out = {}
    for name, val in (("x", mx), ("y", my), ("major", major), ("minor", minor),
                      ("angle", angle), ("contrast", C), ("background", bg_band),
                      ("rise", (bg_band - bg_ring) / np.maximum(C, 1e-6)), ("noise", sigma),
                      ("ring_noise", sig0), ("core_level", np.asarray(LEVELS)[kc]),
                      ("found_level", np.asarray(LEVELS)[k_found]),
                      ("area_ratio", area_ratio), ("shape_residual", shape), ("asymmetry", asym),
                      ("profile_rms", prms), ("area", m0), ("ok", ok), ("border", border),
                      ("open", 1.0 - b_sec.max(axis=1)), ("kept", m0 / m0_full), ("saturated", sat_near)):
        out[name] = val
    return out




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


