"""Candidate grouping of the blob detector: one candidate per blob top.

The dense stage (:mod:`carapost.core.blob_candidates`) finds a blob at several scales and
pyramid levels; :func:`representatives` climbs every candidate to its peak and keeps one per
peak (and one per plateau of close peaks), which :mod:`carapost.core.blobs` then fits.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .blob_candidates import Candidates, climb, refine_level

__all__ = ["representatives", "MERGE_PLATEAUS"]

#: Merge representatives whose peaks are on one plateau (see :func:`representatives`).
MERGE_PLATEAUS = True


def representatives(pyr: list[np.ndarray], noise_of: Callable[[np.ndarray], np.ndarray], cand: Candidates,
                    c75: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One candidate per blob top.

    Every candidate climbs to its peak on its refinement level; candidates that reach the
    same peak pixel are one group. The representative is the smallest-scale member
    whose ring contrast is at least 0.8 of the group's best (a scale much smaller than the
    blob has its ring inside it and little contrast; a much bigger one dilutes its centre).
    Representatives whose peaks are very close (one plateau) are then merged.

    ``pyr`` is the pyramid of the signed image, ``noise_of`` gives the pixel noise (grey levels)
    of pyramid levels (int (M,) -> float64 (M,)), ``c75`` the candidates' ring contrast (N,).
    Returns the representatives' indices, their peak pixels ``px, py``, level and radius
    estimate (full-resolution px).
    """
    n = len(cand)
    if n == 0:
        z = np.zeros(0, np.int64)
        return z, z, z, z, np.zeros(0)
    ref = np.minimum(refine_level(cand.radius), len(pyr) - 1)
    px = np.zeros(n, np.int64)
    py = np.zeros(n, np.int64)
    top = np.zeros(n)
    for k in np.unique(ref):
        sel = np.flatnonzero(ref == k)
        sh = cand.level[sel] - k
        x = np.where(sh >= 0, cand.x[sel] << np.maximum(sh, 0), cand.x[sel] >> np.maximum(-sh, 0))
        y = np.where(sh >= 0, cand.y[sel] << np.maximum(sh, 0), cand.y[sel] >> np.maximum(-sh, 0))
        px[sel], py[sel], top[sel] = climb(pyr[int(k)], x, y)
    # Same refinement level and same peak pixel: one group.
    key = (ref * (1 << 20) + py) * (1 << 20) + px
    _, label = np.unique(key, return_inverse=True)
    best = np.zeros(label.max() + 1)
    np.maximum.at(best, label, c75)
    eligible = c75 >= 0.8 * best[label]
    # Smallest radius among the eligible members of each group (ties: highest contrast).
    order = np.lexsort((-c75, cand.radius, ~eligible, label))
    first = np.ones(n, bool)
    first[1:] = label[order][1:] != label[order][:-1]
    rep = np.sort(order[first])
    # Peaks of one plateau (a flat or clipped dot top, noise): representatives whose peaks
    # are closer than half the smaller radius (at least 2 px) are one blob; the one on the
    # higher top stays (a dot on a band is above the band's own peaks); when the tops are
    # equal within the noise (one plateau) it takes the better scale estimate.
    radius = cand.radius.copy()
    if len(rep) > 1 and MERGE_PLATEAUS:
        from scipy.spatial import cKDTree

        s = 2.0 ** ref[rep]
        pts = np.stack([px[rep] * s, py[rep] * s], axis=1)
        lim = np.maximum(2.0, 0.5 * cand.radius[rep])
        pairs = cKDTree(pts).query_pairs(r=float(lim.max()), output_type="ndarray")
        if len(pairs):
            i, j = pairs[:, 0], pairs[:, 1]
            ri, rj = cand.radius[rep[i]], cand.radius[rep[j]]
            close = (np.linalg.norm(pts[i] - pts[j], axis=1) <= np.minimum(lim[i], lim[j])) & \
                (np.maximum(ri, rj) <= 1.7 * np.minimum(ri, rj))
            i, j = i[close], j[close]
            win_i = top[rep[i]] >= top[rep[j]]
            loser, winner = np.where(win_i, j, i), np.where(win_i, i, j)
            # On one plateau (tops equal within the noise) the better scale estimate (higher
            # ring contrast) gives the radius.
            tol = 4.0 * noise_of(ref[rep[winner]]) / 3.0 + 2.0
            same = (top[rep[winner]] - top[rep[loser]] <= tol) & (c75[rep[loser]] > c75[rep[winner]])
            radius[rep[winner[same]]] = cand.radius[rep[loser[same]]]
            keep = np.ones(len(rep), bool)
            keep[loser] = False
            rep = rep[keep]
    return rep, px[rep], py[rep], ref[rep], radius[rep]
