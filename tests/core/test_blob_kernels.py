"""The compiled kernels of the blob fit (carapost/core/blob_kernels*.py) against the numpy
versions they replace, on random patches and on the patches of rendered frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from blob_images import RenderConfig, render_frame

from carapost.core import blob_kernels as K
from carapost.core import blob_kernels_dense as KD
from carapost.core.blob_candidates import climb, signed_image
from carapost.core.blob_fit import (LEVELS, _flood, _plane_fit, _prefer_informative, _thresholds, search_levels)
from carapost.core.blob_outline import fit_outline_parts
from carapost.core.blob_patches import box3, dot_rows, extract_patches, patch_grid

BLACK, WHITE = -1, 1


def _dot_patches(n: int, half: int, seed: int) -> np.ndarray:
    """uint8 (n, S, S): blurred elliptic dots of random size, contrast and offset on a shaded,
    noisy background, some next to a band, some clipped (the kinds of patch the fit sees)."""
    rng = np.random.default_rng(seed)
    s = 2 * half + 1
    off = np.arange(s) - half
    y, x = np.meshgrid(off, off, indexing="ij")
    out = np.empty((n, s, s), np.uint8)
    for k in range(n):
        a, b = rng.uniform(1.5, 0.6 * half, 2)
        th = rng.uniform(0, np.pi)
        cx, cy = rng.uniform(-1.5, 1.5, 2)
        u = (x - cx) * np.cos(th) + (y - cy) * np.sin(th)
        v = -(x - cx) * np.sin(th) + (y - cy) * np.cos(th)
        dot = 1.0 / (1.0 + np.exp(4.0 * (np.sqrt((u / a) ** 2 + (v / b) ** 2) - 1.0)))
        img = rng.uniform(40, 180) + rng.uniform(-3, 3) * x + rng.uniform(-3, 3) * y
        img = img + rng.uniform(15, 120) * dot + rng.normal(0, rng.uniform(0.5, 6), (s, s))
        if k % 4 == 1:                                            # a band through the dot
            img += rng.uniform(10, 60) * (np.abs(y - x * rng.uniform(-1, 1) - cy) < rng.uniform(1, 3))
        if k % 7 == 3:                                            # clipped
            img = img * 1.8
        out[k] = np.clip(img, 0, 255).astype(np.uint8)
    return out


def _search_levels_numpy(pu, bad, sat, radius, half, max_radius, pixel_noise):
    """Steps 1-2 of the fit as vectorised numpy (the version the kernels replaced): ring plane,
    peak, flood levels (run to convergence) and level search. Returns a dict of arrays over
    all patches."""
    n = len(pu)
    S = 2 * half + 1
    dy, dx, dxf, dyf, mono, edge = patch_grid(half)
    p = pu.astype(np.float32)
    dead = (pu <= 4) | (pu >= 251)
    rho2 = (dxf * dxf + dyf * dyf)[None]
    r0 = np.asarray(radius, np.float32)[:, None, None]
    r_in = np.minimum(1.5 * r0 + 1.5, half - 1.5)
    ring = _prefer_informative((rho2 >= r_in * r_in) & (rho2 <= float(half * half)) & ~bad & ~sat, dead)
    d0, sig0, n0, c0 = _plane_fit(p, ring, mono, iters=1)
    ds = box3(d0)
    near = rho2 <= np.maximum(1.5, 0.5 * r0) ** 2
    flat = np.where(near, ds, -np.inf).reshape(n, -1)
    pk = np.argmax(flat, axis=1)
    peak = flat[np.arange(n), pk].astype(np.float64)
    pky, pkx = np.divmod(pk, S)
    scale = (200.0 / peak).astype(np.float32)[:, None, None]
    lvl = np.clip(ds * scale, 0, 255).astype(np.uint8)
    thr = _thresholds()
    L = _flood(lvl, pky, pkx, 10 * S, int(thr[0]) - 1)           # to convergence: exact
    masks = (L.reshape(n, -1)[:, None, :] >= thr[None, :, None]).astype(np.float32)
    m = dot_rows(masks.reshape(n * len(thr), -1), mono[:, :6]).reshape(n, len(thr), 6).astype(np.float64)
    area = m[..., 0]
    a_s = np.maximum(area, 1.0)
    vx = m[..., 3] / a_s - (m[..., 1] / a_s) ** 2 + 1.0 / 12.0
    vy = m[..., 5] / a_s - (m[..., 2] / a_s) ** 2 + 1.0 / 12.0
    vxy = m[..., 4] / a_s - m[..., 1] * m[..., 2] / (a_s * a_s)
    fill = area / (4.0 * np.pi * np.sqrt(np.maximum(vx * vy - vxy * vxy, 1e-6)))
    edge_max = L.reshape(n, -1)[:, edge.ravel()].max(axis=1)
    valid = (edge_max[:, None] < thr[None]) & (area <= (np.pi * (1.3 * max_radius + 2.0) ** 2)[:, None])
    noise_band = 1.0 - 5.0 * (pixel_noise / 3.0) / peak
    shaped = np.asarray(LEVELS)[None] <= np.minimum(noise_band, 0.8)[:, None]
    valid &= (fill >= 0.9) | (area < 20) | ~shaped
    run = np.cumprod(valid[:, ::-1], axis=1)[:, ::-1].astype(bool)
    has = run[:, -1]
    k_found = np.where(has, np.argmax(run, axis=1), len(thr) - 1)
    return dict(d0=d0, ds=ds, sig0=sig0, n0=n0, c0=c0, pk=pk, peak=peak, lvl=lvl, L=L, area=area, fill=fill,
                valid=valid, k_found=k_found, has=has)


@pytest.mark.parametrize("half", [8, 14])
def test_plane_fit_kernel_equals_numpy(half):
    """The robust plane of one patch over a random mask: residual, sigma, pixels used and
    coefficients as the vectorised fit's (float32 rounding)."""
    rng = np.random.default_rng(half)
    s = 2 * half + 1
    p = _dot_patches(40, half, seed=half).astype(np.float32)
    mask = rng.random((40, s, s)) < 0.6
    mono = patch_grid(half)[4]
    resid, sigma, n_used, coef = _plane_fit(p, mask, mono, iters=1)
    for k in range(40):
        w = mask[k].astype(np.uint8)
        out = np.zeros((s, s), np.float32)
        sg, nu, c0, c1, c2 = K.plane_fit(p[k], w, half, 1, 0, s, 0, s, out, 0, s, 0, s)
        assert nu == n_used[k]
        np.testing.assert_allclose([sg, c0, c1, c2], [sigma[k], *coef[k]], rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(out, resid[k], atol=1e-3)


def test_box3_kernels_equal_opencv():
    """The compiled 3x3 mean (a whole patch and single pixels) equals OpenCV's blur with a
    constant border."""
    rng = np.random.default_rng(0)
    d = rng.normal(0, 50, (5, 17, 17)).astype(np.float32)
    ref = box3(d)
    for k in range(5):
        out = np.zeros((17, 17), np.float32)
        K.box3(d[k], out, 0, 17, 0, 17, np.zeros((19, 17)))
        np.testing.assert_allclose(out, ref[k], rtol=1e-6, atol=1e-5)
        for i, j in ((0, 0), (16, 3), (8, 8), (5, 16)):
            assert abs(K.mean3(d[k], i, j) - ref[k, i, j]) <= 1e-5 * max(1.0, abs(ref[k, i, j]))


@pytest.mark.parametrize("half", [8, 11, 18])
def test_ring_and_level_steps_equal_numpy(half):
    """Steps 1-2 (ring plane, peak, flood levels, per-level areas and fills, the core level
    found) of random dot patches, some with bad and saturated pixels, as the vectorised numpy
    version computes them."""
    n = 120
    rng = np.random.default_rng(half + 100)
    pu = _dot_patches(n, half, seed=half + 7)
    s = 2 * half + 1
    bad = np.zeros((n, s, s), bool)
    bad[::5, :, :3] = True                                         # patches at the image border
    sat = (pu >= 250) & (np.arange(n) % 2 == 0)[:, None, None]
    radius = rng.uniform(1.5, 0.5 * half, n).astype(np.float32)
    max_radius = np.full(n, 0.8 * half)
    pixel_noise = rng.uniform(0.5, 4.0, n)
    ref = _search_levels_numpy(pu, bad, sat, radius, half, max_radius, pixel_noise)
    d0, sig0, n0, c0, pk, peak = K.ring_step(pu, bad, sat, radius, half)
    np.testing.assert_allclose(d0, ref["d0"], atol=2e-3)
    np.testing.assert_allclose(sig0, ref["sig0"], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(c0, ref["c0"], rtol=1e-5, atol=1e-4)
    assert np.array_equal(n0, ref["n0"]) and np.array_equal(pk, ref["pk"])
    np.testing.assert_allclose(peak, ref["peak"], rtol=1e-5)
    ok = (peak > sig0) & (peak > 0.5)
    assert ok.sum() > 0.8 * n
    a = np.flatnonzero(ok)
    lvl, L, area, fill, edge_max, valid, k_found, has = K.level_step(d0[a], peak[a], pk[a], half, max_radius[a],
                                                                     pixel_noise[a])
    # The fixed-point levels may differ by one where float rounding crosses an integer.
    assert np.abs(lvl.astype(int) - ref["lvl"][a]).max() <= 1
    same = (lvl == ref["lvl"][a]).reshape(len(a), -1).all(axis=1)
    assert same.mean() > 0.9
    assert np.array_equal(L[same], ref["L"][a][same])
    assert np.array_equal(area[same], ref["area"][a][same])
    np.testing.assert_allclose(fill[same], ref["fill"][a][same], rtol=1e-9)
    assert np.array_equal(k_found[same], ref["k_found"][a][same])
    assert np.array_equal(has[same], ref["has"][a][same]) and has.sum() > 0.3 * len(a)


def test_flood_kernel_is_the_exact_reconstruction():
    """The priority flood of level_step equals the iterated clipped 3x3 dilation run to
    convergence, on noisy patches with several bright structures (paths around obstacles)."""
    rng = np.random.default_rng(3)
    n, half = 60, 14
    s = 2 * half + 1
    d0 = cv2.GaussianBlur(rng.normal(0, 1, (n * s, s)).astype(np.float32), (0, 0), 1.2).reshape(n, s, s)
    d0 = 60 + 200 * d0 / np.abs(d0).max(axis=(1, 2), keepdims=True)
    pk = np.argmax(d0.reshape(n, -1), axis=1)
    peak = d0.reshape(n, -1)[np.arange(n), pk].astype(np.float64)
    # (level_step floods the 3x3 mean of d0, returned as lvl: the reference floods that too)
    lvl, L = K.level_step(d0.astype(np.float32), peak, pk, half, np.full(n, 50.0), np.full(n, 1.0))[:2]
    ref = _flood(lvl, pk // s, pk % s, 10 * s, 99)
    assert np.array_equal(L, ref)
    assert (L > 99).sum() > 20 * n


@pytest.mark.parametrize("polarity", [BLACK, WHITE])
def test_outline_kernel_equals_numpy(polarity):
    """Steps 3-6 of the compiled kernel and of the numpy version (cropped windows, batches
    per window size) on the patches of a rendered frame — dots, texture spots, merged pairs,
    a saturated region, patches at the image border and next to a mask — with forced core
    levels: every field agrees to float32 rounding and the same fits are rejected."""
    cfg = RenderConfig(texture=0.12, size=(300, 400), n_dots=40, merged_pairs=4,
                       polarity="white" if polarity > 0 else "black", saturated_region=polarity > 0)
    fr = render_frame(cfg, seed=21)
    sig = signed_image(fr.image, polarity)
    rng = np.random.default_rng(2)
    pts = np.concatenate([fr.xy, rng.uniform([0, 0], [400, 300], (80, 2))])
    cx, cy = np.rint(pts[:, 0]).astype(np.int64), np.rint(pts[:, 1]).astype(np.int64)
    cx, cy = np.clip(cx, 0, 399), np.clip(cy, 0, 299)
    mask = np.zeros(sig.shape, bool)
    mask[100:110, 150:220] = True
    sat = (250, 255) if polarity > 0 else None
    parts = []
    for half, r in ((8, 2.0), (11, 4.0), (18, 8.0)):
        pat = extract_patches(sig, cx, cy, half, bad=mask, saturated=sat)
        st = search_levels(pat, np.full(len(cx), r), max_radius=np.full(len(cx), 14.0),
                           pixel_noise=np.full(len(cx), 2.0))
        sel = st.alive
        parts.append((st, sel, np.where(np.arange(len(sel)) % 3 == 0, 0.9, 0.0)))
    comp = fit_outline_parts(parts, polarity=polarity)
    ref = fit_outline_parts(parts, polarity=polarity, compiled=False)
    for a, b in zip(comp, ref):
        assert a.ok.sum() > 10
        assert np.array_equal(a.ok, b.ok) and np.array_equal(a.border, b.border)
        for name in a.__dataclass_fields__:
            if name in ("ok", "border"):
                continue
            np.testing.assert_allclose(getattr(a, name)[a.ok], getattr(b, name)[a.ok], rtol=1e-4, atol=1e-4,
                                       err_msg=name)


def test_patch_and_climb_kernels_equal_numpy():
    """Patch extraction (inside the image, clamped at its border, a mask, saturated values) and the uphill
    climb of the candidate grouping give what their numpy versions give."""
    rng = np.random.default_rng(4)
    img = cv2.GaussianBlur(rng.integers(0, 256, (120, 160)).astype(np.uint8), (0, 0), 2.0)
    img[40:50, 60:75] = 255
    mask = rng.random(img.shape) < 0.05
    cx, cy = rng.integers(0, 160, 400), rng.integers(0, 120, 400)
    inside = (cx >= 11) & (cx < 160 - 11) & (cy >= 11) & (cy < 120 - 11)
    assert 50 < inside.sum() < 350                    # the kernel's row-copy path and its clamped one
    for bad in (None, mask):
        for sat in (None, (250, 255)):
            a = extract_patches(img, cx, cy, 11, bad=bad, saturated=sat)
            b = extract_patches(img, cx, cy, 11, bad=bad, saturated=sat, compiled=False)
            assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("pu", "bad", "sat"))
    a = climb(img, cx, cy)
    b = climb(img, cx, cy, compiled=False)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))
    assert (a[0] != cx).mean() > 0.5


