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

__all__ = ["local_maxima", "climb_step", "laplacian_histograms"]

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
    """:func:`_laplacian_histograms` (see there): returns ``(keep, every)``."""
    keep, every = np.zeros(1021, np.int64), np.zeros(1021, np.int64)
    _laplacian_histograms(img, keep, every)
    return keep, every


@nb.njit(**_JIT)
def _laplacian_histograms(img, keep, every):
    """Histograms (int64 (1021,)) of the absolute 4-neighbour Laplacian of ``img`` (uint8
    (H, W)) on every third pixel from ``(1, 1)`` (the samples of
    :func:`carapost.core.blob_candidates.pixel_noise`), added to ``keep`` over the informative
    centres (neither black nor clipped) and to ``every`` over all of them."""
    H, W = img.shape
    for i in range(1, H - 1, 3):
        for j in range(1, W - 1, 3):
            c = int(img[i, j])
            v = abs(4 * c - int(img[i - 1, j]) - int(img[i + 1, j]) - int(img[i, j - 1]) - int(img[i, j + 1]))
            every[v] += 1
            if FLAT_LO < c < FLAT_HI:
                keep[v] += 1
