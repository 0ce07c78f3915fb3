"""Permutation path: decide the labels of a few confusable markers over the whole take at once.

The shape check (:mod:`carapost.core.label_shape`) judges each tracklet segment on its own
evidence. Where a few markers sit close together (Facial-Sing's section4-1/4-2, 5-9 mm
apart, one often missing), a segment's shape barely tells them apart, and a confusion that
the labeller carried on over many segments stays wherever the evidence is weak. Here the
labels of a small group of markers are decided over the whole take as one path:

* the *states* are the permutations of the group's labels (``k!`` of them, ``k <= 5``),
  relative to the current labels;
* a state's cost in a frame is the take's shape cost
  (:func:`~carapost.core.label_shape.shape_costs`, truncated squared z-scores) of the group
  and of every marker with a partner in it, with the group's labels permuted;
* the state may change only where one of the group's points changes tracklet (``pieces``:
  where the labeller made a decision), at a cost ``switch_cost``; the segment holding the
  reference frame (and any segment with a hinted group point) keeps the current labels.

The cheapest path (Viterbi over segments) is returned as :class:`~carapost.core.swaps.Relabel`
runs. A confusion that continuity carried over many segments is then undone as a whole when
the frames where the shape can tell the markers apart outweigh the frames where it cannot;
a segment is changed on its own only when its evidence pays for two switches.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import permutations

import numpy as np

from .label_shape import ShapeModel
from .swaps import Relabel

__all__ = ["permutation_path", "confusable_groups"]


def confusable_groups(relabels: Sequence[Relabel], *, max_size: int = 5) -> list[np.ndarray]:
    """Groups of markers the repairs ``relabels`` permuted together (connected components of
    their cycles), each of 2..``max_size`` markers, as sorted int64 arrays."""
    parent: dict[int, int] = {}

    def find(a: int) -> int:
        while parent.setdefault(a, a) != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for r in relabels:
        for cyc in r.pairs:
            for m in cyc[1:]:
                parent[find(int(m))] = find(int(cyc[0]))
    comp: dict[int, list[int]] = {}
    for m in list(parent):
        comp.setdefault(find(m), []).append(m)
    return [np.array(sorted(c), np.int64) for c in comp.values() if 2 <= len(c) <= max_size]


def permutation_path(xyz: np.ndarray, pieces: np.ndarray, group: Sequence[int], model: ShapeModel,
                     reference_frame: int, *, switch_cost: float = 300.0, tau: float = 3.0,
                     locked: np.ndarray | None = None) -> list[Relabel]:
    """The cheapest labelling of the markers ``group`` over the take (see the module).

    Parameters
    ----------
    xyz : float (F, M, 3)
        Labelled trajectories, mm, NaN gaps.
    pieces : int (F, M)
        Tracklet carrying each marker's sample (-1 none); the state may change only where a
        group member's piece changes.
    group : sequence of int
        2 to 5 markers.
    model : ShapeModel
        The shape around the reference frame.
    reference_frame : int
        Its segment keeps the current labels.
    switch_cost : float
        Cost of a change of state (units of summed truncated squared z-scores).
    tau : float
        Truncation of the z-scores.
    locked : bool (F,), optional
        Frames whose current labels must stay (hinted group points).

    Returns
    -------
    list of Relabel
        Runs of frames where the cheapest path differs from the current labels, with
        ``score`` the path's total gain over the current labels.
    """
    x = np.asarray(xyz, np.float64)
    F, M, _ = x.shape
    g = np.asarray(group, np.int64)
    if not 2 <= g.size <= 5:
        raise ValueError(f"a permutation path needs 2 to 5 markers, got {g.size}")
    pc = np.asarray(pieces)
    perms = np.array(list(permutations(range(g.size))), np.int64)  # identity first
    aff = np.flatnonzero(np.isin(model.partners, g).any(1) | np.isin(np.arange(M), g))
    # segments: runs of frames over which every member stays on the same piece
    p = pc[:, g]
    change = np.ones(F, bool)
    change[1:] = (p[1:] != p[:-1]).any(1)
    starts = np.flatnonzero(change)
    ends = np.r_[starts[1:], F]
    # cost of each state in each frame, summed per segment. A row's cost depends only on the
    # points its own label and its partners' labels receive: it is computed once per distinct
    # assignment of its group columns (k or k(k-1) cases for most rows, not k!)
    X = x.astype(np.float32)
    seg_cost = np.zeros((len(perms), len(starts)))
    pos = {int(m): i for i, m in enumerate(g)}
    for r in aff:
        cols = [int(r)] + [int(q) for q in model.partners[r] if q >= 0]
        rel = sorted({pos[c] for c in cols if c in pos})
        keys, inv = np.unique(perms[:, rel], axis=0, return_inverse=True)
        for u, key in enumerate(keys):
            src = dict(zip((int(g[i]) for i in rel), (int(g[k]) for k in key)))
            c = _row_cost(X, model, int(r), src, tau)
            seg_cost[inv.ravel() == u] += np.add.reduceat(c.astype(np.float64), starts)
    forced = np.zeros(len(starts), bool)
    forced[np.searchsorted(starts, int(reference_frame), side="right") - 1] = True
    if locked is not None:
        lk = np.flatnonzero(np.asarray(locked, bool))
        forced[np.searchsorted(starts, lk, side="right") - 1] = True
    seg_cost[1:, forced] = np.inf
    # Viterbi over segments
    S, P = len(starts), len(perms)
    back = np.zeros((S, P), np.int64)
    dp = seg_cost[:, 0].copy()
    for s in range(1, S):
        j = int(np.argmin(dp))
        stay = dp
        move = dp[j] + switch_cost
        back[s] = np.where(stay <= move, np.arange(P), j)
        dp = np.minimum(stay, move) + seg_cost[:, s]
    state = np.empty(S, np.int64)
    state[-1] = int(np.argmin(dp))
    for s in range(S - 1, 0, -1):
        state[s - 1] = back[s, state[s]]
    gain = float(seg_cost[0].sum() - seg_cost[state, np.arange(S)].sum())
    out: list[Relabel] = []
    s = 0
    while s < S:
        if state[s] == 0:
            s += 1
            continue
        e = s
        while e + 1 < S and state[e + 1] == state[s]:
            e += 1
        perm = np.arange(M)
        perm[g] = g[perms[state[s]]]
        out.append(Relabel(int(starts[s]), int(ends[e]), perm, gain))
        s = e + 1
    return out


def _row_cost(X: np.ndarray, model: ShapeModel, r: int, src: dict[int, int], tau: float,
              min_partners: int = 2) -> np.ndarray:
    """Shape cost (F,) of marker ``r`` when the labels ``c`` in ``src`` hold the points of the
    columns ``src[c]`` (others their own): as :func:`~carapost.core.label_shape.shape_costs`
    with ``unknown = tau^2 / 2`` (``X`` float32 (F, M, 3))."""
    P = model.partners[r]
    has = P >= 0
    own = X[:, src.get(r, r)]  # (F, 3)
    part = X[:, [src.get(int(q), int(q)) for q in np.maximum(P, 0)]]  # (F, K, 3)
    diff = part - own[:, None]
    d = np.sqrt(np.einsum("fki,fki->fk", diff, diff))
    z = (d - model.dist[r].astype(np.float32)) * (1.0 / model.spread[r]).astype(np.float32)
    z2 = np.minimum(z * z, np.float32(tau * tau))
    v = np.isfinite(z2) & has
    cnt = v.sum(-1)
    tot = np.where(v, z2, np.float32(0.0)).sum(-1)
    here = np.isfinite(own[:, 0])
    return np.where(cnt >= min_partners, tot / np.maximum(cnt, 1), np.where(here, 0.5 * tau * tau, 0.0))
