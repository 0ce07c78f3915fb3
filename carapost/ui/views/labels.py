"""Drawing point labels readably: placed without overlaps (:func:`~carapost.ui.label_layout.place_labels`),
on a dark translucent plate so they read on the white brim card as on the dark background, with
a thin leader line when a label had to move away from its point.

Cheap enough to label every point while scrubbing: text sizes and ``QStaticText`` objects are
cached, plates and leader lines are one path each, and while scrubbing (``reuse=True``) the
previous placement is kept relative to the moving points (no new layout; a label new in the
frame waits at most half a second) until the view settles.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
from PySide6.QtCore import QPointF, QRectF
from PySide6.QtGui import QColor, QFont, QFontMetricsF, QPainter, QPainterPath, QPen, QStaticText

from ..label_layout import place_labels
from .paths import segments_path

__all__ = ["LabelPainter", "PLATE", "PAD"]

PLATE = QColor(24, 26, 30)        #: label background (opaque: no blending cost)
LEADER = QColor(150, 152, 158)    #: leader lines (opaque)
PAD = 2.0                         #: px around the text
SELECTED = QColor(0, 255, 255)
RELAYOUT_S = 0.5                  #: while scrubbing, labels new in the frame are placed at most this often


class LabelPainter:
    """Draws labels for one view, remembering text sizes and the last placement."""

    def __init__(self) -> None:
        self._sizes: dict[tuple[str, str], tuple[float, float]] = {}
        self._static: dict[tuple[str, str], QStaticText] = {}
        self._last: tuple[tuple, dict[str, tuple[float, float]]] | None = None
        self._when = 0.0
        #: boxes ``x0 y0 x1 y1`` (N, 4) of the labels drawn last (NaN rows: left out)
        self.boxes = np.zeros((0, 4))

    def _size(self, fkey: str, fm: QFontMetricsF, text: str) -> tuple[float, float]:
        k = (fkey, text)
        s = self._sizes.get(k)
        if s is None:
            if len(self._sizes) > 8192:
                self._sizes.clear()
            s = self._sizes[k] = (fm.horizontalAdvance(text) + 2 * PAD, fm.height() + PAD)
        return s

    def _text(self, fkey: str, text: str) -> QStaticText:
        k = (fkey, text)
        st = self._static.get(k)
        if st is None:
            if len(self._static) > 8192:
                self._static.clear()
            st = self._static[k] = QStaticText(text)
            st.setPerformanceHint(QStaticText.PerformanceHint.AggressiveCaching)
        return st

    def draw(self, p: QPainter, anchors: np.ndarray, texts: Sequence[str], *, mark: float, font: QFont,
             obstacles: np.ndarray | None = None, highlight: Sequence[bool] | None = None,
             reuse: bool = False) -> np.ndarray:
        """Draw ``texts`` next to ``anchors`` (N, 2) widget px, in priority order.

        ``obstacles`` (M, 2) are other marks to keep clear of; ``highlight`` (N,) labels are
        drawn cyan (selected points); ``reuse`` (scrubbing) keeps each label's previous offset
        from its point instead of a new layout, placing labels new in the frame at most every
        ``RELAYOUT_S`` seconds. Returns which labels were drawn (N,)
        bool: a label with no free place is left out rather than drawn over another.
        """
        anchors = np.asarray(anchors, float).reshape(-1, 2)
        n = len(anchors)
        if n == 0:
            self.boxes = np.zeros((0, 4))
            return np.zeros(0, bool)
        p.setFont(font)
        fkey = font.key()
        fm = QFontMetricsF(font)
        sizes = np.array([self._size(fkey, fm, t) for t in texts], float)
        dev = p.device()
        bounds = (float(dev.width()), float(dev.height()))
        key = (fkey, bounds, float(mark))
        fresh = self._last is not None and self._last[0] == key and time.monotonic() - self._when < RELAYOUT_S
        if reuse and self._last is not None and self._last[0] == key and (
                fresh or all(t in self._last[1] for t in texts)):
            # every label keeps its offset from its point; one not placed last time waits
            last = self._last[1]
            offsets = np.array([last.get(t, (np.nan, np.nan)) for t in texts], float).reshape(-1, 2)
            placed = np.isfinite(offsets).all(1)
            corners = anchors + offsets
        else:
            corners, placed = place_labels(anchors, sizes, mark=mark, bounds=bounds, obstacles=obstacles)
            off = corners - anchors
            self._when = time.monotonic()
            self._last = (key, {t: tuple(off[i]) for i, t in enumerate(texts) if placed[i]})
        self.boxes = np.where(placed[:, None], np.c_[corners, corners + sizes], np.nan)
        idx = np.flatnonzero(placed)
        if len(idx) == 0:
            return placed
        hi = np.zeros(n, bool) if highlight is None else np.asarray(highlight, bool)
        lo, wh = corners[idx], sizes[idx]
        near = np.clip(anchors[idx], lo, lo + wh)          # nearest point of each label to its mark
        far = np.hypot(*(near - anchors[idx]).T) > mark * 1.8 + 2
        p.save()
        if far.any():
            p.setPen(QPen(LEADER, 1.0))
            a, b = anchors[idx][far], near[far]
            p.drawPath(segments_path(a[:, 0], a[:, 1], b[:, 0], b[:, 1]))
        plates = QPainterPath()
        for (x, y), (w, h) in zip(lo.tolist(), wh.tolist()):
            plates.addRoundedRect(QRectF(x, y, w, h), 2.5, 2.5)
        p.fillPath(plates, PLATE)
        white = QColor(255, 255, 255)
        current = None
        for j, i in enumerate(idx.tolist()):
            colour = SELECTED if hi[i] else white
            if colour is not current:
                p.setPen(colour)
                current = colour
            p.drawStaticText(QPointF(lo[j, 0] + PAD, lo[j, 1] + PAD / 2), self._text(fkey, texts[i]))
        p.restore()
        return placed
