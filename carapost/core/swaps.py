"""Swap detection and repair on labelled trajectories (ours or imported).

A swap is two (or more) markers exchanging labels over a range of frames. It shows as a
*jump*: in the frame where it starts (and where it ends) each marker's position relative to
its neighbours changes by about the distance between the markers, while everywhere else the
motion is smooth.

1. :func:`jump_scores`: for every marker and frame, the neighbour-compensated third
   difference ``J = 1.5 (x[f] - x[f-1]) - 0.5 (x[f+1] - x[f-2])`` (zero for any quadratic
   motion; a step of size ``d`` gives a peak of ``d`` with side lobes of ``-d / 2``) minus the
   median of the same quantity over the marker's most rigidly attached neighbours.
2. Trajectories are cut into segments at the peaks of ``|J|`` above ``threshold`` times the
   marker's robust noise level, and at gaps.
3. The segments are relabelled by the assignment engine of :mod:`carapost.core.label_assign`
   (global assignment at every segment start against constant-velocity and neighbour-shape
   predictions) with a strong preference for each segment's current label, starting from the
   frame with the most markers.
4. Where the new labels differ from the old ones, the difference is a column permutation per
   frame; consecutive frames with the same permutation form a :class:`Relabel`. When the
   permutation in force at the end of the take is not the identity, the repair is rebased on
   whichever end (first or last frame) keeps more samples unchanged.

:func:`apply_relabel` applies the repairs to trajectories (an undoable operation stores the
``Relabel`` list and applies the inverse to undo); :func:`relabel_points` applies them to a
(F, N) label array.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .label_engine import AssignmentEngine, AssignmentParams
from .label_tracks import segments_from_trajectories

__all__ = ["Relabel", "SwapReport", "jump_scores", "detect_swaps", "apply_relabel", "relabel_points",
           "invert_relabels", "stable_neighbours"]


@dataclass(frozen=True)
class Relabel:
    """A label permutation over a frame range.

    Attributes
    ----------
    start, end : int
        Frames ``start <= f < end``.
    perm : int64 (M,)
        New trajectories are ``new[f, m] = old[f, perm[m]]`` in the range.
    score : float
        Evidence, mm: the largest neighbour-compensated jump at the range's boundaries among
        the markers it moves (the "worst first" order of :class:`SwapReport`).
    """

    start: int
    end: int
    perm: np.ndarray
    score: float = 0.0

    @property
    def markers(self) -> list[int]:
        """Markers whose label changes in the range."""
        return [int(m) for m in np.flatnonzero(self.perm != np.arange(len(self.perm)))]

    @property
    def pairs(self) -> list[tuple[int, ...]]:
        """The permutation's cycles longer than one, e.g. ``[(3, 7)]`` for a swapped pair."""
        seen: set[int] = set()
        out = []
        for m in self.markers:
            if m in seen:
                continue
            cyc = [m]
            seen.add(m)
            k = int(self.perm[m])
            while k != m and k not in seen:
                cyc.append(k)
                seen.add(k)
                k = int(self.perm[k])
            out.append(tuple(cyc))
        return out

    def to_dict(self) -> dict:
        return {"start": self.start, "end": self.end, "cycles": [list(c) for c in self.pairs],
                "score": round(float(self.score), 3)}


@dataclass
class SwapReport:
    """Result of :func:`detect_swaps`.

    Attributes
    ----------
    relabels : list of Relabel
        The repairs, worst (highest score) first.
    jumps : int64 (K, 2) and float (K,)
        ``jump_frames[k] = (frame, marker)`` of every flagged jump, worst first, and its size
        ``jump_size[k]`` (mm); jumps a repair explains are included.
    """

    relabels: list[Relabel] = field(default_factory=list)
    jump_frames: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    jump_size: np.ndarray = field(default_factory=lambda: np.zeros(0))


