"""Graph view: x/y/z of the selected points (and their 2D track in one sensor) against frame.

Two pyqtgraph plots with linked frame axes: "Recon Data" (3D, mm) and "Track Data" (2D of
the chosen sensor, px). Red = x, green = y, blue = z; NaN frames are drawn as gaps
(``connect='finite'``); a movable line marks the current frame (drag it to scrub).
"""

from __future__ import annotations

import logging

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QApplication, QLabel, QMenu, QVBoxLayout, QWidget

from carapost.ops import settings as settings_ops

from ..document import Document
from .base import NO_TAKE, BaseView, add_action, add_toggle, plain_right_click

__all__ = ["GraphView"]

log = logging.getLogger("carapost")

COLOURS = ((230, 60, 60), (60, 200, 60), (80, 140, 255))
MAX_POINTS = 12  #: plotted at most (the first selected)
AXIS_W = 62      #: width of the value axes, px (equal, so the two plots' frames line up)


def _axis_label(axes: str, unit: str) -> str:
    """``x y z (mm)`` with each coordinate in its curve colour (the legend of the plot; mm is
    the 3D plot, px the 2D one). Short, so it fits beside a low plot."""
    spans = " ".join(f'<span style="color:#{r:02x}{g:02x}{b:02x}">{a}</span>' for a, (r, g, b) in zip(axes, COLOURS))
    return f"{spans} ({unit})"


class _ViewBox(pg.ViewBox):
    """A ViewBox with the guide's mouse: a plain right-click asks for our context menu (not
    pyqtgraph's), Alt+Shift+drag zooms to the dragged rectangle, Ctrl+drag sets the active range."""

    menuRequested = Signal(object)
    rangeDragged = Signal(int, int)

    def mouseClickEvent(self, ev) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        if ev.button() == Qt.MouseButton.RightButton:
            ev.accept()
            self.menuRequested.emit(ev.screenPos().toPoint())
        else:
            super().mouseClickEvent(ev)

    def mouseDragEvent(self, ev, axis=None) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        mods = ev.modifiers()
        if ev.button() == Qt.MouseButton.LeftButton and mods & Qt.KeyboardModifier.ControlModifier:
            ev.accept()
            if ev.isFinish():
                a = self.mapSceneToView(ev.buttonDownScenePos()).x()
                b = self.mapSceneToView(ev.scenePos()).x()
                lo, hi = sorted((int(round(a)), int(round(b))))
                self.rangeDragged.emit(lo, hi)
            return
        alt_shift = Qt.KeyboardModifier.AltModifier | Qt.KeyboardModifier.ShiftModifier
        if ev.button() == Qt.MouseButton.LeftButton and (mods & alt_shift) == alt_shift:
            mode = self.state["mouseMode"]
            self.state["mouseMode"] = pg.ViewBox.RectMode
            try:
                super().mouseDragEvent(ev, axis)
            finally:
                self.state["mouseMode"] = mode
            return
        super().mouseDragEvent(ev, axis)


