"""Views and the timebar driven with the mouse, as a user would."""

import numpy as np
import pytest
from PySide6.QtCore import QPoint, Qt

from carapost.model.take import Recon
from carapost.ui.views.camera_view import CameraView, rotation_matrix
from carapost.ui.views.continuity import ContinuityView
from carapost.ui.views.graph_view import GraphView
from carapost.ui.views.paths import affine
from carapost.ui.views.view3d import View3D

from uihelpers import inject_truth

NO, CTRL = Qt.KeyboardModifier.NoModifier, Qt.KeyboardModifier.ControlModifier
SHIFT, ALT = Qt.KeyboardModifier.ShiftModifier, Qt.KeyboardModifier.AltModifier
LEFT = Qt.MouseButton.LeftButton


@pytest.fixture
def points(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    inject_truth(loaded, synth, markers=6)
    return loaded


def widget_xy(view, xy):
    return QPoint(*np.round(affine(view.image_to_widget(), np.asarray(xy, float))).astype(int))


def test_rotation_matrix_maps_corners():
    w, h = 640, 360
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    for rot, first in ((0, [0, 0]), (90, [h - 1, 0]), (180, [w - 1, h - 1]), (270, [0, w - 1])):
        out = affine(rotation_matrix(rot, w, h), corners)
        np.testing.assert_allclose(out[0], first)
        size = (h, w) if rot in (90, 270) else (w, h)
        assert out.min() == 0 and np.allclose(out.max(0), np.array(size) - 1)


def test_camera_view_selection_with_the_mouse(qtbot, points):
    w = points
    w.workspace.set_layout(1)
    view = w.workspace.slots[0].set_view("sensor", 0)
    view.resize(640, 360)
    view.fit_to_window()
    take = w.doc.take
    # Click on a point's observation selects the point.
    col = 0
    qtbot.mouseClick(view, LEFT, NO, widget_xy(view, take.obs_xy[0, col, 0]))
    assert w.doc.sel_points == [int(take.points.ids[col])] and w.doc.active_camera == 0
    # Ctrl+click adds another, Ctrl+click again removes it.
    qtbot.mouseClick(view, LEFT, CTRL, widget_xy(view, take.obs_xy[0, 1, 0]))
    assert len(w.doc.sel_points) == 2
    qtbot.mouseClick(view, LEFT, CTRL, widget_xy(view, take.obs_xy[0, 1, 0]))
    assert len(w.doc.sel_points) == 1
    # Click on an unused detection selects the detection.
    det = take.detections[0]
    free = [i for i in range(det.count(0)) if not (take.obs_det[0, :, 0] == i).any()]
    xy = det.xy(0)[free]
    others = np.r_[det.xy(0), take.obs_xy[0, :, 0]]
    sep = [np.sort(np.linalg.norm(others - p, axis=1))[1] for p in xy]
    i = free[int(np.argmax(sep))]
    qtbot.mouseClick(view, LEFT, NO, widget_xy(view, det.xy(0)[i]))
    assert w.doc.sel_detections == [(0, 0, i)] and w.doc.sel_points == []
    # Click on empty space clears; a drag box selects points and free detections inside.
    qtbot.mouseClick(view, LEFT, NO, QPoint(2, 2))
    assert not w.doc.sel_points and not w.doc.sel_detections
    qtbot.mousePress(view, LEFT, NO, QPoint(1, 1))
    qtbot.mouseMove(view, QPoint(300, 200))
    qtbot.mouseMove(view, QPoint(view.width() - 2, view.height() - 2))
    qtbot.mouseRelease(view, LEFT, NO, QPoint(view.width() - 2, view.height() - 2))
    assert len(w.doc.sel_points) == take.n_points
    assert len(w.doc.sel_detections) == len(free)
    # Shift+click selects the sensor (explicit camera selection).
    qtbot.mouseClick(view, LEFT, SHIFT, QPoint(50, 50))
    assert w.doc.sel_cameras == [0]


def test_camera_view_zoom_pan_fit_and_options(qtbot, loaded):
    view = loaded.workspace.slots[0].view
    assert isinstance(view, CameraView)
    s0 = view.scale
    view.zoom_at(2.0, view.rect().center().toPointF())
    assert view.scale == pytest.approx(2 * s0) and not view.fitted
    c0 = view.centre.copy()
    view.pan(10, 0)
    assert view.centre[0] == pytest.approx(c0[0] - 10 / view.scale)
    view.fit_to_window()
    assert view.scale == pytest.approx(s0)
    view.actual_size()
    assert view.scale == 1.0
    menu = loaded.workspace.slots[0].context_menu()
    texts = [a.text() for a in menu.actions()]
    for entry in ("Fit To Window", "Actual Size", "Start Measurement", "Clear Measurement", "Center Selection",
                  "Frame Selection", "Border", "Image", "Detections", "Points", "Projections", "Connected",
                  "Unconnected", "Errors", "Blob Preview", "Pixel Report", "ROM", "Sticks", "Point Labels: All"):
        assert entry in texts, entry
    image = next(a for a in menu.actions() if a.text() == "Image")
    image.trigger()
    assert view.options["Image"] is False
    preview = next(a for a in menu.actions() if a.text() == "Blob Preview")
    preview.trigger()
    assert loaded.doc.blob_preview and loaded.actions["view.blob_preview"].isChecked()
    menu.deleteLater()


def test_blob_preview_computes_in_background(qtbot, loaded):
    view = loaded.workspace.slots[0].view
    loaded.actions["view.blob_preview"].trigger()
    assert loaded.doc.blob_preview
    view.grab()
    qtbot.waitUntil(lambda: loaded.previewer.get(0, loaded.doc.frame) is not None, timeout=20000)
    table = loaded.previewer.get(0, loaded.doc.frame)
    assert "x" in table and len(table["x"]) >= 0
    assert len(loaded.doc.take.detections[0]) == 0       # the preview never touches the take


def test_measurement_and_pixel_report(qtbot, loaded):
    view = loaded.workspace.slots[0].view
    view.mode = "measure"
    a, b = QPoint(100, 100), QPoint(160, 100)
    qtbot.mousePress(view, LEFT, NO, a)
    qtbot.mouseMove(view, b)
    qtbot.mouseRelease(view, LEFT, NO, b)
    d = np.linalg.norm(view.measurement[1] - view.measurement[0])
    assert d == pytest.approx(60 / view.scale, rel=0.05)
    view.set_option("Pixel Report", True)
    qtbot.mouseMove(view, QPoint(120, 110))
    assert view._pixel is not None and 0 <= view._pixel[2] <= 255


def test_context_menu_switches_views(qtbot, loaded):
    slot = loaded.workspace.slots[1]
    menu = slot.context_menu()
    view_menu = next(a.menu() for a in menu.actions() if a.text() == "View")
    texts = [a.text() for a in view_menu.actions()]
    assert texts == ["3D", "Graph", "Continuity", "Sensor 0", "Sensor 1", "Sensor 2", "Sensor 3"]
    next(a for a in view_menu.actions() if a.text() == "3D").trigger()
    assert isinstance(slot.view, View3D)
    menu = slot.context_menu()
    assert [a.text() for a in menu.actions() if a.text()][2:5] == ["Fit to Points", "Center Selection",
                                                                   "Frame Selection"]
    view_menu = next(a.menu() for a in menu.actions() if a.text() == "View")
    next(a for a in view_menu.actions() if a.text() == "Graph").trigger()
    assert isinstance(slot.view, GraphView)
    sensor_menu = next(a.menu() for a in slot.context_menu().actions() if a.text() == "Sensor")
    next(a for a in sensor_menu.actions() if a.text() == "Sensor 3").trigger()
    assert isinstance(slot.view, GraphView) and slot.view.camera == 3
    slot.findChild(type(slot.sensor_button), "slot_continuity").click()
    assert isinstance(slot.view, ContinuityView)
    texts = [a.text() for a in slot.context_menu().actions()]
    assert {"Collapse all", "Expand all", "Fit to data"} <= set(texts)


def test_graph_view_curves(qtbot, points):
    w = points
    take = w.doc.take
    take.xyz[1, 0] = np.nan                       # a gap
    w.doc.notify_take_changed()
    w.doc.select([int(take.points.ids[0])])
    view = w.workspace.slots[0].set_view("graph", 0)
    curves = [c for _, c in view._curves]
    assert len(curves) == 5                       # x, y, z and the 2D x, y of sensor 0
    x, y = curves[0].getData()
    assert np.isnan(y[1]) and curves[0].opts["connect"] == "finite"
    w.doc.set_frame(2)
    assert view.lines["recon"].value() == 2
    view.lines["recon"].setValue(1)
    view._line_dragged(view.lines["recon"])
    assert w.doc.frame == 1
    texts = [a.text() for a in w.workspace.slots[0].context_menu().actions()]
    assert {"Fit to data", "Track Data", "Recon Data"} <= set(texts)


def test_continuity_chart_mouse(qtbot, points):
    w = points
    view = w.workspace.slots[0].set_view("continuity")
    view.resize(600, 300)
    canvas = view.canvas
    take = w.doc.take
    rows = view.rows()
    assert rows[:2] == [(0, -1), (1, -1)]
    # Click on the second bar row selects that point and moves to the frame under the mouse.
    qtbot.mouseClick(canvas, LEFT, NO, QPoint(canvas.width() - 3, 14 + 2 + 5))
    assert w.doc.sel_points == [int(take.points.ids[1])] and w.doc.frame == take.n_frames - 1
    # Double-click expands the point into its sensors.
    qtbot.mouseDClick(canvas, LEFT, NO, QPoint(20, 5))
    assert view.rows()[:5] == [(0, -1), (0, 0), (0, 1), (0, 2), (0, 3)]
    view.collapse_all()
    view.expand_all()
    assert len(view.rows()) == take.n_points * (1 + take.n_cameras)
    # Fit to data shows the selected points only.
    view.fit_to_data()
    assert [r for r in view.rows() if r[1] < 0] == [(1, -1)]
    # Ctrl+drag sets the active range (an undoable change).
    x0, x1 = view.x_of(1, canvas.width()), view.x_of(2, canvas.width())
    qtbot.mousePress(canvas, LEFT, CTRL, QPoint(int(x0), 5))
    qtbot.mouseMove(canvas, QPoint(int(x1), 5))
    qtbot.mouseRelease(canvas, LEFT, CTRL, QPoint(int(x1), 5))
    assert take.active_range == (1, 2)


def test_view3d_fit_select_rotate(qtbot, points):
    w = points
    view = w.workspace.slots[0].set_view("3d")
    view.resize(500, 400)
    view.fit()
    take = w.doc.take
    assert take.recon[0, 0] == Recon.MULTI_VIEW
    s = view.project(take.xyz[0])
    assert np.isfinite(s).all() and (s >= 0).all() and (s[:, 0] <= 500).all() and (s[:, 1] <= 400).all()
    qtbot.mouseClick(view, LEFT, NO, QPoint(*np.round(s[2]).astype(int)))
    assert w.doc.sel_points == [int(take.points.ids[2])]
    yaw = view.yaw
    qtbot.mousePress(view, LEFT, SHIFT, QPoint(100, 100))
    qtbot.mouseMove(view, QPoint(160, 100))
    qtbot.mouseRelease(view, LEFT, SHIFT, QPoint(160, 100))
    assert view.yaw != yaw


def test_timebar_scrub_range_and_play(qtbot, loaded):
    w = loaded
    slider = w.timebar.slider
    slider.resize(400, 30)
    qtbot.mouseClick(slider, LEFT, NO, QPoint(int(slider.x_of(2)), 15))
    assert w.doc.frame == 2
    qtbot.mousePress(slider, LEFT, CTRL, QPoint(int(slider.x_of(0)), 15))
    qtbot.mouseMove(slider, QPoint(int(slider.x_of(1)), 15))
    qtbot.mouseRelease(slider, LEFT, CTRL, QPoint(int(slider.x_of(1)), 15))
    assert w.doc.take.active_range == (0, 1)
    w.doc.set_frame(0)
    w.timebar.toggle_play()
    assert w.timebar.buttons["play"].text() == "Stop"
    qtbot.waitUntil(lambda: w.doc.frame == 2 and not w.timebar.playing, timeout=5000)
    assert w.timebar.buttons["play"].text() == "Play"
    w.timebar.spin.setValue(1)
    assert w.doc.frame == 1


def test_layouts(qtbot, loaded):
    ws = loaded.workspace
    assert ws.n_views == 4 and [s.kind for s in ws.visible_slots()] == ["sensor"] * 4
    loaded.findChild(type(loaded.timebar.buttons["play"]), "layout_2").click()
    assert ws.n_views == 2 and sum(s.isVisible() for s in ws.slots) == 2
    loaded.actions["view.layout1"].trigger()
    assert ws.n_views == 1


def test_graph_ctrl_drag_sets_active_range_and_region(qtbot, points):
    w = points
    w.doc.select([int(w.doc.take.points.ids[0])])
    view = w.workspace.slots[0].set_view("graph", 0)
    view._range_dragged(1, 2)
    assert w.doc.take.active_range == (1, 2)
    assert view.regions["recon"].getRegion() == (0.5, 2.5)
    view._range_dragged(-5, 99)
    assert w.doc.take.active_range == (0, 2)


def test_view3d_middle_drag_shuttles_time(qtbot, points):
    view = points.workspace.slots[0].set_view("3d")
    qtbot.mousePress(view, Qt.MouseButton.MiddleButton, NO, QPoint(100, 100))
    qtbot.mouseMove(view, QPoint(115, 100))
    qtbot.mouseRelease(view, Qt.MouseButton.MiddleButton, NO, QPoint(115, 100))
    assert points.doc.frame == 2
