"""The reference guide's menus and shortcut tables, checked against the running window."""

import re
from pathlib import Path

from PySide6.QtGui import QKeySequence

from carapost.ui.actions import ACTIONS, MENUS

DOCS = Path(__file__).resolve().parents[2] / "docs" / "gui.md"

#: Every entry of the guide's menu tables ("Vicon CaraPost menus"), by menu.
GUIDE_MENUS = {
    "File": ["Open", "Clear", "Save", "Save As", "Import Pico Files", "Import Calibration Brim [svg]", "Import XCP",
             "Import Labels From Cara File", "Import Labels From Text File", "Export XCP [Current Frame]",
             "Export C3D", "Export FBX", "Recent Files", "Clear Recent Files", "Exit"],
    "Edit": ["Undo", "Redo", "Clear History", "Create Points From Detections", "Delete Selected",
             "Split Selected Point", "Merge", "Clear Selected [Current Frame]", "Clear Selected [Active Range]",
             "Detach Detections [Current Frame]", "Detach Detections [Active Range]", "Relocate Files",
             "Increment Image Sequence Offset", "Add Target Track", "Edit Target Track", "Stop Point Edit mode",
             "Gaps To Keys", "Remove Unused Detections", "Remove Interpolated 3D Points", "Rename Point",
             "Clear All Labels", "Delete Selected Labels", "Unlabel Selected Points",
             "Create Stick from Selected Point", "Create Stick Mesh", "Edit Stick Color", "Clear Active Range",
             "Restore Properties To Defaults", "Read Blob Parameters From Pico Files"],
    "View": ["Panels", "New Floating Workspace", "Show Calibration Brim SVG", "Full Screen",
             "Toggle Dock Widget Visibility", "Toggle Blob Preview", "Toggle Show Stabilized", "Go To Frame",
             "Go to Start Frame", "Go to End Frame", "Play", "Next Frame", "Prev Frame", "Lock To Point",
             "Next Key Frame", "Prev Key Frame", "Select Point", "Get Point Information",
             "Rotate Selected Sensors Clockwise", "Rotate Selected Sensors Anticlockwise",
             "Select Point With Fewest Gaps", "Go To Next Gap of Selected Point", "Distance Between Two Points",
             "Set Active Range Start", "Set Active Range End", "Reset Active Range", "Set View Range to Active Range",
             "Reset View Range", "Center Selection All 2D Views", "Frame Selection All 2D Views"],
    "Process": ["Detect Blobs [Active Range]", "Detect Blobs [Current Frame]", "Load ROM", "Initialize from ROM",
                "Initialize from ROM [Brim Only]", "Initialize Default Calibration Brim [v2.0]",
                "Initialize Default Calibration Brim [v1.1]", "Initialize Default Calibration Brim [v1.0]",
                "Solve Calibration Brim [Manual]", "Initialize 3D", "Bundle Current Frame [Unconstrained]",
                "Bundle Sequence [Unconstrained]", "Track Forwards [Sequence]", "Track Backwards [Sequence]",
                "Track Forwards [Single Frame]", "Track Backwards [Single Frame]", "Stabilize Data [Manual]",
                "Stabilize Data [Assisted]", "Align Data", "Interpolate Gaps"],
    "Help": ["View latest help on vicon.com", "View installed help", "Check For Updates", "Licensing",
             "Show 3rd Party Licenses", "About"],
}

#: The guide's shortcut tables (and the shortcuts printed in its menu tables): key -> action.
GUIDE_SHORTCUTS = [
    ("Ctrl+O", "file.open"), ("Ctrl+S", "file.save"), ("Space", "view.play"), ("Ctrl+F", "view.toggle_docks"),
    ("F", "view.full_screen"), ("Ctrl+B", "view.blob_preview"), ("Ctrl+Shift+S", "view.stabilized"),
    ("Ctrl+Right", "view.rotate_cw"), ("Ctrl+Left", "view.rotate_ccw"), ("Ctrl+G", "view.goto"),
    ("Home", "view.start"), ("End", "view.end"), ("Right", "view.next"), ("Left", "view.prev"),
    ("Shift+Right", "view.next_key"), ("Shift+Left", "view.prev_key"), ("Ctrl+1", "view.range_start"),
    ("Ctrl+2", "view.range_end"), ("Ctrl+3", "view.range_reset"), ("Ctrl+P", "view.select_point"),
    ("Ctrl+A", "view.fewest_gaps"), ("M", "edit.merge"), ("Ctrl+D", "edit.delete"), ("Ctrl+H", "edit.detach_frame"),
    ("Ctrl+Shift+H", "edit.detach_range"), ("Shift+A", "edit.add_target"), ("Shift+E", "edit.edit_target"),
    ("Shift+S", "edit.stop_edit"), ("S", "edit.stick"), ("Ctrl+R", "edit.rename"), ("Ctrl+W", "process.track_fwd_1"),
    ("Ctrl+U", "edit.unlabel"), ("C", "view.center"), ("Shift+C", "view.frame_selection"),
    ("Ctrl+Z", "edit.undo"), ("Ctrl+Y", "edit.redo"),
]


