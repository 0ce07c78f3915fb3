"""Qt-free numpy helpers behind the views and the View menu's navigation commands.

Everything here is a pure function on the take's arrays (no Qt, no file I/O), vectorised over
frames and points, so the continuity chart of a 10,000-frame, 200-point take is computed in a
few milliseconds. Colour codes are small integers mapped to colours by the views.
"""

from __future__ import annotations

import numpy as np

from carapost.model.take import ObsSource

__all__ = [
    "GAP", "RED", "ORANGE", "YELLOW", "LIGHT_GREEN", "DARK_GREEN",
    "S_GAP", "S_BLOB", "S_PATCH", "S_KEYFRAME", "S_TARGET0", "N_TARGET_LEVELS",
    "continuity_codes", "sensor_codes", "reduce_columns", "CONTINUITY_PRIORITY", "SENSOR_PRIORITY",
    "gap_counts", "point_with_fewest_gaps", "next_gap_frame",
    "points_in_polygon", "ellipse_outlines", "circle_outlines",
]

# Overall continuity of a point (Continuity chart, Selected Point pane top bar).
GAP, RED, ORANGE, YELLOW, LIGHT_GREEN, DARK_GREEN = range(6)
# Per-sensor continuity.
S_GAP, S_BLOB, S_PATCH, S_KEYFRAME = 0, 1, 2, 3
S_TARGET0 = 8           #: first of the target-track quality levels (red ... green)
N_TARGET_LEVELS = 8

#: When many frames share one pixel column, the code with the highest priority is shown, so
#: a one-frame gap or a red frame stays visible however far the chart is zoomed out.
CONTINUITY_PRIORITY = np.array([5, 4, 3, 2, 1, 0], np.uint8)      # gap > red > ... > dark green
SENSOR_PRIORITY = np.zeros(S_TARGET0 + N_TARGET_LEVELS, np.uint8)
SENSOR_PRIORITY[[S_GAP, S_BLOB, S_PATCH, S_KEYFRAME]] = [N_TARGET_LEVELS + 2, 0, 1, N_TARGET_LEVELS + 3]
SENSOR_PRIORITY[S_TARGET0:] = np.arange(N_TARGET_LEVELS + 1, 1, -1)  # poor quality wins


def continuity_codes(xyz: np.ndarray, obs_xy: np.ndarray) -> np.ndarray:
    """Continuity colour of every point in every frame.

    Parameters
    ----------
    xyz : float array (F, P, 3)
        Point positions, mm (NaN = no 3D point).
    obs_xy : float array (F, P, C, 2)
        2D observations, raw px (NaN = none).

    Returns
    -------
    uint8 array (F, P)
        ``GAP`` where there is no 3D point; otherwise by the number of contributing cameras:
        0 ``RED`` (fully interpolated), 1 ``ORANGE``, 2 ``YELLOW``, 3 ``LIGHT_GREEN``,
        4 or more ``DARK_GREEN``.
    """
    has = np.isfinite(xyz).all(-1)
    n = np.isfinite(obs_xy[..., 0]).sum(-1)
    codes = (RED + np.minimum(n, 4)).astype(np.uint8)
    codes[~has] = GAP
    return codes


def sensor_codes(obs_src: np.ndarray, obs_q: np.ndarray, obs_xy: np.ndarray, keyframes: tuple[np.ndarray, np.ndarray,
                 np.ndarray] | None = None, point_ids: np.ndarray | None = None) -> np.ndarray:
    """Per-sensor continuity colour of every point in every frame.

    Parameters
    ----------
    obs_src : uint8 array (F, P, C)
        :class:`~carapost.model.take.ObsSource` of each observation.
    obs_q : float array (F, P, C)
        Target-track quality 0..1 (NaN if none).
    obs_xy : float array (F, P, C, 2)
        Observations (NaN = none): a sensor without an observation is a gap.
    keyframes : (frame, point_id, camera) arrays, optional
        Target-track keyframes, drawn white.
    point_ids : int array (P,), optional
        Ids of the point columns (needed with ``keyframes``).

    Returns
    -------
    uint8 array (F, P, C)
        ``S_GAP``, ``S_BLOB`` (dark blue), ``S_PATCH`` (light blue), ``S_KEYFRAME`` (white) or
        ``S_TARGET0 + level`` (level 0 = poor/red ... ``N_TARGET_LEVELS - 1`` = good/green).
    """
    present = np.isfinite(obs_xy[..., 0])
    codes = np.full(obs_src.shape, S_GAP, np.uint8)
    codes[present & (obs_src == ObsSource.BLOB)] = S_BLOB
    codes[present & (obs_src == ObsSource.PATCH)] = S_PATCH
    target = present & (obs_src == ObsSource.TARGET)
    q = np.nan_to_num(obs_q, nan=0.0)
    level = np.clip((q * N_TARGET_LEVELS).astype(np.int64), 0, N_TARGET_LEVELS - 1)
    codes[target] = (S_TARGET0 + level[target]).astype(np.uint8)
    codes[present & (obs_src == ObsSource.KEYFRAME)] = S_KEYFRAME
    if keyframes is not None and point_ids is not None and len(keyframes[0]):
        kf, kid, kc = (np.asarray(a) for a in keyframes)
        order = np.argsort(point_ids)
        pos = np.searchsorted(point_ids[order], kid)
        pos = np.clip(pos, 0, max(len(order) - 1, 0))
        ok = (len(order) > 0) & (point_ids[order][pos] == kid) & (kf >= 0) & (kf < codes.shape[0]) & \
            (kc >= 0) & (kc < codes.shape[2])
        codes[kf[ok], order[pos[ok]], kc[ok]] = S_KEYFRAME
    return codes