class GraphView(BaseView):
    """Coordinates of the selected points over time."""

    kind = "graph"
    frameDragged = Signal(int)

    def __init__(self, doc: Document, camera: int = 0, parent: QWidget | None = None) -> None:
        super().__init__(doc, parent)
        self.camera = camera
        self.show_recon = True
        self.show_track = True
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.canvas = pg.GraphicsLayoutWidget()
        self.canvas.setBackground((30, 32, 36))
        lay.addWidget(self.canvas)
        self.plots: dict[str, pg.PlotItem] = {}
        self.lines: dict[str, pg.InfiniteLine] = {}
        self.regions: dict[str, pg.LinearRegionItem] = {}
        for row, (key, label) in enumerate((("recon", _axis_label("xyz", "mm")), ("track", _axis_label("xy", "px")))):
            vb = _ViewBox()
            vb.menuRequested.connect(self.request_context_menu)
            plot = self.canvas.addPlot(row=row, col=0, viewBox=vb)
            plot.setMenuEnabled(False)
            plot.hideButtons()
            plot.setLabel("left", label)
            plot.getAxis("left").setWidth(AXIS_W)   # both frame axes start at the same x
            plot.showGrid(x=True, y=True, alpha=0.2)
            plot.setDownsampling(auto=True, mode="peak")
            plot.setClipToView(True)
            vb.rangeDragged.connect(self._range_dragged)
            vb.sigRangeChangedManually.connect(self._zoomed_by_hand)
            region = pg.LinearRegionItem(movable=False, brush=pg.mkBrush(70, 130, 200, 40),
                                         pen=pg.mkPen(None))
            region.setZValue(-10)
            plot.addItem(region, ignoreBounds=True)
            self.regions[key] = region
            line = pg.InfiniteLine(angle=90, movable=True, pen=pg.mkPen((255, 255, 255), width=1))
            line.sigDragged.connect(self._line_dragged)
            plot.addItem(line, ignoreBounds=True)
            self.plots[key], self.lines[key] = plot, line
        self.plots["track"].setXLink(self.plots["recon"])
        self.plots["track"].setLabel("bottom", "frame")
        self._curves: list[tuple[pg.PlotItem, pg.PlotDataItem]] = []
        self._fitted = True    # frames follow the view range until the user zooms or pans
        self.hint = QLabel(self)   # what to do when there is nothing to plot
        self.hint.setObjectName("graphHint")
        self.hint.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.hint.setWordWrap(True)
        self.hint.setStyleSheet("color: rgb(175, 178, 185); background: transparent;")
        self.hint.setAttribute(Qt.WidgetAttribute.WA_TransparentForMouseEvents, True)
        self.rebuild()

    def title(self) -> str:
        return f"Graph - Sensor {self.camera}"

    def set_camera(self, camera: int) -> None:
        self.camera = camera
        self.rebuild()

    # ------------------------------------------------------------------ data
    def rebuild(self) -> None:
        """Recreate the curves for the current selection (cheap: a handful of arrays)."""
        for plot, curve in self._curves:
            plot.removeItem(curve)
        self._curves = []
        self.plots["recon"].setVisible(self.show_recon)
        self.plots["track"].setVisible(self.show_track)
        if not self.doc.has_take:
            self._set_hint(NO_TAKE)
            for plot in self.plots.values():
                plot.setTitle(None)
            return
        take = self.doc.take
        cols = self.doc.selected_columns()
        self._set_hint("" if cols else "Select points to graph them\n(click, Ctrl+click or drag a box in a camera or"
                       " 3D view, or click a row of the continuity chart)")
        names = [take.points.name(c) for c in cols[:MAX_POINTS]]
        title = ""
        if names:
            title = f"{names[0]} (solid)" + (f", {', '.join(names[1:4])}{' …' if len(names) > 4 else ''} (dashed)"
                                              if len(names) > 1 else "")
            if len(cols) > MAX_POINTS:
                title += f" — first {MAX_POINTS} of {len(cols)}"
        self.plots["recon"].setTitle(title or None, size="9pt", color="#c8c8c8")
        frames = np.arange(take.n_frames, dtype=float)
        xyz_all = take.xyz_stabilized if self.doc.show_stabilized else take.xyz
        cam = self.camera if 0 <= self.camera < take.n_cameras else -1
        for i, col in enumerate(cols[:MAX_POINTS]):
            style = Qt.PenStyle.SolidLine if i == 0 else Qt.PenStyle.DashLine
            for k in range(3):
                pen = pg.mkPen(COLOURS[k], width=1.5, style=style)
                curve = self.plots["recon"].plot(frames, xyz_all[:, col, k], pen=pen, connect="finite")
                self._curves.append((self.plots["recon"], curve))
            if cam >= 0 and np.isfinite(take.obs_xy[:, col, cam, 0]).any():
                for k in range(2):
                    pen = pg.mkPen(COLOURS[k], width=1.5, style=style)
                    curve = self.plots["track"].plot(frames, take.obs_xy[:, col, cam, k].astype(float), pen=pen,
                                                     connect="finite")
                    self._curves.append((self.plots["track"], curve))
        a, b = take.active_range
        for region in self.regions.values():
            region.setRegion((a - 0.5, b + 0.5))
        self.on_frame(self.doc.frame)
        self.fit_to_data()

    def _set_hint(self, text: str) -> None:
        """Show ``text`` instead of the (empty) plots, or the plots when ``text`` is empty."""
        self.hint.setText(text)
        self.hint.setVisible(bool(text))
        self.canvas.setVisible(not text)
        self._place_hint()

    def _place_hint(self) -> None:
        self.hint.setGeometry(20, 0, max(self.width() - 40, 10), self.height())
        self.hint.raise_()

    def resizeEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        super().resizeEvent(event)
        self._place_hint()
        if self._fitted:   # a range set before the plots were laid out is off by the axis widths
            self.fit_to_data()

    def _zoomed_by_hand(self, *_args: object) -> None:
        self._fitted = False

    def fit_to_data(self) -> None:
        if not self.doc.has_take:
            return
        a, b = self.doc.take.view_range
        self._fitted = True
        for plot in self.plots.values():
            plot.enableAutoRange(axis="y")
            plot.setXRange(a, b, padding=0.01)

    def on_session(self) -> None:
        self.rebuild()

    def on_take(self) -> None:
        self.rebuild()

    def on_selection(self) -> None:
        self.rebuild()

    def on_display(self) -> None:
        self.rebuild()

    def on_frame(self, frame: int) -> None:
        for line in self.lines.values():
            line.blockSignals(True)
            line.setValue(frame)
            line.blockSignals(False)

    def _range_dragged(self, lo: int, hi: int) -> None:
        """Ctrl+drag: Set Active Range (an undoable change)."""
        if self.doc.has_take:
            n = self.doc.take.n_frames
            lo, hi = int(np.clip(lo, 0, n - 1)), int(np.clip(hi, 0, n - 1))
            try:
                self.doc.apply(settings_ops.set_active_range(self.doc.take, lo, hi))
            except ValueError as exc:
                log.error("%s", exc)

    def _line_dragged(self, line: pg.InfiniteLine) -> None:
        self.doc.set_frame(int(round(line.value())))

    # ------------------------------------------------------------------ context menu
    def fill_context_menu(self, menu: QMenu) -> None:
        add_action(menu, "Fit to data", self.fit_to_data, enabled=bool(self.doc.sel_points))
        add_toggle(menu, "Track Data", self.show_track, lambda on: self._set("show_track", on))
        add_toggle(menu, "Recon Data", self.show_recon, lambda on: self._set("show_recon", on))

    def _set(self, name: str, on: bool) -> None:
        setattr(self, name, bool(on))
        self.rebuild()

    def request_context_menu(self, global_pos: object) -> None:
        if plain_right_click(QApplication.keyboardModifiers()):
            super().request_context_menu(global_pos)
