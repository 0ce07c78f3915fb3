"""Camera (2D) view: one sensor's video with detections, points, projections and labels.

Drawn with ``QPainter``: the image through a ``QTransform`` (rotation, zoom, pan), overlays as a
few ``QPainterPath`` objects built with numpy in screen coordinates (fixed-size marks at any
zoom). Colours follow the reference guide's glossary: detections red ellipses with a centre
cross, points blue rings, connected projections yellow crosses in circles, unconnected
projections orange x's in circles, errors yellow lines, blob preview green rings.

Mouse (the guide's shortcuts): click / Ctrl+click / drag a box to select; Shift+click selects
the sensor; Alt+Shift+drag lassoes; Shift or Alt + right-drag zooms; Shift or Alt + middle
(or left+right) drag pans; middle-drag or the wheel shuttles time; Ctrl+wheel zooms.
"""

from __future__ import annotations

import logging

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt, QTimer
from PySide6.QtGui import QBrush, QColor, QImage, QMouseEvent, QPainter, QTransform, QWheelEvent
from PySide6.QtWidgets import QMenu, QWidget

from .. import queries
from ..document import Document
from .base import NO_TAKE, BaseView, add_action, add_toggle, draw_hint, plain_right_click
from .blob_preview import BlobPreviewer
from .camera_overlay import Overlay, compute_overlay, image_size
from .camera_paint import GREEN, ORANGE, YELLOW, OverlayPainting, pen
from .labels import LabelPainter
from .paths import affine, outlines_path, polygon

__all__ = ["CameraView", "rotation_matrix"]

log = logging.getLogger("carapost")

PICK = 9.0          # click tolerance, screen px

OPTIONS = {"Border": True, "Image": True, "Detections": True, "Points": True, "Projections": True,
           "Connected": True, "Unconnected": True, "Errors": True, "Pixel Report": False, "ROM": False,
           "Sticks": True, "Point Labels: All": False}


def rotation_matrix(rotation: int, width: int, height: int) -> np.ndarray:
    """2x3 affine map from image pixels to the display rotated ``rotation`` degrees clockwise."""
    w1, h1 = width - 1, height - 1
    return {0: np.array([[1.0, 0, 0], [0, 1, 0]]), 90: np.array([[0.0, -1, h1], [1, 0, 0]]),
            180: np.array([[-1.0, 0, w1], [0, -1, h1]]), 270: np.array([[0.0, 1, 0], [-1, 0, w1]])}[rotation % 360]


def _qtransform(M: np.ndarray) -> QTransform:
    return QTransform(M[0, 0], M[1, 0], M[0, 1], M[1, 1], M[0, 2], M[1, 2])


