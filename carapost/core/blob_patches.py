"""Stacks of square patches around blob candidates, and the batched image operations on them.

The per-candidate stage of the blob detector (:mod:`carapost.core.blob_fit`) works on a stack
``(N, S, S)`` of patches (:func:`extract_patches`); morphology and filters run on a "mosaic" of
the stack (the patches one under another with blank rows between them) in single OpenCV calls,
and the polynomial background fits share one cached grid of offsets and monomials per size.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Patches", "extract_patches", "patch_grid", "mosaic", "unmosaic", "dilate", "dilate_many", "box3",
           "dot_rows", "MONO", "MONO_INDEX", "K3", "SEP"]

SEP = 5  # blank rows between patches in a mosaic (> the largest dilation radius)


#: Largest ``M * P * k`` of one product in :func:`dot_rows` (OpenBLAS runs GEMMs up to 4 x 65536
#: multiply-adds on the calling thread only).
_DOT_CHUNK = 200_000


def dot_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a tall ``a (M, P)`` and a thin ``b (P, k)``, in row blocks small enough
    that a multi-threaded BLAS keeps each product on the calling thread: waking its threads
    for these skinny products costs more CPU time than computing them, and competes with
    :func:`carapost.core.detect_range.detect_frames`' own threads."""
    m, p = a.shape
    rows = max(1, _DOT_CHUNK // max(p * b.shape[1], 1))
    if m <= rows:
        return a @ b
    out = np.empty((m, b.shape[1]), np.result_type(a, b))
    for i in range(0, m, rows):
        np.matmul(a[i:i + rows], b, out=out[i:i + rows])
    return out


def mosaic(a: np.ndarray, fill: float = 0) -> np.ndarray:
    """Stack ``(N, S, S)`` patches vertically with ``SEP`` rows of ``fill`` between them."""
    n, s, _ = a.shape
    mos = np.full((n, s + SEP, s), fill, a.dtype if a.dtype != bool else np.uint8)
    mos[:, :s] = a
    return mos.reshape(n * (s + SEP), s)


def unmosaic(mos: np.ndarray, n: int, s: int) -> np.ndarray:
    return mos.reshape(n, s + SEP, s)[:, :s]


_KERNELS = {r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)) for r in (1, 2, 3, 4)}
K3 = np.ones((3, 3), np.uint8)


def dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """Dilate each ``(S, S)`` mask of a stack by a disc of radius ``r`` (1..4) px."""
    n, s, _ = mask.shape
    if n == 0:
        return mask.copy()
    return unmosaic(cv2.dilate(mosaic(mask), _KERNELS[r]), n, s).astype(bool)


#: Rows of each disc kernel: ``(dy, half width)``.
_KERNEL_ROWS = {r: [(i - r, int(np.flatnonzero(k[i]).max()) - r) for i in range(k.shape[0])]
                for r, k in _KERNELS.items()}


def dilate_many(mask: np.ndarray, radii: tuple[int, ...]) -> list[np.ndarray]:
    """:func:`dilate` of one stack by several radii (one mosaic). A disc is a stack of
    horizontal segments: the mosaic is dilated once per segment width (shared by the radii)
    and each dilation is the maximum of those rows shifted by the segments' offsets (the
    blank rows between the patches keep the shifts inside each patch); the same as one
    dilation by the disc, in about half the time."""
    n, s, _ = mask.shape
    if n == 0:
        return [mask.copy() for _ in radii]
    mos = mosaic(mask)
    rows: dict[int, np.ndarray] = {}
    out = []
    for r in radii:
        acc = np.zeros_like(mos)
        for dy, w in _KERNEL_ROWS[r]:
            if w not in rows:
                rows[w] = cv2.dilate(mos, np.ones((1, 2 * w + 1), np.uint8)) if w > 0 else mos
            h = rows[w]
            if dy > 0:
                np.maximum(acc[:-dy], h[dy:], out=acc[:-dy])
            elif dy < 0:
                np.maximum(acc[-dy:], h[:dy], out=acc[-dy:])
            else:
                np.maximum(acc, h, out=acc)
        out.append(unmosaic(acc, n, s).astype(bool))
    return out


def box3(d: np.ndarray) -> np.ndarray:
    """3x3 mean of each ``(S, S)`` float32 patch of a stack (edge values approximate)."""
    n, s, _ = d.shape
    if n == 0:
        return d.copy()
    out = cv2.blur(mosaic(d), (3, 3), borderType=cv2.BORDER_CONSTANT)
    return unmosaic(out, n, s)


