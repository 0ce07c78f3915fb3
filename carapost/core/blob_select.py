"""Duplicates and nested detections of one polarity (the last step of the blob detector,
:func:`carapost.core.blobs.analyse_blobs`): resolved by probability and contrast only, before
the user's threshold, so that raising the threshold only ever removes detections."""

from __future__ import annotations

import numpy as np

__all__ = ["unique_detections", "CONTAINER_SCORE"]

#: A fitted blob with at least this probability hides smaller, weaker-contrast detections
#: inside its ellipse (rim maxima and interior texture of big blobs).
CONTAINER_SCORE = 0.3


def _in_ellipse(px: np.ndarray, py: np.ndarray, out: dict[str, np.ndarray], j: np.ndarray,
                margin: float) -> np.ndarray:
    """Whether each point lies inside ellipse ``j`` grown by ``margin`` px."""
    dx = px - out["x"][j]
    dy = py - out["y"][j]
    c, s = np.cos(out["angle"][j]), np.sin(out["angle"][j])
    u = (dx * c + dy * s) / (out["major"][j] + margin)
    v = (-dx * s + dy * c) / (out["minor"][j] + margin)
    return u * u + v * v <= 1.0


def unique_detections(out: dict[str, np.ndarray], score: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Mask of fitted candidates kept after removing duplicates and nested detections.

    Two detections closer than ``max(1, minor/2)`` px are one blob: the more probable stays.
    A detection whose centre lies inside a bigger one's ellipse (grown by 0.5 px) is either a
    dot on a darker band (it has at least half the bigger one's contrast and is more probable:
    the bigger one is dropped) or a rim maximum / interior texture of the bigger blob (it is
    dropped when the bigger one is plausible, probability >= ``CONTAINER_SCORE``). The result
    does not depend on the user's threshold, so raising the threshold only ever removes
    detections.
    """
    from scipy.spatial import cKDTree

    keep = ok.copy()
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        return keep
    x, y, major, minor = out["x"], out["y"], out["major"], out["minor"]
    pts = np.stack([x[idx], y[idx]], axis=1)
    pairs = cKDTree(pts).query_pairs(r=float(major[idx].max()) + 0.5, output_type="ndarray")
    if len(pairs) == 0:
        return keep
    a, b = idx[pairs[:, 0]], idx[pairs[:, 1]]
    d = np.hypot(x[a] - x[b], y[a] - y[b])
    # Near-duplicates: the lower score loses.
    dup = d < np.maximum(1.0, 0.5 * np.minimum(minor[a], minor[b]))
    better_a = (score[a] > score[b]) | ((score[a] == score[b]) & (a < b))
    lose = np.where(better_a, b, a)[dup]
    # Nested: a smaller blob inside a bigger one. If it stands out from the bigger one (at
    # least half its contrast) and is more probable, it is a dot on a darker band (eyebrow,
    # lip line) and the band goes; otherwise it is a ripple of the bigger blob and goes.
    big_a = major[a] >= major[b]
    big, small = np.where(big_a, a, b), np.where(big_a, b, a)
    inside = ~dup & _in_ellipse(x[small], y[small], out, big, 0.5)
    contrast = out["contrast"]
    dot_on_band = inside & (contrast[small] >= 0.5 * contrast[big]) & (score[small] > score[big])
    ripple = inside & ~dot_on_band & (score[big] >= CONTAINER_SCORE)
    keep[big[dot_on_band]] = False
    keep[lose] = False
    keep[small[ripple]] = False
    return keep
