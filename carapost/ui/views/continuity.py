"""Continuity chart: one bar per point coloured by the number of contributing cameras.

Dark green 4 / light green 3 / yellow 2 / orange 1 / red interpolated / nothing for a gap;
expanded points (double-click, or "Expand all") add one bar per sensor: dark blue blob, light
blue patch, white keyframe, green..red target-track quality. Bars are drawn as one ``QImage``
for all visible rows (numpy colour lookup, columns reduced so short gaps stay visible), so a
10,000-frame take with hundreds of points scrolls and scrubs smoothly. The Selected Point pane
draws the same bars with :class:`ContinuityData` and :func:`render_rows`.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QColor, QImage, QMouseEvent, QPainter, QPen, QWheelEvent
from PySide6.QtWidgets import QApplication, QHBoxLayout, QMenu, QScrollBar, QWidget

from carapost.ops import settings as settings_ops

from .. import queries
from ..document import Document
from .base import NO_TAKE, BaseView, add_action, draw_hint, plain_right_click

__all__ = ["ContinuityView", "ContinuityData", "render_rows", "CONTINUITY_LUT", "SENSOR_LUT"]

BACKGROUND = 0xFF26282E


def _rgb(r: int, g: int, b: int) -> int:
    return 0xFF000000 | (r << 16) | (g << 8) | b


CONTINUITY_LUT = np.array([BACKGROUND, _rgb(220, 30, 30), _rgb(255, 140, 0), _rgb(240, 220, 0), _rgb(120, 220, 90),
                           _rgb(0, 120, 40)], np.uint32)
SENSOR_LUT = np.full(queries.S_TARGET0 + queries.N_TARGET_LEVELS, BACKGROUND, np.uint32)
SENSOR_LUT[[queries.S_BLOB, queries.S_PATCH, queries.S_KEYFRAME]] = [_rgb(20, 60, 200), _rgb(110, 180, 255),
                                                                     _rgb(255, 255, 255)]
_t = np.linspace(0, 1, queries.N_TARGET_LEVELS)
SENSOR_LUT[queries.S_TARGET0:] = [_rgb(int(230 * (1 - v)), int(60 + 170 * v), 30) for v in _t]
LABEL_W = 130
ROW_H, SENSOR_H, GAP_H = 13, 10, 2


class ContinuityData:
    """Continuity codes of the open take, recomputed lazily after each change."""

    def __init__(self, doc: Document) -> None:
        self.doc = doc
        self._codes: np.ndarray | None = None
        self._sensor: np.ndarray | None = None
        self.version = 0

    def invalidate(self) -> None:
        self._codes = self._sensor = None
        self.version += 1

    def codes(self) -> np.ndarray:
        """(F, P) overall codes."""
        if self._codes is None:
            take = self.doc.take
            xyz = take.xyz_stabilized if self.doc.show_stabilized else take.xyz
            self._codes = queries.continuity_codes(xyz, take.obs_xy)
        return self._codes

    def sensor(self) -> np.ndarray:
        """(F, P, C) per-sensor codes."""
        if self._sensor is None:
            take = self.doc.take
            kf = take.keyframes
            self._sensor = queries.sensor_codes(take.obs_src, take.obs_q, take.obs_xy,
                                                (kf.frame, kf.point_id, kf.camera), take.points.ids)
        return self._sensor

    def rows(self, rows: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
        """Codes ``(R, F)`` and sensor-row flags of rows ``(column, camera or -1)``."""
        F = self.doc.take.n_frames
        out = np.zeros((len(rows), F), np.uint8)
        is_sensor = np.array([c >= 0 for _, c in rows], bool)
        if len(rows):
            cols = np.array([p for p, _ in rows], np.int64)
            cams = np.array([c for _, c in rows], np.int64)
            if (~is_sensor).any():
                out[~is_sensor] = self.codes()[:, cols[~is_sensor]].T
            if is_sensor.any():
                out[is_sensor] = self.sensor()[:, cols[is_sensor], cams[is_sensor]].T
        return out, is_sensor


def render_rows(codes: np.ndarray, is_sensor: np.ndarray, f0: int, f1: int, width: int,
                heights: np.ndarray) -> QImage:
    """An image of continuity bars: row ``i`` is ``heights[i]`` pixels tall (plus a gap)."""
    width = max(int(width), 1)
    rgb = np.full((len(codes), width), BACKGROUND, np.uint32)
    for flag, lut, pr in ((False, CONTINUITY_LUT, queries.CONTINUITY_PRIORITY), (True, SENSOR_LUT,
                                                                              queries.SENSOR_PRIORITY)):
        m = is_sensor == flag
        if m.any():
            rgb[m] = lut[queries.reduce_columns(codes[m], f0, f1, width, pr)]
    blank = np.full((1, width), BACKGROUND, np.uint32)
    full = np.vstack([rgb, blank])
    R = len(codes)
    seq = np.stack([np.arange(R), np.full(R, R)], 1).ravel()          # row i, then the blank row
    reps = np.stack([np.asarray(heights, np.int64), np.full(R, GAP_H)], 1).ravel()
    order = np.repeat(seq, reps)
    pixels = np.ascontiguousarray(full[order]) if len(order) else np.ascontiguousarray(blank)
    img = QImage(pixels.data, width, pixels.shape[0], width * 4, QImage.Format.Format_RGB32).copy()
    return img


class _Canvas(QWidget):
    """The drawing surface of a :class:`ContinuityView` (labels column and bars)."""

    def __init__(self, view: "ContinuityView") -> None:
        super().__init__(view)
        self.view = view
        self.setMouseTracking(False)
        self.setMinimumSize(200, 60)
        self.setContextMenuPolicy(Qt.ContextMenuPolicy.CustomContextMenu)
        self.customContextMenuRequested.connect(
            lambda pos: plain_right_click(QApplication.keyboardModifiers()) and view.request_context_menu(
                self.mapToGlobal(pos)))

    def paintEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        p = QPainter(self)
        try:
            self.view.paint(p, self.width(), self.height())
        finally:
            p.end()

    def mousePressEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        self.view.press(e)

    def mouseMoveEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        self.view.move(e)

    def mouseReleaseEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        self.view.release(e)

    def mouseDoubleClickEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        self.view.double_click(e)

    def wheelEvent(self, e: QWheelEvent) -> None:  # noqa: N802
        self.view.wheelEvent(e)


class ContinuityView(BaseView):
    """The continuity chart of all points (or, after "Fit to data", the selected ones)."""

    kind = "continuity"

    def __init__(self, doc: Document, parent: QWidget | None = None) -> None:
        super().__init__(doc, parent)
        self.data = ContinuityData(doc)
        self.expanded: set[int] = set()       # point ids
        self.only: list[int] | None = None    # point ids shown after "Fit to data"
        self.x_range: tuple[int, int] | None = None
        self._drag: dict | None = None
        self._cache: tuple[tuple, QImage] | None = None
        lay = QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(0)
        self.canvas = _Canvas(self)
        self.scroll = QScrollBar(Qt.Orientation.Vertical)
        self.scroll.valueChanged.connect(self.canvas.update)
        lay.addWidget(self.canvas, 1)
        lay.addWidget(self.scroll)

    def title(self) -> str:
        return "Continuity"

    # ------------------------------------------------------------------ rows
    def rows(self) -> list[tuple[int, int]]:
        if not self.doc.has_take:
            return []
        take = self.doc.take
        ids = take.points.ids
        cols = range(take.n_points) if self.only is None else [int(np.flatnonzero(ids == i)[0])
                                                               for i in self.only if np.any(ids == i)]
        out = []
        for c in cols:
            out.append((c, -1))
            if int(ids[c]) in self.expanded:
                out.extend((c, k) for k in range(take.n_cameras))
        return out

    def _layout(self) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray]:
        rows = self.rows()
        h = np.array([SENSOR_H if c >= 0 else ROW_H for _, c in rows], np.int64)
        tops = np.r_[0, np.cumsum(h + GAP_H)][:-1] if len(rows) else np.zeros(0, np.int64)
        total = int((h + GAP_H).sum()) if len(rows) else 0
        self.scroll.setRange(0, max(0, total - self.canvas.height()))
        self.scroll.setPageStep(max(1, self.canvas.height()))
        return rows, h, tops

    def frames(self) -> tuple[int, int]:
        if not self.doc.has_take:
            return (0, 0)
        return self.x_range if self.x_range is not None else self.doc.take.view_range

    def frame_at(self, x: float, width: int) -> int:
        f0, f1 = self.frames()
        bw = max(width - LABEL_W, 1)
        return int(np.clip(f0 + np.floor((x - LABEL_W) / bw * (f1 - f0 + 1)), f0, f1))

    def x_of(self, frame: float, width: int) -> float:
        f0, f1 = self.frames()
        return LABEL_W + (frame - f0 + 0.5) / (f1 - f0 + 1) * (width - LABEL_W)

    # ------------------------------------------------------------------ hooks
    def on_session(self) -> None:
        self.expanded.clear()
        self.only = None
        self.x_range = None
        self.on_take()

    def on_take(self) -> None:
        self.data.invalidate()
        self._cache = None
        self.canvas.update()

    def on_display(self) -> None:
        self.on_take()

    def on_frame(self, frame: int) -> None:
        self.canvas.update()

    def on_selection(self) -> None:
        self.canvas.update()

    # ------------------------------------------------------------------ painting
    def paint(self, p: QPainter, width: int, height: int) -> None:
        p.fillRect(0, 0, width, height, QColor(BACKGROUND))
        if not self.doc.has_take:
            draw_hint(p, QRectF(0, 0, width, height), NO_TAKE)
            return
        if self.doc.take.n_points == 0:
            draw_hint(p, QRectF(0, 0, width, height), "No points yet\n(Process > Initialize 3D, or Edit > Create"
                      " Points From Detections)")
            return
        take = self.doc.take
        rows, h, tops = self._layout()
        y0 = self.scroll.value()
        vis = np.flatnonzero((tops + h >= y0) & (tops <= y0 + height))
        f0, f1 = self.frames()
        bw = width - LABEL_W
        if len(vis) and bw > 0:
            key = (self.data.version, f0, f1, bw, tuple(vis[[0, -1]]), len(rows), tuple(self.expanded),
                   self.doc.show_stabilized)
            if self._cache is None or self._cache[0] != key:
                codes, is_sensor = self.data.rows([rows[i] for i in vis])
                self._cache = (key, render_rows(codes, is_sensor, f0, f1, bw, h[vis]))
            p.drawImage(QPointF(LABEL_W, tops[vis[0]] - y0), self._cache[1])
        a, b = take.active_range
        shade = QColor(0, 0, 0, 110)
        xa, xb = self.x_of(a - 0.5, width), self.x_of(b + 0.5, width)
        if xa > LABEL_W:
            p.fillRect(QRectF(LABEL_W, 0, xa - LABEL_W, height), shade)
        if xb < width:
            p.fillRect(QRectF(xb, 0, width - xb, height), shade)
        sel = set(self.doc.selected_columns())
        font = p.font()
        font.setPixelSize(11)
        small = p.font()
        small.setPixelSize(SENSOR_H - 1)   # sensor rows: the text fits its row (no overlap)
        for i in vis:
            col, cam = rows[i]
            y = tops[i] - y0
            p.setFont(font if cam < 0 else small)
            if col in sel and cam < 0:   # the selected point's name and an outline round its bar
                p.fillRect(QRectF(0, y - 1, LABEL_W - 2, h[i] + 2), QColor(60, 90, 150))
                p.setPen(QPen(QColor(120, 170, 255), 1))
                p.setBrush(Qt.BrushStyle.NoBrush)
                p.drawRect(QRectF(LABEL_W - 1.5, y - 1.5, width - LABEL_W + 0.5, h[i] + 2))
            p.setPen(QColor(230, 230, 230) if cam < 0 else QColor(160, 160, 170))
            text = take.points.name(col) if cam < 0 else f"    Sensor {cam}"
            p.drawText(QRectF(4, y, LABEL_W - 8, h[i]), Qt.AlignmentFlag.AlignVCenter, text)
        x = self.x_of(self.doc.frame, width)
        pen = QPen(QColor(255, 255, 255), 1)
        p.setPen(pen)
        p.drawLine(QPointF(x, 0), QPointF(x, height))
        if self._drag and self._drag.get("kind") in ("range", "zoom"):
            xs = sorted((self.x_of(self._drag["f0"], width), self.x_of(self._drag["f1"], width)))
            p.fillRect(QRectF(xs[0], 0, xs[1] - xs[0], height), QColor(255, 255, 255, 50))

    # ------------------------------------------------------------------ mouse
    def _row_at(self, y: float) -> tuple[int, int] | None:
        rows, h, tops = self._layout()
        yy = y + self.scroll.value()
        hit = np.flatnonzero((tops <= yy) & (yy < tops + h + GAP_H))
        return rows[int(hit[0])] if len(hit) else None

    def press(self, e: QMouseEvent) -> None:
        if not self.doc.has_take or e.button() != Qt.MouseButton.LeftButton:
            return
        mods = e.modifiers()
        pos, w = e.position(), self.canvas.width()
        f = self.frame_at(pos.x(), w)
        if mods & Qt.KeyboardModifier.ControlModifier and pos.x() > LABEL_W:
            self._drag = {"kind": "range", "f0": f, "f1": f}
        elif (mods & Qt.KeyboardModifier.AltModifier) and (mods & Qt.KeyboardModifier.ShiftModifier):
            self._drag = {"kind": "zoom", "f0": f, "f1": f}
        else:
            row = self._row_at(pos.y())
            if row is not None:
                pid = int(self.doc.take.points.ids[row[0]])
                self.doc.select([pid], toggle=bool(mods & Qt.KeyboardModifier.ControlModifier))
            if pos.x() > LABEL_W:
                self.doc.set_frame(f)
                self._drag = {"kind": "scrub"}
        self.canvas.update()

    def move(self, e: QMouseEvent) -> None:
        if self._drag is None:
            return
        f = self.frame_at(e.position().x(), self.canvas.width())
        if self._drag["kind"] == "scrub":
            self.doc.set_frame(f)
        else:
            self._drag["f1"] = f
            self.canvas.update()

    def release(self, e: QMouseEvent) -> None:
        d, self._drag = self._drag, None
        if d is None:
            return
        lo, hi = sorted((d.get("f0", 0), d.get("f1", 0)))
        if d["kind"] == "range":
            self.doc.apply(settings_ops.set_active_range(self.doc.take, lo, hi))
        elif d["kind"] == "zoom" and hi > lo:
            self.x_range = (lo, hi)
            self._cache = None
        self.canvas.update()

    def double_click(self, e: QMouseEvent) -> None:
        row = self._row_at(e.position().y())
        if row is not None and row[1] < 0:
            pid = int(self.doc.take.points.ids[row[0]])
            self.expanded ^= {pid}
            self._cache = None
            self.canvas.update()

    # ------------------------------------------------------------------ context menu
    def fill_context_menu(self, menu: QMenu) -> None:
        add_action(menu, "Collapse all", self.collapse_all)
        add_action(menu, "Expand all", self.expand_all)
        add_action(menu, "Fit to data", self.fit_to_data)

    def collapse_all(self) -> None:
        self.expanded.clear()
        self._cache = None
        self.canvas.update()

    def expand_all(self) -> None:
        if self.doc.has_take:
            self.expanded = set(self.doc.take.points.ids.tolist())
            self._cache = None
            self.canvas.update()

    def fit_to_data(self) -> None:
        """Show the selected points only (all points if none is selected), whole view range."""
        self.only = list(self.doc.sel_points) or None
        self.x_range = None
        self._cache = None
        self.scroll.setValue(0)
        self.canvas.update()
