"""3D view: points coloured by reconstruction type, the brim, cameras, rays and sticks.

Drawn with ``QPainter`` through an orbiting perspective camera of our own (no OpenGL, so it
works offscreen). Mouse: click / Ctrl+click / drag a box to select, Alt+Shift+drag lassoes;
Shift or Alt + left-drag rotates, + right-drag zooms, + middle-drag pans; middle-drag or the
wheel shuttles time.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QBrush, QColor, QMouseEvent, QPainter, QPen
from PySide6.QtWidgets import QApplication, QMenu, QWidget

from carapost.core.camera import camera_centre
from carapost.model.take import PointKind, Recon

from .. import queries
from ..document import Document
from .base import NO_TAKE, BaseView, add_action, add_toggle, draw_hint, plain_right_click
from .labels import LabelPainter
from .paths import outlines_path, segments_path

__all__ = ["View3D", "RECON_COLOURS"]

#: Reconstruction-type colours (the guide: yellow matched, orange single-sensor/patch, red interpolated).
RECON_COLOURS = {Recon.MULTI_VIEW: QColor(255, 225, 0), Recon.SINGLE_SENSOR: QColor(255, 140, 0),
                 Recon.INTERPOLATED: QColor(230, 40, 40)}
BRIM = QColor(90, 170, 255)
BRIM_MODEL = QColor(140, 140, 150)
CAMERA = QColor(200, 200, 200)
ROM = QColor(170, 210, 255)
OPTIONS = {"Face Points": True, "Calibration Brim Points": True, "Reconstruction Type Colors": True, "Cameras": True,
           "Rays": True, "ROM": False, "Sticks": True, "Point Labels :All": False}
RADIUS = 4.0


def _rot(yaw: float, pitch: float) -> np.ndarray:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return Rx @ Ry


def _pen(c: QColor, w: float = 1.0, style: Qt.PenStyle = Qt.PenStyle.SolidLine) -> QPen:
    p = QPen(c, w, style)
    p.setCosmetic(True)
    return p


class View3D(BaseView):
    """Perspective view of the take's 3D data in the current frame."""

    kind = "3d"

    def __init__(self, doc: Document, parent: QWidget | None = None) -> None:
        super().__init__(doc, parent)
        self.options = dict(OPTIONS)
        self.yaw, self.pitch = 0.0, 0.0
        self.target = np.zeros(3)
        self.distance = 400.0
        self._fitted = False
        self._drag: dict | None = None
        self._labels = LabelPainter()
        self.setMinimumSize(120, 90)
        self.setMouseTracking(False)
        self.setContextMenuPolicy(Qt.ContextMenuPolicy.CustomContextMenu)
        self.customContextMenuRequested.connect(
            lambda pos: plain_right_click(QApplication.keyboardModifiers()) and self.request_context_menu(
                self.mapToGlobal(pos)))

    def title(self) -> str:
        return "3D"

    # ------------------------------------------------------------------ projection
    def _xyz(self) -> np.ndarray:
        take = self.doc.take
        return (take.xyz_stabilized if self.doc.show_stabilized else take.xyz)[self.doc.frame]

    def focal(self) -> float:
        return 0.9 * min(self.width(), self.height())

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points ``(N, 3)`` mm to widget pixels ``(N, 2)`` (NaN behind the eye)."""
        X = np.asarray(X, float).reshape(-1, 3)
        R = _rot(self.yaw, self.pitch)
        v = (X - self.target) @ R.T
        depth = self.distance - v[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            f = self.focal() / np.where(depth > 1e-3, depth, np.nan)
        return np.c_[self.width() / 2 + v[:, 0] * f, self.height() / 2 - v[:, 1] * f]

    def _camera_centres(self) -> np.ndarray:
        take = self.doc.take
        R, t = take.R[self.doc.frame], take.t[self.doc.frame]
        if take.n_cameras == 0:
            return np.zeros((0, 3))
        return camera_centre(R, t)

    def fit(self, cols: list[int] | None = None) -> None:
        """Fit to Points: the selected points (all if none), framing them in the view."""
        if not self.doc.has_take:
            return
        X = self._xyz()
        pts = X[cols] if cols else X
        pts = pts[np.isfinite(pts).all(1)]
        if len(pts) == 0 and not cols:
            cams = self._camera_centres()
            pts = cams[np.isfinite(cams).all(1)]
        if len(pts) == 0:
            return
        self.target = pts.mean(0)
        radius = max(float(np.linalg.norm(pts - self.target, axis=1).max()), 20.0)
        self.distance = 2.4 * radius + radius
        self._fitted = True
        self.update()

    def center_selection(self) -> None:
        cols = self.doc.selected_columns()
        X = self._xyz()[cols] if cols else np.zeros((0, 3))
        X = X[np.isfinite(X).all(1)]
        if len(X):
            self.target = X.mean(0)
            self.update()

    def frame_selection(self) -> None:
        self.fit(self.doc.selected_columns() or None)

    def on_session(self) -> None:
        self._fitted = False
        self.fit()

    def on_take(self) -> None:
        if not self._fitted:
            self.fit()
        self.update()

    def on_frame(self, frame: int) -> None:
        if self.doc.lock_to_point and self.doc.sel_points:
            self.center_selection()
        self.update()

    # ------------------------------------------------------------------ painting
    def paintEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        p = QPainter(self)
        try:
            p.fillRect(self.rect(), QColor(38, 40, 46))
            if not self.doc.has_take:
                draw_hint(p, QRectF(self.rect()), NO_TAKE)
                return
            p.setRenderHint(QPainter.RenderHint.Antialiasing, True)
            self._paint(p)
            if not np.isfinite(self._xyz()).any():
                draw_hint(p, QRectF(self.rect()), "No 3D points in this frame\n(Process > Initialize 3D, or track"
                          " into this frame)", top=True)
        finally:
            p.end()

    def _discs(self, p: QPainter, s: np.ndarray, colour: QColor, radius: float = RADIUS) -> None:
        ok = np.isfinite(s).all(1)
        if not ok.any():
            return
        ox, oy = queries.circle_outlines(s[ok, 0], s[ok, 1], radius, n=12)
        path = outlines_path(ox, oy)
        p.fillPath(path, QBrush(colour))
        p.setPen(_pen(colour.darker(160)))
        p.drawPath(path)

    def _paint(self, p: QPainter) -> None:
        take, f = self.doc.take, self.doc.frame
        X = self._xyz()
        s = self.project(X) if take.n_points else np.zeros((0, 2))
        kind = take.points.kind
        recon = take.recon[f]
        sel = np.array(self.doc.selected_columns(), np.int64)
        self._paint_axes(p)
        if self.options["Cameras"]:
            self._paint_cameras(p)
        if self.options["Calibration Brim Points"] and take.brim is not None and not np.any(kind == PointKind.BRIM):
            self._discs(p, self.project(take.brim.xyz), BRIM_MODEL, 2.5)
        if self.options["Sticks"] and len(take.sticks) and take.n_points:
            ids = take.points.ids
            order = np.argsort(ids)
            cols = order[np.clip(np.searchsorted(ids[order], take.sticks), 0, len(ids) - 1)]
            for colour in np.unique(take.stick_colours, axis=0):
                m = (take.stick_colours == colour).all(1)
                a, b = s[cols[m, 0]], s[cols[m, 1]]
                p.setPen(_pen(QColor(*map(int, colour)), 1.2))
                p.drawPath(segments_path(a[:, 0], a[:, 1], b[:, 0], b[:, 1]))
        if self.options["Rays"] and len(sel):
            cams = self._camera_centres()
            obs = np.isfinite(take.obs_xy[f][sel][..., 0])          # (k, C)
            k, c = np.nonzero(obs)
            a, b = s[sel[k]], self.project(cams[c]) if len(c) else np.zeros((0, 2))
            p.setPen(_pen(QColor(120, 220, 255, 160), 1.0))
            if len(k):
                p.drawPath(segments_path(a[:, 0], a[:, 1], b[:, 0], b[:, 1]))
        if self.options["ROM"] and self.doc.rom is not None and self.doc.rom.n_points:
            rom = self.doc.rom
            fr = int(np.clip(take.params.rom.rom_frame_index, 0, rom.n_frames - 1))
            self._discs(p, self.project(rom.xyz[fr]), ROM, 2.5)
        self._paint_points(p, X, s, kind, recon)
        if len(sel):
            ok = np.isfinite(s[sel]).all(1)
            if ok.any():
                ox, oy = queries.circle_outlines(s[sel][ok, 0], s[sel][ok, 1], RADIUS + 3)
                p.setPen(_pen(QColor(255, 255, 255), 2))
                p.drawPath(outlines_path(ox, oy))
        self._paint_labels(p, s, sel)
        if self._drag and self._drag.get("kind") == "box" and self._drag.get("moved"):
            p.setPen(_pen(QColor(255, 255, 255), 1, Qt.PenStyle.DashLine))
            p.drawRect(QRectF(self._drag["start"], self._drag["pos"]).normalized())

    def _paint_points(self, p: QPainter, X: np.ndarray, s: np.ndarray, kind: np.ndarray, recon: np.ndarray) -> None:
        """Brim and face points as discs, far ones first so that near points cover them (about 10 us
        a point: fine for the few hundred points of a face)."""
        colours = [BRIM] + list(RECON_COLOURS.values())
        which = np.full(len(s), -1)
        if self.options["Calibration Brim Points"]:
            which[kind == PointKind.BRIM] = 0
        if self.options["Face Points"]:
            face = kind == PointKind.FACE
            if self.options["Reconstruction Type Colors"]:
                for i, r in enumerate(RECON_COLOURS, start=1):
                    which[face & (recon == r)] = i
                which[face & (recon == Recon.NONE)] = 1 + list(RECON_COLOURS).index(Recon.MULTI_VIEW)
            else:
                which[face] = 1 + list(RECON_COLOURS).index(Recon.MULTI_VIEW)
        show = np.flatnonzero((which >= 0) & np.isfinite(s).all(1))
        if not len(show):
            return
        v = (X[show] - self.target) @ _rot(self.yaw, self.pitch).T
        show = show[np.argsort(v[:, 2])]                     # eye looks along -z: far (small z) first
        pens = [_pen(c.darker(160)) for c in colours]
        brushes = [QBrush(c) for c in colours]
        for i in show.tolist():
            k = int(which[i])
            p.setPen(pens[k])
            p.setBrush(brushes[k])
            p.drawEllipse(QPointF(float(s[i, 0]), float(s[i, 1])), RADIUS, RADIUS)
        p.setBrush(Qt.BrushStyle.NoBrush)

    def _paint_axes(self, p: QPainter) -> None:
        R = _rot(self.yaw, self.pitch)
        o = np.array([34.0, self.height() - 34.0])
        for axis, colour, name in ((0, QColor(230, 60, 60), "X"), (1, QColor(60, 200, 60), "Y"),
                                   (2, QColor(80, 120, 255), "Z")):
            d = R[:, axis]
            e = o + 24 * np.array([d[0], -d[1]])
            p.setPen(_pen(colour, 2))
            p.drawLine(QPointF(*o), QPointF(*e))
            p.drawText(QPointF(*(e + 2)), name)

    def _paint_cameras(self, p: QPainter) -> None:
        take, f = self.doc.take, self.doc.frame
        R, t = take.R[f], take.t[f]
        for c in range(take.n_cameras):
            if not (np.isfinite(R[c]).all() and np.isfinite(t[c]).all()):
                continue
            intr = take.cameras[c].intrinsics
            w, h = take.cameras[c].image_size if take.cameras[c].image_size[0] > 0 else intr.sensor_size
            cx, cy = intr.principal_point
            z = 25.0
            corners_c = np.array([[(u - cx) / intr.focal_length * z, (v - cy) / intr.focal_length * z, z]
                                  for u, v in ((0, 0), (w, 0), (w, h), (0, h))])
            centre = camera_centre(R[c], t[c])
            corners = (corners_c - t[c]) @ R[c]
            s = self.project(np.vstack([centre, corners]))
            if not np.isfinite(s).all():
                continue
            p.setPen(_pen(CAMERA, 1.2))
            idx = [1, 2, 3, 4]
            p.drawPath(segments_path(np.r_[s[[0] * 4, 0], s[idx, 0]], np.r_[s[[0] * 4, 1], s[idx, 1]],
                                     np.r_[s[idx, 0], s[[2, 3, 4, 1], 0]], np.r_[s[idx, 1], s[[2, 3, 4, 1], 1]]))
            p.drawText(QPointF(*(s[0] + 4)), str(c))

    def _paint_labels(self, p: QPainter, s: np.ndarray, sel: np.ndarray) -> None:
        take = self.doc.take
        disp = take.params.display
        show = set(sel.tolist()) if disp.point_labels_selected else set()
        if self.options["Point Labels :All"] or disp.point_labels_all:
            show |= {c for c in range(take.n_points) if take.points.labels[c]}
        sel_set = set(sel.tolist())
        cols = np.array(sorted(show, key=lambda c: (c not in sel_set, c)), np.int64)
        cols = cols[np.isfinite(s[cols]).all(1)] if len(cols) else cols
        font = p.font()
        font.setPointSize(int(disp.font_size))
        self._labels.draw(p, s[cols], [take.points.name(c) for c in cols.tolist()], mark=RADIUS + 3, font=font,
                          obstacles=s, highlight=[c in sel_set for c in cols.tolist()])

    # ------------------------------------------------------------------ mouse
    def mousePressEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        mods, btn = e.modifiers(), e.button()
        shift = bool(mods & Qt.KeyboardModifier.ShiftModifier)
        alt = bool(mods & Qt.KeyboardModifier.AltModifier)
        pos = e.position()
        if btn == Qt.MouseButton.LeftButton and shift and alt:
            self._drag = {"kind": "lasso", "points": [(pos.x(), pos.y())]}
        elif btn == Qt.MouseButton.LeftButton and (shift or alt):
            self._drag = {"kind": "rotate", "last": pos}
        elif btn == Qt.MouseButton.RightButton and (shift or alt):
            self._drag = {"kind": "zoom", "last": pos}
        elif btn == Qt.MouseButton.MiddleButton and (shift or alt):
            self._drag = {"kind": "pan", "last": pos}
        elif btn == Qt.MouseButton.MiddleButton:
            self._drag = {"kind": "shuttle", "start": pos, "frame": self.doc.frame}
        elif btn == Qt.MouseButton.LeftButton:
            self._drag = {"kind": "box", "start": pos, "pos": pos, "moved": False,
                          "add": bool(mods & Qt.KeyboardModifier.ControlModifier)}
        e.accept()

    def mouseMoveEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        d = self._drag
        if d is None:
            return
        pos = e.position()
        if d["kind"] == "rotate":
            self.yaw += (pos.x() - d["last"].x()) * 0.01
            self.pitch = float(np.clip(self.pitch + (pos.y() - d["last"].y()) * 0.01, -1.55, 1.55))
            d["last"] = pos
        elif d["kind"] == "zoom":
            self.distance = float(np.clip(self.distance * np.exp((pos.y() - d["last"].y()) / 150.0), 5.0, 1e6))
            d["last"] = pos
        elif d["kind"] == "pan":
            scale = self.distance / self.focal()
            R = _rot(self.yaw, self.pitch)
            self.target = self.target - R.T @ np.array([(pos.x() - d["last"].x()) * scale,
                                                        -(pos.y() - d["last"].y()) * scale, 0.0])
            d["last"] = pos
        elif d["kind"] == "shuttle":
            self.doc.set_frame(d["frame"] + int((pos.x() - d["start"].x()) / 6))
        elif d["kind"] == "box":
            d["pos"] = pos
            d["moved"] = d["moved"] or (pos - d["start"]).manhattanLength() > 4
        elif d["kind"] == "lasso":
            d["points"].append((pos.x(), pos.y()))
        self.update()

    def mouseReleaseEvent(self, e: QMouseEvent) -> None:  # noqa: N802
        d, self._drag = self._drag, None
        if d is None or not self.doc.has_take:
            return
        take = self.doc.take
        if not take.params.selection.points or take.n_points == 0:
            self.update()
            return
        s = self.project(self._xyz())
        if d["kind"] == "box":
            if d["moved"]:
                r = QRectF(d["start"], d["pos"]).normalized()
                inside = (s[:, 0] >= r.left()) & (s[:, 0] <= r.right()) & (s[:, 1] >= r.top()) & (s[:, 1] <= r.bottom())
                self.doc.select(take.points.ids[inside].tolist(), add=d["add"])
            else:
                q = np.array([d["start"].x(), d["start"].y()])
                dist = np.linalg.norm(s - q, axis=1)
                dist[~np.isfinite(dist)] = np.inf
                if len(dist) and dist.min() <= 9:
                    self.doc.select([int(take.points.ids[int(np.argmin(dist))])], toggle=d["add"])
                elif not d["add"]:
                    self.doc.clear_selection()
        elif d["kind"] == "lasso" and len(d["points"]) > 2:
            inside = queries.points_in_polygon(s, np.array(d["points"]))
            self.doc.select(take.points.ids[inside].tolist())
        self.update()

    # ------------------------------------------------------------------ context menu
    def fill_context_menu(self, menu: QMenu) -> None:
        add_action(menu, "Fit to Points", lambda: self.fit(self.doc.selected_columns() or None))
        add_action(menu, "Center Selection", self.center_selection)
        add_action(menu, "Frame Selection", self.frame_selection)
        menu.addSeparator()
        for name in OPTIONS:
            add_toggle(menu, name, self.options[name], lambda on, n=name: self._set(n, on))

    def _set(self, name: str, on: bool) -> None:
        self.options[name] = bool(on)
        self.update()
