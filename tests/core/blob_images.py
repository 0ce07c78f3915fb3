"""Test-image renderer for the blob detector: painted dots with exact ground truth.

Dots are ellipses (projected circles) of 2-10 px semi-axes rendered with exact sub-pixel
coverage (supersampling), on a shaded, textured "skin" background, then blurred, given
signal-dependent noise, quantised to 8 bits and optionally JPEG-compressed. Occluders (a
region with its own texture whose edge cuts through dots), touching/overlapping dot pairs,
saturated regions and low light can be switched on. The ground-truth centre of each dot is
the exact centre of its ellipse in the pixel convention of the project (the centre of the
top-left pixel is ``(0, 0)``).

Used by ``tests/core/test_blobs.py``, ``benchmarks/bench_blobs.py`` and
``benchmarks/fit_blob_score.py``. Not part of the package.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from carapost.synth.evaluate import grazing_dots

__all__ = ["RenderConfig", "RenderedFrame", "render_frame", "match", "evaluate", "TruthDots", "truth_dots",
           "jpeg_roundtrip"]


@dataclass
class RenderConfig:
    """What to render. Sizes in pixels, intensities in 8-bit grey levels."""

    size: tuple[int, int] = (720, 1280)          # (H, W)
    n_dots: int = 150
    radius: tuple[float, float] = (2.0, 10.0)    # major semi-axis range
    aspect: tuple[float, float] = (0.45, 1.0)    # minor / major
    polarity: str = "black"                      # "black", "white" or "both"
    min_gap: float = 4.0                         # free space between dots (px)
    skin: float = 150.0                          # mean background level before shading
    black_paint: tuple[float, float] = (0.08, 0.3)   # paint reflectance relative to skin
    white_paint: tuple[float, float] = (1.45, 1.7)
    texture: float = 0.06                        # relative amplitude of skin texture
    shading: float = 0.5                         # relative amplitude of the illumination gradient
    blur: tuple[float, float] = (0.5, 1.0)       # Gaussian PSF sigma range (px)
    read_noise: float = 1.5                      # grey levels
    shot_noise: float = 0.08                     # variance per grey level of signal
    jpeg_quality: int | None = None
    low_light: float = 1.0                       # global gain (< 1 for a dark take)
    occluders: int = 0                           # occluding regions whose edges cut dots
    merged_pairs: int = 0                        # touching / overlapping pairs of dots
    saturated_region: bool = False               # a large region clipped at 255
    supersample: int = 8


@dataclass
class RenderedFrame:
    """An image and its ground truth.

    Attributes
    ----------
    image : uint8 (H, W)
    xy : float64 (N, 2)
        Exact ellipse centres, px.
    axes : float64 (N, 2)
        Major and minor semi-axes, px.
    angle : float64 (N,)
        Major-axis direction, radians from +x towards +y.
    polarity : int8 (N,)
        +1 white, -1 black.
    visible_frac : float64 (N,)
        Fraction of the dot's area not hidden by an occluder, a saturated region or the image
        border.
    clean : bool (N,)
        Fully visible and not touching another dot: the detector must find these.
    partial : bool (N,)
        Partly occluded, merged with another dot, or cut by the image border: excluded from the
        recall and precision denominators (detections near them are reported separately).
    """

    image: np.ndarray
    xy: np.ndarray
    axes: np.ndarray
    angle: np.ndarray
    polarity: np.ndarray
    visible_frac: np.ndarray
    clean: np.ndarray
    partial: np.ndarray
    extra: dict = field(default_factory=dict)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Zero-mean unit-std Gaussian random field with correlation length ``sigma`` px."""
    h, w = shape
    k = max(1, int(sigma // 4))
    small = rng.normal(size=(h // k + 2, w // k + 2)).astype(np.float32)
    small = cv2.GaussianBlur(small, (0, 0), sigma / k)
    f = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR) if k > 1 else small[:h, :w]
    f = f - f.mean()
    return f / max(float(f.std()), 1e-9)


def _ellipse_coverage(cx: float, cy: float, a: float, b: float, th: float, x0: int, y0: int,
                      h: int, w: int, ss: int) -> np.ndarray:
    """Exact-ish area coverage of an ellipse over pixels ``[y0, y0+h) x [x0, x0+w)``."""
    off = (np.arange(ss) + 0.5) / ss - 0.5
    ys = (y0 + np.arange(h))[:, None] + off[None, :]            # (h, ss)
    xs = (x0 + np.arange(w))[:, None] + off[None, :]            # (w, ss)
    dx = xs[None, None, :, :] - cx                              # (1,1,w,ss)
    dy = ys[:, :, None, None] - cy                              # (h,ss,1,1)
    c, s = np.cos(th), np.sin(th)
    u = dx * c + dy * s
    v = -dx * s + dy * c
    inside = (u / a) ** 2 + (v / b) ** 2 <= 1.0                  # (h, ss, w, ss)
    return inside.mean(axis=(1, 3))


def _place_dots(rng: np.random.Generator, cfg: RenderConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random non-overlapping ellipses: centres (N,2), axes (N,2), angles (N,)."""
    H, W = cfg.size
    xy, ax, an = [], [], []
    tries = 0
    while len(xy) < cfg.n_dots and tries < cfg.n_dots * 200:
        tries += 1
        a = rng.uniform(*cfg.radius)
        b = a * rng.uniform(*cfg.aspect)
        p = np.array([rng.uniform(-0.3 * a, W - 1 + 0.3 * a) if rng.random() < 0.03 else rng.uniform(a + 2, W - a - 3),
                      rng.uniform(a + 2, H - a - 3)])
        if xy:
            d = np.linalg.norm(np.asarray(xy) - p, axis=1)
            if np.any(d < np.asarray(ax)[:, 0] + a + cfg.min_gap):
                continue
        xy.append(p)
        ax.append((a, b))
        an.append(rng.uniform(-np.pi / 2, np.pi / 2))
    return np.asarray(xy, float).reshape(-1, 2), np.asarray(ax, float).reshape(-1, 2), np.asarray(an, float)


def render_frame(cfg: RenderConfig | None = None, seed: int = 0) -> RenderedFrame:
    """Render one frame with ground truth (see the module docstring)."""
    cfg = cfg or RenderConfig()
    rng = np.random.default_rng(seed)
    H, W = cfg.size
    ss = cfg.supersample

    xy, axes, ang = _place_dots(rng, cfg)
    # Touching / overlapping pairs: move a second dot onto the edge of an existing one.
    merged = np.zeros(len(xy), bool)
    if cfg.merged_pairs:
        k = min(cfg.merged_pairs, len(xy) // 2)
        for i in range(k):
            j = len(xy) - 1 - i
            d = rng.uniform(0.75, 1.05) * (axes[i, 1] + axes[j, 1])
            phi = rng.uniform(0, 2 * np.pi)
            xy[j] = xy[i] + d * np.array([np.cos(phi), np.sin(phi)])
            axes[j] = (axes[j, 0], axes[j, 0])   # make it round so the distance is meaningful
            axes[i] = (axes[i, 0], axes[i, 0])
            merged[[i, j]] = True
        xy[:, 0] = np.clip(xy[:, 0], 12, W - 13)
        xy[:, 1] = np.clip(xy[:, 1], 12, H - 13)
    n = len(xy)
    if cfg.polarity == "both":
        pol = np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)
    else:
        pol = np.full(n, 1 if cfg.polarity == "white" else -1, np.int8)

    # Reflectance: skin texture (two scales) with painted dots.
    refl = 1.0 + cfg.texture * (0.6 * _smooth_noise(rng, (H, W), 12.0) + 0.4 * _smooth_noise(rng, (H, W), 1.5))
    refl = refl.astype(np.float64)
    cover_total = np.zeros((H, W))
    for i in range(n):
        a, b = axes[i]
        x0 = int(np.floor(xy[i, 0] - a - 1))
        y0 = int(np.floor(xy[i, 1] - a - 1))
        x1 = int(np.ceil(xy[i, 0] + a + 2))
        y1 = int(np.ceil(xy[i, 1] + a + 2))
        cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
        if cx1 <= cx0 or cy1 <= cy0:
            continue
        cov = _ellipse_coverage(xy[i, 0], xy[i, 1], a, b, ang[i], cx0, cy0, cy1 - cy0, cx1 - cx0, ss)
        paint = rng.uniform(*(cfg.white_paint if pol[i] > 0 else cfg.black_paint))
        sl = (slice(cy0, cy1), slice(cx0, cx1))
        refl[sl] = refl[sl] * (1 - cov) + paint * cov
        cover_total[sl] += cov

    # Fraction of each dot inside the image (dots near the border).
    in_image = np.ones(n)
    for i in range(n):
        a, b = axes[i]
        if xy[i, 0] - a < 0 or xy[i, 0] + a > W - 1 or xy[i, 1] - a < 0 or xy[i, 1] + a > H - 1:
            x0 = int(np.floor(xy[i, 0] - a - 1))
            y0 = int(np.floor(xy[i, 1] - a - 1))
            size = int(np.ceil(2 * a + 3))
            cov = _ellipse_coverage(xy[i, 0], xy[i, 1], a, b, ang[i], x0, y0, size, size, ss)
            yy, xx = np.mgrid[y0:y0 + size, x0:x0 + size]
            inside = (xx >= -0.5) & (xx <= W - 0.5) & (yy >= -0.5) & (yy <= H - 0.5)
            in_image[i] = (cov * inside).sum() / max(cov.sum(), 1e-9)
    # A dot within 1.5 px of the border is "partial" even when it is inside the image.
    at_border = ((xy[:, 0] - axes[:, 0] < 1.5) | (xy[:, 0] + axes[:, 0] > W - 2.5)
                 | (xy[:, 1] - axes[:, 0] < 1.5) | (xy[:, 1] + axes[:, 0] > H - 2.5))

    # Occluders: large ellipses with their own texture and brightness, drawn over the dots.
    occ_cov = np.zeros((H, W))
    for _ in range(cfg.occluders):
        cx, cy = rng.uniform(0.15 * W, 0.85 * W), rng.uniform(0.15 * H, 0.85 * H)
        A, B = rng.uniform(80, 220), rng.uniform(60, 160)
        th = rng.uniform(0, np.pi)
        x0, y0 = int(max(cx - A - 2, 0)), int(max(cy - A - 2, 0))
        x1, y1 = int(min(cx + A + 3, W)), int(min(cy + A + 3, H))
        cov = _ellipse_coverage(cx, cy, A, B, th, x0, y0, y1 - y0, x1 - x0, 2)
        sl = (slice(y0, y1), slice(x0, x1))
        occ_cov[sl] = np.maximum(occ_cov[sl], cov)
    if cfg.occluders:
        occ_level = rng.uniform(0.45, 0.75) if rng.random() < 0.5 else rng.uniform(1.25, 1.5)
        occ_refl = occ_level * (1.0 + 0.04 * _smooth_noise(rng, (H, W), 3.0))
        refl = refl * (1 - occ_cov) + occ_refl * occ_cov
    # Visible fraction of each dot after occlusion.
    vis_occ = np.ones(n)
    for i in range(n):
        a = axes[i, 0]
        x0, y0 = int(max(np.floor(xy[i, 0] - a - 1), 0)), int(max(np.floor(xy[i, 1] - a - 1), 0))
        x1, y1 = int(min(np.ceil(xy[i, 0] + a + 2), W)), int(min(np.ceil(xy[i, 1] + a + 2), H))
        if x1 <= x0 or y1 <= y0:
            vis_occ[i] = 0
            continue
        cov = _ellipse_coverage(xy[i, 0], xy[i, 1], axes[i, 0], axes[i, 1], ang[i], x0, y0, y1 - y0, x1 - x0, 4)
        tot = cov.sum()
        vis_occ[i] = (cov * (1 - occ_cov[y0:y1, x0:x1])).sum() / max(tot, 1e-9)

    # Illumination: smooth gradient plus a radial fall-off.
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    gx, gy = rng.normal(size=2)
    g = (gx * (xx / W - 0.5) + gy * (yy / H - 0.5))
    g = g / max(np.abs(g).max(), 1e-9)
    rr = ((xx - W * rng.uniform(0.3, 0.7)) ** 2 + (yy - H * rng.uniform(0.3, 0.7)) ** 2) / (0.5 * W) ** 2
    shade = (1.0 + cfg.shading * 0.6 * g) * (1.0 - cfg.shading * 0.4 * np.clip(rr, 0, 1.5))
    signal = cfg.skin * cfg.low_light * shade * refl

    sat = np.zeros((H, W), bool)
    if cfg.saturated_region:
        cx, cy = rng.uniform(0.3 * W, 0.7 * W), rng.uniform(0.3 * H, 0.7 * H)
        sat = ((xx - cx) / 140.0) ** 2 + ((yy - cy) / 90.0) ** 2 <= 1.0
        signal = np.where(sat, 400.0, signal)

    sigma_psf = rng.uniform(*cfg.blur)
    signal = cv2.GaussianBlur(signal.astype(np.float32), (0, 0), sigma_psf)
    noise_sd = np.sqrt(cfg.read_noise ** 2 + cfg.shot_noise * np.maximum(signal, 0))
    img = signal + noise_sd * rng.normal(size=(H, W)).astype(np.float32)
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if cfg.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)])
        assert ok
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)

    # Saturated region: dots inside are invisible, dots on its edge are partial.
    vis_sat = np.ones(n)
    if cfg.saturated_region:
        for i in range(n):
            a = axes[i, 0]
            x0, y0 = int(max(np.floor(xy[i, 0] - a - 1), 0)), int(max(np.floor(xy[i, 1] - a - 1), 0))
            x1, y1 = int(min(np.ceil(xy[i, 0] + a + 2), W)), int(min(np.ceil(xy[i, 1] + a + 2), H))
            if x1 <= x0 or y1 <= y0:
                continue
            # Blur spreads the saturated level a few pixels: count a 4 px margin as hidden.
            yy0, xx0 = np.mgrid[y0:y1, x0:x1]
            cov = _ellipse_coverage(xy[i, 0], xy[i, 1], axes[i, 0], axes[i, 1], ang[i], x0, y0, y1 - y0, x1 - x0, 2)
            d_sat = np.hypot(((xx0 - cx) / 140.0), ((yy0 - cy) / 90.0))
            hidden = d_sat <= 1.0 + 4.0 / 90.0
            vis_sat[i] = (cov * ~hidden).sum() / max(cov.sum(), 1e-9)

    vis = in_image * vis_occ * vis_sat
    clean = (vis >= 1.0) & ~merged & ~at_border
    # An occluder edge "near" a dot also disturbs it (blur): require 1.5 px of clearance.
    if cfg.occluders:
        occ_near = cv2.dilate((occ_cov > 0.001).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        for i in np.flatnonzero(clean):
            a = axes[i, 0]
            x0, y0 = int(max(np.floor(xy[i, 0] - a - 1), 0)), int(max(np.floor(xy[i, 1] - a - 1), 0))
            x1, y1 = int(min(np.ceil(xy[i, 0] + a + 2), W)), int(min(np.ceil(xy[i, 1] + a + 2), H))
            cov = _ellipse_coverage(xy[i, 0], xy[i, 1], axes[i, 0], axes[i, 1], ang[i], x0, y0, y1 - y0, x1 - x0, 2)
            if (cov * occ_near[y0:y1, x0:x1]).sum() > 0:
                clean[i] = False
    partial = ~clean & (vis > 0.02)
    return RenderedFrame(image=img, xy=xy, axes=axes, angle=ang, polarity=pol, visible_frac=vis,
                         clean=clean, partial=partial,
                         extra={"psf_sigma": sigma_psf, "saturated": sat, "occluder": occ_cov})


def match(det_xy: np.ndarray, true_xy: np.ndarray, radius: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Greedy nearest matching of detections to truth within ``radius`` px.

    Returns ``det_to_true (D,)`` (index or -1) and ``dist (D,)`` (NaN where unmatched).
    """
    from scipy.spatial import cKDTree

    det_xy = np.asarray(det_xy, float).reshape(-1, 2)
    true_xy = np.asarray(true_xy, float).reshape(-1, 2)
    out = np.full(len(det_xy), -1)
    dist = np.full(len(det_xy), np.nan)
    if len(det_xy) == 0 or len(true_xy) == 0:
        return out, dist
    tree = cKDTree(true_xy)
    d, j = tree.query(det_xy, k=1, distance_upper_bound=radius)
    order = np.argsort(d)
    taken = np.zeros(len(true_xy), bool)
    for i in order:
        if not np.isfinite(d[i]) or taken[j[i]]:
            continue
        taken[j[i]] = True
        out[i] = j[i]
        dist[i] = d[i]
    return out, dist


def evaluate(frames: list[RenderedFrame], dets: list[dict], radius: float = 1.5,
             polarity: int | None = None) -> dict:
    """Recall, precision and centre errors of detections against clean truth dots.

    Truth dots marked ``partial`` (and detections matched to them, or lying within their
    major axis + 2 px) are excluded from both denominators and counted separately.
    """
    tp = fn = fp = 0
    near_partial = 0
    errs = []
    for fr, d in zip(frames, dets):
        keep = np.ones(len(fr.xy), bool) if polarity is None else fr.polarity == polarity
        clean = fr.clean & keep
        partial = fr.partial & keep
        dxy = np.stack([np.asarray(d["x"], float), np.asarray(d["y"], float)], axis=1)
        j, dist = match(dxy, fr.xy[clean | partial], radius)
        idx = np.flatnonzero(clean | partial)
        jj = np.where(j >= 0, idx[np.maximum(j, 0)], -1)
        is_clean = (jj >= 0) & clean[np.maximum(jj, 0)]
        is_part = (jj >= 0) & partial[np.maximum(jj, 0)]
        tp += int(is_clean.sum())
        errs.extend(dist[is_clean].tolist())
        fn += int(clean.sum() - is_clean.sum())
        un = jj < 0
        if un.any() and partial.any():
            dd = np.linalg.norm(dxy[un, None, :] - fr.xy[partial][None], axis=2)
            close = (dd < fr.axes[partial, 0][None] + 2.0).any(axis=1)
        else:
            close = np.zeros(int(un.sum()), bool)
        near_partial += int(is_part.sum() + close.sum())
        fp += int((~close).sum())
    errs_a = np.asarray(errs)
    return {
        "recall": tp / max(tp + fn, 1),
        "precision": tp / max(tp + fp, 1),
        "tp": tp, "fn": fn, "fp": fp,
        "excluded_near_partial": near_partial,
        "median_err": float(np.median(errs_a)) if len(errs_a) else float("nan"),
        "p95_err": float(np.percentile(errs_a, 95)) if len(errs_a) else float("nan"),
    }


@dataclass
class TruthDots:
    """The dots of one synthetic-take image (markers, then brim dots), from its ground truth.

    ``xy`` (n, 2) px; ``visible``, ``partly_hidden``, ``brim``, ``cut`` (touching the image
    border), ``grazing`` (drawn, but seen beyond the generator's visibility angle:
    :func:`carapost.synth.evaluate.grazing_dots`) bool (n,); ``radius`` (n,) px;
    ``polarity`` int8 (n,) (+1 white, -1 black).
    """

    xy: np.ndarray
    visible: np.ndarray
    partly_hidden: np.ndarray
    radius: np.ndarray
    polarity: np.ndarray
    brim: np.ndarray
    cut: np.ndarray
    grazing: np.ndarray


def truth_dots(truth, frame: int, camera: int, marker_polarity: int, brim_polarity: int,
               shape: tuple[int, int]) -> TruthDots:
    """The markers and brim dots of ``truth`` (a synthetic take's ``SynthTruth``) projected
    in ``camera`` at ``frame``, for an image of ``shape`` (H, W)."""
    f, c, tr = frame, camera, truth
    mk = np.isfinite(tr.centroid_xy[f, :, c, 0])
    br = np.isfinite(tr.brim_centroid_xy[f, :, c, 0])
    xy = np.concatenate([tr.centroid_xy[f, mk, c], tr.brim_centroid_xy[f, br, c]])
    rad = np.concatenate([tr.radius_px[f, mk, c], tr.brim_radius_px[f, br, c]])
    H, W = shape
    cut = (xy[:, 0] - rad < 1) | (xy[:, 1] - rad < 1) | (xy[:, 0] + rad > W - 2) | (xy[:, 1] + rad > H - 2)
    return TruthDots(xy=xy,
                     visible=np.concatenate([tr.visible[f, mk, c], tr.brim_visible[f, br, c]]),
                     partly_hidden=np.concatenate([tr.partly_hidden[f, mk, c], np.zeros(br.sum(), bool)]),
                     radius=rad,
                     polarity=np.concatenate([np.full(mk.sum(), marker_polarity),
                                              np.full(br.sum(), brim_polarity)]).astype(np.int8),
                     brim=np.concatenate([np.zeros(mk.sum(), bool), np.ones(br.sum(), bool)]),
                     cut=cut,
                     grazing=np.concatenate([grazing_dots(tr, f, c)[mk], np.zeros(br.sum(), bool)]))


def jpeg_roundtrip(image: np.ndarray, quality: int) -> np.ndarray:
    """``image`` (uint8 (H, W)) encoded as JPEG at ``quality`` and decoded (unchanged if 0)."""
    if not quality:
        return image
    return cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_GRAYSCALE)

