"""How far an upper-eyelid marker travels in a blink, from the eye's geometry (no ROM needed).

The take never shows the lid more than part-way closed (the marker is lost in the lashes and
the fold), and the part it shows fits a shallow closure with a long hold as well as a deep one
with a short hold: the pulse fit of :mod:`carapost.core.gapfill_blink` leaves the depth
undetermined (its residual changes by < 0.01 mm between depths of 5 and 12 mm on the
synthetic takes). What fixes the depth is where the closed lid ends up, and that is anatomy:

**Model** (a complete blink; the lower lid does not move — it moves ~1 mm, mostly nasally,
Doane 1980, Am J Ophthalmol 89:507):

* the upper lid margin comes down until it meets the lower lid margin: it travels the
  palpebral fissure height ``H``;
* a lid marker sits on the tarsal skin at ``a`` mm from its lid margin (upper marker above the
  upper margin, lower marker below the lower margin); the tarsal plate (the upper one about
  10 mm high at its centre, Gray's Anatomy 41st ed.) is rigid, so the upper marker travels with
  its margin, along the closing direction ``v`` seen at the start and end
  of every blink;
* so, measured along ``v`` in the take's open frames, the upper-lid marker is
  ``S = a + H + a`` from the lower-lid marker it closes onto, and the closing depth is
  ``D = S - 2 a`` (the closed markers are ``2 a`` apart, the margins touching between them).

**Priors** (literature and marker placement; stated, not fitted to any take):

* :data:`LID_MARKER_OFFSET_MM` ``a = 2.5`` mm — eyelid markers are placed on the tarsal skin
  just clear of the lashes (a placement convention of the marker layout; change it to the
  layout's own value);
* :data:`PALPEBRAL_FISSURE_MM` ``H = 9.7`` mm — mean vertical palpebral aperture in primary
  gaze, 9.7 ± 1.2 mm (Read, Collins, Carney & Iskander 2006, Optom Vis Sci 83:715; normal
  range 8-11 mm). Used only when the marker set has no lower-lid marker: ``D = H``, and only
  for markers the caller names as upper eyelids (by label): a jaw or forehead marker whose gap
  happens to look like a blink has no lower lid either.

**The lower-lid marker** is found by geometry, not by name: using the median offset of every point
from the upper-lid marker over the take (in the marker's neighbourhood frame), it is the point
closest to the closing path ``p + s v`` ahead of the marker
(``0 < s <`` :data:`MAX_REACH_MM`, at most ``max(`` :data:`MAX_PERP_MM` ``, 0.3 s)`` off the path)
that does not blink itself (is seen while the marker is hidden). A geometry giving
``D >`` :data:`MAX_DEPTH_MM` is not an eye.

Array contract: ``xyz (F, P, 3)`` mm with NaN gaps; masks ``(F, P)`` bool; frames 0-based.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gapfill import neighbour_motion

__all__ = ["LID_MARKER_OFFSET_MM", "PALPEBRAL_FISSURE_MM", "MAX_DEPTH_MM", "MAX_REACH_MM", "MAX_PERP_MM", "LidGeometry",
           "lid_closing_depth"]

#: Prior: distance of an eyelid marker from its lid margin (each lid), mm.
LID_MARKER_OFFSET_MM = 2.5
#: Prior: vertical palpebral fissure height, mm (Read et al. 2006: 9.7 +- 1.2 mm).
PALPEBRAL_FISSURE_MM = 9.7
#: Plausibility: a lower-lid geometry giving a depth above this (the prior's mean + 3 SD) is
#: not an eye (a forehead or jaw marker whose gap looked like a blink), mm.
MAX_DEPTH_MM = PALPEBRAL_FISSURE_MM + 3 * 1.2
#: The lower-lid marker is at most this far ahead of the upper-lid marker along the closing
#: direction, mm (twice the largest normal fissure plus two marker offsets).
MAX_REACH_MM = 30.0
#: ... and at most ``max(MAX_PERP_MM, 0.3 s)`` off the closing path, mm.
MAX_PERP_MM = 3.0


@dataclass
class LidGeometry:
    """The closing geometry of one upper-lid marker.

    Attributes
    ----------
    point : int
        Upper-lid marker column.
    partner : int
        Column of the lower-lid marker it closes onto (-1: none found).
    separation_mm : float
        ``S``: median distance along the closing direction from the marker to the partner
        over the take's frames (NaN without a partner), mm.
    off_path_mm : float
        The partner's median distance from the closing path, mm (NaN without one).
    depth_mm : float
        The closing depth ``D``, mm.
    source : str
        ``"lower_lid"`` (``D = S - 2 a``) or ``"fissure_prior"`` (``D = H``).
    """

    point: int
    partner: int
    separation_mm: float
    off_path_mm: float
    depth_mm: float
    source: str


def lid_closing_depth(xyz: np.ndarray, known: np.ndarray, point: int, direction: np.ndarray, ref: int, *,
                      blink_frames: np.ndarray, rank_cost: np.ndarray | None = None, n_neighbours: int = 8,
                      marker_offset_mm: float = LID_MARKER_OFFSET_MM, fissure_mm: float = PALPEBRAL_FISSURE_MM,
                      max_frames: int = 400) -> LidGeometry:
    """The closing depth of an upper-lid marker from the eye's geometry (module doc).

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm, NaN where missing.
    known : bool array (F, P)
        Usable samples.
    point : int
        The upper-lid marker's column.
    direction : array (3,)
        Unit closing direction in the neighbourhood frame of frame ``ref``.
    ref : int
        Reference frame of ``direction`` (the marker is known there).
    blink_frames : int array
        Frames where the marker is hidden in a blink: the partner must be seen in most of them
        (a lid marker that blinks with it is not the lower lid).
    rank_cost, n_neighbours
        Neighbour ranking for the neighbourhood rotations (:func:`neighbour_motion`).
    marker_offset_mm, fissure_mm : float
        The priors ``a`` and ``H``.
    max_frames : int
        At most this many frames (evenly spread) are used for the median offsets.

    Returns
    -------
    LidGeometry
    """
    if not marker_offset_mm >= 0 or not fissure_mm > 0:
        raise ValueError(f"lid priors must be non-negative offset and positive fissure, got {marker_offset_mm}, "
                         f"{fissure_mm}")
    v = np.asarray(direction, dtype=float)
    v = v / np.linalg.norm(v)
    fr = np.flatnonzero(known[:, point])
    if len(fr) > max_frames:
        fr = fr[np.linspace(0, len(fr) - 1, max_frames).round().astype(int)]
    fallback = LidGeometry(int(point), -1, float("nan"), float("nan"), float(fissure_mm), "fissure_prior")
    if len(fr) == 0:
        return fallback
    _, rot, _ = neighbour_motion(xyz, known, np.full(len(fr), point), np.full(len(fr), ref), fr,
                                 n_neighbours=n_neighbours, rank_cost=rank_cost)
    d = xyz[fr] - xyz[fr, point][:, None]                      # (n, P, 3) world offsets
    d = np.einsum("nji,npj->npi", rot, d)                      # into the reference frame
    d[~known[fr]] = np.nan
    seen = known[fr].sum(0)
    with np.errstate(invalid="ignore"):
        med = np.nanmedian(np.where(seen[None, :, None] > 0, d, 0.0), axis=0)   # (P, 3)
    s = med @ v
    perp = np.linalg.norm(med - s[:, None] * v, axis=1)
    ok = (seen >= max(3, len(fr) // 4)) & (s > 0) & (s < MAX_REACH_MM) & (perp <= np.maximum(MAX_PERP_MM, 0.3 * s))
    ok[point] = False
    bf = np.asarray(blink_frames, dtype=np.int64)
    if len(bf):
        ok &= known[bf].mean(0) >= 0.5                         # the lower lid is seen while the upper one is hidden
    if not ok.any():
        return fallback
    q = int(np.flatnonzero(ok)[np.argmin(perp[ok])])
    depth = float(s[q] - 2.0 * marker_offset_mm)
    if not 0.0 < depth <= MAX_DEPTH_MM:
        return fallback                                        # no eye: nothing on the path is a lower lid
    return LidGeometry(int(point), q, float(s[q]), float(perp[q]), depth, "lower_lid")
