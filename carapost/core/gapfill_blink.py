"""Blink gaps: fill a marker's gap with a fitted closing-and-reopening pulse of its own motion.

An upper-eyelid marker in a blink moves unlike every visible marker around it: the lid comes
down over the eye and goes back up while the brows, the lower lid and the cheeks stay put, and
the marker is usually lost (in the lashes and the fold) while the lid is more than part-way
closed. Neighbour interpolation (:func:`carapost.core.gapfill.fill_gaps`) can only blend the
lid's position at the two ends of the gap, so it misses the closure by most of its depth.

This module models such a gap as an *excursion* of the marker relative to its neighbourhood:

1. **Baseline**: the guide's neighbour prediction across a *window* reaching ``window_s``
   seconds either side of the gap (anchored at the window's ends, where the lid is open), so
   the head and face motion are followed and the excursion is what is left:
   ``r(f) = X(f) - baseline(f)`` at the window's known frames.
2. **Which gaps**: a gap is an excursion gap when it is no longer than ``max_blink_s``, the
   marker is already displaced from its baseline by more than ``min_excursion_mm`` at a known
   frame next to the gap, most of that displacement was gained in the last frame before the
   gap (or lost in the first after it: a blink is sudden), and the displacements going in and
   coming out point the same way.
3. **Direction**: the marker's excursions all point one way (the lid closes along one path):
   ``v`` is the principal direction of its residuals over all its excursion gaps, each
   residual first turned back by its neighbourhood's rotation since a reference frame (so a
   head turn between blinks does not tilt the path).
4. **Pulse**: the excursion along ``v`` is ``D * A(f)``, with ``A`` a smooth pulse — a
   raised-cosine closing of ``rise`` frames from onset ``t``, a ``hold`` at full closure and a
   raised-cosine reopening of ``fall`` frames (the usual description of blink kinematics: a
   fast closing and a slower opening; the fit keeps ``rise <= fall``). The depth ``D`` is
   shared by all the marker's blinks (a lid closes as far every time); onset and durations are
   per blink, pulled towards their common (geometric) mean by a soft penalty in a second pass.
   They are fitted by least squares to the residuals at the known frames of every window (the
   partly closed lid seen going into and coming out of the gap), with hinge penalties for a
   visibility level ``h`` shared by the blinks: the seen frames are below it and the hidden
   frames above it — the marker is hidden *because* the lid is closing.
   The pulse rides on a linear drift of the baseline along ``v`` per blink (small, softly
   pulled to zero: the neighbour baseline of a sparse marker set drifts when the brows move).
5. **Fill**: ``baseline(f) + (D A(f) + drift(f)) R(f) v`` in the gap, ``R(f)`` the
   neighbourhood's rotation.

Gaps that are not excursion gaps, gaps whose excursion is not along the marker's common
direction, blinks whose pulse leaves a residual above ``max(0.3 mm, 5 % of D)`` at the seen
frames, markers whose fit fails, and markers with a known depth smaller than the excursion
seen next to their gaps keep the neighbour fill.

The depth is the weak part: the take shows the lid only part-way closed, and a shallow blink
with a long closed hold fits those frames as well as a deep one with a short hold. So the
depth is given — measured on a range-of-motion take (:func:`excursion_depths`), or taken from
the eye's geometry (``depth_model="geometry"``, the default: the lower-lid marker the lid
closes onto, or a palpebral-fissure prior; :mod:`carapost.core.gapfill_lid`) — or, with
``depth_model="fit"``, fitted (loosely) with the pulse.

Array contract: ``xyz (F, P, 3)`` mm with NaN gaps; masks ``(F, P)`` bool; frames 0-based.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from .gapfill import GapFillResult, checked_fill_arrays, distance_spread, fill_gaps, gap_runs, neighbour_motion
from .gapfill_lid import LID_MARKER_OFFSET_MM, PALPEBRAL_FISSURE_MM, lid_closing_depth

__all__ = ["BlinkFit", "blink_pulse", "fill_blink_gaps", "excursion_depths"]


#: How strongly the closing and reopening durations of one marker's blinks are pulled
#: together (mm of residual per unit of log duration ratio).
_SHARE_WEIGHT = 1.0
#: Gating: the excursions either side of a gap must agree in direction (cosine), and so must
#: a gap's excursion and the marker's common closing direction.
_MIN_COS = 0.7
#: ... and the excursion one frame further from the gap must be at most this share of the one
#: at its edge (a blink is sudden; slow drifts from the neighbourhood are not blinks).
_MAX_EDGE_RATIO = 0.6
#: The pulse rides on a linear drift of the window baseline along the closing direction (a
#: brow raise moves the lid and the brows by different amounts, so the neighbour baseline
#: drifts): level at the gap's middle and change from there to the window's ends, each within
#: +-_DRIFT_MAX_MM mm, softly pulled to zero (weight _DRIFT_WEIGHT per mm).
_DRIFT = True
_DRIFT_MAX_MM = 2.0
_DRIFT_WEIGHT = 0.3
#: A blink whose pulse leaves an RMS residual above ``max(_MAX_RMS_MM, _MAX_RMS_FRACTION * D)``
#: at its seen frames is not a blink: it keeps the neighbour fill.
_MAX_RMS_MM = 0.3
_MAX_RMS_FRACTION = 0.05


@dataclass
class BlinkFit:
    """The fitted pulses of one marker (:func:`fill_blink_gaps` reports one per marker).

    Attributes
    ----------
    point : int
        Point column.
    direction : array (3,)
        Unit direction of the excursion (closing), in the world frame of the first gap's
        anchor frame (it turns with the marker's neighbourhood).
    depth_mm : float
        ``D``: full excursion, mm.
    pulses : list of (first, last, t, rise, hold, fall)
        Per gap: its frames (inclusive) and the fitted onset (frame) and durations (frames).
    rms_mm : float
        RMS residual of the fit at the known window frames, mm.
    depth_source : str
        Where ``depth_mm`` came from: ``"given"`` (``depths``, e.g. a ROM), ``"lower_lid"`` /
        ``"fissure_prior"`` (the eye's geometry, :mod:`carapost.core.gapfill_lid`) or
        ``"fit"`` (fitted to the pulse).
    partner : int
        The lower-lid marker the lid closes onto (``"lower_lid"``; else -1).
    """

    point: int
    direction: np.ndarray
    depth_mm: float
    pulses: list[tuple[int, int, float, float, float, float]] = field(default_factory=list)
    rms_mm: float = float("nan")
    depth_source: str = "fit"
    partner: int = -1


def blink_pulse(f: np.ndarray, t: float, rise: float, hold: float, fall: float) -> np.ndarray:
    """Blink amplitude 0..1 at frames ``f``: raised-cosine closing over ``rise`` frames from
    ``t``, ``hold`` frames closed, raised-cosine opening over ``fall`` frames.

    Parameters
    ----------
    f : array
        Frames (float).
    t, rise, hold, fall : float
        Onset (frame) and durations (frames, ``rise, fall > 0``, ``hold >= 0``).

    Returns
    -------
    array like ``f``
    """
    f = np.asarray(f, dtype=float)
    up = np.clip((f - t) / rise, 0.0, 1.0)
    down = np.clip((f - t - rise - hold) / fall, 0.0, 1.0)
    return 0.25 * (1.0 - np.cos(np.pi * up)) * (1.0 + np.cos(np.pi * down))


def _windows(fill_p: np.ndarray, known_p: np.ndarray, first: np.ndarray, last: np.ndarray,
             half: int) -> tuple[np.ndarray, np.ndarray]:
    """Window ends (known anchor frames) around each gap of one point: at most ``half`` frames
    beyond the gap, not reaching into the point's neighbouring gaps; -1 where the gap touches
    the start (end) of the data."""
    F = len(fill_p)
    wa = np.full(len(first), -1)
    wb = np.full(len(first), -1)
    for i, (g0, g1) in enumerate(zip(first, last)):
        a = g0 - 1
        while a - 1 >= 0 and g0 - (a - 1) <= half + 1 and known_p[a - 1] and not fill_p[a - 1]:
            a -= 1
        wa[i] = a if a >= 0 and known_p[a] else -1
        b = g1 + 1
        while b + 1 < F and (b + 1) - g1 <= half + 1 and known_p[b + 1] and not fill_p[b + 1]:
            b += 1
        wb[i] = b if b < F and known_p[b] else -1
    return wa, wb


def _baseline(xyz: np.ndarray, known: np.ndarray, p: int, wa: int, wb: int, frames: np.ndarray,
              rank_cost: np.ndarray | None, n_neighbours: int) -> np.ndarray:
    """The guide's neighbour prediction of point ``p`` at ``frames`` from anchors ``wa`` and
    ``wb`` (either may be -1), blended by position; array (len(frames), 3)."""
    n = len(frames)
    pts = np.full(n, p)
    preds = []
    for anchor in (wa, wb):
        if anchor < 0:
            preds.append(None)
            continue
        moved, _, _ = neighbour_motion(xyz, known, pts, np.full(n, anchor), frames, n_neighbours=n_neighbours,
                                       rank_cost=rank_cost)
        preds.append(moved)
    if preds[0] is None:
        return preds[1]
    if preds[1] is None:
        return preds[0]
    s = ((frames - wa) / max(wb - wa, 1))[:, None]
    return (1.0 - s) * preds[0] + s * preds[1]


def _fit_point(blinks: list[dict], fps: float,
               depth: float | None = None) -> tuple[float, list[np.ndarray], list[float], list[np.ndarray]] | None:
    """Least-squares fit of the depth and per-blink pulses to the excursions of one point.

    Each blink dict has ``g0, g1`` (gap frames), ``f`` (known window frames, float), ``s``
    (excursion along the direction at those frames, mm) and ``hidden`` (gap frames, float).
    Parameters: depth ``D`` (fixed to ``depth`` when given), a visibility level ``h`` shared by
    the blinks (the marker is seen below it and hidden above it: hinge penalties), and per
    blink ``t, hold, rise / fall, fall`` and (:data:`_DRIFT`) a linear drift of the baseline
    along the direction, ``c0 + c1 (f - mid) / half`` (``mid``, ``half``: the gap's middle and
    the window's half length, in each blink dict), softly pulled to zero. A second pass pulls
    each blink's durations towards the first pass's geometric means (:data:`_SHARE_WEIGHT`).
    Returns ``(D, [t, rise, hold, fall] per blink, RMS residual per blink mm, [c0, c1] per
    blink mm)`` or None."""
    max_dur = max(2.0, 0.5 * fps)
    smax = max((float(np.max(b["s"])) for b in blinks if len(b["s"])), default=0.0)
    if smax <= 0 and depth is None:
        return None
    smax = max(smax, 1e-3)
    n = len(blinks)
    if depth is None:
        lo, hi = [smax, 0.0], [20.0 * smax, 20.0 * smax]
    else:
        lo, hi = [depth - 1e-9, 0.0], [depth + 1e-9, 20.0 * max(smax, depth)]
    K = 6 if _DRIFT else 4
    for b in blinks:
        g0, g1 = b["g0"], b["g1"]
        lo += [g0 - max_dur - 1.0, 0.0, 0.1, 0.5] + ([-_DRIFT_MAX_MM, -_DRIFT_MAX_MM] if _DRIFT else [])
        hi += [g0 + 0.5, (g1 - g0 + 1) + 2.0, 1.0, max_dur] + ([_DRIFT_MAX_MM, _DRIFT_MAX_MM] if _DRIFT else [])
    lo_a, hi_a = np.array(lo), np.array(hi)
    # which parameters each residual row depends on (finite differences grouped accordingly)
    rows = []
    for i, b in enumerate(blinks):
        m = 2 * len(b["f"]) + len(b["hidden"]) + 2 + (2 if _DRIFT else 0)
        blk = np.zeros((m, 2 + K * n), bool)
        blk[:, :2] = True
        blk[:, 2 + K * i: 2 + K * (i + 1)] = True
        rows.append(blk)
    sparsity = np.concatenate(rows)

    def pulse(x: np.ndarray, i: int) -> tuple[float, float, float, float]:
        t, hold, q, fall = x[2 + K * i: 6 + K * i]
        return t, max(0.5, q * fall), hold, fall       # closing no slower than reopening

    def drift(x: np.ndarray, i: int, f: np.ndarray) -> np.ndarray:
        """The baseline's drift along the direction at frames ``f``: ``c0`` at the gap's middle,
        ``c1`` at the window's ends (a line)."""
        if not _DRIFT:
            return np.zeros(len(f))
        b = blinks[i]
        c0, c1 = x[6 + K * i: 8 + K * i]
        return c0 + c1 * (f - b["mid"]) / b["half"]

    def make_residuals(means: tuple[float, float] | None):
        w = 0.0 if means is None else _SHARE_WEIGHT

        def residuals(x: np.ndarray) -> np.ndarray:
            D, h = x[0], x[1]
            out = []
            for i, b in enumerate(blinks):
                p = pulse(x, i)
                seen = D * blink_pulse(b["f"], *p)
                share = [0.0, 0.0] if means is None else [w * (np.log(p[1]) - means[0]), w * (np.log(p[3]) - means[1])]
                out += [seen + drift(x, i, b["f"]) - b["s"], np.maximum(0.0, seen - h),
                        np.maximum(0.0, h - D * blink_pulse(b["hidden"], *p)), share]
                if _DRIFT:
                    out.append(_DRIFT_WEIGHT * x[6 + K * i: 8 + K * i])
            return np.concatenate(out)
        return residuals

    best = None
    for rise0, fall0 in ((0.05, 0.1), (0.1, 0.2), (0.2, 0.3)):
        r0, f0 = min(max_dur, max(1.0, rise0 * fps)), min(max_dur, max(1.0, fall0 * fps))
        x0 = [depth if depth is not None else 2.0 * smax, 1.05 * smax]
        for b in blinks:
            g0, g1 = b["g0"], b["g1"]
            t = g0 - 0.5 - 0.5 * r0                   # half closed between the last seen frame and the gap
            hold = max(0.0, (g1 + 0.5 - 0.5 * f0) - (t + r0))
            x0 += [t, hold, min(1.0, r0 / f0), f0] + ([0.0, 0.0] if _DRIFT else [])
        x0_a = np.clip(np.array(x0), lo_a + 1e-10, hi_a - 1e-10)
        sol = least_squares(make_residuals(None), x0_a, bounds=(lo_a, hi_a), x_scale="jac", max_nfev=200,
                            jac_sparsity=sparsity)
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None:
        return None
    x = best.x
    if n > 1 and _SHARE_WEIGHT > 0:
        durs = np.array([pulse(x, i) for i in range(n)])
        means = (float(np.log(durs[:, 1]).mean()), float(np.log(durs[:, 3]).mean()))
        x = least_squares(make_residuals(means), np.clip(x, lo_a + 1e-10, hi_a - 1e-10), bounds=(lo_a, hi_a),
                          x_scale="jac", max_nfev=200, jac_sparsity=sparsity).x
    rms = [float(np.sqrt(np.mean((x[0] * blink_pulse(b["f"], *pulse(x, i)) + drift(x, i, b["f"]) - b["s"]) ** 2)))
           if len(b["f"]) else float("nan") for i, b in enumerate(blinks)]
    drifts = [x[6 + K * i: 8 + K * i].copy() if _DRIFT else np.zeros(2) for i in range(n)]
    return float(x[0]), [np.array(pulse(x, i)) for i in range(n)], rms, drifts


def excursion_depths(xyz: np.ndarray, points: np.ndarray, *, n_neighbours: int = 8, rigidity_weight: float = 30.0,
                     percentile: float = 99.0) -> np.ndarray:
    """How far each point moves away from its neighbourhood: the depth of a blink, learnt
    from a range-of-motion take where the lid is seen closing.

    Every frame's position of the point is compared with its neighbourhood's motion from a
    reference frame (the one with the most points present); the excursion is the projection
    of that residual on its principal direction, and the depth is its ``percentile`` minus
    its median (the eye is open most of the time), in the direction of the larger tail.

    Parameters
    ----------
    xyz : array (F, P, 3)
        A take with the points seen through their excursions (NaN where missing), mm.
    points : int array (N,)
        Columns to measure.
    percentile : float
        Upper percentile taken as the full excursion (robust to a few bad frames).

    Returns
    -------
    array (N,)
        Depths, mm (NaN for a point seen in fewer than 10 frames).
    """
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"xyz must have shape (F, P, 3), got {xyz.shape}")
    F, P, _ = xyz.shape
    points = np.asarray(points, dtype=np.int64)
    known = np.isfinite(xyz).all(-1)
    rank_cost = (rigidity_weight * distance_spread(xyz, known)) ** 2 if rigidity_weight > 0 else None
    ref = int(np.argmax(known.sum(1)))
    out = np.full(len(points), np.nan)
    for i, p in enumerate(points):
        fr = np.flatnonzero(known[:, p])
        if len(fr) < 10 or not known[ref, p]:
            continue
        moved, _, _ = neighbour_motion(xyz, known, np.full(len(fr), p), np.full(len(fr), ref), fr,
                                       n_neighbours=n_neighbours, rank_cost=rank_cost)
        e = xyz[fr, p] - moved
        e = e - np.median(e, axis=0)
        _, _, Vt = np.linalg.svd(e, full_matrices=False)
        s = e @ Vt[0]
        up, down = np.percentile(s, percentile), -np.percentile(s, 100.0 - percentile)
        out[i] = max(up, down)
    return out


def fill_blink_gaps(xyz: np.ndarray, fill: np.ndarray, *, frame_rate: float, known: np.ndarray | None = None,
                    base: GapFillResult | None = None, window_s: float = 0.2, min_excursion_mm: float = 1.0,
                    max_blink_s: float = 0.5, n_neighbours: int = 8, rigidity_weight: float = 30.0,
                    depths: dict[int, float] | None = None, depth_model: str = "geometry",
                    lid_marker_offset_mm: float = LID_MARKER_OFFSET_MM,
                    fissure_mm: float = PALPEBRAL_FISSURE_MM, lid_points: Collection[int] | None = None,
                    **neighbour_options: object) -> tuple[GapFillResult, list[BlinkFit]]:
    """Fill gaps by the neighbour method, and blink-like gaps by a fitted pulse (module doc).

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm, NaN in gaps. Not modified.
    fill : bool array (F, P)
        Samples to fill.
    frame_rate : float
        Frames per second (> 0): sets the window and the pulse duration bounds (at most 0.5 s
        per phase).
    known : bool array (F, P), optional
        Samples to predict from (default ``finite & ~fill``).
    base : GapFillResult, optional
        A neighbour fill of the same samples to start from (computed if not given, with
        ``n_neighbours``, ``rigidity_weight`` and ``neighbour_options`` passed to
        :func:`~carapost.core.gapfill.fill_gaps`).
    window_s : float
        How far either side of a gap the excursion is measured, seconds.
    min_excursion_mm : float
        A gap is treated as a blink when the marker is displaced from its neighbour baseline
        by more than this at a known frame next to the gap.
    max_blink_s : float
        Longer gaps are not blinks (seconds).
    n_neighbours, rigidity_weight
        As for :func:`~carapost.core.gapfill.fill_gaps` (baseline prediction).
    depths : dict {point column: mm}, optional
        Known full excursion of a marker (e.g. :func:`excursion_depths` of a range-of-motion
        take). Without it the depth comes from ``depth_model``.
    depth_model : {"geometry", "fit"}
        A marker without a known depth: ``"geometry"`` (default) takes it from the eye's
        geometry — the lower-lid marker the lid closes onto, or the palpebral fissure prior
        (:func:`carapost.core.gapfill_lid.lid_closing_depth`); ``"fit"`` fits it to the pulse.
    lid_marker_offset_mm, fissure_mm : float
        The geometry's priors (:data:`~carapost.core.gapfill_lid.LID_MARKER_OFFSET_MM`,
        :data:`~carapost.core.gapfill_lid.PALPEBRAL_FISSURE_MM`).
    lid_points : collection of int, optional
        Columns known to be upper-eyelid markers (e.g. by label). With ``depth_model=
        "geometry"``, a marker without a lower-lid marker on its closing path takes the
        fissure prior only if it is one of these; any other such marker keeps the neighbour
        fill (a jaw or forehead gap that looks like a blink). Default: none.

    Returns
    -------
    (GapFillResult, list of BlinkFit)
        The filled positions (blink gaps replaced by the pulse fill), and one fit per marker
        with blink gaps.

    Raises
    ------
    ValueError
        Mismatched shapes, non-positive frame rate or window.
    """
    xyz, fill = checked_fill_arrays(xyz, fill)
    if not frame_rate > 0:
        raise ValueError(f"frame_rate must be positive, got {frame_rate}")
    if not window_s > 0:
        raise ValueError(f"window_s must be positive, got {window_s}")
    if depth_model not in ("geometry", "fit"):
        raise ValueError(f"depth_model must be 'geometry' or 'fit', got {depth_model!r}")
    finite = np.isfinite(xyz).all(-1)
    known = finite & ~fill if known is None else np.asarray(known, dtype=bool) & finite & ~fill
    if base is None:
        base = fill_gaps(xyz, fill, known=known, n_neighbours=n_neighbours, rigidity_weight=rigidity_weight,
                         **neighbour_options)  # type: ignore[arg-type]
    out = base.xyz.copy()
    fits: list[BlinkFit] = []
    if not fill.any():
        return GapFillResult(out, base.filled.copy(), base.on_ray.copy()), fits
    rank_cost = (rigidity_weight * distance_spread(xyz, known)) ** 2 if rigidity_weight > 0 else None
    half = max(2, int(round(window_s * frame_rate)))
    max_gap = max(2, int(round(max_blink_s * frame_rate)))
    gp, gf, gl = gap_runs(fill)
    for p in np.unique(gp):
        sel = gp == p
        first, last = gf[sel], gl[sel]
        wa, wb = _windows(fill[:, p], known[:, p], first, last, half)
        cand = []
        for g0, g1, a, b in zip(first, last, wa, wb):
            if a < 0 and b < 0:
                continue
            lo_f = a if a >= 0 else g0
            hi_f = b if b >= 0 else g1
            frames = np.arange(lo_f, hi_f + 1)
            base_w = _baseline(xyz, known, int(p), int(a), int(b), frames, rank_cost, n_neighbours)
            seen = known[frames, p]
            r = np.where(seen[:, None], xyz[frames, p] - base_w, np.nan)
            edge = [r[f - lo_f] for f in (g0 - 1, g1 + 1) if lo_f <= f <= hi_f and known[f, p]]
            norms = [float(np.linalg.norm(e)) for e in edge]
            if g1 - g0 + 1 > max_gap or max(norms, default=0.0) <= min_excursion_mm:
                continue
            # a blink is sudden: most of the excursion seen at the gap's edge was gained in the
            # last frame before it (lost in the first frame after it)
            big = int(np.argmax(norms))
            f_edge = (g0 - 1, g1 + 1)[big] if len(edge) == 2 else [f for f in (g0 - 1, g1 + 1)
                                                                    if lo_f <= f <= hi_f and known[f, p]][0]
            f_next = f_edge - 1 if f_edge < g0 else f_edge + 1
            if not (lo_f <= f_next <= hi_f and known[f_next, p]) or \
                    np.linalg.norm(r[f_next - lo_f]) > _MAX_EDGE_RATIO * norms[big]:
                continue
            if len(edge) == 2 and min(norms) > 0.3 * min_excursion_mm and \
                    edge[0] @ edge[1] < _MIN_COS * norms[0] * norms[1]:
                continue                              # going in and coming out in different directions
            cand.append({"g0": int(g0), "g1": int(g1), "frames": frames, "base": base_w, "r": r, "seen": seen,
                             "edge": [f for f in (g0 - 1, g1 + 1) if lo_f <= f <= hi_f and known[f, p]]})
        if not cand:
            continue
        # one frame of reference for the point's excursions: its neighbourhood's rotation from
        # the first window's anchor to every window frame (the head turns between blinks)
        ref = int(cand[0]["frames"][0] if known[cand[0]["frames"][0], p] else cand[0]["frames"][-1])
        for c in cand:
            _, c["rot"], _ = neighbour_motion(xyz, known, np.full(len(c["frames"]), p), np.full(len(c["frames"]), ref),
                                              c["frames"], n_neighbours=n_neighbours, rank_cost=rank_cost)
            c["r"] = np.einsum("nji,nj->ni", c["rot"], c["r"])     # into the reference frame
        R = np.concatenate([c["r"][c["seen"]] for c in cand])
        R = R[np.linalg.norm(R, axis=1) > 0.25 * min_excursion_mm]
        if len(R) < 1:
            continue
        _, _, Vt = np.linalg.svd(R, full_matrices=False)
        v = Vt[0]
        if (R @ v).sum() < 0:
            v = -v

        def along(c: dict) -> bool:
            e = max((c["r"][f - c["frames"][0]] for f in c["edge"]), key=np.linalg.norm)
            return bool(e @ v >= _MIN_COS * np.linalg.norm(e))
        cand = [c for c in cand if along(c)]          # gaps whose excursion is not the common closing
        if not cand:
            continue
        blinks = [{"g0": c["g0"], "g1": c["g1"], "f": c["frames"][c["seen"]].astype(float),
                   "s": c["r"][c["seen"]] @ v, "hidden": np.arange(c["g0"], c["g1"] + 1, dtype=float),
                   "mid": 0.5 * (c["g0"] + c["g1"]), "half": max(1.0, 0.5 * (c["frames"][-1] - c["frames"][0]))}
                  for c in cand]
        d = None if depths is None else depths.get(int(p))
        source, partner = "given", -1
        if (d is None or not np.isfinite(d)) and depth_model == "geometry":
            geo = lid_closing_depth(xyz, known, int(p), v, ref, rank_cost=rank_cost, n_neighbours=n_neighbours,
                                    blink_frames=np.concatenate([np.arange(c["g0"], c["g1"] + 1) for c in cand]),
                                    marker_offset_mm=lid_marker_offset_mm, fissure_mm=fissure_mm)
            d, source, partner = geo.depth_mm, geo.source, geo.partner
            if source == "fissure_prior" and (lid_points is None or int(p) not in lid_points):
                continue                              # not known to be a lid, and no lower lid in its way
        elif d is None or not np.isfinite(d):
            source = "fit"
        if d is not None and np.isfinite(d) and d < max(float(np.max(b["s"], initial=0.0)) for b in blinks):
            continue                                  # the known depth cannot explain what is seen
        res = _fit_point(blinks, frame_rate, None if d is None or not np.isfinite(d) else float(d))
        if res is None:
            continue
        D, pulses, rms, drifts = res
        ok = [r <= max(_MAX_RMS_MM, _MAX_RMS_FRACTION * D) for r in rms]
        if not any(ok):
            continue
        fit = BlinkFit(int(p), v, D, rms_mm=float(np.sqrt(np.mean(np.square([r for r, k in zip(rms, ok) if k])))),
                       depth_source=source, partner=partner)
        for c, b, x, dr, k in zip(cand, blinks, pulses, drifts, ok):
            if not k:
                continue                              # the pulse does not explain what was seen
            g = np.arange(c["g0"], c["g1"] + 1)
            amp = D * blink_pulse(g, *x) + dr[0] + dr[1] * (g - b["mid"]) / b["half"]
            i = g - c["frames"][0]
            out[g, p] = c["base"][i] + amp[:, None] * np.einsum("nij,j->ni", c["rot"][i], v)
            fit.pulses.append((c["g0"], c["g1"], *map(float, x)))
        fits.append(fit)
    return GapFillResult(out, base.filled.copy(), base.on_ray.copy()), fits
