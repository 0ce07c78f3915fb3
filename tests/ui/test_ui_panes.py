"""The dock panes: History, Labelling, Log, Properties, Selection, Selected Point, Tracker."""

import logging

import numpy as np
from PySide6.QtCore import Qt

from carapost.ops import settings as settings_ops
from carapost.ui.panes.history import UNDONE
from carapost.ui.panes.labelling import ABSENT, ASSIGNED, UNASSIGNED, label_states
from carapost.ui.panes.log_pane import LEVEL_COLOURS

from uihelpers import inject_truth


def test_history_pane_view_of_undo_stack(loaded):
    w = loaded
    take = w.doc.take
    for a in (0, 1, 2):
        w.doc.apply(settings_ops.set_active_range(take, a, 2))
    hist = w.panes["history"]
    lst = hist.list
    assert lst.count() == 4 and lst.item(1).text() == "Active Range 0-2"
    w.doc.undo.undo()
    w.doc.undo.undo()
    assert [applied for _, applied in hist.entries()] == [True, False, False]
    assert lst.item(3).foreground().color() == UNDONE and lst.item(2).foreground().color() == UNDONE
    assert lst.item(1).foreground().color() != UNDONE
    # Clicking an entry moves the history there.
    hist._clicked(lst.item(3))
    assert w.doc.undo.index() == 3 and take.active_range == (2, 2)
    # Clear History (the pane's button) empties the stack but the project stays modified.
    assert w.isWindowModified()
    w.actions["edit.clear_history"].trigger()
    assert w.doc.undo.count() == 0 and lst.count() == 1
    assert w.doc.modified and w.isWindowModified()


