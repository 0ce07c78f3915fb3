"""Dense stage of the blob detector: multi-scale centre-surround response and candidates.

The image is signed so that the wanted blobs are bright (black blobs: ``255 - image``). On an
image pyramid (``cv2.pyrDown``), a difference of box filters — the mean of a small square minus
the mean of the ring around it, outer side 11 px at each level — responds to blobs of a few
pixels at that level (``x 2**level`` in the full image). A linear illumination gradient gives
zero response. The search starts at pyramid level 1 (a quarter of the pixels): the first level
has inner sides 1, 3 and 5 px (full-resolution radii about 1.1, 3.4 and 5.6 px), the next ones
3 and 5 px. Candidates only need to fall inside their dot; the fit
(:mod:`carapost.core.blob_fit`) works at full resolution.

Each response map is divided by a robust estimate of its own spread over the image (1.4826 x
the median absolute response over informative pixels: the response of the background, i.e.
noise plus texture), which turns it into a signal-to-clutter ratio ("SNR"). With
``adaptive`` the spread is estimated per tile (uneven lighting). Candidates are local maxima
(3x3) of the best SNR over the scales of a level above a low threshold, then non-maximum
suppression between scales (:func:`_suppress`). :func:`ring_test` then measures each
candidate's contrast against a ring of pixels around it at full resolution, a cheap test
that removes edges and texture before the fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .blob_kernels_dense import climb_step, laplacian_histograms, local_maxima, ring_samples

__all__ = ["Candidates", "ResponseLevel", "RingTest", "signed_image", "pyramid", "detection_scales", "climb",
           "responses", "find_candidates", "ring_test", "pixel_noise", "informative", "OUTER_SIDE",
           "refine_level", "MAX_REFINE_RADIUS"]

#: Outer box side (px at the pyramid level) of every centre-surround filter.
OUTER_SIDE: int = 11
#: Inner box sides at the first detection level and at the coarser ones.
_FIRST_SIDES: tuple[int, ...] = (1, 3, 5)
_SIDES: tuple[int, ...] = (3, 5)
#: First pyramid level searched for candidates.
_FIRST_LEVEL = 1
#: Smallest pixel-noise std (grey levels) assumed: the 8-bit quantisation noise, so that a
#: synthetic, noise-free image does not give infinite SNR.
_MIN_PIXEL_NOISE = 0.5
#: Grey levels at or below / at or above which a pixel is black / saturated (no information).
_FLAT_LO, _FLAT_HI = 4, 251
#: Tile size (px at the level) for the adaptive (local) spread estimate.
_TILE = 32
#: Largest blob radius refined at full resolution; bigger blobs are refined on the pyramid
#: level where their radius is at most this many pixels.
MAX_REFINE_RADIUS = 8.0


def _radius_of_side(side: int, level: int) -> float:
    """Full-resolution radius (px) of the disc with the area of a ``side`` box at ``level``."""
    return side / np.sqrt(np.pi) * 2.0 ** level


@dataclass
class Candidates:
    """Candidate blob centres.

    Attributes
    ----------
    x, y : int arrays (N,)
        Position of the candidate at its pyramid level (level pixels).
    level : int array (N,)
        Pyramid level the candidate was found on.
    radius : float64 (N,)
        Radius estimate in full-resolution pixels (from the best-matching scale).
    snr : float64 (N,)
        Best normalised response (signal-to-clutter ratio) at the candidate.
    """

    x: np.ndarray
    y: np.ndarray
    level: np.ndarray
    radius: np.ndarray
    snr: np.ndarray

    def __len__(self) -> int:
        return len(self.x)

    def subset(self, sel: np.ndarray) -> "Candidates":
        """The candidates selected by an index or bool array."""
        return Candidates(self.x[sel], self.y[sel], self.level[sel], self.radius[sel], self.snr[sel])

    def full_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """Candidate positions in full-resolution pixels, float64 ``(N,)`` each."""
        s = 2.0 ** self.level
        return self.x * s, self.y * s


@dataclass
class ResponseLevel:
    """Normalised responses of one pyramid level.

    ``per_scale`` holds each scale's SNR map (float32 (h, w)), ``sides`` its inner box side,
    ``radius`` its full-resolution radius (px) and ``spread`` the response spread it was
    divided by (grey levels: a number, or a map with ``adaptive``); ``outer`` is the sum of
    the signed image over the outer box (uint16). ``snr`` is the best SNR over the scales
    (computed when first asked for: the preview needs it, the detector does not).
    """

    level: int
    per_scale: list[np.ndarray]
    sides: tuple[int, ...]
    radius: tuple[float, ...]
    spread: list
    outer: np.ndarray

    @property
    def snr(self) -> np.ndarray:
        best = self.__dict__.get("_snr")
        if best is None:
            best = self.per_scale[0]
            for other in self.per_scale[1:]:
                best = cv2.max(best, other)
            self.__dict__["_snr"] = best
        return best


def informative(img: np.ndarray) -> np.ndarray:
    """Pixels that carry image information: neither black (<= 4) nor saturated (>= 251).

    Noise and clutter statistics are taken over these only, so that a large black background
    (or a clipped region) does not make the rest of the image look noise-free.
    """
    return (img > _FLAT_LO) & (img < _FLAT_HI)


def pixel_noise(img: np.ndarray, compiled: bool = True) -> float:
    """Robust standard deviation (grey levels) of pixel noise plus fine texture of a uint8 image.

    1.4826 x the median absolute 4-neighbour Laplacian over every third informative pixel
    (:func:`informative`), divided by ``sqrt(20)`` (the Laplacian's gain on white noise); at
    least the 8-bit quantisation noise. ``compiled``: the median from the histogram of the
    (integer) Laplacian values (:func:`carapost.core.blob_kernels_dense.laplacian_histograms`, the
    same value), else by partitioning them.
    """
    if compiled:
        keep, every = laplacian_histograms(np.ascontiguousarray(img, np.uint8))
        hist = keep if keep.sum() >= 256 else every
        size = int(hist.sum())
        if size == 0:
            return _MIN_PIXEL_NOISE
        med = float(np.searchsorted(np.cumsum(hist), size // 2, side="right"))
        return max(1.4826 * med / np.sqrt(20.0), 0.29)
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


def detection_scales(min_radius: float, max_radius: float) -> dict[int, tuple[int, ...]]:
    """``{level: inner box sides}`` of the scales covering ``[min_radius, max_radius]`` (px).

    A scale of radius ``r`` covers blobs of radius ``r / 1.6 .. r * 1.6``.
    """
    out: dict[int, tuple[int, ...]] = {}
    level = _FIRST_LEVEL
    while True:
        sides = _FIRST_SIDES if level == _FIRST_LEVEL else _SIDES
        keep = tuple(s for s in sides
                     if _radius_of_side(s, level) * 1.6 >= min_radius and _radius_of_side(s, level) / 1.6 <= max_radius)
        if keep:
            out[level] = keep
        if _radius_of_side(sides[-1], level) / 1.6 > max_radius or level > 12:
            break
        level += 1
    if not out:
        out[_FIRST_LEVEL] = _FIRST_SIDES[-1:]
    return out


def refine_level(radius: np.ndarray | float) -> np.ndarray:
    """Pyramid level on which a blob of ``radius`` (full-resolution px) is fitted: the finest
    where its radius is at most :data:`MAX_REFINE_RADIUS` px."""
    r = np.maximum(np.asarray(radius, float), 1e-6)
    return np.clip(np.ceil(np.log2(r / MAX_REFINE_RADIUS)), 0, None).astype(np.int64)


def pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """``[image, pyrDown(image), ...]`` with up to ``levels`` entries (uint8); stops when a level
    would be smaller than twice the outer box."""
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


def responses(img: np.ndarray, level: int, sides: tuple[int, ...], *, adaptive: bool = False) -> ResponseLevel:
    """Normalised centre-surround responses of one pyramid level image (uint8, blobs bright).

    Parameters
    ----------
    img : uint8 (h, w)
        The signed image at this level.
    level : int
        Pyramid level (for the radii).
    sides : tuple of int
        Inner box sides (odd).
    adaptive : bool
        Estimate the response spread per tile instead of over the whole image.

    Returns
    -------
    ResponseLevel
    """
    n_out = OUTER_SIDE * OUTER_SIDE
    outer = cv2.boxFilter(img, cv2.CV_16U, (OUTER_SIDE, OUTER_SIDE), normalize=False,
                          borderType=cv2.BORDER_REFLECT)
    valid = informative(img[1::3, 1::3])
    outer_sub = outer[1::3, 1::3].astype(np.float32) * (1.0 / n_out)
    per_scale = []
    spreads = []
    for side in sides:
        n_in = side * side
        if side == 1:
            inner = img
        else:
            inner = cv2.boxFilter(img, cv2.CV_16U, (side, side), normalize=False, borderType=cv2.BORDER_REFLECT)
        # inner mean - ring mean = c (inner mean - outer mean)
        c = n_out / (n_out - n_in)
        sub = c * (inner[1::3, 1::3].astype(np.float32) * (1.0 / n_in) - outer_sub)
        floor = _MIN_PIXEL_NOISE * np.sqrt(1.0 / n_in + 1.0 / (n_out - n_in))
        spread = _robust_spread(sub, valid, adaptive, floor, img.shape)
        if isinstance(spread, np.ndarray):
            snr = cv2.addWeighted(inner, c / n_in, outer, -c / n_out, 0.0, dtype=cv2.CV_32F)
            snr /= spread
        else:
            snr = cv2.addWeighted(inner, c / n_in / spread, outer, -c / n_out / spread, 0.0, dtype=cv2.CV_32F)
        per_scale.append(snr)
        spreads.append(spread)
    return ResponseLevel(level=level, per_scale=per_scale, sides=tuple(sides),
                         radius=tuple(_radius_of_side(s, level) for s in sides), spread=spreads, outer=outer)


def find_candidates(levels: list[ResponseLevel], *, min_snr: float, polarity: int, min_weber: float = 0.0,
                    max_candidates: int = 20000) -> Candidates:
    """Local maxima of every scale's SNR map above ``min_snr`` and with a rough Weber
    contrast of at least ``min_weber``.

    Maxima are taken per scale, not of the best response over the scales: a dot on a dark
    band (an eyebrow, a lip line) is a maximum at its own scale even where the band's bigger
    scale responds more. The neighbourhood is 3x3 for inner sides up to 3 px and 5x5 for
    bigger ones (one maximum per blob top). The rough Weber contrast is the response over the
    outer box's mean grey level in the original image (for white blobs: the smaller of that
    and the headroom to 255): paint is a large relative change, skin texture a small one.
    Maxima of different scales are all kept; duplicates are resolved by the ring test and
    after the fit. At most ``max_candidates`` (the strongest) are kept.
    """
    xs, ys, ls, rs, ss = [], [], [], [], []
    for lv in levels:
        h, w = lv.outer.shape
        if h < 3 or w < 3:
            continue
        outer = lv.outer.ravel()
        for m, side, r, spread in zip(lv.per_scale, lv.sides, lv.radius, lv.spread):
            k = 3 if side <= 3 else 5
            # Pixels above the threshold, off the border, that are the maximum of their
            # neighbourhood (one compiled pass: the threshold first, few pixels pass it).
            mf = m.ravel()
            pk = local_maxima(m, k, min_snr)
            if len(pk) == 0:
                continue
            val = mf[pk].astype(np.float64)
            if min_weber > 0:
                bg = outer[pk] * (1.0 / (OUTER_SIDE * OUTER_SIDE))
                bg = np.minimum(bg, 255.0 - bg) if polarity > 0 else 255.0 - bg
                sp = spread.ravel()[pk] if isinstance(spread, np.ndarray) else spread
                ok = val * sp >= min_weber * np.maximum(bg, 1.0)
                pk, val = pk[ok], val[ok]
            yy, xx = np.divmod(pk, w)
            xs.append(xx)
            ys.append(yy)
            ls.append(np.full(len(pk), lv.level))
            rs.append(np.full(len(pk), r))
            ss.append(val)
    if not xs:
        z = np.zeros(0, np.int64)
        return Candidates(z, z, z, np.zeros(0), np.zeros(0))
    cand = Candidates(np.concatenate(xs).astype(np.int64), np.concatenate(ys).astype(np.int64),
                      np.concatenate(ls).astype(np.int64), np.concatenate(rs), np.concatenate(ss))
    if len(cand) > max_candidates:
        top = np.argsort(-cand.snr, kind="stable")[:max_candidates]
        top.sort()
        cand = cand.subset(top)
    return cand


@dataclass
class RingTest:
    """Contrast of each candidate against a ring of pixels around it (see :func:`ring_test`).

    Attributes
    ----------
    centre : float64 (N,)
        Mean of the signed image over the candidate's inner box (grey levels).
    ring : float64 (N, K)
        Signed image on the ring, sorted ascending (grey levels).
    noise : float64 (N,)
        Pixel noise of the candidate's pyramid level (grey levels).
    polarity : int
    """

    centre: np.ndarray
    ring: np.ndarray
    noise: np.ndarray
    polarity: int

    def contrast(self, q: float) -> np.ndarray:
        """``centre`` minus the ``q`` quantile of the ring (grey levels)."""
        k = int(round(q * (self.ring.shape[1] - 1)))
        return self.centre - self.ring[:, k]

    def background(self) -> np.ndarray:
        """Median of the ring in the original image's grey levels; for white blobs the
        smaller of that and the headroom to 255 (the room a white dot has)."""
        k = (self.ring.shape[1] - 1) // 2
        bg = 0.5 * (self.ring[:, k] + self.ring[:, k + 1])
        return np.minimum(bg, 255.0 - bg) if self.polarity > 0 else 255.0 - bg


_RING_N = 12
_RING_ANG = np.linspace(0.0, 2 * np.pi, _RING_N, endpoint=False)
_RING_SIN, _RING_COS = np.sin(_RING_ANG), np.cos(_RING_ANG)


def ring_test(pyr: list[np.ndarray], levels: list[ResponseLevel], cand: Candidates, noise: dict[int, float],
              polarity: int, compiled: bool = True) -> RingTest:
    """Inner-box mean and ring samples of every candidate on its detection level.

    The ring has 12 samples at ``1.5 r + 1.5`` px around the candidate (``r`` the radius of
    its scale at that level): outside a blob of that scale, so a blob has the whole ring
    below its centre, an edge only half of it, and a scale much smaller than the blob a ring
    inside the blob (no contrast).

    Parameters
    ----------
    pyr : list of uint8 arrays
        Pyramid of the signed image.
    levels : list of ResponseLevel
        The responses the candidates came from.
    cand : Candidates
    noise : dict of int to float
        Pixel noise per level (filled in when missing).
    polarity : int
    compiled : bool
        The ring's samples from :func:`carapost.core.blob_kernels_dense.ring_samples` (the
        same values), else numpy indexing and sorting.
    """
    n = len(cand)
    centre = np.zeros(n)
    ring = np.zeros((n, _RING_N))
    nz = np.zeros(n)
    n_out = OUTER_SIDE * OUTER_SIDE
    for lv in levels:
        k = lv.level
        sel = np.flatnonzero(cand.level == k)
        if len(sel) == 0:
            continue
        img = pyr[k]
        H, W = img.shape
        if k not in noise:
            noise[k] = pixel_noise(img)
        cx, cy = cand.x[sel], cand.y[sel]
        flat = cy * W + cx
        # inner mean = response / c + outer mean (the response is inner mean - ring mean).
        side = np.zeros(len(sel))
        resp = np.zeros(len(sel))
        for si, (sd, r) in enumerate(zip(lv.sides, lv.radius)):
            m = cand.radius[sel] == r
            if not m.any():
                continue
            sp = lv.spread[si]
            sp = sp.ravel()[flat[m]] if isinstance(sp, np.ndarray) else sp
            resp[m] = lv.per_scale[si].ravel()[flat[m]] * sp
            side[m] = sd
        c = n_out / (n_out - side * side)
        centre[sel] = resp / c + lv.outer.ravel()[flat] * (1.0 / n_out)
        rho = 1.5 * cand.radius[sel] / 2.0 ** k + 1.5
        if compiled:
            ring[sel] = ring_samples(img, cx, cy, rho, _RING_SIN, _RING_COS)
        else:
            rr = np.clip(np.rint(cy[:, None] + rho[:, None] * _RING_SIN[None]).astype(np.int64), 0, H - 1)
            cc = np.clip(np.rint(cx[:, None] + rho[:, None] * _RING_COS[None]).astype(np.int64), 0, W - 1)
            ring[sel] = np.sort(img[rr, cc].astype(np.float64), axis=1)
        nz[sel] = noise[k]
    return RingTest(centre=centre, ring=ring, noise=nz, polarity=polarity)


def climb(img: np.ndarray, x: np.ndarray, y: np.ndarray, steps: int = 16, compiled: bool = True
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move each point uphill on the 3x3 mean of ``img`` (one pixel per step, 8 neighbours)
    until it reaches a local maximum or ``steps`` steps are done. Returns the end points and
    the 3x3 mean there (pixels beyond the border repeat the border). ``compiled``: the loop of
    :func:`carapost.core.blob_kernels_dense.climb_step` (the same result), else vectorised numpy
    over the points still moving."""
    x, y = np.array(x, np.int64), np.array(y, np.int64)
    if compiled:
        top = climb_step(np.ascontiguousarray(img), x, y, steps)
        return x, y, top
    H, W = img.shape
    top = np.zeros(len(x))
    if len(x) == 0:
        return x, y, top
    pad = cv2.copyMakeBorder(img, 2, 2, 2, 2, cv2.BORDER_REPLICATE).ravel()
    Wp = W + 4
    off = ((np.arange(5)[:, None] - 2) * Wp + np.arange(5)[None] - 2).ravel()    # 5x5 window
    moving = np.arange(len(x))
    for _ in range(steps):
        if len(moving) == 0:
            break
        win = pad[((y[moving] + 2) * Wp + x[moving] + 2)[:, None] + off[None]].astype(np.float32).reshape(-1, 5, 5)
        s = win[:, :-2] + win[:, 1:-1] + win[:, 2:]
        box = (s[:, :, :-2] + s[:, :, 1:-1] + s[:, :, 2:]).reshape(len(moving), 9)
        top[moving] = box[:, 4] / 9.0
        # Prefer staying put on ties (plateaus).
        box[:, 4] += 1e-3
        arg = np.argmax(box, axis=1)
        dy, dx = np.divmod(arg, 3)
        step = arg != 4
        x[moving] = np.clip(x[moving] + dx - 1, 0, W - 1)
        y[moving] = np.clip(y[moving] + dy - 1, 0, H - 1)
        moving = moving[step]
    return x, y, top
