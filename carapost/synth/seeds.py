"""Seed correspondences for brim solving and 3D initialization, from the ground truth.

The structure (raw pixels, cameras keyed by channel as strings)::

    {"frame": 0,
     "brim": [{"brim_index": 3, "xy": {"0": [612.4, 88.1], "1": [...], ...}}, ...],
     "face": [{"name": "Nose_Tip", "xy": {"0": [640.2, 401.7], "2": [...]}}, ...]}
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from .take import SynthTake

__all__ = ["seeds_for"]


def _spread(points: np.ndarray, n: int, first: int) -> list[int]:
    """Indices of ``n`` points chosen by farthest-point sampling, starting at ``first``."""
    chosen = [first]
    d = np.linalg.norm(points - points[first], axis=1)
    while len(chosen) < min(n, len(points)):
        k = int(np.argmax(d))
        if d[k] <= 0:
            break
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(points - points[k], axis=1))
    return chosen


def _xy(xy: np.ndarray, vis: np.ndarray) -> dict[str, list[float]]:
    return {str(c): [round(float(xy[c, 0]), 3), round(float(xy[c, 1]), 3)] for c in np.flatnonzero(vis)}


def seeds_for(synth: "SynthTake", frame: int = 0, n_face: int = 8, min_brim: int = 4,
              n_brim: int = 6) -> dict:
    """Hand-match-like seeds of a synthetic take's frame.

    Parameters
    ----------
    synth : SynthTake
    frame : int
    n_face : int
        Face markers to seed (5..10), spread over the face; each is visible in both cameras
        of at least one caddy (markers visible in all cameras are preferred).
    min_brim : int
        Fewest brim dots; dots visible in every camera are chosen, spread over the card.
    n_brim : int
        Brim dots to seed when more than ``min_brim`` are visible everywhere.

    Returns
    -------
    dict
        ``{"frame", "brim": [{"brim_index", "xy"}], "face": [{"name", "xy"}]}`` with raw-pixel
        positions keyed by camera channel (as a string) for the cameras seeing the point.

    Raises
    ------
    ValueError
        If the frame is out of range or not enough brim dots / face markers are visible.
    """
    tr = synth.truth
    if not 0 <= frame < tr.n_frames:
        raise ValueError(f"frame must be within 0..{tr.n_frames - 1}, got {frame}")
    if not 1 <= n_face <= len(tr.names):
        raise ValueError(f"n_face must be within 1..{len(tr.names)}, got {n_face}")
    caddies = synth.caddies
    # brim: dots visible in every camera, spread over the card
    bvis = tr.brim_visible[frame]
    full = np.flatnonzero(bvis.all(axis=1))
    if len(full) < min_brim:
        raise ValueError(f"only {len(full)} brim dots are visible in every camera at frame {frame}; "
                         f"need {min_brim}")
    pts = tr.brim_xyz[full, :2]
    first = int(np.argmin(pts[:, 0] + pts[:, 1]))
    bsel = sorted(full[_spread(pts, max(min_brim, n_brim), first)])
    brim = [{"brim_index": int(b), "xy": _xy(tr.brim_xy[frame, b], bvis[b])} for b in bsel]
    # face: markers seen by both cameras of a caddy, preferring all cameras
    vis = tr.visible[frame]
    caddy_ok = np.zeros(len(tr.names), bool)
    for a, b in caddies:
        caddy_ok |= vis[:, a] & vis[:, b]
    all_ok = vis.all(axis=1)
    pool = np.flatnonzero(all_ok)
    if len(pool) < n_face:
        pool = np.flatnonzero(caddy_ok)
    if len(pool) < n_face:
        raise ValueError(f"only {len(pool)} face markers are visible in both cameras of a caddy at frame "
                         f"{frame}; need {n_face}")
    uv = tr.marker_uv[pool]
    names = tr.names
    start = names.index("Nose_Tip") if "Nose_Tip" in names and names.index("Nose_Tip") in pool else int(pool[0])
    fsel = pool[_spread(uv, n_face, int(np.flatnonzero(pool == start)[0]))]
    face = [{"name": names[m], "xy": _xy(tr.xy[frame, m], vis[m])} for m in fsel]
    return {"frame": int(frame), "brim": brim, "face": face}
