"""Sub-pixel template matching for the Target Tracker.

A *pattern* (the Target Tracker's blue box) is cut from a keyframe image around the keyed
position; in another frame it is compared, by normalised cross-correlation (OpenCV
``matchTemplate`` with ``TM_CCOEFF_NORMED``), with every placement inside the *search* window
(the green cross). The best placement is refined to sub-pixel precision by fitting a parabola
through the score peak in x and in y, then re-sampling the window (bilinear) centred on the new
estimate and fitting again, until the correction is below a hundredth of a pixel. Re-centring
removes the "pixel locking" bias of a single parabola fit: at the fixed point the peak is
symmetric, whatever its shape.

Coordinates are raw pixels, centre of the top-left pixel at ``(0, 0)`` (OpenCV's convention,
so ``cv2.getRectSubPix`` is used without a half-pixel shift). Boxes are ``(x0, y0, x1, y1)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BoxGeometry", "box_geometry", "cut_patch", "subpixel_peak", "Match", "locate", "MIN_TEMPLATE_STD"]

#: Patterns whose grey levels vary less than this (standard deviation) cannot be matched.
MIN_TEMPLATE_STD = 0.5


@dataclass(frozen=True)
class BoxGeometry:
    """A box relative to a tracked position, as whole-pixel patch sizes.

    Attributes
    ----------
    size : tuple of int
        ``(width, height)`` of the patch, odd, at least 3.
    offset : array (2,)
        Box centre minus the tracked position, px.
    """

    size: tuple[int, int]
    offset: np.ndarray


def _odd(extent: float) -> int:
    n = int(round(float(extent)))
    return max(3, n + 1 if n % 2 == 0 else n)


def box_geometry(box_rel: np.ndarray) -> BoxGeometry:
    """Patch size and centre offset of a box ``(x0, y0, x1, y1)`` given relative to the position.

    Raises
    ------
    ValueError
        If the box is not finite or has ``x1 <= x0`` or ``y1 <= y0``.
    """
    b = np.asarray(box_rel, dtype=float).reshape(4)
    if not np.isfinite(b).all() or b[2] <= b[0] or b[3] <= b[1]:
        raise ValueError(f"a box must be finite with x0 < x1 and y0 < y1, got {b.tolist()}")
    return BoxGeometry((_odd(b[2] - b[0]), _odd(b[3] - b[1])), np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2]))


def cut_patch(image: np.ndarray, centre: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A ``(height, width)`` float32 patch of ``image`` centred on the sub-pixel ``centre``.

    Bilinear interpolation; pixels outside the image repeat the border (``cv2.getRectSubPix``).

    Parameters
    ----------
    image : array (H, W)
        uint8 or float32 grey levels.
    centre : array (2,)
        Patch centre, raw px.
    size : tuple of int
        ``(width, height)``.
    """
    cx, cy = float(centre[0]), float(centre[1])
    return cv2.getRectSubPix(image, (int(size[0]), int(size[1])), (cx, cy), patchType=cv2.CV_32F)


def subpixel_peak(score: np.ndarray, iy: int, ix: int) -> tuple[float, float, float]:
    """Sub-pixel offset ``(dx, dy)`` and value of the peak of ``score`` near ``(iy, ix)``.

    A parabola through three samples in each direction; an axis where the peak lies on the border
    (or the samples are not concave) gets no correction. Offsets are clipped to half a pixel.
    """
    h, w = score.shape
    v = float(score[iy, ix])
    dx = dy = 0.0
    value = v
    if 0 < ix < w - 1:
        a, c = float(score[iy, ix - 1]), float(score[iy, ix + 1])
        den = a - 2.0 * v + c
        if den < 0:
            dx = min(0.5, max(-0.5, 0.5 * (a - c) / den))
            value = max(value, v - 0.25 * (a - c) * dx)
    if 0 < iy < h - 1:
        a, c = float(score[iy - 1, ix]), float(score[iy + 1, ix])
        den = a - 2.0 * v + c
        if den < 0:
            dy = min(0.5, max(-0.5, 0.5 * (a - c) / den))
            value = max(value, v - 0.25 * (a - c) * dy)
    return dx, dy, value


