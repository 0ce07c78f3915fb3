"""Vectorised drawing helpers: numpy outlines and segments to one ``QPainterPath`` each.

Drawing hundreds of ellipses one ``drawEllipse`` call at a time costs a Python call per item;
building one path from numpy arrays (pyqtgraph's ``arrayToQPath``) draws them in one call.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QPointF
from PySide6.QtGui import QPainterPath, QPolygonF

__all__ = ["PathBuilder", "outlines_path", "segments_path", "crosses_path", "xs_path", "polygon", "affine", "EMPTY"]

EMPTY = QPainterPath()


class PathBuilder:
    """Collects outlines and segments (numpy arrays) drawn with one pen, then builds one path."""

    def __init__(self) -> None:
        self._x: list[np.ndarray] = []
        self._y: list[np.ndarray] = []
        self._c: list[np.ndarray] = []

    def outlines(self, ox: np.ndarray, oy: np.ndarray) -> "PathBuilder":
        """Closed outlines ``(N, K)`` (rows with NaN are skipped)."""
        ox, oy = np.asarray(ox, float), np.asarray(oy, float)
        if ox.size:
            ok = np.isfinite(ox).all(1) & np.isfinite(oy).all(1)
            c = np.ones(ox[ok].shape, np.int32)
            c[:, -1] = 0
            self._x.append(ox[ok].ravel())
            self._y.append(oy[ok].ravel())
            self._c.append(c.ravel())
        return self

    def segments(self, x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray) -> "PathBuilder":
        x0, y0, x1, y1 = (np.asarray(a, float).ravel() for a in (x0, y0, x1, y1))
        ok = np.isfinite(x0) & np.isfinite(y0) & np.isfinite(x1) & np.isfinite(y1)
        if ok.any():
            self._x.append(np.stack([x0[ok], x1[ok]], 1).ravel())
            self._y.append(np.stack([y0[ok], y1[ok]], 1).ravel())
            self._c.append(np.tile(np.array([1, 0], np.int32), int(ok.sum())))
        return self

    def crosses(self, x: np.ndarray, y: np.ndarray, r: np.ndarray | float) -> "PathBuilder":
        x, y = np.asarray(x, float), np.asarray(y, float)
        r = np.broadcast_to(np.asarray(r, float), x.shape)
        return self.segments(np.r_[x - r, x], np.r_[y, y - r], np.r_[x + r, x], np.r_[y, y + r])

    def xs(self, x: np.ndarray, y: np.ndarray, r: np.ndarray | float) -> "PathBuilder":
        x, y = np.asarray(x, float), np.asarray(y, float)
        r = np.broadcast_to(np.asarray(r, float), x.shape)
        return self.segments(np.r_[x - r, x - r], np.r_[y - r, y + r], np.r_[x + r, x + r], np.r_[y + r, y - r])

    def path(self) -> QPainterPath:
        if not self._x:
            return QPainterPath()
        x, y, c = np.concatenate(self._x), np.concatenate(self._y), np.concatenate(self._c)
        if len(x) == 0:
            return QPainterPath()
        return pg.arrayToQPath(x, y, connect=c, finiteCheck=False)


def outlines_path(ox: np.ndarray, oy: np.ndarray) -> QPainterPath:
    """Closed outlines ``(N, K)`` (last vertex repeats the first) as one path."""
    ox, oy = np.asarray(ox, float), np.asarray(oy, float)
    if ox.size == 0:
        return QPainterPath()
    connect = np.ones(ox.shape, np.int32)
    connect[:, -1] = 0
    ok = np.isfinite(ox).all(1) & np.isfinite(oy).all(1)
    if not ok.all():
        ox, oy, connect = ox[ok], oy[ok], connect[ok]
        if ox.size == 0:
            return QPainterPath()
    return pg.arrayToQPath(ox.ravel(), oy.ravel(), connect=connect.ravel(), finiteCheck=False)


def segments_path(x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray) -> QPainterPath:
    """Line segments ``(x0, y0) -> (x1, y1)`` (each (N,)) as one path; NaN segments skipped."""
    x0, y0, x1, y1 = (np.asarray(a, float).ravel() for a in (x0, y0, x1, y1))
    ok = np.isfinite(x0) & np.isfinite(y0) & np.isfinite(x1) & np.isfinite(y1)
    if not ok.any():
        return QPainterPath()
    x = np.stack([x0[ok], x1[ok]], 1).ravel()
    y = np.stack([y0[ok], y1[ok]], 1).ravel()
    return pg.arrayToQPath(x, y, connect="pairs", finiteCheck=False)


def crosses_path(x: np.ndarray, y: np.ndarray, r: np.ndarray | float) -> QPainterPath:
    """``+`` marks of half-size ``r`` centred on ``(x, y)``."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    r = np.broadcast_to(np.asarray(r, float), x.shape)
    return segments_path(np.r_[x - r, x], np.r_[y, y - r], np.r_[x + r, x], np.r_[y, y + r])


def xs_path(x: np.ndarray, y: np.ndarray, r: np.ndarray | float) -> QPainterPath:
    """``x`` marks of half-size ``r`` centred on ``(x, y)``."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    r = np.broadcast_to(np.asarray(r, float), x.shape)
    return segments_path(np.r_[x - r, x - r], np.r_[y - r, y + r], np.r_[x + r, x + r], np.r_[y + r, y - r])


def polygon(xy: np.ndarray) -> QPolygonF:
    """A ``QPolygonF`` from ``(N, 2)`` points."""
    return QPolygonF([QPointF(float(a), float(b)) for a, b in np.asarray(xy, float).reshape(-1, 2)])


def affine(M: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Apply a 2x3 affine matrix to points ``(..., 2)``."""
    xy = np.asarray(xy, float)
    return xy @ M[:, :2].T + M[:, 2]