# ------------------------------------------------------------------------ neighbours
def stable_neighbours(xyz: np.ndarray, k: int = 6, *, sample: int = 60) -> np.ndarray:
    """For each marker, the ``k`` markers whose distance to it varies least over the take.

    Parameters
    ----------
    xyz : float (F, M, 3)
    k : int
    sample : int
        At most this many evenly spaced frames are used.

    Returns
    -------
    int64 (M, k')
        ``k' = min(k, M - 1)``; rows ordered by increasing spread of the distance (plus a
        small preference for near markers). A marker with too little data gets its nearest
        markers by median distance.
    """
    F, M, _ = xyz.shape
    k = min(k, M - 1)
    if k <= 0:
        return np.zeros((M, 0), np.int64)
    idx = np.unique(np.linspace(0, F - 1, min(F, sample)).astype(int))
    X = xyz[idx]
    sq = np.einsum("smi,smi->sm", X, X)
    d2 = sq[:, :, None] + sq[:, None, :] - 2.0 * np.matmul(X, X.transpose(0, 2, 1))
    d = np.sqrt(np.maximum(d2, 0.0))  # (S, M, M), NaN where either marker is missing
    fin = np.isfinite(d)
    n = fin.sum(0)
    dz = np.where(fin, d, 0.0)
    mean = dz.sum(0) / np.maximum(n, 1)
    spread = np.sqrt(np.maximum((dz * dz).sum(0) / np.maximum(n, 1) - mean ** 2, 0.0))
    score = np.where(n >= 3, spread + 0.02 * mean, np.inf)
    np.fill_diagonal(score, np.inf)
    return np.argsort(score, axis=1, kind="stable")[:, :k].astype(np.int64)


