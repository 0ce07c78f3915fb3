"""Seed 002's hand heuristics: repair swapped finger markers in one labelled frame.

They apply to marker sets named like ``Hands_R_L4``: ``Hands_``, the hand (``R`` / ``L``), the
finger (``T`` thumb, ``I`` index, ``M`` middle, ``R`` ring, ``L`` little) and the joint (1 at the
knuckle (MCP) to 4 at the fingertip). Each finger is a chain 1-2-3-4 of "bones".

* **Crossing bones**: when the bones of two neighbouring fingers cross in 3D (their closest
  points lie inside both bones and are within ``crossover_mm``), the markers beyond the
  crossing are swapped between the fingers - if the swap uncrosses them.
* **Impossible fingertip bend**: when the fingertip bends backwards (the angle between bones
  2-3 and 3-4 is at least ``tip_angle`` radians, i.e. the DIP joint angle is below about 65
  degrees at the default), the fingertip and DIP markers (3 and 4) are swapped - if that
  straightens the finger.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["HandModel", "hand_model", "hand_skeleton", "segment_crossing", "hand_swaps"]

_NAME = re.compile(r"^Hands_([RL])_([TIMRL])([1-4])$")
_FINGERS = "TIMRL"


@dataclass(frozen=True)
class HandModel:
    """Marker indices of the hand naming scheme.

    Attributes
    ----------
    fingers : dict
        ``fingers[(hand, finger)] = [i1, i2, i3, i4]`` marker indices (-1 where absent), e.g.
        ``fingers[("R", "I")]``.
    """

    fingers: dict[tuple[str, str], list[int]]

    def neighbour_pairs(self) -> list[tuple[list[int], list[int]]]:
        """Chains of neighbouring fingers of the same hand (thumb-index, index-middle, ...)."""
        out = []
        for hand in "RL":
            for a, b in zip(_FINGERS[:-1], _FINGERS[1:]):
                if (hand, a) in self.fingers and (hand, b) in self.fingers:
                    out.append((self.fingers[(hand, a)], self.fingers[(hand, b)]))
        return out


def hand_model(names: Sequence[str]) -> HandModel | None:
    """The hand model of a marker set, or None if no name follows the scheme."""
    fingers: dict[tuple[str, str], list[int]] = {}
    for i, n in enumerate(names):
        m = _NAME.match(n.strip())
        if m:
            chain = fingers.setdefault((m.group(1), m.group(2)), [-1, -1, -1, -1])
            chain[int(m.group(3)) - 1] = i
    return HandModel(fingers) if fingers else None


def hand_skeleton(names: Sequence[str]) -> np.ndarray:
    """Seed 002's skeleton for the hand scheme: each joint's parent is the previous joint of the
    same finger and its child the next one. Returns (M, 2) parent, child (-1 where none)."""
    sk = np.full((len(names), 2), -1, np.int64)
    model = hand_model(names)
    if model is None:
        return sk
    for chain in model.fingers.values():
        for a, b in zip(chain[:-1], chain[1:]):
            if a >= 0 and b >= 0:
                sk[b, 0] = a
                sk[a, 1] = b
    return sk


def segment_crossing(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> float:
    """Distance between bones ``p0-p1`` and ``q0-q1`` at their closest approach, if that
    approach lies inside both bones; inf otherwise (or for parallel bones or missing points)."""
    u, v, w0 = p1 - p0, q1 - q0, p0 - q0
    a, b, c, d, e = u @ u, u @ v, v @ v, u @ w0, v @ w0
    den = a * c - b * b
    if not np.isfinite(den) or den <= 1e-12 * max(a * c, 1e-300):
        return np.inf
    s = (b * e - c * d) / den
    t = (a * e - b * d) / den
    if not (0.0 <= s <= 1.0 and 0.0 <= t <= 1.0):
        return np.inf
    return float(np.linalg.norm(w0 + s * u - t * v))


def _angle(v1: np.ndarray, v2: np.ndarray) -> float:
    n1, n2 = np.linalg.norm(v1), np.linalg.norm(v2)
    if not (n1 > 0 and n2 > 0):
        return 0.0
    return float(np.arccos(np.clip(v1 @ v2 / (n1 * n2), -1.0, 1.0)))


def _bone(X: np.ndarray, chain: list[int], k: int) -> tuple[np.ndarray, np.ndarray] | None:
    a, b = chain[k], chain[k + 1]
    if a < 0 or b < 0 or not (np.isfinite(X[a]).all() and np.isfinite(X[b]).all()):
        return None
    return X[a], X[b]


def _crossed(X: np.ndarray, A: list[int], B: list[int], k: int, thresh: float) -> bool:
    ba, bb = _bone(X, A, k), _bone(X, B, k)
    return ba is not None and bb is not None and segment_crossing(*ba, *bb) <= thresh


def _swapped(X: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    Y = X.copy()
    for a, b in pairs:
        Y[[a, b]] = Y[[b, a]]
    return Y


def hand_swaps(X: np.ndarray, model: HandModel, *, crossover_mm: float = 5.0,
               tip_angle: float = 2.0) -> list[tuple[int, int]]:
    """Marker swaps that the hand heuristics make in one frame.

    Parameters
    ----------
    X : float (M, 3)
        The frame's labelled marker positions, mm, NaN where missing.
    model : HandModel
    crossover_mm : float
        Bones closer than this at a crossing count as crossed.
    tip_angle : float
        Radians; a bend between bones 2-3 and 3-4 at least this large is impossible.

    Returns
    -------
    list of (int, int)
        Marker index pairs whose positions (labels) are exchanged, in the order applied.
    """
    Y = np.array(X, np.float64, copy=True)
    out: list[tuple[int, int]] = []
    for A, B in model.neighbour_pairs():
        # from the fingertip bones inwards: swap the markers beyond the first crossed bone
        for k in (2, 1, 0):
            if not _crossed(Y, A, B, k, crossover_mm):
                continue
            pairs = [(A[i], B[i]) for i in range(k + 1, 4) if A[i] >= 0 and B[i] >= 0]
            if not pairs:
                break
            Z = _swapped(Y, pairs)
            if not any(_crossed(Z, A, B, j, crossover_mm) for j in range(k, 3)):
                Y = Z
                out.extend(pairs)
            break
    for chain in model.fingers.values():
        i2, i3, i4 = chain[1], chain[2], chain[3]
        if min(i2, i3, i4) < 0 or not np.isfinite(Y[[i2, i3, i4]]).all():
            continue
        if _angle(Y[i3] - Y[i2], Y[i4] - Y[i3]) >= tip_angle:
            if _angle(Y[i4] - Y[i2], Y[i3] - Y[i4]) < tip_angle:
                Y[[i3, i4]] = Y[[i4, i3]]
                out.append((i3, i4))
    return out
