"""Context features of fitted blobs: what surrounds a blob at about twice its size.

Eye corners, nostrils, pupils, lip corners and eyebrows make blob-like fits; what tells them
from a painted dot is the structure around them (a dark eye beside an eye corner, an iris
round a pupil, a band running through a brow). :func:`context_ring` samples two rings round
every fitted ellipse and reduces them to the classifier's ``ctx_*`` features
(``carapost/core/blob_score.py``).
"""

from __future__ import annotations

import cv2
import numpy as np

from .blob_kernels_dense import context_points

__all__ = ["context_ring", "sample_bilinear"]


#: Samples on the context ring, and its size: the fitted ellipse scaled by 2 and grown by
#: 1.5 px (beyond the local background band: the wider structure the blob sits in).
_CTX_SAMPLES = 16
_CTX_SCALE, _CTX_GROW = 2.0, 1.5
#: Scale of the inner context ring (just outside the blob's edge: a pupil's iris).
_CTX_INNER_SCALE = 1.3
#: Cosine and sine of the samples' angles.
_COS_T = np.cos(np.arange(_CTX_SAMPLES) * (2.0 * np.pi / _CTX_SAMPLES))
_SIN_T = np.sin(np.arange(_CTX_SAMPLES) * (2.0 * np.pi / _CTX_SAMPLES))


_SAMPLE_ROW = 1024  # cv2.remap refuses maps of 32767 or more rows or columns: samples go in rows of this length


def sample_bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at float32 pixel positions ``x, y`` ``(N,)`` -> float64 ``(N,)``."""
    n = len(x)
    pad = -n % _SAMPLE_ROW
    mx = np.concatenate([x, np.zeros(pad, np.float32)]).reshape(-1, _SAMPLE_ROW)
    my = np.concatenate([y, np.zeros(pad, np.float32)]).reshape(-1, _SAMPLE_ROW)
    out = np.empty(mx.shape, img.dtype)
    for r in range(0, len(mx), 16384):                      # rows too stay below remap's limit
        out[r:r + 16384] = cv2.remap(img, mx[r:r + 16384], my[r:r + 16384], cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].astype(np.float64)


def context_ring(ctx_img: np.ndarray, out: dict[str, np.ndarray], polarity: int, compiled: bool = True) -> None:
    """Context of each fitted blob at about twice its size, in units of its contrast.

    Samples the signed, 3x3-smoothed image ``ctx_img`` (blobs bright) at :data:`_CTX_SAMPLES`
    points of the fitted ellipse scaled by ``_CTX_SCALE`` and grown by ``_CTX_GROW`` px,
    relative to the local background, over the contrast. Sets ``out["ctx_max"]`` (the
    darkest direction: an eye or a nostril beside an eye corner), ``out["ctx_mean"]`` (a
    pupil inside its iris) and ``out["ctx_line"]`` (the larger of the two opposite samples'
    minimum: a line or band through the blob, as at a lip corner or on an eyebrow), and
    ``out["ctx_inner"]``, the mean on a second ring at ``_CTX_INNER_SCALE`` (a pupil's iris),
    ``(N,)``. ``compiled``: the sample points from
    :func:`carapost.core.blob_kernels_dense.context_points` (the same points), else numpy.
    """
    n = len(out["x"])
    if n == 0:
        for k in ("ctx_max", "ctx_mean", "ctx_line", "ctx_inner"):
            out[k] = np.zeros(0)
        return
    H, W = ctx_img.shape
    if compiled:
        sx, sy = context_points(out["x"], out["y"], out["major"], out["minor"], np.cos(out["angle"]),
                                np.sin(out["angle"]), _COS_T, _SIN_T, (_CTX_SCALE, _CTX_INNER_SCALE), _CTX_GROW, (H, W))
    else:
        maj = np.nan_to_num(out["major"])[:, None]
        mnr = np.nan_to_num(out["minor"])[:, None]
        u = np.concatenate([(_CTX_SCALE * maj + _CTX_GROW) * _COS_T[None],
                            (_CTX_INNER_SCALE * maj + _CTX_GROW) * _COS_T[None]], axis=1)
        v = np.concatenate([(_CTX_SCALE * mnr + _CTX_GROW) * _SIN_T[None],
                            (_CTX_INNER_SCALE * mnr + _CTX_GROW) * _SIN_T[None]], axis=1)
        ca, sa = np.cos(out["angle"])[:, None], np.sin(out["angle"])[:, None]
        sx = np.clip(np.nan_to_num(out["x"])[:, None] + u * ca - v * sa, 0, W - 1).astype(np.float32)
        sy = np.clip(np.nan_to_num(out["y"])[:, None] + u * sa + v * ca, 0, H - 1).astype(np.float32)
    vals = sample_bilinear(ctx_img, sx.ravel(), sy.ravel()).reshape(n, 2 * _CTX_SAMPLES)
    bg = out["background"] if polarity > 0 else 255.0 - out["background"]
    sig = (vals - bg[:, None]) / np.maximum(out["contrast"], 1.0)[:, None]
    half = _CTX_SAMPLES // 2
    out["ctx_max"] = sig[:, :_CTX_SAMPLES].max(axis=1)
    out["ctx_mean"] = sig[:, :_CTX_SAMPLES].mean(axis=1)
    out["ctx_line"] = np.minimum(sig[:, :half], sig[:, half:_CTX_SAMPLES]).max(axis=1)
    out["ctx_inner"] = sig[:, _CTX_SAMPLES:].mean(axis=1)
