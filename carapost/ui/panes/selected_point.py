"""Selected Point pane: continuity of the one selected point — an overall bar (as in the
continuity chart) and one bar per sensor (dark blue blob, light blue patch, white keyframe,
green..red target-track quality). Empty when no point or several points are selected."""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QColor, QMouseEvent, QPainter, QPen
from PySide6.QtWidgets import QWidget

from ..document import Document
from ..views.base import draw_hint
from ..views.continuity import ContinuityData, render_rows

__all__ = ["SelectedPointPane"]

LABEL_W, BAR_H, SENSOR_H = 110, 16, 11


class SelectedPointPane(QWidget):
    def __init__(self, doc: Document, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        self.data = ContinuityData(doc)
        self.setMinimumHeight(90)
        doc.takeChanged.connect(self._invalidate)
        doc.sessionChanged.connect(self._invalidate)
        doc.displayChanged.connect(self._invalidate)
        doc.selectionChanged.connect(self.update)
        doc.frameChanged.connect(lambda _f: self.update())

    def _invalidate(self) -> None:
        self.data.invalidate()
        self.update()

    def point(self) -> int:
        cols = self.doc.selected_columns()
        return cols[0] if len(cols) == 1 else -1

    def hint(self) -> str:
        """What the empty pane says."""
        if not self.doc.has_take:
            return "No take open"
        n = len(self.doc.selected_columns())
        if n == 0:
            return "Select one point to see its continuity in every sensor"
        return f"{n} points selected: select one point to see its continuity in every sensor"

    def rows(self) -> list[tuple[int, int]]:
        col = self.point()
        if col < 0:
            return []
        return [(col, -1)] + [(col, c) for c in range(self.doc.take.n_cameras)]

    def _frames(self) -> tuple[int, int]:
        return self.doc.take.view_range

    def paintEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        p = QPainter(self)
        try:
            p.fillRect(self.rect(), QColor(38, 40, 46))
            rows = self.rows() if self.doc.has_take else []
            if not rows:
                draw_hint(p, QRectF(self.rect()), self.hint())
                return
            take = self.doc.take
            f0, f1 = self._frames()
            heights = np.array([BAR_H] + [SENSOR_H] * (len(rows) - 1))
            codes, is_sensor = self.data.rows(rows)
            img = render_rows(codes, is_sensor, f0, f1, self.width() - LABEL_W - 4, heights)
            p.drawImage(QPointF(LABEL_W, 4), img)
            y = 4.0
            font = p.font()
            font.setPointSize(8)
            p.setFont(font)
            for (col, cam), h in zip(rows, heights):
                p.setPen(QColor(230, 230, 230))
                p.drawText(QRectF(4, y, LABEL_W - 6, h), Qt.AlignmentFlag.AlignVCenter,
                           take.points.name(col) if cam < 0 else f"Sensor {cam}")
                y += h + 2
            x = LABEL_W + (self.doc.frame - f0 + 0.5) / (f1 - f0 + 1) * (self.width() - LABEL_W - 4)
            p.setPen(QPen(QColor(255, 255, 255), 1))
            p.drawLine(QPointF(x, 0), QPointF(x, y + 2))
        finally:
            p.end()

    def mousePressEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        """Click on the bars to go to that frame."""
        if self.doc.has_take and self.point() >= 0 and e.position().x() > LABEL_W:
            f0, f1 = self._frames()
            w = max(self.width() - LABEL_W - 4, 1)
            self.doc.set_frame(int(f0 + (e.position().x() - LABEL_W) / w * (f1 - f0 + 1)))
