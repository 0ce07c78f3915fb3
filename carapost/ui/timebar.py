"""The timebar: play controls, frame stepping, the time slider with the active and view
ranges, and the progress bar of long operations under the play controls."""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt, QTimer, Signal
from PySide6.QtGui import QColor, QMouseEvent, QPainter, QPen, QWheelEvent
from PySide6.QtWidgets import QHBoxLayout, QLabel, QSpinBox, QToolButton, QVBoxLayout, QWidget

from carapost.ops import settings as settings_ops

from .document import Document
from .workers import JobRunner, ProgressPanel

__all__ = ["Timebar", "TimeSlider"]


class TimeSlider(QWidget):
    """The frames of the view range, the active range (highlighted), keyframes of the selected
    points (ticks) and the current frame. Click or drag to scrub; Ctrl+drag sets the active
    range; the wheel steps frames."""

    rangeDragged = Signal(int, int)

    def __init__(self, doc: Document, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        self._drag: dict | None = None
        self.setMinimumHeight(30)
        self.setMinimumWidth(120)
        for sig in (doc.frameChanged, doc.takeChanged, doc.sessionChanged, doc.selectionChanged):
            sig.connect(self.update)

    def _range(self) -> tuple[int, int]:
        return self.doc.take.view_range if self.doc.has_take else (0, 0)

    def x_of(self, f: float) -> float:
        a, b = self._range()
        return 8 + (f - a) / max(b - a, 1) * (self.width() - 16)

    def frame_at(self, x: float) -> int:
        a, b = self._range()
        return int(np.clip(round(a + (x - 8) / max(self.width() - 16, 1) * (b - a)), a, b))

    def paintEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        p = QPainter(self)
        try:
            h = self.height()
            p.fillRect(self.rect(), QColor(34, 36, 40))
            if not self.doc.has_take:
                return
            take = self.doc.take
            a, b = self._range()
            p.fillRect(QRectF(8, h / 2 - 4, self.width() - 16, 8), QColor(70, 72, 78))
            ra, rb = take.active_range
            x0, x1 = self.x_of(max(ra, a)), self.x_of(min(rb, b))
            if x1 >= x0:
                p.fillRect(QRectF(x0, h / 2 - 4, max(x1 - x0, 2), 8), QColor(70, 130, 200))
            span = max(b - a, 1)
            per_px = span / max(self.width() - 16, 1)
            step = next(k * 10 ** e for e in range(0, 9) for k in (1, 2, 5) if k * 10 ** e / per_px >= 45)
            p.setPen(QColor(150, 150, 150))
            font = p.font()
            font.setPointSize(7)
            p.setFont(font)
            first = int(np.ceil(a / step) * step)
            ticks = np.arange(first, b + 1, step)
            if len(ticks) <= 40:
                for t in ticks:
                    x = self.x_of(t)
                    p.drawLine(QPointF(x, h - 9), QPointF(x, h - 5))
                    p.drawText(QPointF(x + 2, h - 1), str(take.first_frame_number + int(t)))
            kf = take.keyframes
            if len(kf) and self.doc.sel_points:
                frames = np.unique(kf.frame[np.isin(kf.point_id, self.doc.sel_points)])
                p.setPen(QPen(QColor(255, 255, 255), 1))
                for f in frames[(frames >= a) & (frames <= b)]:
                    x = self.x_of(f)
                    p.drawLine(QPointF(x, 2), QPointF(x, 8))
            if self._drag and self._drag.get("kind") == "range":
                lo, hi = sorted((self._drag["f0"], self._drag["f1"]))
                x0 = self.x_of(lo)
                p.fillRect(QRectF(x0, 0, max(self.x_of(hi) - x0, 2), h), QColor(255, 255, 255, 50))
            x = self.x_of(self.doc.frame)
            p.setPen(QPen(QColor(255, 200, 0), 2))
            p.drawLine(QPointF(x, 1), QPointF(x, h - 10))
        finally:
            p.end()

    def mousePressEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        if not self.doc.has_take or e.button() != Qt.MouseButton.LeftButton:
            return
        f = self.frame_at(e.position().x())
        if e.modifiers() & Qt.KeyboardModifier.ControlModifier:
            self._drag = {"kind": "range", "f0": f, "f1": f}
        else:
            self._drag = {"kind": "scrub"}
            self.doc.set_frame(f)

    def mouseMoveEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        if self._drag is None:
            return
        f = self.frame_at(e.position().x())
        if self._drag["kind"] == "range":
            self._drag["f1"] = f
            self.update()
        else:
            self.doc.set_frame(f)

    def mouseReleaseEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        d, self._drag = self._drag, None
        if d is not None and d["kind"] == "range":
            lo, hi = sorted((d["f0"], d["f1"]))
            self.doc.apply(settings_ops.set_active_range(self.doc.take, lo, hi))
        self.update()

    def wheelEvent(self, e: QWheelEvent) -> None:  # noqa: N802
        if self.doc.has_take:
            self.doc.set_frame(self.doc.frame + (-1 if e.angleDelta().y() > 0 else 1))
        e.accept()


class Timebar(QWidget):
    """Play/stop, stepping, frame number, time slider, layout buttons and the job progress."""

    layoutRequested = Signal(int)

    def __init__(self, doc: Document, jobs: JobRunner, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        outer = QVBoxLayout(self)
        outer.setContentsMargins(2, 2, 2, 2)
        outer.setSpacing(1)
        row = QHBoxLayout()
        row.setSpacing(2)
        self.buttons: dict[str, QToolButton] = {}
        for key, text, tip in (("start", "|<", "Go to Start Frame (Home)"),
                               ("prev_key", "<<", "Prev Key Frame (Shift+Left)"),
                               ("prev", "<", "Prev Frame (Left)"), ("play", "Play", "Play / Stop (Space)"),
                               ("next", ">", "Next Frame (Right)"),
                               ("next_key", ">>", "Next Key Frame (Shift+Right)"),
                               ("end", ">|", "Go to End Frame (End)")):
            b = QToolButton()
            b.setText(text)
            b.setToolTip(tip)
            b.setObjectName(f"time_{key}")
            b.setAutoRaise(True)
            b.setFocusPolicy(Qt.FocusPolicy.NoFocus)
            row.addWidget(b)
            self.buttons[key] = b
        self.buttons["play"].setMinimumWidth(44)
        self.spin = QSpinBox()
        self.spin.setKeyboardTracking(False)
        self.spin.setToolTip("Current frame (0-based)")
        self.spin.valueChanged.connect(self.doc.set_frame)
        row.addWidget(self.spin)
        self.info = QLabel()
        self.info.setMinimumWidth(1)   # shrinks (clipped) before the slider does in a small window
        row.addWidget(self.info)
        self.slider = TimeSlider(doc)
        row.addWidget(self.slider, 1)
        for n in (1, 2, 4):
            b = QToolButton()
            b.setText(str(n))
            b.setObjectName(f"layout_{n}")
            b.setToolTip(f"Workspace: {n} view{'s' if n > 1 else ''} (restores the default zoom)")
            b.setFocusPolicy(Qt.FocusPolicy.NoFocus)
            b.clicked.connect(lambda _c=False, nn=n: self.layoutRequested.emit(nn))
            row.addWidget(b)
        outer.addLayout(row)
        self.progress = ProgressPanel(jobs)
        outer.addWidget(self.progress)
        self.timer = QTimer(self)
        self.timer.timeout.connect(self._tick)
        self.buttons["start"].clicked.connect(lambda: doc.set_frame(0))
        self.buttons["end"].clicked.connect(lambda: doc.set_frame(doc.n_frames - 1))
        self.buttons["prev"].clicked.connect(lambda: doc.set_frame(doc.frame - 1))
        self.buttons["next"].clicked.connect(lambda: doc.set_frame(doc.frame + 1))
        self.buttons["play"].clicked.connect(self.toggle_play)
        doc.frameChanged.connect(self._frame)
        doc.sessionChanged.connect(self._session)
        doc.takeChanged.connect(self._session)
        self._session()

    @property
    def playing(self) -> bool:
        return self.timer.isActive()

    def toggle_play(self) -> None:
        """Play (Space): every frame at the take's rate; the button becomes Stop."""
        if self.playing:
            self.stop()
        elif self.doc.has_take:
            if self.doc.frame >= self.doc.take.view_range[1]:
                self.doc.set_frame(self.doc.take.view_range[0])
            self.timer.start(max(1, int(round(1000 / self.doc.take.frame_rate))))
            self.buttons["play"].setText("Stop")

    def stop(self) -> None:
        self.timer.stop()
        self.buttons["play"].setText("Play")

    def _tick(self) -> None:
        if not self.doc.has_take or self.doc.frame >= self.doc.take.view_range[1]:
            self.stop()
            return
        self.doc.set_frame(self.doc.frame + 1)

    def _session(self) -> None:
        has = self.doc.has_take
        self.spin.blockSignals(True)
        self.spin.setRange(0, max(0, self.doc.n_frames - 1) if has else 0)
        self.spin.setValue(self.doc.frame)
        self.spin.blockSignals(False)
        self.setEnabled(True)
        for b in self.buttons.values():
            b.setEnabled(has)
        self.spin.setEnabled(has)
        if not has:
            self.stop()
        self._frame(self.doc.frame)

    def _frame(self, f: int) -> None:
        self.spin.blockSignals(True)
        self.spin.setValue(f)
        self.spin.blockSignals(False)
        if self.doc.has_take:
            take = self.doc.take
            a, b = take.active_range
            self.info.setText(f"of {take.n_frames - 1}   #{take.first_frame_number + f}   active {a}-{b}")
            self.info.setToolTip(f"Last frame {take.n_frames - 1}; frame number #{take.first_frame_number + f}; "
                                 f"active range {a}-{b}")
        else:
            self.info.setText("")
