"""Dense stage of the blob detector: multi-scale centre-surround response and candidates.

The image is signed so that the wanted blobs are bright (black blobs: ``255 - image``). On an
image pyramid (``cv2.pyrDown``), a difference of box filters — the mean of a small square minus
the mean of the ring around it, inner sides 3 and 5 px and outer side 11 px at each level —
responds to blobs of radius about 1.7 and 2.8 px at that level (``x 2**level`` in the full
image). A linear illumination gradient gives zero response.

Each response map is divided by a robust estimate of its own spread over the image (1.4826 x
the median absolute response: the response of the background, i.e. noise plus texture), which
turns it into a signal-to-clutter ratio ("SNR"). With ``adaptive`` the spread is estimated per
tile (uneven lighting: dark regions have smaller noise and smaller contrast, so they get their
own scale). Candidates are local maxima of the best SNR over the scales of a level that exceed
a low threshold; they are refined and scored by :mod:`carapost.core.blob_fit` and
:mod:`carapost.core.blob_score`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Candidates", "ResponseLevel", "signed_image", "pyramid", "level_range", "responses",
           "find_candidates", "pixel_noise", "informative", "INNER_SIDES", "OUTER_SIDE", "scale_radius"]

#: Inner box sides (px at the pyramid level) and the common outer box side.
INNER_SIDES: tuple[int, ...] = (3, 5)
OUTER_SIDE: int = 11
#: Radius (px at the level) of the disc best matched by each inner box: equal area.
_RADIUS_OF_SIDE = {s: s / np.sqrt(np.pi) for s in INNER_SIDES}
#: Smallest response spread (grey levels x sqrt(1/n_in + 1/n_ring)) accepted for a level: the
#: 8-bit quantisation noise, so a synthetic, noise-free image does not give infinite SNR.
_MIN_PIXEL_NOISE = 0.5
#: Grey levels at or below / at or above which a pixel is black / saturated (no information).
_FLAT_LO, _FLAT_HI = 4, 251
#: Tile size (px at the level) for the adaptive (local) spread estimate.
_TILE = 32


@dataclass
class Candidates:
    """Candidate blob centres in full-resolution pixels.

    Attributes
    ----------
    x, y : int arrays (N,)
        Position of the candidate at its pyramid level (level pixels).
    level : int array (N,)
        Pyramid level (0 = full resolution).
    radius : float64 (N,)
        Radius estimate in full-resolution pixels.
    snr : float64 (N,)
        Best normalised response (signal-to-clutter ratio) at the candidate.
    weber : float64 (N,)
        Centre-surround response over the surround's grey level in the original image (a
        rough Weber contrast: paint is a large relative change, skin texture a small one).
    """

    x: np.ndarray
    y: np.ndarray
    level: np.ndarray
    radius: np.ndarray
    snr: np.ndarray
    weber: np.ndarray

    def __len__(self) -> int:
        return len(self.x)

    def subset(self, sel: np.ndarray) -> "Candidates":
        """The candidates selected by an index or bool array."""
        return Candidates(self.x[sel], self.y[sel], self.level[sel], self.radius[sel], self.snr[sel],
                          self.weber[sel])


@dataclass
class ResponseLevel:
    """Normalised responses of one pyramid level.

    ``snr`` is the best SNR over the scales (float32 (h, w)); ``per_scale`` holds each scale's
    SNR map (index into :data:`INNER_SIDES`) and ``spread`` the response spread it was divided
    by (a number, or a map with ``adaptive``); ``outer`` is the mean of the signed image over
    the outer box.
    """

    level: int
    snr: np.ndarray
    per_scale: list[np.ndarray]
    spread: list
    outer: np.ndarray


def scale_radius(level: int | np.ndarray, scale_index: int | np.ndarray) -> np.ndarray:
    """Full-resolution radius (px) matched by ``INNER_SIDES[scale_index]`` at ``level``."""
    r = np.asarray([_RADIUS_OF_SIDE[s] for s in INNER_SIDES])[np.asarray(scale_index)]
    return r * (2.0 ** np.asarray(level))


def informative(img: np.ndarray) -> np.ndarray:
    """Pixels that carry image information: neither black (<= 4) nor saturated (>= 251).

    Noise and clutter statistics are taken over these only, so that a large black background
    (or a clipped region) does not make the rest of the image look noise-free.
    """
    return (img > _FLAT_LO) & (img < _FLAT_HI)


def pixel_noise(img: np.ndarray) -> float:
    """Robust standard deviation (grey levels) of pixel noise plus fine texture of a uint8 image.

    1.4826 x the median absolute 4-neighbour Laplacian over every third informative pixel
    (:func:`informative`), divided by ``sqrt(20)`` (the Laplacian's gain on white noise); at
    least the 8-bit quantisation noise.
    """
    a = img.astype(np.int16)
    c = a[1:-1:3, 1:-1:3]
    h, w = c.shape
    lap = (4 * c - a[:-2:3, 1:-1:3][:h, :w] - a[2::3, 1:-1:3][:h, :w]
           - a[1:-1:3, :-2:3][:h, :w] - a[1:-1:3, 2::3][:h, :w])
    keep = informative(img[1:-1:3, 1:-1:3])
    v = np.abs(lap[keep]) if keep.sum() >= 256 else np.abs(lap).ravel()
    if v.size == 0:
        return _MIN_PIXEL_NOISE
    med = float(np.partition(v, v.size // 2)[v.size // 2])
    return max(1.4826 * med / np.sqrt(20.0), 0.29)


def signed_image(image: np.ndarray, polarity: int) -> np.ndarray:
    """``image`` (uint8) if ``polarity`` is +1 (white blobs), ``255 - image`` if -1 (black)."""
    return image if polarity > 0 else cv2.bitwise_not(image)


def level_range(min_radius: float, max_radius: float) -> range:
    """Pyramid levels whose scales cover ``[min_radius, max_radius]`` (full-resolution px)."""
    rs = [_RADIUS_OF_SIDE[s] for s in INNER_SIDES]
    lo_r, hi_r = min(rs), max(rs)
    # A level covers about [lo_r/1.4, hi_r*1.4] x 2**level.
    lo, hi = lo_r / 1.4, hi_r * 1.4
    first = max(0, int(np.floor(np.log2(max(min_radius, 1e-3) / lo))))
    last = max(0, int(np.ceil(np.log2(max(max_radius, 1e-3) / hi))))
    first = min(first, last)
    return range(first, last + 1)


def pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """``[image, pyrDown(image), ...]`` with ``levels`` entries (uint8)."""
    out = [image]
    for _ in range(levels - 1):
        prev = out[-1]
        if min(prev.shape) < 2 * OUTER_SIDE:
            break
        out.append(cv2.pyrDown(prev))
    return out


def _robust_spread(resp: np.ndarray, valid: np.ndarray, adaptive: bool, floor: float,
                   shape: tuple[int, int]) -> np.ndarray | float:
    """1.4826 x median |resp| of a subsampled response, globally or per tile.

    ``resp`` is the response on every third pixel of a level of ``shape`` and ``valid`` marks
    the informative ones (the global estimate uses only those, if there are enough); the
    per-tile map is returned at the full level size (bilinear).
    """
    a = np.abs(resp)
    if not adaptive or min(shape) < 2 * _TILE:
        sub = a[valid] if int(valid.sum()) >= 256 else a.ravel()
        if sub.size == 0:
            return floor
        med = float(np.partition(sub, sub.size // 2)[sub.size // 2])
        return max(1.4826 * med, floor)
    t = _TILE // 3
    th, tw = a.shape[0] // t, a.shape[1] // t
    a = a[:th * t, :tw * t].reshape(th, t, tw, t).transpose(0, 2, 1, 3).reshape(th, tw, -1)
    med = np.maximum(1.4826 * np.median(a, axis=2), floor).astype(np.float32)
    # A tile full of blobs over-estimates its clutter: take the smaller of the neighbours.
    med = cv2.erode(med, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    med = cv2.blur(med, (3, 3), borderType=cv2.BORDER_REPLICATE)
    return cv2.resize(med, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def responses(img: np.ndarray, level: int, *, adaptive: bool = False) -> ResponseLevel:
    """Normalised centre-surround responses of one pyramid level image (uint8, blobs bright).

    Parameters
    ----------
    img : uint8 (h, w)
        The signed image at this level.
    level : int
        Pyramid level (only recorded).
    adaptive : bool
        Estimate the response spread per tile instead of over the whole image.

    Returns
    -------
    ResponseLevel
    """
    n_out = OUTER_SIDE * OUTER_SIDE
    outer = cv2.boxFilter(img, cv2.CV_32F, (OUTER_SIDE, OUTER_SIDE), borderType=cv2.BORDER_REFLECT)
    per_scale = []
    spreads = []
    valid = informative(img[1::3, 1::3])
    for side in INNER_SIDES:
        n_in = side * side
        inner = cv2.boxFilter(img, cv2.CV_32F, (side, side), borderType=cv2.BORDER_REFLECT)
        # inner - ring = c (inner - outer), with ring = (n_out outer - n_in inner) / (n_out - n_in)
        c = n_out / (n_out - n_in)
        sub = c * (inner[1::3, 1::3] - outer[1::3, 1::3])
        floor = _MIN_PIXEL_NOISE * np.sqrt(1.0 / n_in + 1.0 / (n_out - n_in))
        spread = _robust_spread(sub, valid, adaptive, floor, img.shape)
        if isinstance(spread, np.ndarray):
            snr = cv2.addWeighted(inner, c, outer, -c, 0.0)
            snr /= spread
        else:
            snr = cv2.addWeighted(inner, c / spread, outer, -c / spread, 0.0)
        per_scale.append(snr)
        spreads.append(spread)
    best = per_scale[0]
    for other in per_scale[1:]:
        best = cv2.max(best, other)
    return ResponseLevel(level=level, snr=best, per_scale=per_scale, spread=spreads, outer=outer)


def find_candidates(levels: list[ResponseLevel], *, min_snr: float, min_radius: float,
                    max_radius: float, polarity: int, min_weber: float = 0.0,
                    max_candidates: int = 4000) -> Candidates:
    """Local maxima (3x3) of each level's best SNR above ``min_snr``, then non-maximum
    suppression between scales and levels (see :func:`_suppress`).

    Candidates whose scale radius is far outside ``[min_radius, max_radius]`` are dropped (the
    final radius test is on the fitted ellipse), and so are those whose rough Weber contrast
    is below ``min_weber``. At most ``max_candidates`` (the strongest) are kept.
    """
    xs, ys, ls, rs, ss, ws = [], [], [], [], [], []
    for lv in levels:
        snr = lv.snr
        h, w = snr.shape
        flat = snr.ravel()
        above = np.flatnonzero(snr > min_snr)
        yy, xx = np.divmod(above, w)
        inner = (yy > 0) & (yy < h - 1) & (xx > 0) & (xx < w - 1)
        pk = above[inner]
        v = flat[pk]
        is_max = np.ones(len(pk), bool)
        for off in (-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1):
            is_max &= v >= flat[pk + off]
        pk = pk[is_max]
        if len(pk) == 0:
            continue
        yy, xx = np.divmod(pk, w)
        vals = np.stack([m.ravel()[pk] for m in lv.per_scale], axis=1)
        sc = np.argmax(vals, axis=1)
        r = scale_radius(lv.level, sc)
        best = vals[np.arange(len(pk)), sc]
        spread = np.stack([sp.ravel()[pk] if isinstance(sp, np.ndarray) else np.full(len(pk), sp)
                           for sp in lv.spread], axis=1)[np.arange(len(pk)), sc]
        outer = lv.outer.ravel()[pk]
        bg = outer if polarity > 0 else 255.0 - outer
        weber = best * spread / np.maximum(bg, 1.0)
        keep = (r * 1.6 >= min_radius) & (r / 1.6 <= max_radius) & (weber >= min_weber)
        ws.append(weber[keep].astype(np.float64))
        xs.append(xx[keep])
        ys.append(yy[keep])
        ls.append(np.full(int(keep.sum()), lv.level))
        rs.append(r[keep])
        ss.append(vals[keep, sc[keep]].astype(np.float64))
    if not xs:
        z = np.zeros(0, np.int64)
        return Candidates(z, z, z, np.zeros(0), np.zeros(0), np.zeros(0))
    cand = Candidates(np.concatenate(xs).astype(np.int64), np.concatenate(ys).astype(np.int64),
                      np.concatenate(ls).astype(np.int64), np.concatenate(rs), np.concatenate(ss),
                      np.concatenate(ws))
    cand = _suppress(cand)
    if len(cand) > max_candidates:
        top = np.argsort(-cand.snr, kind="stable")[:max_candidates]
        top.sort()
        cand = cand.subset(top)
    return cand


def _suppress(cand: Candidates) -> Candidates:
    """Non-maximum suppression within each pyramid level.

    A candidate is dropped when one with a higher SNR lies closer than 0.8 x the larger of
    their radii, at the same pyramid level (a second maximum on the plateau of a blob; two
    separate dots are at least the sum of their radii apart) or at an adjacent scale (radii
    within a factor 1.5: the same blob seen twice). Candidates of clearly different scales are
    kept: a dot on an eyebrow is a small blob inside a big one. Remaining duplicates are
    resolved after fitting (:func:`carapost.core.blobs.analyse_blobs`).
    """
    from scipy.spatial import cKDTree

    if len(cand) < 2:
        return cand
    s = 2.0 ** cand.level
    pts = np.stack([cand.x * s, cand.y * s], axis=1)
    pairs = cKDTree(pts).query_pairs(r=float(0.8 * cand.radius.max()), output_type="ndarray")
    if len(pairs) == 0:
        return cand
    i, j = pairs[:, 0], pairs[:, 1]
    d = np.linalg.norm(pts[i] - pts[j], axis=1)
    ri, rj = cand.radius[i], cand.radius[j]
    similar = (cand.level[i] == cand.level[j]) | (np.maximum(ri, rj) <= 1.5 * np.minimum(ri, rj))
    hit = (d < 0.8 * np.maximum(ri, rj)) & similar
    i, j = i[hit], j[hit]
    loser = np.where(cand.snr[i] >= cand.snr[j], j, i)
    keep = np.ones(len(cand), bool)
    keep[loser] = False
    return cand.subset(np.flatnonzero(keep))
