"""Align Data: a coordinate frame defined by three points.

Convention (right-handed, documented in ``docs/stabilization.md``):

* the **origin** is the first point ``p0``;
* the **x axis** points from ``p0`` towards the second point ``p1``;
* the third point ``p2`` lies in the **xy plane**, on the side of positive ``y``;
* ``z = x × y``.

The aligned coordinates of a point ``X`` are ``A (X - p0)``, whose rows are the unit axes.
"""

from __future__ import annotations

import numpy as np

__all__ = ["frame_from_points", "apply_frame"]


def frame_from_points(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frame of three points (see the module docstring).

    Parameters
    ----------
    p0, p1, p2 : arrays (3,)
        Points, mm.

    Returns
    -------
    A : array (3, 3)
        Rotation whose rows are the new x, y, z axes in the old coordinates.
    origin : array (3,)
        ``p0``.

    Raises
    ------
    ValueError
        If a point is missing (NaN) or the three points are (nearly) collinear.
    """
    p0, p1, p2 = (np.asarray(p, dtype=float).reshape(3) for p in (p0, p1, p2))
    if not (np.isfinite(p0).all() and np.isfinite(p1).all() and np.isfinite(p2).all()):
        raise ValueError("Align Data: each of the three points needs a position in the frame")
    x = p1 - p0
    nx = np.linalg.norm(x)
    scale = max(nx, np.linalg.norm(p2 - p0), 1e-12)
    if nx < 1e-9 * scale or nx == 0:
        raise ValueError("Align Data: the first two points coincide")
    x = x / nx
    v = p2 - p0
    y = v - (v @ x) * x
    ny = np.linalg.norm(y)
    if ny < 1e-6 * scale:
        raise ValueError("Align Data: the three points are collinear")
    y = y / ny
    z = np.cross(x, y)
    return np.stack([x, y, z]), p0


def apply_frame(xyz: np.ndarray, A: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """``A (X - origin)`` for points ``(..., 3)``; NaN stays NaN."""
    xyz = np.asarray(xyz, dtype=float)
    return np.einsum("ij,...j->...i", A, xyz - origin)