def test_labelling_states_and_rename(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    w = loaded
    inject_truth(w, synth, markers=2)
    take = w.doc.take
    take.labels = ["Chin", "Nose", "Brow"]
    take.points.labels[0] = "Chin"
    take.points.labels[1] = "Nose"
    take.xyz[1, 1] = np.nan          # Nose has no data in frame 1
    w.doc.notify_take_changed()
    pane = w.panes["labelling"]
    colours = [pane.list.item(i).foreground().color() for i in range(3)]
    assert colours == [ASSIGNED, ASSIGNED, UNASSIGNED]
    w.doc.set_frame(1)
    assert pane.list.item(1).foreground().color() == ABSENT
    assert label_states(["A", "B"], ["A", ""], np.array([False, True])) == ["absent", "unassigned"]
    # Double-click editing renames the label in the list and on its point (undoable).
    item = pane.list.item(0)
    item.setText("Chin2")
    assert take.labels[0] == "Chin2" and take.points.labels[0] == "Chin2"
    w.doc.undo.undo()
    assert take.labels[0] == "Chin" and take.points.labels[0] == "Chin"
    # Assign the selected label to the selected point.
    w.doc.select([int(take.points.ids[1])])
    pane.list.clearSelection()
    pane.list.item(2).setSelected(True)
    pane.assign_selected()
    assert take.points.labels[1] == "Brow"
    # Delete Selected Labels (the pane's button) removes the label from the list and the point.
    pane.list.clearSelection()
    pane.list.item(2).setSelected(True)
    w.findChild(type(pane.assign), "edit.delete_labels").click()
    assert "Brow" not in take.labels and take.points.labels[1] == ""


def test_log_pane_levels_and_colours(loaded):
    pane = loaded.panes["log"]
    n = pane.table.rowCount()
    lg = logging.getLogger("carapost.tracking")
    lg.info("hello")
    lg.warning("careful")
    lg.error("broken")
    t = pane.table
    assert t.rowCount() == n + 3
    rows = [[t.item(n + i, c).text() for c in range(4)] for i in range(3)]
    assert [r[1] for r in rows] == ["Default", "Warn", "Error"]
    assert [r[2] for r in rows] == ["Tracking"] * 3
    assert [r[3] for r in rows] == ["hello", "careful", "broken"]
    assert t.item(n + 1, 3).foreground().color() == LEVEL_COLOURS[logging.WARNING]
    assert t.item(n + 2, 3).foreground().color() == LEVEL_COLOURS[logging.ERROR]
    # A user error of a command lands in the log as an error, not as a traceback.
    loaded.actions["edit.split"].trigger()
    assert t.item(t.rowCount() - 1, 1).text() == "Error" and "select exactly one point" in t.item(t.rowCount() - 1, 3).text()


def test_properties_edit_undo_and_reject(loaded):
    w = loaded
    take = w.doc.take
    props = w.panes["properties"]
    thr = props.sections["blobs"].editors["black_threshold"]
    thr.setValue(0.55)
    assert take.params.blobs.black_threshold == 0.55
    w.doc.undo.undo()
    assert take.params.blobs.black_threshold == 0.4 and thr.value() == 0.4
    # Min radius above max radius is rejected by the parameters: logged, editor reverted.
    lo = props.sections["blobs"].editors["black_min_radius"]
    hi = props.sections["blobs"].editors["black_max_radius"]
    hi.setValue(10.0)
    n = w.doc.undo.count()
    lo.setValue(20.0)
    assert take.params.blobs.black_min_radius == 4.0 and lo.value() == 4.0
    assert w.doc.undo.count() == n
    # Checkboxes and choices too; the preset chooser applies the sparse marker-set values.
    props.sections["display"].editors["point_labels_all"].setChecked(True)
    assert take.params.display.point_labels_all
    props.sections["export"].editors["units"].setCurrentText("cm")
    assert take.params.export.units == "cm"
    props.preset.activated.emit(props.preset.findText("sparse"))
    assert take.params.init3d.max_allowed_depth == 60.0
    w.actions["edit.restore_properties"].trigger()
    assert take.params.init3d.max_allowed_depth == 35.0 and not take.params.display.point_labels_all


def test_tracker_pane(loaded):
    pane = loaded.panes["tracker"]
    assert set(pane.buttons) >= {"tracker.back_to_start", "tracker.forward_to_end", "tracker.clear",
                                 "tracker.add_keyframe"}
    pane.editors.editors["break_threshold"].setValue(0.7)
    assert loaded.doc.take.params.tracker.break_threshold == 0.7
    pane.settings_button.setChecked(False)
    assert not pane.box.isVisible()


def test_selection_pane_camera_selection(loaded):
    w = loaded
    pane = w.panes["selection"]
    assert pane.cameras.count() == 4
    pane.cameras.item(2).setCheckState(Qt.CheckState.Checked)
    assert w.doc.sel_cameras == [2] and w.doc.target_cameras() == [2]
    w.doc.toggle_camera(0)
    assert pane.cameras.item(0).checkState() == Qt.CheckState.Checked
    w.actions["view.rotate_cw"].trigger()
    assert [c.rotation for c in w.doc.take.cameras] == [90, 0, 90, 0]
    w.doc.undo.undo()
    assert [c.rotation for c in w.doc.take.cameras] == [0, 0, 0, 0]


def test_selection_pane_follows_the_active_camera_view(qtbot, loaded):
    """Clicking in a camera view makes it the active one; the pane says so at once."""
    w = loaded
    pane = w.panes["selection"]
    w.workspace.set_layout(4)
    view = w.workspace.camera_views()[1]
    qtbot.mouseClick(view, Qt.MouseButton.LeftButton, pos=view.rect().center())
    assert w.doc.active_camera == view.camera
    assert pane.summary.text().endswith(f"active camera view: {view.camera}")


def test_selected_point_pane(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    inject_truth(loaded, synth, markers=3)
    pane = loaded.panes["selected_point"]
    take = loaded.doc.take
    assert pane.rows() == []
    loaded.doc.select(take.points.ids[:2].tolist())
    assert pane.rows() == []                     # several points: empty
    loaded.doc.select([int(take.points.ids[0])])
    assert pane.rows() == [(0, -1), (0, 0), (0, 1), (0, 2), (0, 3)]
    codes, is_sensor = pane.data.rows(pane.rows())
    assert codes.shape == (5, 3) and is_sensor.tolist() == [False, True, True, True, True]


def test_panels_menu_and_toggle_docks(loaded):
    w = loaded
    dock = w.docks["log"]
    dock.toggleViewAction().trigger()
    assert not dock.isVisible()
    dock.toggleViewAction().trigger()
    assert dock.isVisible()
    w.actions["view.toggle_docks"].trigger()
    assert not any(d.isVisible() for d in w.docks.values())
    assert w.workspace.isVisible() and w.timebar.isVisible()
    w.actions["view.toggle_docks"].trigger()
    assert dock.isVisible()