def reduce_columns(codes: np.ndarray, f0: int, f1: int, width: int, priority: np.ndarray) -> np.ndarray:
    """Resample rows of per-frame codes to ``width`` pixel columns over frames ``f0..f1``.

    Parameters
    ----------
    codes : uint8 array (R, F)
    f0, f1 : int
        First and last frame shown (inclusive).
    width : int
        Pixel columns.
    priority : uint8 array
        Priority of each code; where several frames share a column the highest wins.

    Returns
    -------
    uint8 array (R, width)
    """
    width = max(int(width), 1)
    f0, f1 = int(f0), int(f1)
    n = f1 - f0 + 1
    sub = codes[:, f0:f1 + 1]
    if n <= 0 or sub.shape[1] == 0:
        return np.zeros((codes.shape[0], width), np.uint8)
    if n <= width:  # each frame spans one or more columns
        col_frame = np.minimum((np.arange(width) * n) // width, n - 1)
        return sub[:, col_frame]
    starts = (np.arange(width) * n) // width
    pr = priority[sub]
    best = np.maximum.reduceat(pr, starts, axis=1)
    inverse = np.zeros(int(priority.max()) + 1, np.uint8)
    inverse[priority] = np.arange(len(priority), dtype=np.uint8)
    return inverse[best]


def gap_counts(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gaps of every point: number of gap runs and of gap frames.

    A gap is a run of frames without data that has data on both sides (leading and trailing
    missing frames are not gaps to fill).

    Parameters
    ----------
    valid : bool array (F, P)

    Returns
    -------
    runs, frames : int arrays (P,)
    """
    F, P = valid.shape
    if F == 0 or P == 0:
        return np.zeros(P, np.int64), np.zeros(P, np.int64)
    idx = np.arange(F)[:, None]
    first = np.where(valid.any(0), np.argmax(valid, 0), F)
    last = np.where(valid.any(0), F - 1 - np.argmax(valid[::-1], 0), -1)
    inside = (idx > first) & (idx < last) & ~valid
    starts = inside & np.vstack([np.ones((1, P), bool), ~inside[:-1]])
    return starts.sum(0), inside.sum(0)


def point_with_fewest_gaps(valid: np.ndarray, candidates: np.ndarray | None = None) -> int:
    """"Select Point With Fewest Gaps": the point with the fewest gap runs (at least one),
    ties broken by fewer gap frames, then by column; -1 if no point has a gap."""
    runs, frames = gap_counts(valid)
    cols = np.arange(valid.shape[1]) if candidates is None else np.asarray(candidates, np.int64)
    cols = cols[runs[cols] > 0]
    if len(cols) == 0:
        return -1
    order = np.lexsort((cols, frames[cols], runs[cols]))
    return int(cols[order[0]])


def next_gap_frame(valid: np.ndarray, frame: int) -> int:
    """"Go To Next Gap of Selected Point": the frame just before the next gap after ``frame``.

    Parameters
    ----------
    valid : bool array (F,)
        Frames where the point has data.
    frame : int
        Current frame.

    Returns
    -------
    int
        The last valid frame before the next gap that starts after ``frame`` (wrapping to the
        first gap of the take); -1 if the point has no gap.
    """
    v = np.asarray(valid, bool)
    starts = np.flatnonzero(v[:-1] & ~v[1:]) + 1       # first missing frame of each run
    if len(starts) == 0:
        return -1
    # Only runs that end in data again are gaps (not the missing tail of the take).
    last_valid = np.flatnonzero(v)
    starts = starts[starts < (last_valid[-1] if len(last_valid) else 0)]
    if len(starts) == 0:
        return -1
    after = starts[starts - 1 > frame]
    return int((after[0] if len(after) else starts[0]) - 1)


def points_in_polygon(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd test of points ``xy (N, 2)`` against a closed polygon ``poly (M, 2)``; (N,) bool."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    poly = np.asarray(poly, float).reshape(-1, 2)
    if len(poly) < 3 or len(xy) == 0:
        return np.zeros(len(xy), bool)
    x, y = xy[:, 0:1], xy[:, 1:2]
    x0, y0 = poly[:, 0][None], poly[:, 1][None]
    x1, y1 = np.roll(poly[:, 0], -1)[None], np.roll(poly[:, 1], -1)[None]
    cross = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    hit = cross & (x < xi)
    return (hit.sum(1) % 2 == 1) & np.isfinite(xy).all(1)


def ellipse_outlines(x: np.ndarray, y: np.ndarray, a: np.ndarray, b: np.ndarray, angle: np.ndarray,
                     n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Closed outlines of ellipses (centre, semi-axes ``a``/``b``, rotation ``angle`` rad).

    Returns
    -------
    ox, oy : float arrays (N, n + 1)
        Outline vertices; the last repeats the first.
    """
    phi = np.linspace(0, 2 * np.pi, n + 1)
    c, s = np.cos(phi)[None], np.sin(phi)[None]
    ca, sa = np.cos(angle)[:, None], np.sin(angle)[:, None]
    ex, ey = a[:, None] * c, b[:, None] * s
    return x[:, None] + ex * ca - ey * sa, y[:, None] + ex * sa + ey * ca


def circle_outlines(x: np.ndarray, y: np.ndarray, r: np.ndarray | float, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Closed circle outlines, (N, n + 1) each."""
    x = np.asarray(x, float)
    r = np.broadcast_to(np.asarray(r, float), x.shape)
    return ellipse_outlines(x, np.asarray(y, float), r, r, np.zeros_like(x), n)
