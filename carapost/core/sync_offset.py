"""Frame offset between two videos from epipolar agreement of moving markers.

Two calibrated, static cameras film the same moving markers. If camera b's frame ``f + k``
was exposed at the same time as camera a's frame ``f``, a marker's detections in those frames
lie on each other's epipolar lines; at other offsets a moving marker does not. Counting, for
each candidate offset ``k``, the detection pairs within a small epipolar distance over many
frames gives a curve that peaks at the true offset, above a floor of coincidences and static
points (which agree at every offset). A parabola through the peak and its neighbours gives a
sub-frame estimate.

No peak (``contrast`` near 1) means no offset in the range makes the pair agree: the
calibration, not the timing, is what is wrong for that pair.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from carapost.core.camera import Intrinsics, symmetric_epipolar_distance

__all__ = ["OffsetScores", "epipolar_offset_scores"]


@dataclass(frozen=True)
class OffsetScores:
    """Result of :func:`epipolar_offset_scores`.

    Attributes
    ----------
    offsets : array (K,) int
        Candidate offsets ``k`` (camera b's frame ``f + k`` against camera a's frame ``f``).
    counts : array (K,) int
        Detection pairs within the epipolar tolerance, summed over the frames.
    best : int
        The offset with the largest count.
    subframe : float
        ``best`` refined by a parabola through its neighbours' counts (``best`` at the ends).
    contrast : float
        Largest count over the median count: near 1, no offset stands out.
    """

    offsets: np.ndarray
    counts: np.ndarray
    best: int
    subframe: float
    contrast: float


def epipolar_offset_scores(xy_a: Sequence[np.ndarray], xy_b: Sequence[np.ndarray],
                           intr_a: Intrinsics, R_a: np.ndarray, t_a: np.ndarray,
                           intr_b: Intrinsics, R_b: np.ndarray, t_b: np.ndarray, *,
                           offsets: Sequence[int] = range(-10, 11), frames: Sequence[int] | None = None,
                           max_epipolar_px: float = 2.0) -> OffsetScores:
    """Score candidate frame offsets of camera b against camera a.

    Parameters
    ----------
    xy_a, xy_b : sequences of arrays (n_f, 2)
        Raw-pixel detections per frame of each camera (frame ``f`` is ``xy_a[f]``).
    intr_a, R_a, t_a, intr_b, R_b, t_b
        The two cameras (world-to-camera poses, mm).
    offsets : sequence of int
        Candidate offsets ``k``.
    frames : sequence of int, optional
        Camera a's frames used; by default every frame ``f`` for which ``f + k`` exists in
        camera b for all ``k`` (the same frames for every offset, so counts compare).
    max_epipolar_px : float
        A pair counts when its symmetric epipolar distance is below this.

    Returns
    -------
    OffsetScores

    Raises
    ------
    ValueError
        No frame of camera a has all its offset frames in camera b.
    """
    offsets = np.asarray(list(offsets), dtype=int)
    if frames is None:
        lo, hi = max(0, -offsets.min()), min(len(xy_a), len(xy_b) - offsets.max())
        frames = range(lo, hi)
    frames = [f for f in frames if 0 <= f < len(xy_a) and 0 <= f + offsets.min() and f + offsets.max() < len(xy_b)]
    if not frames:
        raise ValueError(f"epipolar_offset_scores: no frame of camera a ({len(xy_a)} frames) has all offsets "
                         f"{offsets.min()}..{offsets.max()} in camera b ({len(xy_b)} frames)")
    counts = np.zeros(len(offsets), dtype=int)
    for f in frames:
        a = np.asarray(xy_a[f], float).reshape(-1, 2)
        if len(a) == 0:
            continue
        for i, k in enumerate(offsets):
            b = np.asarray(xy_b[f + k], float).reshape(-1, 2)
            if len(b):
                d = symmetric_epipolar_distance(a[:, None], b[None], intr_a, R_a, t_a, intr_b, R_b, t_b)
                counts[i] += int(np.count_nonzero(d < max_epipolar_px))
    j = int(np.argmax(counts))
    sub = float(offsets[j])
    if 0 < j < len(counts) - 1 and offsets[j + 1] - offsets[j - 1] == 2:
        c0, c1, c2 = counts[j - 1:j + 2].astype(float)
        den = c0 - 2 * c1 + c2
        if den < 0:
            sub += float(np.clip(0.5 * (c0 - c2) / den, -0.5, 0.5))
    med = float(np.median(counts))
    return OffsetScores(offsets=offsets, counts=counts, best=int(offsets[j]), subframe=sub,
                        contrast=float(counts[j] / med) if med > 0 else float("inf"))
