"""Seed 002's labeller: per-frame nearest-neighbour assignment with its heuristics.

Frame by frame, going forwards from the first labelled (hinted) frame and then backwards from
it, every marker takes the point nearest to where it was in the previous frame, but only if

* no other marker is nearer to that point (the point goes to the nearest marker; the others
  are missing in this frame),
* the point is within ``dist_thresh`` of the marker's previous position, or within
  ``missing_thresh`` if the marker was missing in the previous frame,
* the point lies inside the bounding box of all markers in the previous frame grown by
  ``bbox_margin`` (points outside are noise reflections and are ignored).

A missing marker keeps a position for the next frame: with a skeleton (at most one parent and
one child per marker) it is carried by its parent and child - each gives the marker's previous
offset from it added to its new position, and the two are averaged - otherwise it stays where
it was. The options of the seed all exist, as hints (see :mod:`carapost.core.labelling`):
"frame mappings" are single hinted points, "fallback frames" fully hinted frames, "fully
labelled markers" markers hinted in every frame; ``ignore`` takes markers out of the labelling;
``hand_heuristics`` enables :mod:`carapost.core.label_hands` for the hand naming scheme.

Defaults are the seed's thresholds converted to millimetres (it worked in metres).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .label_hands import hand_model, hand_swaps
from .labelling import LabelResult, ProgressFn, check_hints, check_points

__all__ = ["label_nearest", "skeleton_order"]


def skeleton_order(skeleton: np.ndarray) -> np.ndarray:
    """Markers ordered parents first (depth in the parent chain, then index); (M,)."""
    M = len(skeleton)
    depth = np.zeros(M, np.int64)
    for m in range(M):
        d, p, seen = 0, int(skeleton[m, 0]), {m}
        while p >= 0 and p not in seen:
            seen.add(p)
            d += 1
            p = int(skeleton[p, 0])
        depth[m] = d
    return np.lexsort((np.arange(M), depth))


def label_nearest(points: np.ndarray, hints: np.ndarray | None, n_markers: int, *,
                  names: Sequence[str] | None = None, skeleton: np.ndarray | None = None,
                  dist_thresh: float = 15.0, missing_thresh: float = 30.0, bbox_margin: float = 30.0,
                  ignore: Sequence[int] = (), hand_heuristics: bool = False, crossover_mm: float = 5.0,
                  tip_angle: float = 2.0, backward: bool = True,
                  progress: ProgressFn | None = None) -> LabelResult:
    """Label unlabelled point clouds with seed 002's nearest-neighbour method.

    Parameters
    ----------
    points : float (F, N, 3)
        Point clouds, mm, any order within a frame, NaN rows empty.
    hints : int (F, N) or None
        Known labels; at least one point must be hinted (the first hinted frame is where the
        labelling starts). Hinted points always keep their hint.
    n_markers : int
    names : sequence of str, optional
        Marker names (needed by the hand heuristics).
    skeleton : int (M, 2), optional
        Parent and child of each marker (-1 none), e.g. from
        :func:`~carapost.core.labelling.skeleton_from_sticks` or
        :func:`~carapost.core.label_hands.hand_skeleton`.
    dist_thresh, missing_thresh : float
        Largest move from the previous frame, mm, for a marker seen / missing there.
    bbox_margin : float
        Growth of the previous frame's bounding box, mm.
    ignore : sequence of int
        Markers left out: their hinted points keep their hints, nothing else takes them.
    hand_heuristics : bool
        Apply the crossing-bones and fingertip-bend repairs (needs ``names`` in the hand
        scheme; ignored otherwise).
    crossover_mm, tip_angle : float
        Hand heuristic thresholds (mm, radians).
    backward : bool
        Also label the frames before the first hinted frame (going backwards from it).
    progress : callable, optional
        ``progress(done, total)`` every 500 frames; returning False stops early.

    Returns
    -------
    LabelResult
        ``report``: ``reference_frame``, ``unlabelled_points``, ``hand_swaps``.

    Raises
    ------
    ValueError
        Bad shapes, hints, skeleton or thresholds; no hinted point.
    """
    pts, valid = check_points(points)
    F, N, _ = pts.shape
    h = check_hints(hints, (F, N), n_markers, valid)
    if not (h >= 0).any():
        raise ValueError("the nearest-neighbour method needs hints: at least one labelled frame")
    if min(dist_thresh, missing_thresh, bbox_margin) < 0:
        raise ValueError("thresholds must not be negative")
    M = n_markers
    sk = np.full((M, 2), -1, np.int64) if skeleton is None else np.asarray(skeleton, np.int64)
    if sk.shape != (M, 2) or sk.max(initial=-1) >= M or sk.min(initial=-1) < -1:
        raise ValueError(f"skeleton must have shape ({M}, 2) with marker indices or -1")
    active = np.ones(M, bool)
    for m in ignore:
        if not 0 <= int(m) < M:
            raise ValueError(f"ignored marker {m} is outside 0..{M - 1}")
        active[int(m)] = False
    hands = hand_model(names) if (hand_heuristics and names is not None) else None
    if names is not None and len(names) != M:
        raise ValueError(f"{len(names)} names for {M} markers")

    t0 = int(np.flatnonzero((h >= 0).any(1))[0])
    labels = np.full((F, N), -1, np.int32)
    order = skeleton_order(sk)
    state = _State(M)
    n_hand = 0
    frames = list(range(t0, F)) + (list(range(t0 - 1, -1, -1)) if backward else [])
    saved = None
    for k, f in enumerate(frames):
        if f == t0 - 1:  # start of the backward pass: back to the state after the first frame
            state = saved
        lab, swaps = _label_frame(pts[f], valid[f], h[f], state, active, sk, order, dist_thresh,
                                  missing_thresh, bbox_margin, hands, crossover_mm, tip_angle)
        labels[f] = lab
        n_hand += swaps
        if f == t0:
            saved = state.copy()
        if progress is not None and (k + 1) % 500 == 0 and progress(k + 1, len(frames)) is False:
            break
    report = {"method": "nearest", "reference_frame": t0, "unlabelled_points": int((valid & (labels < 0)).sum()),
              "hand_swaps": n_hand}
    return LabelResult(labels, report)


class _State:
    """Per-marker position for the next frame (seen or extrapolated) and whether the marker was
    missing in the last frame; ``known`` is False until a marker has had a position."""

    def __init__(self, M: int) -> None:
        self.pos = np.full((M, 3), np.nan)
        self.missing = np.zeros(M, bool)
        self.known = np.zeros(M, bool)

    def copy(self) -> "_State":
        s = _State(len(self.pos))
        s.pos, s.missing, s.known = self.pos.copy(), self.missing.copy(), self.known.copy()
        return s


def _label_frame(X: np.ndarray, v: np.ndarray, hf: np.ndarray, st: _State, active: np.ndarray, sk: np.ndarray,
                 order: np.ndarray, dist_thresh: float, missing_thresh: float, margin: float, hands,
                 crossover_mm: float, tip_angle: float) -> tuple[np.ndarray, int]:
    M = len(st.pos)
    lab = np.where(v & (hf >= 0), hf, -1).astype(np.int32)
    taken = np.zeros(M, bool)
    taken[lab[lab >= 0]] = True
    cand = np.flatnonzero(v & (lab < 0))
    known = st.known & active
    if cand.size and known.any():
        prev = st.pos[known]
        lo, hi = prev.min(0) - margin, prev.max(0) + margin
        inside = ((X[cand] >= lo) & (X[cand] <= hi)).all(1)
        cand = cand[inside]
    targets = np.flatnonzero(known & ~taken)
    if cand.size and targets.size:
        D = np.sqrt(((st.pos[targets][:, None, :] - X[cand][None]) ** 2).sum(-1))  # (T, C)
        nn = D.argmin(1)
        dn = D[np.arange(len(targets)), nn]
        # each point goes to its nearest marker only: among markers choosing the same point,
        # the nearest wins and the others are missing in this frame
        o = np.lexsort((dn, nn))
        first = np.ones(len(o), bool)
        first[1:] = nn[o][1:] != nn[o][:-1]
        win = np.zeros(len(targets), bool)
        win[o[first]] = True
        thr = np.where(st.missing[targets], missing_thresh, dist_thresh)
        ok = win & (dn < thr)
        lab[cand[nn[ok]]] = targets[ok]
    n_swaps = 0
    if hands is not None:
        Xl = np.full((M, 3), np.nan)
        j = np.flatnonzero(lab >= 0)
        Xl[lab[j]] = X[j]
        pairs = hand_swaps(Xl, hands, crossover_mm=crossover_mm, tip_angle=tip_angle)
        for a, b in pairs:
            ia, ib = np.flatnonzero(lab == a), np.flatnonzero(lab == b)
            lab[ia], lab[ib] = b, a
        n_swaps = len(pairs)
    # new state: seen markers take their points, missing ones are extrapolated (parents first)
    seen = np.zeros(M, bool)
    j = np.flatnonzero(lab >= 0)
    new = np.full((M, 3), np.nan)
    new[lab[j]] = X[j]
    seen[lab[j]] = True
    done = seen.copy()
    for m in order:
        if seen[m] or not st.known[m]:
            continue
        est = []
        for rel in (int(sk[m, 0]), int(sk[m, 1])):  # parent, child
            if rel >= 0 and done[rel] and st.known[rel]:
                est.append(new[rel] + (st.pos[m] - st.pos[rel]))
        new[m] = np.mean(est, axis=0) if est else st.pos[m]
        done[m] = True
    st.known |= seen
    st.pos = np.where(st.known[:, None], new, np.nan)
    st.missing = st.known & ~seen
    return lab, n_swaps