class CameraView(OverlayPainting, BaseView):
    """The video of one sensor with its overlays."""

    kind = "sensor"

    def __init__(self, doc: Document, camera: int, previewer: BlobPreviewer | None = None,
                 parent: QWidget | None = None) -> None:
        super().__init__(doc, parent)
        self.camera = camera
        self.previewer = previewer
        self.options = dict(OPTIONS)
        self.scale = 1.0
        self.centre = np.zeros(2)
        self.fitted = True
        self.mode = ""                     # "Add Target Track" / "Edit Target Track" / "measure"
        self.measurement: tuple[np.ndarray, np.ndarray] | None = None
        self._drag: dict | None = None
        self._hover = -1
        self._pixel: tuple[float, float, int] | None = None
        self._qimage: tuple[tuple, QImage] | None = None
        self._labels = LabelPainter()
        self.fast = False                  # while scrubbing: no antialiasing, smooth again when idle
        self._settle = QTimer(self)
        self._settle.setSingleShot(True)
        self._settle.setInterval(150)
        self._settle.timeout.connect(self._settled)
        self.setMouseTracking(True)
        self.setMinimumSize(120, 90)
        self.setFocusPolicy(Qt.FocusPolicy.ClickFocus)
        self.setContextMenuPolicy(Qt.ContextMenuPolicy.CustomContextMenu)
        self.customContextMenuRequested.connect(self._context)
        if previewer is not None:
            self._listen(previewer.ready, self._preview_ready)

    # ------------------------------------------------------------------ geometry
    def title(self) -> str:
        if not self.doc.has_take or self.camera >= self.doc.take.n_cameras:
            return f"Sensor {self.camera}"
        return f"Sensor {self.camera} - {self.doc.take.cameras[self.camera].name}"

    def _valid_camera(self) -> bool:
        return self.doc.has_take and 0 <= self.camera < self.doc.take.n_cameras

    def _size(self) -> tuple[int, int]:
        return image_size(self.doc.take, self.camera) if self._valid_camera() else (1280, 720)

    def _rotation(self) -> int:
        return self.doc.take.cameras[self.camera].rotation if self._valid_camera() else 0

    def display_size(self) -> tuple[int, int]:
        w, h = self._size()
        return (h, w) if self._rotation() in (90, 270) else (w, h)

    def image_to_widget(self) -> np.ndarray:
        """2x3 affine map from raw image pixels to widget pixels."""
        A = rotation_matrix(self._rotation(), *self._size())
        s = self.scale
        wc = np.array([self.width() / 2.0, self.height() / 2.0])
        return np.hstack([s * A[:, :2], (s * (A[:, 2] - self.centre) + wc)[:, None]])

    def widget_to_image(self, xy: np.ndarray) -> np.ndarray:
        M = self.image_to_widget()
        inv = np.linalg.inv(np.vstack([M, [0, 0, 1]]))[:2]
        return affine(inv, xy)

    def fit_to_window(self) -> None:
        dw, dh = self.display_size()
        self.scale = max(min(self.width() / dw, self.height() / dh), 1e-3)
        self.centre = np.array([(dw - 1) / 2.0, (dh - 1) / 2.0])
        self.fitted = True
        self.update()

    def actual_size(self) -> None:
        self.scale = 1.0
        self.fitted = False
        self.update()

    def zoom_at(self, factor: float, pos: QPointF) -> None:
        p = np.array([pos.x(), pos.y()])
        wc = np.array([self.width() / 2.0, self.height() / 2.0])
        disp = (p - wc) / self.scale + self.centre
        self.scale = float(np.clip(self.scale * factor, 0.02, 64.0))
        self.centre = disp - (p - wc) / self.scale
        self.fitted = False
        self.update()

    def pan(self, dx: float, dy: float) -> None:
        self.centre = self.centre - np.array([dx, dy]) / self.scale
        self.fitted = False
        self.update()

    def _selected_xy(self) -> np.ndarray:
        if not self._valid_camera():
            return np.zeros((0, 2))
        cols = self.doc.selected_columns()
        ov = self._overlay()
        xy = ov.point_xy(self.doc.take.n_points)[cols] if cols else np.zeros((0, 2))
        dets = [d for d in self.doc.sel_detections if d[0] == self.camera and d[1] == self.doc.frame]
        if dets:
            idx = [d[2] for d in dets]
            xy = np.vstack([xy, np.c_[ov.det["x"][idx], ov.det["y"][idx]]])
        return xy[np.isfinite(xy).all(1)]

    def center_selection(self) -> None:
        xy = self._selected_xy()
        if len(xy):
            A = rotation_matrix(self._rotation(), *self._size())
            self.centre = affine(A, xy).mean(0)
            self.fitted = False
            self.update()

    def frame_selection(self) -> None:
        xy = self._selected_xy()
        if len(xy):
            A = rotation_matrix(self._rotation(), *self._size())
            d = affine(A, xy)
            lo, hi = d.min(0), d.max(0)
            span = np.maximum(hi - lo, 40.0) * 1.6
            self.centre = (lo + hi) / 2
            self.scale = float(min(self.width() / span[0], self.height() / span[1]))
            self.fitted = False
            self.update()

    def resizeEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        if self.fitted:
            self.fit_to_window()
        super().resizeEvent(event)

    # ------------------------------------------------------------------ document hooks
    def on_session(self) -> None:
        self._qimage = None
        self.fit_to_window()

    def on_take(self) -> None:
        if self.fitted:
            self.fit_to_window()
        self.update()

    def on_frame(self, frame: int) -> None:
        if self.doc.lock_to_point and self.doc.sel_points:
            self.center_selection()
        self.fast = True
        self._settle.start()
        self.update()

    def _settled(self) -> None:
        self.fast = False
        self.update()

    def _preview_ready(self, camera: int, frame: int) -> None:
        if camera == self.camera and frame == self.doc.frame and self.doc.blob_preview:
            self.update()

    def _overlay(self) -> Overlay:
        return compute_overlay(self.doc.take, self.camera, self.doc.frame)

    # ------------------------------------------------------------------ painting
    def _image(self) -> QImage | None:
        img = self.doc.image(self.camera)
        if img is None:
            return None
        key = (id(img), self.camera, self.doc.frame)
        if self._qimage is None or self._qimage[0] != key:
            h, w = img.shape
            q = QImage(img.data, w, h, int(img.strides[0]), QImage.Format.Format_Grayscale8)
            q.ndarray = img  # type: ignore[attr-defined]  # keep the pixels alive with the image
            self._qimage = (key, q)
        return self._qimage[1]

    def paintEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        p = QPainter(self)
        try:
            self._paint(p)
        finally:
            p.end()

    def _paint(self, p: QPainter) -> None:
        p.fillRect(self.rect(), QColor(60, 60, 60))
        if not self._valid_camera():
            draw_hint(p, QRectF(self.rect()), NO_TAKE if not self.doc.has_take
                      else f"The take has no sensor {self.camera}")
            return
        take, f = self.doc.take, self.doc.frame
        M = self.image_to_widget()
        w, h = self._size()
        T = _qtransform(M)
        qimg = self._image() if self.options["Image"] else None
        p.save()
        p.setTransform(T)
        if qimg is not None:
            p.setRenderHint(QPainter.RenderHint.SmoothPixmapTransform, self.scale < 1.0 and not self.fast)
            p.drawImage(QRectF(-0.5, -0.5, w, h), qimg)
        elif self.options["Border"]:
            p.fillRect(QRectF(-0.5, -0.5, w, h), QBrush(QColor(90, 90, 90), Qt.BrushStyle.Dense4Pattern))
        else:
            p.fillRect(QRectF(-0.5, -0.5, w, h), QColor(128, 128, 128))
        p.restore()
        p.setRenderHint(QPainter.RenderHint.Antialiasing, not self.fast)
        ov = self._overlay()
        sel_cols = set(self.doc.selected_columns())
        if self.options["Detections"]:
            self._paint_detections(p, M, ov)
        if self.doc.blob_preview and self.previewer is not None:
            table = self.previewer.get(self.camera, f)
            if table is not None and len(table["x"]):
                ox, oy = queries.ellipse_outlines(*(np.asarray(table[k], float) for k in ("x", "y", "major", "minor",
                                                                                          "angle")), n=20)
                q = affine(M, np.stack([ox, oy], -1))
                p.setPen(pen(GREEN, 1.5))
                p.drawPath(outlines_path(q[..., 0] , q[..., 1]))
        if self.options["Sticks"] and len(take.sticks):
            self._paint_sticks(p, M, ov)
        if self.options["Points"]:
            self._paint_points(p, M, ov, sel_cols)
        if self.options["Projections"]:
            self._paint_projections(p, M, ov, sel_cols)
        if self.options["ROM"] and self.doc.rom is not None:
            self._paint_rom(p, M)
        self._paint_keyframes(p, M)
        self._paint_selection(p, M, ov, sel_cols)
        self._paint_labels(p, M, ov, sel_cols)
        self._paint_hud(p, M)

    def _paint_hud(self, p: QPainter, M: np.ndarray) -> None:
        font = p.font()
        font.setPointSize(9)
        p.setFont(font)
        y = 16
        if self.camera in self.doc.sel_cameras:
            p.setPen(pen(ORANGE, 3))
            p.drawRect(QRectF(1.5, 1.5, self.width() - 3, self.height() - 3))
        if self.mode and self.mode != "measure":
            p.setPen(YELLOW)
            p.drawText(QPointF(8, y), self.mode)
            y += 16
        if self.options["Pixel Report"] and self._pixel is not None:
            x, yy, g = self._pixel
            p.setPen(QColor(255, 255, 255))
            p.drawText(QPointF(8, y), f"x {x:.1f}  y {yy:.1f}  grey {g}")
            y += 16
        if self.measurement is not None:
            a, b = self.measurement
            s = affine(M, np.array([a, b]))
            p.setPen(pen(GREEN, 1.5))
            p.drawLine(QPointF(*s[0]), QPointF(*s[1]))
            p.drawText(QPointF(*(s[1] + 6)), f"{np.linalg.norm(b - a):.1f} px")
        if self._drag and self._drag.get("kind") == "box" and self._drag.get("moved"):
            p.setPen(pen(QColor(255, 255, 255), 1, Qt.PenStyle.DashLine))
            p.setBrush(Qt.BrushStyle.NoBrush)
            p.drawRect(QRectF(self._drag["start"], self._drag["pos"]).normalized())
        if self._drag and self._drag.get("kind") == "lasso" and len(self._drag["points"]) > 1:
            p.setPen(pen(QColor(255, 255, 255), 1, Qt.PenStyle.DashLine))
            p.drawPolyline(polygon(np.array(self._drag["points"])))

    # ------------------------------------------------------------------ picking
    def _pick(self, pos: QPointF) -> tuple[str, object] | None:
        """The point (by id) or detection nearest to ``pos`` within the pick tolerance."""
        if not self._valid_camera():
            return None
        take, sel = self.doc.take, take_params(self)
        M = self.image_to_widget()
        ov = self._overlay()
        q = np.array([pos.x(), pos.y()])
        if sel.points and take.n_points:
            xy = affine(M, ov.point_xy(take.n_points))
            d = np.linalg.norm(xy - q, axis=1)
            d[~np.isfinite(d)] = np.inf
            if len(d) and d.min() <= PICK:
                return "point", int(take.points.ids[int(np.argmin(d))])
        if sel.detections and len(ov.det.get("x", ())):
            c = affine(M, np.c_[ov.det["x"], ov.det["y"]])
            d = np.linalg.norm(c - q, axis=1)
            tol = np.maximum(PICK, ov.det["major"] * self.scale)
            hit = d <= tol
            if hit.any():
                i = int(np.argmin(np.where(hit, d, np.inf)))
                return "detection", (self.camera, self.doc.frame, i)
        return None

    def _select_region(self, inside, add: bool) -> None:  # type: ignore[no-untyped-def]
        take, sel = self.doc.take, take_params(self)
        M = self.image_to_widget()
        ov = self._overlay()
        ids: list[int] = []
        dets: list[tuple[int, int, int]] = []
        if sel.points and take.n_points:
            xy = affine(M, ov.point_xy(take.n_points))
            ids = take.points.ids[np.flatnonzero(inside(xy))].tolist()
        if sel.detections and len(ov.det.get("x", ())):
            c = affine(M, np.c_[ov.det["x"], ov.det["y"]])
            hit = np.flatnonzero(inside(c) & (ov.det_owner < 0))
            dets = [(self.camera, self.doc.frame, int(i)) for i in hit]
        self.doc.select(ids, dets, add=add)

    # ------------------------------------------------------------------ mouse
    def mousePressEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        mods, btn, buttons = e.modifiers(), e.button(), e.buttons()
        shift_alt = bool(mods & (Qt.KeyboardModifier.ShiftModifier | Qt.KeyboardModifier.AltModifier))
        pos = e.position()
        if self._valid_camera():
            self.doc.set_active_camera(self.camera)
        both = (buttons & Qt.MouseButton.LeftButton) and (buttons & Qt.MouseButton.RightButton)
        if (btn == Qt.MouseButton.MiddleButton or both) and (shift_alt or both):
            self._drag = {"kind": "pan", "last": pos}
        elif btn == Qt.MouseButton.MiddleButton:
            self._drag = {"kind": "shuttle", "start": pos, "frame": self.doc.frame}
        elif btn == Qt.MouseButton.RightButton and shift_alt:
            self._drag = {"kind": "zoom", "last": pos, "anchor": pos}
        elif btn == Qt.MouseButton.LeftButton:
            alt = bool(mods & Qt.KeyboardModifier.AltModifier)
            shift = bool(mods & Qt.KeyboardModifier.ShiftModifier)
            if alt and shift:
                self._drag = {"kind": "lasso", "points": [(pos.x(), pos.y())]}
            elif shift:
                if self._valid_camera() and take_params(self).sensors:
                    self.doc.toggle_camera(self.camera)
                self._drag = None
            elif self.mode == "measure":
                a = self.widget_to_image(np.array([pos.x(), pos.y()]))
                self.measurement = (a, a.copy())
                self._drag = {"kind": "measure"}
            elif self.mode:
                self._point_edit_click(self.widget_to_image(np.array([pos.x(), pos.y()])))
                self._drag = None
            else:
                self._drag = {"kind": "box", "start": pos, "pos": pos, "moved": False,
                              "add": bool(mods & Qt.KeyboardModifier.ControlModifier)}
        e.accept()

    def _point_edit_click(self, xy: np.ndarray) -> None:
        """Add Target Track (a new point keyed here) / Edit Target Track (key the selected point)."""
        from ..adapters import ops

        if not self._valid_camera():
            return
        doc, take = self.doc, self.doc.take
        try:
            if self.mode == "Add Target Track":
                first = take.next_point_id
                if doc.apply(ops("target").add_target_track(take, self.camera, doc.frame, xy)):
                    doc.select(range(first, take.next_point_id))
            else:
                cols = doc.selected_columns()
                if len(cols) != 1:
                    raise ValueError("Edit Target Track: select exactly one point")
                doc.apply(ops("target").edit_target_track(take, cols[0], self.camera, doc.frame, xy))
        except ValueError as exc:
            log.error("%s", exc)

    def mouseMoveEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        pos = e.position()
        d = self._drag
        if d is None:
            self._update_hover(pos)
            return
        kind = d["kind"]
        if kind == "pan":
            self.pan(pos.x() - d["last"].x(), pos.y() - d["last"].y())
            d["last"] = pos
        elif kind == "zoom":
            self.zoom_at(float(np.exp(-(pos.y() - d["last"].y()) / 150.0)), d["anchor"])
            d["last"] = pos
        elif kind == "shuttle":
            self.doc.set_frame(d["frame"] + int((pos.x() - d["start"].x()) / 6))
        elif kind == "measure" and self.measurement is not None:
            self.measurement = (self.measurement[0], self.widget_to_image(np.array([pos.x(), pos.y()])))
            self.update()
        elif kind == "box":
            d["pos"] = pos
            d["moved"] = d["moved"] or (pos - d["start"]).manhattanLength() > 4
            self.update()
        elif kind == "lasso":
            d["points"].append((pos.x(), pos.y()))
            self.update()

    def mouseReleaseEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        d, self._drag = self._drag, None
        if d is None:
            return
        if d["kind"] == "box" and self._valid_camera():
            if d["moved"]:
                r = QRectF(d["start"], d["pos"]).normalized()
                self._select_region(lambda xy: (xy[:, 0] >= r.left()) & (xy[:, 0] <= r.right()) &
                                    (xy[:, 1] >= r.top()) & (xy[:, 1] <= r.bottom()), d["add"])
            else:
                hit = self._pick(d["start"])
                if hit is None:
                    if not d["add"]:
                        self.doc.clear_selection()
                elif hit[0] == "point":
                    self.doc.select([hit[1]], toggle=d["add"])
                else:
                    self.doc.select((), [hit[1]], toggle=d["add"])
        elif d["kind"] == "lasso" and self._valid_camera() and len(d["points"]) > 2:
            poly = np.array(d["points"])
            self._select_region(lambda xy: queries.points_in_polygon(xy, poly), False)
        elif d["kind"] == "measure":
            self.mode = ""
        self.update()

    def _update_hover(self, pos: QPointF) -> None:
        if not self._valid_camera():
            return
        hit = self._pick(pos)
        take = self.doc.take
        hover = take.points.index_of(hit[1]) if hit is not None and hit[0] == "point" else -1
        if self.options["Pixel Report"]:
            xy = self.widget_to_image(np.array([pos.x(), pos.y()]))
            img = self.doc.image(self.camera)
            g = -1
            if img is not None:
                ix, iy = int(round(xy[0])), int(round(xy[1]))
                if 0 <= iy < img.shape[0] and 0 <= ix < img.shape[1]:
                    g = int(img[iy, ix])
            self._pixel = (float(xy[0]), float(xy[1]), g)
            self.update()
        if hover != self._hover:
            self._hover = hover
            self.update()

    def wheelEvent(self, event: QWheelEvent) -> None:  # noqa: N802
        if event.modifiers() & Qt.KeyboardModifier.ControlModifier:
            self.zoom_at(1.2 if event.angleDelta().y() > 0 else 1 / 1.2, event.position())
            event.accept()
        else:
            super().wheelEvent(event)

    # ------------------------------------------------------------------ context menu
    def _context(self, pos) -> None:  # type: ignore[no-untyped-def]
        from PySide6.QtWidgets import QApplication

        if plain_right_click(QApplication.keyboardModifiers()):
            self.request_context_menu(self.mapToGlobal(pos))

    def fill_context_menu(self, menu: QMenu) -> None:
        add_action(menu, "Fit To Window", self.fit_to_window)
        add_action(menu, "Actual Size", self.actual_size)
        add_action(menu, "Start Measurement", lambda: setattr(self, "mode", "measure"))
        add_action(menu, "Clear Measurement", self._clear_measurement)
        add_action(menu, "Center Selection", self.center_selection)
        add_action(menu, "Frame Selection", self.frame_selection)
        menu.addSeparator()
        for name in ("Border", "Image", "Detections", "Points", "Projections", "Connected", "Unconnected", "Errors"):
            add_toggle(menu, name, self.options[name], lambda on, n=name: self.set_option(n, on))
        add_toggle(menu, "Blob Preview", self.doc.blob_preview, lambda on: self.doc.set_display("blob_preview", on))
        for name in ("Pixel Report", "ROM", "Sticks", "Point Labels: All"):
            add_toggle(menu, name, self.options[name], lambda on, n=name: self.set_option(n, on))

    def set_option(self, name: str, on: bool) -> None:
        self.options[name] = bool(on)
        self.update()

    def _clear_measurement(self) -> None:
        self.measurement = None
        self.update()


def take_params(view: CameraView):  # type: ignore[no-untyped-def]
    """The take's Selection section (what may be selected)."""
    return view.doc.take.params.selection