# ----------------------------------------------------------------------------- jumps
def jump_scores(xyz: np.ndarray, neighbours: np.ndarray | None = None, *,
                min_raw: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour-compensated jumps of every marker in every frame, mm.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, NaN gaps.
    neighbours : int (M, K), optional
        From :func:`stable_neighbours` (computed if omitted).
    min_raw : float
        Only entries whose uncompensated value exceeds this are compensated (the others are
        returned uncompensated); 0 compensates everything. Compensation only lowers a jump
        caused by common motion, so entries below a detection floor need none.

    Returns
    -------
    J3 : float64 (F, M)
        ``|J|`` from the third difference (see the module docstring), NaN where the marker
        lacks one of the samples ``f - 2 .. f + 1``.
    J1 : float64 (F, M)
        ``|x[f] - x[f-1] - median of the neighbours' same step|``, NaN where ``f - 1`` or
        ``f`` is missing: the fallback next to gaps, where ``J3`` does not exist.

    Both are compensated by the median of the same quantity over the marker's neighbours that
    have it (not compensated where none has).
    """
    x = np.asarray(xyz, np.float64)
    F, M, _ = x.shape
    J3 = np.full((F, M, 3), np.nan)
    if F >= 4:
        J3[2:F - 1] = 1.5 * (x[2:F - 1] - x[1:F - 2]) - 0.5 * (x[3:F] - x[0:F - 3])
    J1 = np.full((F, M, 3), np.nan)
    J1[1:] = x[1:] - x[:-1]
    if neighbours is None:
        neighbours = stable_neighbours(x)
    out = []
    for J in (J3, J1):
        mag = np.sqrt((J * J).sum(-1))
        if neighbours.shape[1]:
            f, m = np.nonzero(mag > min_raw) if min_raw > 0 else np.nonzero(np.isfinite(mag))
            if f.size:
                Jn = J[f[:, None], neighbours[m]]  # (S, K, 3)
                comp = J[f, m] - _median_rows(Jn)
                mag[f, m] = np.sqrt((comp * comp).sum(-1))
        out.append(mag)
    return out[0], out[1]


def _median_rows(a: np.ndarray) -> np.ndarray:
    """Median over axis 1 of (S, K, 3) ignoring NaN (0 where all are NaN), (S, 3)."""
    s = np.sort(a, axis=1)  # NaN last
    cnt = np.isfinite(a[..., 0]).sum(1)
    lo = np.maximum((cnt - 1) // 2, 0)
    hi = np.maximum(cnt // 2, 0)
    r = np.arange(len(a))
    med = 0.5 * (s[r, lo] + s[r, hi])
    return np.where((cnt > 0)[:, None] & np.isfinite(med), med, 0.0)


def _level(J: np.ndarray) -> np.ndarray:
    """Median of each marker's finite values (0 if none), (M,)."""
    Js = np.sort(np.where(np.isfinite(J), J, np.inf), axis=0)
    n = np.isfinite(J).sum(0)
    k = np.maximum((n - 1) // 2, 0)
    lv = np.take_along_axis(Js, k[None], axis=0)[0]
    return np.where(n > 0, lv, 0.0)


def _peaks(J3: np.ndarray, J1: np.ndarray, threshold: float, floor: float) -> np.ndarray:
    """Jumps: values of ``J3`` above ``threshold`` x the marker's median level (and the
    ``floor``, mm) that are not side lobes (at least 0.6 x both neighbours in time), and,
    where ``J3`` does not exist, ``J1`` above the same rule; bool (F, M)."""
    lim3 = np.maximum(threshold * _level(J3), floor)
    Jz = np.where(np.isfinite(J3), J3, 0.0)
    up = np.zeros_like(Jz)
    dn = np.zeros_like(Jz)
    up[1:] = Jz[:-1]
    dn[:-1] = Jz[1:]
    # a step gives one peak with side lobes of a half; a one-frame outlier gives twin peaks
    peaks = (Jz > lim3[None]) & (Jz >= 0.6 * up) & (Jz >= 0.6 * dn)
    lim1 = np.maximum(threshold * _level(J1), floor)
    near_gap = ~np.isfinite(J3) & np.isfinite(J1)
    return peaks | (near_gap & (np.where(near_gap, J1, 0.0) > lim1[None]))


# ----------------------------------------------------------------------------- detect
def detect_swaps(xyz: np.ndarray, *, threshold: float = 8.0, floor_mm: float | None = None,
                 fixed: Sequence[int] = (), reference_frame: int | None = None,
                 params: AssignmentParams | None = None) -> SwapReport:
    """Find swapped labels in labelled trajectories and the permutations that repair them.

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, mm, NaN gaps.
    threshold : float
        A jump is flagged where ``|J|`` exceeds ``threshold`` times the marker's median
        ``|J|`` (and ``floor_mm``).
    floor_mm : float, optional
        Smallest jump flagged, mm (default: a fifth of the median nearest-marker distance).
    fixed : sequence of int
        Markers known to be right (never relabelled, never given another marker's data).
    reference_frame : int, optional
        A frame known to be labelled right: relabelling starts there and never changes it.
        By default it starts at the frame with the most markers, and where the labels in
        force at the end of the take differ from that frame's, the repair keeps whichever
        end relabels fewer samples.
    params : AssignmentParams, optional
        Engine tuning (``prior_bonus`` sets how strongly current labels are kept).

    Returns
    -------
    SwapReport

    Raises
    ------
    ValueError
        ``xyz`` is not (F, M, 3).
    """
    x = np.asarray(xyz, np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"trajectories must have shape (frames, markers, 3), got {x.shape}")
    F, M, _ = x.shape
    valid = np.isfinite(x).all(-1)
    if reference_frame is not None and not 0 <= int(reference_frame) < F:
        raise ValueError(f"reference frame {reference_frame} is outside 0..{F - 1}")
    if F < 2 or M < 2 or not valid.any():
        return SwapReport()
    nb = stable_neighbours(x)
    if floor_mm is None:
        floor_mm = 0.2 * _median_spacing(x)
    J3, J1 = jump_scores(x, nb, min_raw=0.5 * floor_mm)
    peaks = _peaks(J3, J1, threshold, floor_mm)
    J = np.where(np.isfinite(J3), J3, J1)
    fx = np.zeros(M, bool)
    fx[list(fixed)] = True
    peaks[:, fx] = False
    jf, jm = np.nonzero(peaks)
    size = J[jf, jm]
    order = np.argsort(-size, kind="stable")
    report = SwapReport(jump_frames=np.stack([jf, jm], 1)[order].astype(np.int64), jump_size=size[order])
    if jf.size:
        report.relabels = _jump_relabels(x, peaks, J, fx, reference_frame, params)
    return report


def _jump_relabels(x: np.ndarray, peaks: np.ndarray, J: np.ndarray, fx: np.ndarray, reference_frame: int | None,
                   params: AssignmentParams | None) -> list[Relabel]:
    """Relabel the segments cut at jumps and gaps with the assignment engine."""
    F, M, _ = x.shape
    valid = np.isfinite(x).all(-1)

    tracks, owner = segments_from_trajectories(x, peaks)
    p = params or AssignmentParams()
    sig = _motion_sigma(x, p.min_sigma)
    eng = AssignmentEngine(tracks, M, p, sig, prior=owner)
    t0 = int(np.argmax(valid.sum(1))) if reference_frame is None else int(reference_frame)
    alive0 = np.flatnonzero((tracks.start <= t0) & (tracks.end >= t0))
    for t in alive0:
        eng.assign(int(t), int(owner[t]))
    for t in np.flatnonzero(fx[owner]):  # fixed markers keep every segment
        if eng.label[t] < 0:
            eng.assign(int(t), int(owner[t]))
    eng.allowed = ~fx
    eng.set_reference_spacing(np.unique(np.linspace(0, F - 1, min(F, 20)).astype(int)))
    eng.run(t0)
    return _relabels_from_segments(tracks, owner, eng.label.copy(), M, J, rebase=reference_frame is None)


def _median_spacing(x: np.ndarray) -> float:
    F = x.shape[0]
    idx = np.unique(np.linspace(0, F - 1, min(F, 50)).astype(int))
    vals = []
    for f in idx:
        p = x[f][np.isfinite(x[f]).all(1)]
        if len(p) > 1:
            d = np.linalg.norm(p[:, None] - p[None], axis=-1)
            np.fill_diagonal(d, np.inf)
            vals.append(np.median(d.min(1)))
    return float(np.median(vals)) if vals else 1.0


def _motion_sigma(x: np.ndarray, floor: float) -> float:
    """90th percentile of constant-velocity prediction errors, mm."""
    if x.shape[0] < 3:
        return floor
    e = np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1)
    e = e[np.isfinite(e)]
    return float(max(np.percentile(e, 90), floor)) if e.size else floor


def _relabels_from_segments(tracks, owner: np.ndarray, new: np.ndarray, M: int, J: np.ndarray, *,
                            rebase: bool = True) -> list[Relabel]:
    """Per-frame permutations (old column -> new column) from segment relabelling, grouped."""
    F = tracks.n_frames
    moved = np.flatnonzero((new >= 0) & (new != owner))
    if moved.size == 0:
        return []
    # partial maps: mapping[f, old] = new for moved segments
    mapping = np.full((F, M), -1, np.int64)
    for t in moved:
        mapping[tracks.start[t]:tracks.end[t] + 1, owner[t]] = new[t]
    changed = np.flatnonzero((mapping >= 0).any(1))
    perms = np.tile(np.arange(M), (F, 1))
    # frames with the same partial map share a permutation: complete each distinct one once
    key_rows = mapping[changed]
    uniq, inv = np.unique(key_rows, axis=0, return_inverse=True)
    done = [_complete(u, M) for u in uniq]
    for r, f in enumerate(changed):
        perms[f] = done[inv[r]]
    # perms[f] maps old -> new; trajectories need new[f, m] = old[f, src[m]], src = inverse
    src = np.empty_like(perms)
    np.put_along_axis(src, perms, np.tile(np.arange(M), (F, 1)), axis=1)
    if rebase:
        src = _rebase(src)
    return _group(src, J)


def _complete(partial: np.ndarray, M: int) -> np.ndarray:
    """A permutation (old -> new) extending a partial injective map (-1 = undefined): open
    chains ``o1 -> o2 -> ... -> ok`` are closed by ``ok -> o1``."""
    perm = partial.copy()
    src = set(np.flatnonzero(perm >= 0).tolist())
    tgt = set(perm[perm >= 0].tolist())
    for o1 in sorted(src - tgt):  # chain starts: nobody maps to them
        k = o1
        while perm[k] >= 0:
            k = int(perm[k])
        perm[k] = o1
    # cycles already closed need nothing; the rest map to themselves
    rest = perm < 0
    perm[rest] = np.flatnonzero(rest)
    if len(np.unique(perm)) != M:  # should not happen; fall back to the identity
        return np.arange(M)
    return perm


def _rebase(src: np.ndarray) -> np.ndarray:
    """If the permutation in force at the last frame is not the identity, and taking the last
    frame as right instead of the first relabels fewer samples, rebase every frame's
    permutation on it (``new'[f] = P_last^-1 P_f old[f]``)."""
    M = src.shape[1]
    ident = np.arange(M)
    last = src[-1]
    if (last == ident).all():
        return src
    inv_last = np.empty(M, np.int64)
    inv_last[last] = ident
    rebased = src[:, inv_last]
    return rebased if int((rebased != ident).sum()) < int((src != ident).sum()) else src


def _cycles(perm: np.ndarray) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """Non-trivial cycles of ``perm`` as ``(markers, perm values on them)``, canonical order."""
    ident = np.arange(len(perm))
    seen: set[int] = set()
    out = []
    for m in np.flatnonzero(perm != ident):
        m = int(m)
        if m in seen:
            continue
        cyc = [m]
        seen.add(m)
        k = int(perm[m])
        while k != m:
            cyc.append(k)
            seen.add(k)
            k = int(perm[k])
        ms = tuple(sorted(cyc))
        out.append((ms, tuple(int(perm[i]) for i in ms)))
    return out


def _group(src: np.ndarray, J: np.ndarray) -> list[Relabel]:
    """One :class:`Relabel` per maximal frame run of each cycle of the per-frame permutations
    (cycles in force at the same time involve different markers, so the repairs commute)."""
    F, M = src.shape
    change = np.flatnonzero((src[1:] != src[:-1]).any(1)) + 1
    bounds = np.concatenate([[0], change, [F]])
    open_: dict[tuple, int] = {}
    spans: list[tuple[tuple, int, int]] = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        keys = set(_cycles(src[a]))
        for k in list(open_):
            if k not in keys:
                spans.append((k, open_.pop(k), int(a)))
        for k in keys:
            open_.setdefault(k, int(a))
    for k, a in open_.items():
        spans.append((k, a, F))
    out: list[Relabel] = []
    for (ms, vals), a, b in spans:
        perm = np.arange(M)
        perm[list(ms)] = vals
        win = [k for k in (a - 1, a, a + 1, b - 1, b, b + 1) if 0 <= k < F]
        sub = J[np.ix_(win, list(ms))]
        score = float(np.nanmax(sub)) if np.isfinite(sub).any() else 0.0
        out.append(Relabel(a, b, perm, score))
    out.sort(key=lambda r: (-r.score, r.start))
    return out


# ------------------------------------------------------------------------------ apply
def apply_relabel(xyz: np.ndarray, relabels: Sequence[Relabel]) -> np.ndarray:
    """Apply repairs to trajectories (a new array; the input is not changed).

    Parameters
    ----------
    xyz : float (F, M, ...)
        Any per-marker array with frames first and markers second (positions, recon, ...).
    relabels : sequence of Relabel
        Applied in order; each sets ``new[f, m] = old[f, perm[m]]`` for its frames.

    Returns
    -------
    ndarray
        Same shape and dtype as ``xyz``.
    """
    out = np.array(xyz, copy=True)
    for r in relabels:
        if len(r.perm) != out.shape[1]:
            raise ValueError(f"relabel for {len(r.perm)} markers applied to {out.shape[1]}")
        out[r.start:r.end] = out[r.start:r.end][:, r.perm]
    return out


def invert_relabels(relabels: Sequence[Relabel]) -> list[Relabel]:
    """The repairs that undo ``relabels`` (apply them to the repaired trajectories)."""
    out = []
    for r in reversed(list(relabels)):
        inv = np.empty_like(r.perm)
        inv[r.perm] = np.arange(len(r.perm))
        out.append(Relabel(r.start, r.end, inv, r.score))
    return out


def relabel_points(labels: np.ndarray, relabels: Sequence[Relabel]) -> np.ndarray:
    """Apply repairs to a (F, N) marker-index label array (of point clouds).

    A point labelled ``m`` in a repaired frame takes the label ``k`` with ``perm[k] == m``.
    """
    out = np.array(labels, copy=True)
    for r in relabels:
        inv = np.empty_like(r.perm)
        inv[r.perm] = np.arange(len(r.perm))
        blk = out[r.start:r.end]
        out[r.start:r.end] = np.where(blk >= 0, inv[np.maximum(blk, 0)], blk)
    return out
