"""Overlay painting of the camera view: detections, points, projections, sticks, ROM,
keyframes and labels (a mixin of :class:`~carapost.ui.views.camera_view.CameraView`).

Every overlay is built with numpy in screen coordinates and drawn as one ``QPainterPath`` per
pen (see :mod:`carapost.ui.views.paths`), so hundreds of marks cost a handful of draw calls.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtGui import QColor, QPainter, QPen

from carapost.model.take import ObsSource

from .. import queries
from .camera_overlay import Overlay, project_points
from .labels import LabelPainter
from .paths import PathBuilder, affine, outlines_path, segments_path

__all__ = ["OverlayPainting", "RED", "BLUE", "YELLOW", "ORANGE", "GREEN", "SELECT", "PALE_BLUE", "MARK", "pen"]

RED, BLUE, YELLOW, ORANGE = QColor(230, 40, 40), QColor(70, 150, 255), QColor(255, 225, 0), QColor(255, 140, 0)
GREEN, SELECT, PALE_BLUE = QColor(0, 220, 70), QColor(0, 255, 255), QColor(170, 210, 255)
HALO = QColor(0, 0, 0)  #: drawn under selected marks (opaque: no blending cost)
MARK = 6.0          # largest half-size of projection marks, screen px


def pen(colour: QColor, width: float = 1.2, style: Qt.PenStyle = Qt.PenStyle.SolidLine) -> QPen:
    """A cosmetic pen (same width at any zoom)."""
    p = QPen(colour, width, style)
    p.setCosmetic(True)
    return p


class OverlayPainting:
    """Painting methods; the view provides ``doc``, ``camera``, ``scale``, ``options``,
    ``fast``, ``_hover`` and ``_labels``."""

    scale: float
    fast: bool
    _labels: LabelPainter

    @property
    def mark(self) -> float:
        """Half-size of the projection marks: smaller when zoomed out, so dense marker sets
        stay readable."""
        return float(np.clip(16.0 * self.scale, 2.5, MARK))

    def _paint_detections(self, p: QPainter, M: np.ndarray, ov: Overlay) -> None:
        d = ov.det
        if len(d.get("x", ())) == 0:
            return
        ox, oy = queries.ellipse_outlines(d["x"], d["y"], np.maximum(d["major"], 1.0), np.maximum(d["minor"], 1.0),
                                          d["angle"])
        q = affine(M, np.stack([ox, oy], -1))
        c = affine(M, np.c_[d["x"], d["y"]])
        r = np.clip(0.5 * d["minor"] * self.scale, 2.0, 6.0)
        sel = np.zeros(len(d["x"]), bool)
        idx = [i for cam, fr, i in self.doc.sel_detections if cam == self.camera and fr == self.doc.frame]
        sel[idx] = True
        for mask, colour in ((~sel, RED), (sel, SELECT)):
            if mask.any():
                p.setPen(pen(colour, 1.2 if colour is RED else 2.0))
                p.drawPath(PathBuilder().outlines(q[mask, :, 0], q[mask, :, 1]).crosses(c[mask, 0], c[mask, 1],
                                                                                         r[mask]).path())

    def _paint_points(self, p: QPainter, M: np.ndarray, ov: Overlay, sel_cols: set[int]) -> None:
        if len(ov.obs_cols) == 0:
            return
        a = ov.obs_axes
        ox, oy = queries.ellipse_outlines(ov.obs_xy[:, 0], ov.obs_xy[:, 1], a[:, 0] * 1.35 + 1.5,
                                          a[:, 1] * 1.35 + 1.5, a[:, 2])
        q = affine(M, np.stack([ox, oy], -1))
        sel = np.isin(ov.obs_cols, list(sel_cols))
        hover = ov.obs_cols == self._hover
        blob = ov.obs_src == ObsSource.BLOB
        for mask, colour, style, width in ((~sel & blob, BLUE, Qt.PenStyle.SolidLine, 1.6),
                                           (~sel & ~blob, BLUE, Qt.PenStyle.DashLine, 1.6),
                                           (hover & ~sel, QColor(150, 200, 255), Qt.PenStyle.SolidLine, 2.5),
                                           (sel, QColor(255, 255, 255), Qt.PenStyle.SolidLine, 2.5)):
            if mask.any():
                p.setPen(pen(colour, width, style))
                p.drawPath(outlines_path(q[mask, :, 0], q[mask, :, 1]))

    def _paint_projections(self, p: QPainter, M: np.ndarray, ov: Overlay, sel_cols: set[int]) -> None:
        if len(ov.proj_cols) == 0:
            return
        s = affine(M, ov.proj_xy)
        con = ov.proj_connected
        if self.options["Connected"] and con.any():
            ox, oy = queries.circle_outlines(s[con, 0], s[con, 1], self.mark, n=10)
            marks = PathBuilder().outlines(ox, oy).crosses(s[con, 0], s[con, 1], self.mark * 0.7)
            if self.options["Errors"]:
                every = np.full((self.doc.take.n_points, 2), np.nan)
                every[ov.obs_cols] = affine(M, ov.obs_xy)
                obs = every[ov.proj_cols]
                marks.segments(s[con, 0], s[con, 1], obs[con, 0], obs[con, 1])
            p.setPen(pen(YELLOW, 1.2))
            p.drawPath(marks.path())
        if self.options["Unconnected"] and (~con).any():
            p.setPen(pen(ORANGE, 1.2))
            u = ~con
            ox, oy = queries.circle_outlines(s[u, 0], s[u, 1], self.mark, n=10)
            p.drawPath(PathBuilder().outlines(ox, oy).xs(s[u, 0], s[u, 1], self.mark * 0.6).path())
            selu = u & np.isin(ov.proj_cols, list(sel_cols))
            if selu.any():
                p.setPen(pen(QColor(255, 255, 255), 2.0))
                ox, oy = queries.circle_outlines(s[selu, 0], s[selu, 1], self.mark + 2)
                p.drawPath(outlines_path(ox, oy))

    def _paint_selection(self, p: QPainter, M: np.ndarray, ov: Overlay, sel_cols: set[int]) -> None:
        """A ring of fixed screen size around each selected point (observation, else projection),
        white over a dark halo, so the selection is found at a glance at any zoom and on the brim."""
        if not sel_cols:
            return
        cols = np.fromiter(sel_cols, np.int64)
        xy = affine(M, ov.point_xy(self.doc.take.n_points)[cols[cols < self.doc.take.n_points]])
        xy = xy[np.isfinite(xy).all(1)]
        if len(xy) == 0:
            return
        ox, oy = queries.circle_outlines(xy[:, 0], xy[:, 1], max(self.mark + 5.0, 9.0), n=16)
        path = outlines_path(ox, oy)
        p.setPen(pen(HALO, 4.5))
        p.drawPath(path)
        p.setPen(pen(QColor(255, 255, 255), 1.8))
        p.drawPath(path)

    def _paint_sticks(self, p: QPainter, M: np.ndarray, ov: Overlay) -> None:
        take = self.doc.take
        xy = affine(M, ov.point_xy(take.n_points))
        ids = take.points.ids
        order = np.argsort(ids)
        cols = order[np.clip(np.searchsorted(ids[order], take.sticks), 0, len(ids) - 1)]
        a, b = xy[cols[:, 0]], xy[cols[:, 1]]
        colours = take.stick_colours
        for colour in np.unique(colours, axis=0):
            m = (colours == colour).all(1)
            p.setPen(pen(QColor(*map(int, colour)), 1.2))
            p.drawPath(segments_path(a[m, 0], a[m, 1], b[m, 0], b[m, 1]))

    def _paint_rom(self, p: QPainter, M: np.ndarray) -> None:
        rom = self.doc.rom
        take = self.doc.take
        if rom is None or rom.n_points == 0:
            return
        fr = int(np.clip(take.params.rom.rom_frame_index, 0, rom.n_frames - 1))
        _, xy = project_points(take, self.camera, self.doc.frame, rom.xyz[fr])
        s = affine(M, xy)
        p.setPen(pen(PALE_BLUE, 1.2))
        ox, oy = queries.circle_outlines(s[:, 0], s[:, 1], 3.0)
        p.drawPath(outlines_path(ox, oy))

    def _paint_keyframes(self, p: QPainter, M: np.ndarray) -> None:
        kf = self.doc.take.keyframes
        if len(kf) == 0:
            return
        m = (kf.frame == self.doc.frame) & (kf.camera == self.camera)
        if not m.any():
            return
        box = kf.pattern[m].astype(float)
        corners = np.stack([box[:, [0, 1]], box[:, [2, 1]], box[:, [2, 3]], box[:, [0, 3]], box[:, [0, 1]]], 1)
        q = affine(M, corners)
        p.setPen(pen(BLUE, 1.5))
        p.drawPath(outlines_path(q[..., 0], q[..., 1]))
        c = affine(M, kf.xy[m].astype(float))
        p.setPen(pen(YELLOW, 1.2, Qt.PenStyle.DashLine))
        ox, oy = queries.circle_outlines(c[:, 0], c[:, 1], self.mark)
        p.drawPath(outlines_path(ox, oy))

    def _paint_labels(self, p: QPainter, M: np.ndarray, ov: Overlay, sel_cols: set[int]) -> None:
        take = self.doc.take
        disp = take.params.display
        show = set()
        if self.options["Point Labels: All"] or disp.point_labels_all:
            show |= {c for c in range(take.n_points) if take.points.labels[c]}
        if disp.point_labels_selected:
            show |= sel_cols
        if disp.point_labels_preselected and self._hover >= 0:
            show.add(self._hover)
        if not show:
            self._labels.boxes = np.zeros((0, 4))
            return
        xy = affine(M, ov.point_xy(take.n_points))
        font = p.font()
        font.setPointSize(int(disp.font_size))
        # selected first, then the pre-selected one, then the rest: they get the best places
        cols = np.array(sorted(show, key=lambda c: (c not in sel_cols, c != self._hover, c)), np.int64)
        cols = cols[np.isfinite(xy[cols]).all(1)]
        names = [take.points.name(c) for c in cols.tolist()]
        self._labels.draw(p, xy[cols], names, mark=self.mark + 1.5, font=font, obstacles=xy,
                          highlight=[c in sel_cols for c in cols.tolist()], reuse=self.fast)