def test_outline_disc_dilations_as_bits_equal_stamped_and_opencv():
    """The outline kernel's dilations of the core by the discs of radius 2-4, as bit masks of
    the band box's columns (``_grow_bits``), equal the stamped smallest radius
    (``_grow_stamped``, used for boxes wider than 64 columns) and OpenCV's dilation by each
    disc, on random cores (holes, several pieces, at the patch border)."""
    import carapost.core.blob_kernels_region as KO

    rng = np.random.default_rng(5)
    s = 37
    for t in range(40):
        core = np.zeros((s, s), bool)
        cy, cx = rng.integers(0, s, 2) if t % 4 == 0 else rng.integers(8, s - 8, 2)
        r = rng.uniform(1.0, 7.0)
        yy, xx = np.mgrid[:s, :s]
        core |= (yy - cy) ** 2 / r ** 2 + (xx - cx) ** 2 / (r * rng.uniform(0.5, 1.5)) ** 2 <= 1.0
        core &= rng.random((s, s)) > 0.1 * (t % 3)
        core[cy, cx] = True
        ys, xs = np.nonzero(core)
        cy0, cy1, cx0, cx1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        y0, y1, x0, x1 = max(cy0 - 5, 0), min(cy1 + 5, s), max(cx0 - 5, 0), min(cx1 + 5, s)
        by0, by1, bx0, bx1 = max(cy0 - 4, 0), min(cy1 + 4, s), max(cx0 - 4, 0), min(cx1 + 4, s)
        rowbits, dilbits = np.zeros((s, 5), np.uint64), np.zeros((s, 3), np.uint64)
        KO._grow_bits(core, rowbits, dilbits, cy0, cy1, cx0, cx1, by0, by1, bx0)
        grow = np.zeros((s, s), np.int64)
        KO._grow_stamped(core, KO._DISC_R, grow, cy0, cy1, cx0, cx1, y0, y1, x0, x1)
        cols = np.arange(bx0, bx1)
        for k, radius in enumerate((2, 3, 4)):
            bits = np.array([[(int(dilbits[i, k]) >> int(j - bx0)) & 1 for j in cols] for i in range(by0, by1)], bool)
            disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
            ref = cv2.dilate(core.astype(np.uint8), disc, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
            assert np.array_equal(bits, ref[by0:by1, bx0:bx1]), (t, radius)
            assert np.array_equal(bits, grow[by0:by1, bx0:bx1] <= radius), (t, radius)


def test_local_maxima_kernel_equals_dilation():
    """The candidates' local maxima (``local_maxima``: threshold, then the 3x3 or 5x5
    neighbourhood, in one pass) equal the pixels above the threshold, off the border, where
    the map equals its OpenCV dilation — on smooth maps with plateaus (ties), on noise and on
    maps of 3-40 px."""
    rng = np.random.default_rng(11)
    total = 0
    for t in range(30):
        h, w = (int(v) for v in rng.integers(3, 40, 2)) if t % 3 == 0 else (int(rng.integers(60, 200)), 173)
        m = rng.normal(0.0, 3.0, (h, w)).astype(np.float32)
        if t % 2:
            m = np.round(cv2.GaussianBlur(m, (0, 0), 2.0) * 4.0).astype(np.float32)   # plateaus
        thr = float(rng.uniform(-1.0, 2.0))
        for k in (3, 5):
            pk = np.flatnonzero(m[1:-1, 1:-1] > thr)
            pk = (pk // (w - 2) + 1) * w + pk % (w - 2) + 1
            ref = pk[m.ravel()[pk] >= cv2.dilate(m, np.ones((k, k), np.uint8)).ravel()[pk]]
            got = KD.local_maxima(m, k, thr)
            assert np.array_equal(got, ref)
            total += len(ref)
    assert total > 1000


def test_laplacian_histograms_kernel_equals_numpy():
    """The pixel noise's Laplacian histograms (``laplacian_histograms``, counted into
    interleaved copies) equal numpy's counts of the absolute Laplacian on every third pixel,
    over the informative centres and over all; ``pixel_noise`` equals its partition
    version — on noise, on clipped and black regions, on 3-40 px images and on a frame."""
    from carapost.core.blob_candidates import informative, pixel_noise

    rng = np.random.default_rng(12)
    imgs = [render_frame(RenderConfig(texture=0.12, size=(240, 320), n_dots=40), seed=4).image]
    for t in range(20):
        h, w = (int(v) for v in rng.integers(3, 40, 2)) if t % 3 == 0 else (int(rng.integers(60, 200)), 173 + t)
        img = rng.integers(0, 256, (h, w)) if t % 2 else rng.normal(128.0, 1.0 + 10 * t, (h, w))
        img = np.clip(img, 0, 255).astype(np.uint8)
        if t % 4 == 1:
            img[: h // 2] = 255
            img[:, : w // 3] = 0
        imgs.append(img)
    for img in imgs:
        a = img.astype(np.int64)
        c = a[1:-1:3, 1:-1:3]
        lap = np.abs(4 * c - a[:-2:3, 1:-1:3][:c.shape[0], :c.shape[1]] - a[2::3, 1:-1:3][:c.shape[0], :c.shape[1]]
                     - a[1:-1:3, :-2:3][:c.shape[0], :c.shape[1]] - a[1:-1:3, 2::3][:c.shape[0], :c.shape[1]])
        inf = informative(img[1:-1:3, 1:-1:3])
        keep, every = KD.laplacian_histograms(img)
        assert keep.dtype == every.dtype == np.int64
        assert np.array_equal(keep, np.bincount(lap[inf], minlength=1021))
        assert np.array_equal(every, np.bincount(lap.ravel(), minlength=1021))
        if min(img.shape) >= 8:
            assert pixel_noise(img) == pixel_noise(img, compiled=False)


def test_ring_samples_kernel_equals_numpy():
    """The candidates' ring test with the compiled ring (``ring_samples``: samples, clipping at
    the image border, a sorting network) gives what numpy indexing and sorting give, on the candidates
    of a rendered frame's pyramid levels (both polarities; also moved to the image's corner)."""
    from carapost.core import blob_candidates as BC
    from carapost.core.blobs import CANDIDATE_MIN_SNR, CANDIDATE_MIN_WEBER

    for n in (12, 5, 8):                          # the sorting networks, on every 0/1 input
        bits = (np.arange(1 << n)[:, None] >> np.arange(n)[None]) & 1
        for a, b in KD.sorting_network(n):
            bits[:, a], bits[:, b] = np.minimum(bits[:, a], bits[:, b]), np.maximum(bits[:, a], bits[:, b])
        assert (np.diff(bits, axis=1) >= 0).all()
    fr = render_frame(RenderConfig(texture=0.12, size=(240, 320), n_dots=40, polarity="both"), seed=3)
    total = 0
    for pol in (BLACK, WHITE):
        sig = signed_image(fr.image, pol)
        scales = BC.detection_scales(1.5, 14.0)
        pyr = BC.pyramid(sig, max(scales) + 1)
        levels = [BC.responses(pyr[k], k, sides) for k, sides in scales.items() if k < len(pyr)]
        cand = BC.find_candidates(levels, min_snr=CANDIDATE_MIN_SNR, polarity=pol, min_weber=CANDIDATE_MIN_WEBER)
        # ... and every candidate moved next to the image's corners (rings clipped there).
        edge = cand.subset(np.arange(len(cand)))
        h = np.array([pyr[k].shape[0] for k in edge.level])
        edge.x, edge.y = edge.x % 3, h - 1 - edge.y % 3
        for c in (cand, edge):
            a = BC.ring_test(pyr, levels, c, {}, pol)
            b = BC.ring_test(pyr, levels, c, {}, pol, compiled=False)
            assert np.array_equal(a.ring, b.ring) and np.array_equal(a.centre, b.centre)
        total += len(cand)
    assert total > 150


def test_context_points_kernel_equals_numpy():
    """The context ring with the compiled sample points (``context_points``) gives the numpy
    version's features, on the fits of a rendered frame (both polarities) with rows of NaN or
    infinite centres, NaN axes or angles and centres far outside the image added."""
    from carapost.core.blob_context import context_ring
    from carapost.core.blobs import analyse_blobs

    fr = render_frame(RenderConfig(texture=0.12, size=(240, 320), n_dots=40, polarity="both"), seed=4)
    for pol in (BLACK, WHITE):
        an = analyse_blobs(fr.image, pol, min_radius=1.5, max_radius=14.0)
        m = {k: np.asarray(an.measures[k], float).copy() for k in ("x", "y", "major", "minor", "angle",
                                                                     "background", "contrast")}
        assert len(m["x"]) > 30
        odd = {"x": [np.nan, np.inf, -1e6, 5.0], "y": [3.0, -np.inf, 1e6, np.nan],
               "major": [2.0, np.nan, 1e6, 3.0], "minor": [1.0, 2.0, 3.0, np.nan],
               "angle": [0.3, np.nan, 1.0, -2.0], "background": [100.0] * 4, "contrast": [30.0] * 4}
        for k in m:
            m[k] = np.concatenate([m[k], odd[k]])
        ctx = cv2.blur(signed_image(fr.image, pol), (3, 3))
        a, b = dict(m), dict(m)
        context_ring(ctx, a, pol)
        context_ring(ctx, b, pol, compiled=False)
        for k in ("ctx_max", "ctx_mean", "ctx_line", "ctx_inner"):
            assert np.array_equal(a[k], b[k], equal_nan=True), k