_GRIDS: dict[int, tuple] = {}


def patch_grid(half: int) -> tuple:
    """Offsets ``dy, dx`` (int), their float32 copies, monomials and border mask (cached)."""
    g = _GRIDS.get(half)
    if g is None:
        off = np.arange(-half, half + 1)
        dy, dx = np.meshgrid(off, off, indexing="ij")
        dxf, dyf = dx.astype(np.float32), dy.astype(np.float32)
        edge = (np.abs(dx) == half) | (np.abs(dy) == half)
        g = (dy, dx, dxf, dyf, _monomials(dxf, dyf), edge)
        for a in g:
            a.flags.writeable = False
        _GRIDS[half] = g
    return g


#: Exponents (i, j) of the monomials; the first six are the quadratic basis 1, x, y, xx, xy, yy.
MONO = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3),
         (4, 0), (3, 1), (2, 2), (1, 3), (0, 4)]
MONO_INDEX = {e: k for k, e in enumerate(MONO)}


def _monomials(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """``(S*S, 15)`` float32: ``x^i y^j`` for ``i + j <= 4`` in the order of :data:`MONO`."""
    x, y = dx.ravel().astype(np.float64), dy.ravel().astype(np.float64)
    return np.stack([x ** i * y ** j for i, j in MONO], axis=1).astype(np.float32)


@dataclass
class Patches:
    """Square patches around candidate pixels, possibly from several pyramid levels.

    Attributes
    ----------
    pu : uint8 (N, S, S)
        Signed image values (blobs bright).
    bad : bool (N, S, S)
        Pixels to ignore: outside the image or masked by the user.
    sat : bool (N, S, S)
        Saturated pixels of the original image (white blobs).
    half : int
        Patch half size (``S = 2 half + 1``).
    """

    pu: np.ndarray
    bad: np.ndarray
    sat: np.ndarray
    half: int

    def __len__(self) -> int:
        return len(self.pu)

    @classmethod
    def concat(cls, parts: list["Patches"]) -> "Patches":
        """One stack from patch stacks of equal half size."""
        if len(parts) == 1:
            return parts[0]
        return cls(np.concatenate([q.pu for q in parts]), np.concatenate([q.bad for q in parts]),
                   np.concatenate([q.sat for q in parts]), parts[0].half)


def extract_patches(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, half: int, *,
                    bad: np.ndarray | None = None, saturated: tuple[int, int] | None = None,
                    compiled: bool = True) -> Patches:
    """Patches of ``img`` (uint8 (H, W)) centred on pixels ``cx, cy`` (int (N,)).

    Patches crossing the image border are clamped and their outside pixels marked bad;
    ``bad`` (bool (H, W)) adds the user's mask; ``saturated`` is the value range ``(lo, hi)``
    of saturated pixels (white blobs), or None. ``compiled``: one call of
    :func:`carapost.core.blob_kernels.patch_step` (the same patches), else numpy indexing.
    """
    if compiled:
        from .blob_kernels import patch_step

        m = np.zeros((0, 0), bool) if bad is None else np.ascontiguousarray(bad, bool)
        lo, hi = (1, 0) if saturated is None else (int(saturated[0]), int(saturated[1]))
        pu, badp, satp = patch_step(np.ascontiguousarray(img), np.asarray(cx, np.int64), np.asarray(cy, np.int64),
                                    int(half), m, lo, hi)
        return Patches(pu, badp, satp, half)
    H, W = img.shape
    n = len(cx)
    S = 2 * half + 1
    dy, dx = patch_grid(half)[:2]
    inside = (cx >= half) & (cx < W - half) & (cy >= half) & (cy < H - half)
    flat_idx = ((cy * W + cx)[:, None, None] + (dy * W + dx)[None]).astype(np.intp)
    outside = np.zeros((n, S, S), bool)
    if not inside.all():
        e = np.flatnonzero(~inside)
        rows = cy[e, None, None] + dy[None]
        cols = cx[e, None, None] + dx[None]
        outside[e] = (rows < 0) | (rows >= H) | (cols < 0) | (cols >= W)
        flat_idx[e] = np.clip(rows, 0, H - 1) * W + np.clip(cols, 0, W - 1)
    pu = img.ravel()[flat_idx]
    badp = outside if bad is None else outside | bad.ravel()[flat_idx]
    if saturated is None:
        satp = np.zeros_like(outside)
    else:
        satp = (pu >= saturated[0]) & (pu <= saturated[1]) & ~outside
    return Patches(pu, badp, satp, half)
