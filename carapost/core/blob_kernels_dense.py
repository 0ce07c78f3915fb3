"""Compiled (numba) kernels of the blob detector's candidate stage
(:mod:`carapost.core.blob_candidates`): the local maxima of the SNR maps
(:func:`local_maxima`), the candidates' uphill climb (:func:`climb_step`) and the Laplacian
histograms of the pixel noise (:func:`laplacian_histograms`) — one call per map or image
instead of several numpy passes over it, with the same results.

As in :mod:`carapost.core.blob_kernels`: thin Python wrappers allocate the outputs and call
the compiled ``_name`` (``cache=True``, ``nogil=True``).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .blob_kernels import FLAT_HI, FLAT_LO

__all__ = ["local_maxima", "climb_step", "laplacian_histograms", "ring_samples", "context_points"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")


def climb_step(img: np.ndarray, x: np.ndarray, y: np.ndarray, steps: int) -> np.ndarray:
    """:func:`_climb_step` (see there)."""
    top = np.zeros(len(x))
    _climb_step(img, x, y, int(steps), top, np.zeros(9, np.int64))
    return top


@nb.njit(**_JIT)
def _climb_step(img, x, y, steps, top, box):
    """:func:`carapost.core.blob_candidates.climb` compiled: each point ``(x, y)`` (int64 (N,),
    changed in place) moves uphill on the 3x3 mean of ``img`` (uint8 (H, W); pixels beyond the
    border repeat it) to the neighbour with the largest mean (staying put on ties, else the
    first in row-major order) until none is higher or ``steps`` steps are done. The 3x3 mean
    at the end points (float32 values) goes to ``top`` (float64 (N,)); ``box`` is work space."""
    H, W = img.shape
    n = x.shape[0]
    for k in range(n):
        cx, cy = x[k], y[k]
        for _ in range(steps):
            for a in range(3):
                for b in range(3):
                    acc = 0
                    for u in range(3):
                        yy = min(max(cy + a - 1 + u - 1, 0), H - 1)
                        for v in range(3):
                            xx = min(max(cx + b - 1 + v - 1, 0), W - 1)
                            acc += img[yy, xx]
                    box[a * 3 + b] = acc
            top[k] = np.float32(box[4]) / np.float32(9.0)
            best = 2 * box[4] + 1          # the centre wins ties
            arg = 4
            for m in range(9):
                if m != 4 and 2 * box[m] > best:
                    best = 2 * box[m]
                    arg = m
            if arg == 4:
                break
            cx = min(max(cx + arg % 3 - 1, 0), W - 1)
            cy = min(max(cy + arg // 3 - 1, 0), H - 1)
        x[k], y[k] = cx, cy


def local_maxima(m: np.ndarray, k: int, min_snr: float) -> np.ndarray:
    """Flat indices (int64, ascending) of the pixels of ``m`` (float32 (H, W)) off its 1 px
    border that exceed ``min_snr`` (compared in float32, as numpy compares a float32 array
    with a Python float) and that no pixel of their ``k x k`` neighbourhood (``k`` 3 or 5;
    pixels beyond the image ignored) exceeds: the pixels where ``m >= cv2.dilate(m, ones((k,
    k)))``, without dilating the whole map."""
    h, w = m.shape
    out = np.empty(max((h - 2) * (w - 2), 0), np.int64)
    n = _local_maxima(np.ascontiguousarray(m, np.float32), int(k) // 2, np.float32(min_snr), out)
    return out[:n]


@nb.njit(**_JIT)
def _local_maxima(m, r, thr, out):
    """:func:`local_maxima` into ``out``; returns the count. Blocks of 16 pixels none of
    which is above the threshold are skipped at once; then the right neighbour is tested first
    (a pixel below its left neighbour is no maximum: skipped), then the rest of the 3x3 (most
    pixels above the threshold are on a slope and fail there), then the 5x5 ring."""
    H, W = m.shape
    n = 0
    for i in range(1, H - 1):
        j = 1
        while j < W - 1:
            if j % 16 == 1 and j + 16 <= W - 1:
                # A block of 16 pixels without one above the threshold is skipped at once.
                hit = False
                for b in range(j, j + 16):
                    hit |= m[i, b] > thr
                if not hit:
                    j += 16
                    continue
            v = m[i, j]
            if not v > thr:
                j += 1
                continue
            right = m[i, j + 1]
            if right > v:
                j += 1
                continue
            nxt = j + 2 if right < v else j + 1
            if (m[i, j - 1] > v or m[i - 1, j] > v or m[i + 1, j] > v or m[i - 1, j - 1] > v or m[i - 1, j + 1] > v
                    or m[i + 1, j - 1] > v or m[i + 1, j + 1] > v):
                j = nxt
                continue
            top = True
            if r == 2:
                for a in range(max(i - 2, 0), min(i + 3, H)):
                    for b in range(max(j - 2, 0), min(j + 3, W)):
                        if (a == i - 2 or a == i + 2 or b == j - 2 or b == j + 2) and m[a, b] > v:
                            top = False
            if top:
                out[n] = i * W + j
                n += 1
            j = nxt
    return n


def laplacian_histograms(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_laplacian_histograms` (see there): returns ``(keep, every)``, int64 (1021,)
    each: the histograms over the informative centres and over all of them."""
    hist = np.zeros((2 * _LAP_COPIES, 1021), np.int64)
    _laplacian_histograms(img, hist)
    keep = hist[1::2].sum(axis=0)
    return keep, keep + hist[0::2].sum(axis=0)