@dataclass(frozen=True)
class Match:
    """Result of :func:`locate`.

    Attributes
    ----------
    centre : array (2,)
        Best placement of the pattern's centre, raw px.
    scores : array (T,)
        Normalised cross-correlation of each template at ``centre`` (-1..1).
    score : float
        The weighted sum of ``scores`` (the quantity that was maximised).
    """

    centre: np.ndarray
    scores: np.ndarray
    score: float


def _score_maps(window: np.ndarray, templates: Sequence[np.ndarray]) -> np.ndarray:
    return np.stack([cv2.matchTemplate(window, t, cv2.TM_CCOEFF_NORMED) for t in templates])


def locate(image: np.ndarray, templates: Sequence[np.ndarray], weights: Sequence[float], *,
           window_centre: np.ndarray, window_size: tuple[int, int], iterations: int = 4,
           tolerance: float = 0.01) -> Match:
    """Find where templates match best inside a search window, to sub-pixel precision.

    Parameters
    ----------
    image : array (H, W)
        uint8 or float32 grey levels of the frame searched.
    templates : sequence of T arrays (h, w) float32
        Patterns of the same odd size (e.g. the previous and the next keyframe's patch).
    weights : sequence of T floats
        Weight of each template's score map in the combined map (sum 1).
    window_centre : array (2,)
        Centre of the search window, raw px (sub-pixel allowed).
    window_size : tuple of int
        ``(width, height)`` of the search window, odd, at least the template size + 2.
    iterations : int
        Maximum number of re-centring refinements.
    tolerance : float
        Stop refining when the correction is below this, px.

    Returns
    -------
    Match
        ``centre`` is where the *template centre* lies in the image.

    Raises
    ------
    ValueError
        If the templates differ in size or the window is too small for them.
    """
    if not templates:
        raise ValueError("locate needs at least one template")
    th, tw = templates[0].shape
    if any(t.shape != (th, tw) for t in templates):
        raise ValueError("all templates must have the same size")
    ww, wh = int(window_size[0]), int(window_size[1])
    if ww < tw + 2 or wh < th + 2:
        raise ValueError(f"search window {ww}x{wh} px must exceed the pattern {tw}x{th} px by 2 px")
    wts = np.asarray(weights, dtype=np.float64).reshape(-1, 1, 1)
    centre0 = np.asarray(window_centre, dtype=float)
    maps = _score_maps(cut_patch(image, centre0, (ww, wh)), templates)
    comb = (wts * maps).sum(0)
    iy, ix = np.unravel_index(int(np.argmax(comb)), comb.shape)
    dx, dy, _ = subpixel_peak(comb, int(iy), int(ix))
    mh, mw = comb.shape
    c = centre0 + np.array([ix - (mw - 1) / 2 + dx, iy - (mh - 1) / 2 + dy])
    scores = maps[:, iy, ix].astype(float)
    # Re-centre a window of the template size + 1 px on each side on the estimate and refit.
    for _ in range(max(0, iterations)):
        m3 = _score_maps(cut_patch(image, c, (tw + 2, th + 2)), templates)
        comb3 = (wts * m3).sum(0)
        jy, jx = np.unravel_index(int(np.argmax(comb3)), comb3.shape)
        scores = m3[:, jy, jx].astype(float)
        if (jy, jx) != (1, 1):
            c = c + np.array([jx - 1.0, jy - 1.0])
            continue
        dx, dy, _ = subpixel_peak(comb3, 1, 1)
        c = c + np.array([dx, dy])
        if abs(dx) < tolerance and abs(dy) < tolerance:
            break
    return Match(c, scores, float((wts.ravel() * scores).sum()))