def _menu_texts(menu):
    out = []
    for a in menu.actions():
        if a.isSeparator():
            continue
        out.append(a.text().replace("&", ""))
    return out


def test_every_guide_menu_entry_exists(window):
    for title, entries in GUIDE_MENUS.items():
        texts = _menu_texts(window.menus[title])
        missing = [e for e in entries if e not in texts]
        assert not missing, f"{title} menu lacks {missing}"
    panels = _menu_texts(window.panels_menu)
    assert set(panels) == {"Labelling", "History", "Selected Point", "Log", "Properties", "Selection", "Tracker"}


def test_action_table_is_consistent():
    keys = [a.key for a in ACTIONS]
    assert len(keys) == len(set(keys))
    in_menus = {k for ks in MENUS.values() for k in ks}
    assert in_menus - {"-", "@recent", "@panels"} <= set(keys)
    shortcuts = [QKeySequence(a.shortcut).toString() for a in ACTIONS if a.shortcut]
    assert len(shortcuts) == len(set(shortcuts)), "two actions share a shortcut"


def test_unavailable_entries_are_documented():
    text = DOCS.read_text(encoding="utf-8")
    undocumented = [a.text for a in ACTIONS if a.missing and a.text not in text]
    assert not undocumented, f"not listed in docs/gui.md: {undocumented}"


def test_every_guide_shortcut_triggers_its_action(qtbot, loaded, tmp_path):
    w = loaded
    w.prompts.answers.update({"get_int": 1, "save_file": str(tmp_path / "saved.cara")})
    target = w.workspace.slots[0].view
    w.activateWindow()
    failures = []
    for keys, action in GUIDE_SHORTCUTS:
        assert QKeySequence(keys) == w.actions[action].shortcut(), f"{action} has shortcut " \
            f"{w.actions[action].shortcut().toString()}, the guide says {keys}"
        if action == "edit.undo":   # something to undo, so Undo is enabled
            w.actions["view.range_reset"].trigger()
            w.actions["view.range_start"].trigger()
        combo = QKeySequence(keys)[0]
        w.last_action = ""
        qtbot.keyClick(target, combo.key(), combo.keyboardModifiers())
        qtbot.waitUntil(lambda: not w.jobs.busy, timeout=30000)   # e.g. Ctrl+W runs in a worker
        if w.last_action != action:
            failures.append((keys, action, w.last_action))
        if action == "view.play":
            w.timebar.stop()
        if action == "view.full_screen":
            assert w.isFullScreen()
            qtbot.keyClick(target, combo.key(), combo.keyboardModifiers())
            assert not w.isFullScreen()
        if action == "view.toggle_docks":
            assert not any(d.isVisible() for d in w.docks.values())
            qtbot.keyClick(target, combo.key(), combo.keyboardModifiers())
            assert w.docks["properties"].isVisible() or w.docks["selection"].isVisible()
    assert not failures, failures
    assert (tmp_path / "saved.cara").exists()           # Ctrl+S saved the new project


def test_go_to_frame_dialog(loaded):
    loaded.prompts.answers["get_int"] = 2
    loaded.actions["view.goto"].trigger()
    assert loaded.doc.frame == 2


def test_failing_entry_logs_reason(loaded):
    # the guide: "Initialize from ROM fails completely if no ROM take has been loaded. This
    # generates an error message in the Log pane."
    rows = []
    loaded.log_handler.emitter.record.connect(rows.append)
    loaded.actions["process.init_rom"].trigger()
    assert rows and rows[-1][1] == "Error" and re.search("no ROM take has been loaded", rows[-1][3])


def test_shortcut_shows_in_properties(window):
    tree = window.panes["properties"].tree
    heads = [tree.topLevelItem(i).text(0) for i in range(tree.topLevelItemCount())]
    assert "Shortcut" in heads and heads.index("Shortcut") == heads.index("Export") + 1
    sc = tree.topLevelItem(heads.index("Shortcut"))
    rows = {sc.child(i).text(0): sc.child(i).text(1) for i in range(sc.childCount())}
    assert rows["Merge"] == "M" and rows["Go To Frame"] == "Ctrl+G"