#: Copies (a power of two) of the Laplacian histograms that consecutive samples count into in turn (summed
#: afterwards): neighbouring samples mostly fall into the same few bins, and one copy would
#: make each count wait for the previous one's store.
_LAP_COPIES = 4


@nb.njit(**_JIT)
def _laplacian_histograms(img, hist):
    """Histograms of the absolute 4-neighbour Laplacian of ``img`` (uint8 (H, W)) on every
    third pixel from ``(1, 1)`` (the samples of
    :func:`carapost.core.blob_candidates.pixel_noise`), added to ``hist`` int64 (2 C, 1021):
    row ``2 s + 1`` over the informative centres (neither black nor clipped), row ``2 s``
    over the others, the ``C`` copies ``s`` taken in turn along each row of samples."""
    H, W = img.shape
    mask = hist.shape[0] - 2                     # C a power of two: s = 0, 2, .., 2 C - 2
    for i in range(1, H - 1, 3):
        s = 0
        for j in range(1, W - 1, 3):
            c = int(img[i, j])
            v = abs(4 * c - int(img[i - 1, j]) - int(img[i + 1, j]) - int(img[i, j - 1]) - int(img[i, j + 1]))
            hist[s + (FLAT_LO < c < FLAT_HI), v] += 1
            s = (s + 2) & mask


#: A sorting network of 12 inputs (39 compare-exchanges in 9 layers; checked on every 0/1
#: input in ``test_ring_samples_kernel_equals_numpy``): the ring's samples sorted without
#: branches.
_NET12 = np.array([[0, 8], [1, 7], [2, 6], [3, 11], [4, 10], [5, 9],
                   [0, 1], [2, 5], [3, 4], [6, 9], [7, 8], [10, 11],
                   [0, 2], [1, 6], [5, 10], [9, 11],
                   [0, 3], [1, 2], [4, 6], [5, 7], [8, 11], [9, 10],
                   [1, 4], [3, 5], [6, 8], [7, 10],
                   [1, 3], [2, 5], [6, 9], [8, 10],
                   [2, 3], [4, 5], [6, 7], [8, 9],
                   [4, 6], [5, 7],
                   [3, 4], [5, 6], [7, 8]], np.int64)


def sorting_network(n: int) -> np.ndarray:
    """Compare-exchange pairs ``(C, 2)`` int64 that sort ``n`` values in place (``a < b``:
    the smaller goes to ``a``): :data:`_NET12` for 12, else odd-even transposition (``n``
    rounds)."""
    if n == 12:
        return _NET12
    pairs = [(i, i + 1) for r in range(n) for i in range(r % 2, n - 1, 2)]
    return np.array(pairs, np.int64).reshape(-1, 2)


def ring_samples(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, rho: np.ndarray, sin_a: np.ndarray,
                 cos_a: np.ndarray) -> np.ndarray:
    """:func:`_ring_samples` (see there): returns the sorted ring float64 (N, len(sin_a))."""
    out = np.empty((len(cx), len(sin_a)))
    _ring_samples(np.ascontiguousarray(img), np.asarray(cx, np.int64), np.asarray(cy, np.int64),
                  np.asarray(rho, float), np.asarray(sin_a, float), np.asarray(cos_a, float),
                  sorting_network(len(sin_a)), out)
    return out


