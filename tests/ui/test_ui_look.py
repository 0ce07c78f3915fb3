"""What an artist sees: labels that do not overlap, a window that fits a small screen, hints in
empty views and panes, readable controls (issue 5's look-and-feel pass)."""

import numpy as np
import pytest
from PySide6.QtCore import Qt
from PySide6.QtGui import QImage

from carapost.ui.label_layout import place_labels

from uihelpers import inject_truth


@pytest.fixture
def points(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    inject_truth(loaded, synth, markers=8)
    return loaded


def _disjoint(boxes):
    """No two boxes ``x0 y0 x1 y1`` (NaN rows ignored) intersect."""
    b = boxes[np.isfinite(boxes).all(1)]
    inter = ((b[:, None, 0] < b[None, :, 2]) & (b[:, None, 2] > b[None, :, 0]) &
             (b[:, None, 1] < b[None, :, 3]) & (b[:, None, 3] > b[None, :, 1]))
    np.fill_diagonal(inter, False)
    return not inter.any()


def _pixels(widget):
    img = widget.grab().toImage().convertToFormat(QImage.Format.Format_RGB32)
    w, h = img.width(), img.height()
    arr = np.frombuffer(img.constBits(), np.uint32, count=img.bytesPerLine() // 4 * h).reshape(h, -1)[:, :w]
    return np.stack([(arr >> 16) & 255, (arr >> 8) & 255, arr & 255], -1).astype(int)


# ---------------------------------------------------------------- label placement (numpy)
def test_place_labels_brim_grid_zoomed_out_all_placed_without_overlap():
    # 18 brim dots 6 px apart (a brim card seen in a small view): before, all labels were drawn
    # at the same offset and covered each other.
    gx, gy = np.meshgrid(np.arange(6) * 6.0, np.arange(3) * 6.0)
    anchors = np.c_[gx.ravel(), gy.ravel()] + [300, 200]
    sizes = np.tile([48.0, 16.0], (18, 1))
    corners, placed = place_labels(anchors, sizes, mark=4.0, bounds=(640, 400))
    assert placed.all()
    boxes = np.c_[corners, corners + sizes]
    assert _disjoint(boxes)
    assert (boxes[:, :2] >= 0).all() and (boxes[:, 2] <= 640).all() and (boxes[:, 3] <= 400).all()
    # each label stays near its point (within 7 label heights; a leader line joins them)
    near = np.clip(anchors, boxes[:, :2], boxes[:, 2:])
    assert np.hypot(*(near - anchors).T).max() < 7 * 16


def test_place_labels_first_choice_right_above_and_avoids_marks():
    corners, placed = place_labels(np.array([[100.0, 100.0]]), np.array([[40.0, 14.0]]), mark=5, bounds=(400, 300))
    assert placed[0] and corners[0, 0] > 100 and corners[0, 1] + 14 <= 100   # right of and above the point
    # a mark where the label would go: the label moves to a free place
    blocker = np.array([[100.0, 100.0], [125.0, 88.0]])
    corners2, _ = place_labels(blocker[:1], np.array([[40.0, 14.0]]), mark=5, bounds=(400, 300), obstacles=blocker)
    box = np.r_[corners2[0], corners2[0] + [40, 14]]
    assert not (box[0] < 130 and box[2] > 120 and box[1] < 93 and box[3] > 83)


def test_place_labels_out_of_room_leaves_labels_out_never_overlaps():
    anchors = np.tile([[30.0, 20.0]], (10, 1)) + np.arange(10)[:, None] * [1.0, 0.0]
    sizes = np.tile([50.0, 14.0], (10, 1))
    corners, placed = place_labels(anchors, sizes, mark=3, bounds=(120, 60))
    assert 0 < placed.sum() < 10
    assert _disjoint(np.c_[corners, corners + sizes])
    assert np.isnan(corners[~placed]).all()


def test_place_labels_bad_input():
    with pytest.raises(ValueError, match="2 anchors but 1 label sizes"):
        place_labels(np.zeros((2, 2)), np.ones((1, 2)), mark=3, bounds=(10, 10))
    corners, placed = place_labels(np.zeros((0, 2)), np.zeros((0, 2)), mark=3, bounds=(10, 10))
    assert corners.shape == (0, 2) and placed.shape == (0,)


# ---------------------------------------------------------------- labels in the views
def test_3d_view_labels_of_close_points_do_not_overlap(qtbot, points):
    w = points
    take = w.doc.take
    for c in range(take.n_points):
        take.points.labels[c] = f"Marker_{c}"
    # three points 0.5 mm apart: the labels of neighbouring brim dots used to be drawn on top of each other
    take.xyz[w.doc.frame, :3] = take.xyz[w.doc.frame, 0] + np.array([[0, 0, 0], [0.5, 0, 0], [1.0, 0, 0]])
    w.doc.notify_take_changed()
    w.workspace.set_layout(1)
    view = w.workspace.slots[0].set_view("3d")
    view.options["Point Labels :All"] = True
    view.fit()
    view.grab()
    boxes = view._labels.boxes
    assert len(boxes) == take.n_points and np.isfinite(boxes).all()
    assert _disjoint(boxes)


def test_camera_view_labels_of_all_points_do_not_overlap(qtbot, points):
    w = points
    take = w.doc.take
    for c in range(take.n_points):
        take.points.labels[c] = f"Marker_{c}"
    w.doc.notify_take_changed()
    w.workspace.set_layout(4)
    view = w.workspace.slots[0].view
    view.set_option("Point Labels: All", True)
    w.doc.select([int(take.points.ids[2])])
    view.grab()
    boxes = view._labels.boxes
    assert np.isfinite(boxes).all(1).sum() >= take.n_points - 1
    assert _disjoint(boxes)
    # the selected point's label is placed first (it gets the best place)
    assert np.isfinite(boxes[0]).all()


def test_selected_point_stays_visible_on_white(qtbot, points):
    """The selected ring has a dark halo: on a white image its pixels are not all white."""
    w = points
    w.workspace.set_layout(1)
    view = w.workspace.slots[0].set_view("sensor", 0)
    view.resize(640, 360)
    view.fit_to_window()
    view.set_option("Image", False)
    view.set_option("Border", False)
    take = w.doc.take
    w.doc.select([int(take.points.ids[0])])
    view.fast = False
    px = _pixels(view)
    from carapost.ui.views.paths import affine

    x, y = np.round(affine(view.image_to_widget(), take.obs_xy[w.doc.frame, 0, 0].astype(float))).astype(int)
    patch = px[y - 12:y + 13, x - 12:x + 13].reshape(-1, 3)
    assert (patch.max(1) < 60).any(), "no dark halo around the selected point"
    assert (patch.min(1) > 230).any(), "no white selection ring"


# ---------------------------------------------------------------- window size and panes
def test_window_fits_a_small_screen(qtbot, loaded):
    w = loaded
    w.workspace.set_layout(4)
    assert w.minimumSizeHint().width() <= 1000, w.minimumSizeHint()
    w.resize(1024, 640)
    w._size_docks()
    qtbot.wait(20)
    assert w.width() <= 1024
    assert w.workspace.width() >= 0.45 * w.width(), (w.workspace.width(), w.width())


def test_tracker_pane_keeps_short_arrow_buttons(loaded):
    pane = loaded.panes["tracker"]
    loaded.update_actions()
    texts = {k: pane.buttons[k].text() for k in ("tracker.back_to_start", "tracker.back_one", "tracker.forward_one",
                                                 "tracker.forward_to_end")}
    assert texts == {"tracker.back_to_start": "|<", "tracker.back_one": "<", "tracker.forward_one": ">",
                     "tracker.forward_to_end": ">|"}
    assert pane.buttons["tracker.forward_to_end"].toolTip() == "Track forward to end"
    act = loaded.actions["tracker.forward_one"]
    act.setEnabled(False)
    assert not pane.buttons["tracker.forward_one"].isEnabled()
    act.setEnabled(True)
    assert pane.buttons["tracker.forward_one"].isEnabled()


def test_graph_view_hint_legend_and_frame_axis(qtbot, points):
    w = points
    w.workspace.set_layout(1)
    view = w.workspace.slots[0].set_view("graph", 0)
    w.doc.clear_selection()
    assert view.hint.isVisibleTo(view) and not view.canvas.isVisibleTo(view)
    assert "Select points" in view.hint.text()
    take = w.doc.take
    w.doc.select(take.points.ids[:2].tolist())
    assert not view.hint.isVisibleTo(view) and view.canvas.isVisibleTo(view)
    assert "(solid)" in view.plots["recon"].titleLabel.text and "(dashed)" in view.plots["recon"].titleLabel.text
    assert ">x<" in view.plots["recon"].getAxis("left").labelText
    view.resize(500, 300)
    qtbot.wait(20)
    a, b = take.view_range
    widths = {plot.getAxis("left").width() for plot in view.plots.values()}
    assert len(widths) == 1      # the two plots' frame axes line up
    for plot in view.plots.values():
        lo, hi = plot.viewRange()[0]
        assert lo <= a and hi >= b and lo > a - 1 and hi < b + 1


def test_empty_views_and_panes_say_how_to_start(qtbot, window):
    w = window
    assert not w.doc.has_take
    w.workspace.set_layout(4)
    for slot, kind in zip(w.workspace.slots, ("sensor", "3d", "continuity", "graph")):
        view = slot.set_view(kind, 0)
        if kind == "graph":
            assert "Ctrl+O" in view.hint.text() and view.hint.isVisibleTo(view)
        else:
            px = _pixels(view)
            assert (px.min(-1) > 150).sum() > 50, f"{kind} view shows no hint"
    assert w.panes["selected_point"].hint() == "No take open"
    assert w.panes["labelling"].empty.isVisibleTo(w.panes["labelling"])


def test_pane_hints_follow_the_take(qtbot, points):
    w = points
    pane = w.panes["selected_point"]
    w.doc.select(w.doc.take.points.ids[:3].tolist())
    assert pane.hint().startswith("3 points selected")
    w.doc.take.labels = ["Chin"]
    w.doc.notify_take_changed()
    assert not w.panes["labelling"].empty.isVisibleTo(w.panes["labelling"])


def test_selection_pane_check_boxes_are_visible(qtbot, loaded):
    pane = loaded.panes["selection"]
    dock = loaded.docks["selection"]
    dock.show()
    dock.raise_()
    pane.cameras.resize(200, 120)
    px = _pixels(pane.cameras)
    border = (np.abs(px - [160, 162, 170]).max(-1) <= 12).sum()
    assert border > 20, "camera check boxes are not drawn"
    loaded.doc.set_camera_selection([1])
    px = _pixels(pane.cameras)
    assert (np.abs(px - [255, 140, 0]).max(-1) <= 12).sum() > 20, "a checked channel is not shown"


def test_history_pane_long_entries_have_tooltips(loaded):
    pane = loaded.panes["history"]
    assert pane.list.horizontalScrollBarPolicy() == Qt.ScrollBarPolicy.ScrollBarAlwaysOff
    from carapost.ops import settings as settings_ops

    loaded.doc.apply(settings_ops.set_active_range(loaded.doc.take, 0, 1))
    item = pane.list.item(pane.list.count() - 1)
    assert item.toolTip().startswith(item.text())


def test_continuity_sensor_rows_fit_their_text():
    from carapost.ui.views import continuity

    assert continuity.SENSOR_H >= 10 and continuity.ROW_H >= 13


def test_docs_screenshots_script(qtbot, tiny_files, tmp_path):
    """``python -m carapost.ui.screenshots`` writes the three images of docs/gui.md."""
    from PySide6.QtGui import QImage

    from carapost.ui.screenshots import take_screenshots

    _, paths = tiny_files
    saved = take_screenshots(paths["pico_0"], tmp_path, (1024, 640))
    assert [p.name for p in saved] == ["gui_main.png", "gui_views.png", "gui_camera.png"]
    for p in saved:
        img = QImage(str(p))
        assert (img.width(), img.height()) == (1024, 640)


def test_undo_redo_name_the_command(loaded):
    from carapost.ops import settings as settings_ops

    undo, redo = loaded.actions["edit.undo"], loaded.actions["edit.redo"]
    assert undo.text() == "Undo" and undo.statusTip() == "Undo: nothing to undo"
    loaded.doc.apply(settings_ops.set_active_range(loaded.doc.take, 0, 1))
    name = loaded.doc.undo.undoText()
    assert name and undo.statusTip() == f"Undo: {name}"
    undo.trigger()
    assert redo.statusTip() == f"Redo: {name}" and undo.statusTip() == "Undo: nothing to undo"


def test_3d_view_draws_near_points_over_far_ones(qtbot, points):
    from carapost.model.take import Recon
    from carapost.ui.views.view3d import RECON_COLOURS

    w = points
    take = w.doc.take
    f = w.doc.frame
    w.workspace.set_layout(1)
    view = w.workspace.slots[0].set_view("3d")
    view.options["Point Labels :All"] = False
    view.fit()
    view.yaw = view.pitch = 0.0
    # two points on the line of sight through the view's target: one 20 mm nearer the eye
    near, far = 0, 1
    take.xyz[f, far] = view.target
    take.xyz[f, near] = view.target + np.array([0.0, 0.0, 20.0])
    take.recon[f, near], take.recon[f, far] = Recon.SINGLE_SENSOR, Recon.MULTI_VIEW
    w.doc.clear_selection()
    w.doc.notify_take_changed()
    for swap in (False, True):                     # the colour (drawing order by type) must not decide
        if swap:
            take.recon[f, [near, far]] = take.recon[f, [far, near]]
            w.doc.notify_take_changed()
        px = _pixels(view)                           # (lays the view out: project after it)
        s = view.project(take.xyz[f, [near]])[0]
        rgb = px[int(round(s[1])), int(round(s[0]))]
        want = RECON_COLOURS[Recon(int(take.recon[f, near]))]
        assert np.abs(rgb - [want.red(), want.green(), want.blue()]).max() < 40, rgb
