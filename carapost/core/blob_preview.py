"""The blob preview's per-pixel probability map (the guide's blob preview while tuning).

A dense map agreeing with :func:`carapost.core.blobs.detect_blobs`: a detection's centre
pixel carries its score, and no pixel exceeds the threshold without a detection nearby.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..model.detections import BLACK, WHITE
from ..model.params import BlobParameters
from . import blob_score
from .blobs import check_image, analyse_blobs

__all__ = ["blob_probability"]


def blob_probability(image: np.ndarray, params: BlobParameters, polarity: int, *,
                     mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel probability that a pixel is a blob centre, for the blob preview.

    The dense model (normalised response only) gives every pixel a probability; around each
    candidate that was fitted, the map is capped by the candidate's final probability (0 for a
    rejected candidate), and the core of each detection (half its minor axis) carries its
    score. So the map agrees with :func:`detect_blobs`: a detection's centre pixel carries its
    score, and no pixel exceeds the threshold without a detection nearby.

    Parameters
    ----------
    image : uint8 (H, W)
    params : BlobParameters
        Radius range, adaptive flag and threshold (which decides whether the gate is used,
        :func:`carapost.core.blob_score.gate_min_threshold`) of the ``polarity`` are used.
    polarity : int
        ``WHITE`` (+1) or ``BLACK`` (-1).
    mask : bool (H, W), optional

    Returns
    -------
    float32 (H, W)
        Probabilities in 0..1 (0 in masked pixels).
    """
    image, mask = check_image(image, mask)
    if polarity == WHITE:
        rmin, rmax, thr = params.white_min_radius, params.white_max_radius, params.white_threshold
    elif polarity == BLACK:
        rmin, rmax, thr = params.black_min_radius, params.black_max_radius, params.black_threshold
    else:
        raise ValueError(f"polarity must be {WHITE} (white) or {BLACK} (black), got {polarity}")
    an = analyse_blobs(image, polarity, min_radius=rmin, max_radius=rmax,
                       adaptive=params.adaptive_background, mask=mask,
                       gate=thr >= blob_score.gate_min_threshold())
    H, W = image.shape
    prob = np.zeros((H, W), np.float32)
    for lv in an.levels:
        p = blob_score.dense_probability(lv.snr)
        if p.shape != (H, W):
            p = cv2.resize(p, (W, H), interpolation=cv2.INTER_LINEAR)
        np.maximum(prob, p, out=prob)
    # Around every fitted candidate the map is capped by its final score (0 if rejected); the
    # core of each detection (half its minor axis) carries its score.
    if len(an.x):
        fin = np.isfinite(an.x) & np.isfinite(an.y)
        cap = np.where(an.ok, an.score, 0.0)
        rad = np.clip(np.where(an.ok, an.major, np.maximum(an.major, 2.0)), 1.0, 64.0)
        _paint_discs(prob, an.x[fin], an.y[fin], rad[fin], cap[fin], np.minimum)
        det = an.ok & fin
        core = np.clip(0.5 * an.minor[det], 1.0, 64.0)
        _paint_discs(prob, an.x[det], an.y[det], core, an.score[det], np.maximum)
    if mask is not None:
        prob[mask] = 0.0
    return prob


def _paint_discs(prob: np.ndarray, x: np.ndarray, y: np.ndarray, r: np.ndarray, value: np.ndarray,
                 op: np.ufunc) -> None:
    """``prob = op(prob, value_i)`` inside the disc of radius ``r_i`` around each ``(x_i, y_i)``."""
    H, W = prob.shape
    rc = np.ceil(r).astype(int)
    for R in np.unique(rc):
        sel = rc == R
        off = np.arange(-R, R + 1)
        oy, ox = np.meshgrid(off, off, indexing="ij")
        disc = (ox * ox + oy * oy) <= R * R
        oy, ox = oy[disc], ox[disc]
        rows = np.rint(y[sel]).astype(int)[:, None] + oy[None]
        cols = np.rint(x[sel]).astype(int)[:, None] + ox[None]
        inside = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
        vals = np.broadcast_to(value[sel, None], rows.shape).astype(np.float32)
        op.at(prob, (rows[inside], cols[inside]), vals[inside])