@nb.njit(**_JIT)
def _ring_samples(img, cx, cy, rho, sin_a, cos_a, net, out):
    """The ring of :func:`carapost.core.blob_candidates.ring_test` compiled: for each candidate
    pixel ``(cx, cy)`` (int64 (N,)) the pixels of ``img`` (uint8 (H, W)) at ``rint(c + rho
    (cos, sin))`` of the angles (``sin_a``, ``cos_a`` float64 (R,)), clipped to the image,
    sorted ascending by the compare-exchanges ``net`` (:func:`sorting_network`) into ``out``
    float64 (N, R)."""
    H, W = img.shape
    R = sin_a.shape[0]
    for k in range(cx.shape[0]):
        r = rho[k]
        row = out[k]
        for a in range(R):
            y = min(max(int(np.rint(cy[k] + r * sin_a[a])), 0), H - 1)
            x = min(max(int(np.rint(cx[k] + r * cos_a[a])), 0), W - 1)
            row[a] = float(img[y, x])
        for c in range(net.shape[0]):
            i, j = net[c, 0], net[c, 1]
            u, v = row[i], row[j]
            row[i] = min(u, v)
            row[j] = max(u, v)


def context_points(x: np.ndarray, y: np.ndarray, major: np.ndarray, minor: np.ndarray, cos_angle: np.ndarray,
                   sin_angle: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray, scales: tuple[float, float],
                   grow: float, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_context_points` (see there): returns ``sx, sy`` float32 (N, 2 T)."""
    n, t = len(x), len(cos_t)
    sx, sy = np.empty((n, 2 * t), np.float32), np.empty((n, 2 * t), np.float32)
    f = [np.asarray(v, float) for v in (x, y, major, minor, cos_angle, sin_angle, cos_t, sin_t)]
    _context_points(*f, float(scales[0]), float(scales[1]), float(grow), int(shape[0]), int(shape[1]), sx, sy)
    return sx, sy


@nb.njit(**dict(_JIT, inline="always"))
def _finite(v):
    """``np.nan_to_num`` of one float64."""
    if v != v:
        return 0.0
    if v == np.inf:
        return np.finfo(np.float64).max
    if v == -np.inf:
        return -np.finfo(np.float64).max
    return v


@nb.njit(**dict(_JIT, inline="always"))
def _clip_nan(v, hi):
    """``np.clip(v, 0, hi)`` of one float64 (NaN stays NaN)."""
    if v != v:
        return v
    return min(max(v, 0.0), hi)


@nb.njit(**_JIT)
def _context_points(x, y, major, minor, ca, sa, cos_t, sin_t, s_out, s_in, grow, H, W, sx, sy):
    """The sample points of :func:`carapost.core.blob_context.context_ring` compiled: for each
    ellipse (centre ``x, y``, semi-axes ``major, minor``, ``ca, sa`` the cosine and sine of its
    angle; float64 (N,); NaN and infinities as ``np.nan_to_num`` makes them) the points at the
    angles ``cos_t, sin_t`` (T,) of the ellipse scaled by ``s_out`` (columns ``0..T-1``) and by
    ``s_in`` (``T..2T-1``), both grown by ``grow`` px, clipped to the ``H x W`` image, into
    ``sx, sy`` float32 (N, 2 T), with numpy's float64 arithmetic in its order."""
    T = cos_t.shape[0]
    for k in range(x.shape[0]):
        maj = _finite(major[k])
        mnr = _finite(minor[k])
        xk = _finite(x[k])
        yk = _finite(y[k])
        for ring in range(2):
            s = s_out if ring == 0 else s_in
            au = s * maj + grow
            av = s * mnr + grow
            for t in range(T):
                u = au * cos_t[t]
                v = av * sin_t[t]
                c = ring * T + t
                sx[k, c] = np.float32(_clip_nan(xk + u * ca[k] - v * sa[k], W - 1.0))
                sy[k, c] = np.float32(_clip_nan(yk + u * sa[k] + v * ca[k], H - 1.0))
