"""The menus as a table: every menu entry of the reference guide, its shortcut and what it runs.

Each row is an :class:`Act`. Wiring a new operation is one line: give ``op`` a function of an
:class:`OpContext` returning a :class:`~carapost.ops.change.Change` (``worker=True`` runs it in
a worker thread with progress and Cancel), or ``run`` a command taking the main window.
Entries whose operation is still being written carry ``missing`` (the reason); they stay in
the menus, and triggering one logs the reason as an error.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from carapost.ops import detect as detect_ops
from carapost.ops import points as point_ops
from carapost.ops import settings as settings_ops
from carapost.ops.change import Change

from . import cmd_edit as E
from .adapters import ops
from . import cmd_file as F
from . import cmd_help as H
from . import cmd_process as P
from . import cmd_view as V

if TYPE_CHECKING:  # pragma: no cover
    from carapost.model.take import Take
    from carapost.ops.session import Session

    from .main_window import MainWindow

__all__ = ["Act", "OpContext", "ACTIONS", "MENUS", "SEP", "RECENT", "PANELS", "action_table"]


@dataclass
class OpContext:
    """What an operation may use: the take, the current frame and the selection.

    ``points`` are point columns, ``detections`` ``(camera, frame, index)`` triples,
    ``cameras`` the explicit camera selection of the Selection pane (None = all cameras).
    ``progress``/``cancel`` are the worker's callbacks (no-ops on the GUI thread).
    """

    take: "Take"
    session: "Session"
    frame: int
    points: list[int]
    detections: list[tuple[int, int, int]]
    cameras: list[int] | None
    image: Callable[[int, int], np.ndarray]
    progress: Callable[[int, int], None] = lambda done, total: None
    cancel: Callable[[], bool] = lambda: False
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def active_frames(self) -> range:
        a, b = self.take.active_range
        return range(a, b + 1)


@dataclass(frozen=True)
class Act:
    """One menu entry.

    Attributes
    ----------
    key : str
        Stable id (``"edit.merge"``); the QAction's objectName.
    text : str
        The guide's name of the entry.
    shortcut : str
        ``QKeySequence`` text ("" for none).
    run : callable ``(MainWindow) -> None``, optional
        A command.
    op : callable ``(OpContext) -> Change``, optional
        An operation; its change is pushed onto the undo stack.
    worker : bool
        Run ``op`` in a worker thread (progress bar, Cancel).
    needs_take : bool
        Disabled while no take is open.
    edits : bool
        Changes the take: disabled while a worker runs.
    checkable : bool
    missing : str
        Why the entry does not work yet ("" = it works).
    tip : str
    """

    key: str
    text: str
    shortcut: str = ""
    run: Callable[["MainWindow"], None] | None = None
    op: Callable[[OpContext], Change] | None = None
    worker: bool = False
    needs_take: bool = True
    edits: bool = True
    checkable: bool = False
    missing: str = ""
    tip: str = ""


SEP = "-"
RECENT = "@recent"
PANELS = "@panels"



def _cols(c: OpContext, what: str) -> list[int]:
    if not c.points:
        raise ValueError(f"{what}: select points first")
    return c.points


def _track(fn: str) -> Callable[[OpContext], Change]:
    def op(c: OpContext) -> Change:
        return getattr(ops("target"), fn)(c.take, _cols(c, "Target Tracker"), c.frame, c.image,
                                          progress=c.progress, cancel=c.cancel)
    return op


def _blob_track(fn: str) -> Callable[[OpContext], Change]:
    """Track Forwards/Backwards: the selected points (all points if none)."""
    def op(c: OpContext) -> Change:
        return getattr(ops("track"), fn)(c.take, c.image, c.frame, points=c.points or None, progress=c.progress,
                                         cancel=c.cancel)
    return op


def _detect(frames: Callable[[OpContext], Sequence[int]]) -> Callable[[OpContext], Change]:
    def op(c: OpContext) -> Change:
        return detect_ops.detect_blobs(c.take, c.image, frames(c), cameras=c.cameras, progress=c.progress,
                                       cancel=c.cancel, sources=c.session.sources)
    return op


ACTIONS: list[Act] = [
    # ---------------------------------------------------------------------------- File
    Act("file.open", "Open", "Ctrl+O", run=F.open_project, needs_take=False, edits=False),
    Act("file.clear", "Clear", run=F.clear, edits=False),
    Act("file.save", "Save", "Ctrl+S", run=F.save, edits=False),
    Act("file.save_as", "Save As", run=F.save_as, edits=False),
    Act("file.import_pico", "Import Pico Files", run=F.import_pico, needs_take=False, edits=False),
    Act("file.import_brim_svg", "Import Calibration Brim [svg]", run=F.import_brim_svg),
    Act("file.import_xcp", "Import XCP", run=F.import_xcp),
    Act("file.import_labels_cara", "Import Labels From Cara File", run=F.import_labels_cara),
    Act("file.import_labels_text", "Import Labels From Text File", run=F.import_labels_text),
    Act("file.export_xcp", "Export XCP [Current Frame]", run=F.export_xcp, edits=False),
    Act("file.export_c3d", "Export C3D", run=F.export_c3d, edits=False),
    Act("file.export_fbx", "Export FBX", run=F.export_fbx, edits=False),
    Act("file.clear_recent", "Clear Recent Files", run=F.clear_recent, needs_take=False, edits=False),
    Act("file.exit", "Exit", "Ctrl+Q", run=F.exit_app, needs_take=False, edits=False),
    # ---------------------------------------------------------------------------- Edit
    Act("edit.undo", "Undo", "Ctrl+Z"),
    Act("edit.redo", "Redo", "Ctrl+Y"),
    Act("edit.clear_history", "Clear History", run=E.clear_history),
    Act("edit.create_points", "Create Points From Detections", run=E.create_points),
    Act("edit.delete", "Delete Selected", "Ctrl+D", run=E.delete_selected),
    Act("edit.split", "Split Selected Point", run=E.split),
    Act("edit.merge", "Merge", "M", run=E.merge),
    Act("edit.clear_frame", "Clear Selected [Current Frame]", run=E.clear_frame),
    Act("edit.clear_range", "Clear Selected [Active Range]", run=E.clear_range),
    Act("edit.detach_frame", "Detach Detections [Current Frame]", "Ctrl+H", run=E.detach_frame),
    Act("edit.detach_range", "Detach Detections [Active Range]", "Ctrl+Shift+H", run=E.detach_range),
    Act("edit.relocate", "Relocate Files", run=E.relocate_files, edits=False),
    Act("edit.increment_offset", "Increment Image Sequence Offset", run=E.increment_offset),
    Act("edit.add_target", "Add Target Track", "Shift+A", run=E.add_target_track, checkable=True),
    Act("edit.edit_target", "Edit Target Track", "Shift+E", run=E.edit_target_track, checkable=True),
    Act("edit.stop_edit", "Stop Point Edit mode", "Shift+S", run=E.stop_point_edit),
    Act("edit.gaps_to_keys", "Gaps To Keys", op=lambda c: ops("target").gaps_to_keys(c.take, _cols(c, "Gaps To Keys"))),
    Act("edit.remove_unused", "Remove Unused Detections", run=E.remove_unused),
    Act("edit.remove_interpolated", "Remove Interpolated 3D Points", run=E.remove_interpolated),
    Act("edit.rename", "Rename Point", "Ctrl+R", run=E.rename),
    Act("edit.clear_labels", "Clear All Labels", run=E.clear_labels),
    Act("edit.delete_labels", "Delete Selected Labels", run=E.delete_labels),
    Act("edit.unlabel", "Unlabel Selected Points", "Ctrl+U", run=E.unlabel),
    Act("edit.stick", "Create Stick from Selected Point", "S", run=E.create_stick),
    Act("edit.stick_mesh", "Create Stick Mesh", run=E.stick_mesh),
    Act("edit.stick_colour", "Edit Stick Color", run=E.stick_colour),
    Act("edit.clear_active_range", "Clear Active Range", op=lambda c: point_ops.clear_active_range(c.take)),
    Act("edit.restore_properties", "Restore Properties To Defaults",
        op=lambda c: settings_ops.restore_properties(c.take)),
    Act("edit.read_blob_params", "Read Blob Parameters From Pico Files", run=E.read_blob_parameters),
    # ---------------------------------------------------------------------------- View
    Act("view.floating", "New Floating Workspace", run=V.floating_workspace, needs_take=False, edits=False),
    Act("view.brim_svg", "Show Calibration Brim SVG", run=V.show_brim_svg, edits=False),
    Act("view.full_screen", "Full Screen", "F", run=V.full_screen, needs_take=False, edits=False, checkable=True),
    Act("view.toggle_docks", "Toggle Dock Widget Visibility", "Ctrl+F", run=V.toggle_docks, needs_take=False,
        edits=False),
    Act("view.blob_preview", "Toggle Blob Preview", "Ctrl+B", run=V.blob_preview, needs_take=False, edits=False,
        checkable=True),
    Act("view.stabilized", "Toggle Show Stabilized", "Ctrl+Shift+S", run=V.show_stabilized, needs_take=False,
        edits=False, checkable=True),
    Act("view.goto", "Go To Frame", "Ctrl+G", run=V.go_to_frame, edits=False),
    Act("view.start", "Go to Start Frame", "Home", run=V.start_frame, edits=False),
    Act("view.end", "Go to End Frame", "End", run=V.end_frame, edits=False),
    Act("view.play", "Play", "Space", run=V.play, edits=False),
    Act("view.next", "Next Frame", "Right", run=V.next_frame, edits=False),
    Act("view.prev", "Prev Frame", "Left", run=V.prev_frame, edits=False),
    Act("view.lock", "Lock To Point", run=V.lock_to_point, needs_take=False, edits=False, checkable=True),
    Act("view.next_key", "Next Key Frame", "Shift+Right", run=V.next_key, edits=False),
    Act("view.prev_key", "Prev Key Frame", "Shift+Left", run=V.prev_key, edits=False),
    Act("view.select_point", "Select Point", "Ctrl+P", run=V.select_point, edits=False),
    Act("view.point_info", "Get Point Information", run=V.point_information, edits=False),
    Act("view.rotate_cw", "Rotate Selected Sensors Clockwise", "Ctrl+Right", run=V.rotate_cw),
    Act("view.rotate_ccw", "Rotate Selected Sensors Anticlockwise", "Ctrl+Left", run=V.rotate_ccw),
    Act("view.fewest_gaps", "Select Point With Fewest Gaps", "Ctrl+A", run=V.fewest_gaps, edits=False),
    Act("view.next_gap", "Go To Next Gap of Selected Point", run=V.next_gap, edits=False),
    Act("view.distance", "Distance Between Two Points", run=V.distance, edits=False),
    Act("view.range_start", "Set Active Range Start", "Ctrl+1", run=V.range_start),
    Act("view.range_end", "Set Active Range End", "Ctrl+2", run=V.range_end),
    Act("view.range_reset", "Reset Active Range", "Ctrl+3", run=V.range_reset),
    Act("view.view_range", "Set View Range to Active Range", run=V.view_range),
    Act("view.view_range_reset", "Reset View Range", run=V.view_range_reset),
    Act("view.center", "Center Selection All 2D Views", "C", run=V.center_selection, edits=False),
    Act("view.frame_selection", "Frame Selection All 2D Views", "Shift+C", run=V.frame_selection, edits=False),
    Act("view.layout1", "1 View", run=V.layout_1, needs_take=False, edits=False,
        tip="Workspace layout: one view (restores the default zoom of all views)"),
    Act("view.layout2", "2 Views", run=V.layout_2, needs_take=False, edits=False,
        tip="Workspace layout: two views"),
    Act("view.layout4", "4 Views", run=V.layout_4, needs_take=False, edits=False,
        tip="Workspace layout: four views"),
    # ---------------------------------------------------------------------------- Process
    Act("process.detect_range", "Detect Blobs [Active Range]", op=_detect(lambda c: c.active_frames), worker=True),
    Act("process.detect_frame", "Detect Blobs [Current Frame]", op=_detect(lambda c: [c.frame]), worker=True),
    Act("process.load_rom", "Load ROM", run=P.load_rom),
    Act("process.init_rom", "Initialize from ROM", run=P.initialize_from_rom),
    Act("process.init_rom_brim", "Initialize from ROM [Brim Only]", run=P.initialize_from_rom_brim_only),
    Act("process.brim_v20", "Initialize Default Calibration Brim [v2.0]", run=P.brim_v20),
    Act("process.brim_v11", "Initialize Default Calibration Brim [v1.1]", run=P.brim_v11),
    Act("process.brim_v10", "Initialize Default Calibration Brim [v1.0]", run=P.brim_v10),
    Act("process.solve_brim", "Solve Calibration Brim [Manual]", run=P.solve_brim),
    Act("process.init3d", "Initialize 3D", op=lambda c: ops("init3d").initialize_3d_op(c.take, c.frame), worker=True),
    Act("process.init3d_auto", "Initialize 3D [Automatic]",
        op=lambda c: ops("init3d").initialize_3d_op(c.take, c.frame, auto=True), worker=True,
        tip="Initialize 3D without seeds: match detections across the cameras by epipolar distance"),
    Act("process.caddies", "Caddies...", run=P.set_caddies,
        tip="Camera pairs on one side of the head rig (Initialize 3D grows within them), or none"),
    Act("process.bundle_frame", "Bundle Current Frame [Unconstrained]",
        op=lambda c: ops("init3d").bundle_current_frame(c.take, c.frame), worker=True),
    Act("process.bundle_sequence", "Bundle Sequence [Unconstrained]",
        op=lambda c: ops("init3d").bundle_sequence(c.take, np.arange(c.take.n_frames)), worker=True),
    Act("process.track_fwd_seq", "Track Forwards [Sequence]", op=_blob_track("track_forwards_sequence"), worker=True),
    Act("process.track_back_seq", "Track Backwards [Sequence]", op=_blob_track("track_backwards_sequence"),
        worker=True),
    Act("process.track_fwd_1", "Track Forwards [Single Frame]", "Ctrl+W", op=_blob_track("track_forwards_single_frame"),
        worker=True),
    Act("process.track_back_1", "Track Backwards [Single Frame]", op=_blob_track("track_backwards_single_frame"),
        worker=True),
    Act("process.stabilize_manual", "Stabilize Data [Manual]", run=P.stabilize_manual),
    Act("process.stabilize_assisted", "Stabilize Data [Assisted]", run=P.stabilize_assisted),
    Act("process.align", "Align Data", run=P.align_data),
    Act("process.interpolate", "Interpolate Gaps", run=P.interpolate_gaps),
    # ---------------------------------------------------------------------------- Tracker pane
    Act("tracker.back_to_start", "< Track back to start", op=_track("track_back_to_start"), worker=True),
    Act("tracker.back_one", "< Track back one frame", op=_track("track_back_one_frame"), worker=True),
    Act("tracker.forward_one", "> Track forward one frame", op=_track("track_forward_one_frame"), worker=True),
    Act("tracker.forward_to_end", "> Track forward to end", op=_track("track_forward_to_end"), worker=True),
    Act("tracker.clear", "Clear Tracked Points",
        op=lambda c: ops("target").clear_tracked_points(c.take, _cols(c, "Clear Tracked Points"))),
    Act("tracker.add_keyframe", "Add Keyframe To Current Frame",
        op=lambda c: ops("target").add_keyframes(c.take, _cols(c, "Add Keyframe To Current Frame"), c.frame)),
    # ---------------------------------------------------------------------------- Help
    Act("help.online", "View latest help on vicon.com", run=H.online_help, needs_take=False, edits=False),
    Act("help.installed", "View installed help", run=H.installed_help, needs_take=False, edits=False),
    Act("help.updates", "Check For Updates", run=H.check_updates, needs_take=False, edits=False),
    Act("help.licensing", "Licensing", run=H.licensing, needs_take=False, edits=False),
    Act("help.licenses", "Show 3rd Party Licenses", run=H.third_party_licenses, needs_take=False, edits=False),
    Act("help.about", "About", run=H.about, needs_take=False, edits=False),
]

#: Menu layout: action keys, ``SEP``, ``RECENT`` (the Recent Files submenu), ``PANELS``.
MENUS: dict[str, list[str]] = {
    "&File": ["file.open", "file.clear", "file.save", "file.save_as", SEP, "file.import_pico",
              "file.import_brim_svg", "file.import_xcp", "file.import_labels_cara", "file.import_labels_text", SEP,
              "file.export_xcp", "file.export_c3d", "file.export_fbx", SEP, RECENT, "file.clear_recent", SEP,
              "file.exit"],
    "&Edit": ["edit.undo", "edit.redo", "edit.clear_history", SEP, "edit.create_points", "edit.delete", "edit.split",
              "edit.merge", "edit.clear_frame", "edit.clear_range", "edit.detach_frame", "edit.detach_range", SEP,
              "edit.relocate", "edit.increment_offset", SEP, "edit.add_target", "edit.edit_target", "edit.stop_edit",
              "edit.gaps_to_keys", SEP, "edit.remove_unused", "edit.remove_interpolated", SEP, "edit.rename",
              "edit.clear_labels", "edit.delete_labels", "edit.unlabel", "edit.stick", "edit.stick_mesh",
              "edit.stick_colour", SEP, "edit.clear_active_range", "edit.restore_properties",
              "edit.read_blob_params"],
    "&View": [PANELS, "view.floating", "view.brim_svg", "view.full_screen", "view.toggle_docks",
              "view.blob_preview", "view.stabilized", SEP, "view.goto", "view.start", "view.end", "view.play",
              "view.next", "view.prev", "view.lock", "view.next_key", "view.prev_key", SEP, "view.select_point",
              "view.point_info", "view.rotate_cw", "view.rotate_ccw", "view.fewest_gaps", "view.next_gap",
              "view.distance", SEP, "view.range_start", "view.range_end", "view.range_reset", "view.view_range",
              "view.view_range_reset", "view.center", "view.frame_selection", SEP, "view.layout1", "view.layout2",
              "view.layout4"],
    "&Process": ["process.detect_range", "process.detect_frame", SEP, "process.load_rom", "process.init_rom",
                 "process.init_rom_brim", SEP, "process.brim_v20", "process.brim_v11", "process.brim_v10",
                 "process.solve_brim", "process.caddies", "process.init3d", "process.init3d_auto",
                 "process.bundle_frame", "process.bundle_sequence", SEP,
                 "process.track_fwd_seq", "process.track_back_seq", "process.track_fwd_1", "process.track_back_1",
                 SEP, "process.stabilize_manual", "process.stabilize_assisted", "process.align",
                 "process.interpolate"],
    "&Help": ["help.online", "help.installed", "help.updates", "help.licensing", "help.licenses", "help.about"],
}


def action_table() -> dict[str, Act]:
    """The actions by key (keys are unique)."""
    table = {a.key: a for a in ACTIONS}
    if len(table) != len(ACTIONS):  # pragma: no cover - a programming error caught by the tests
        raise RuntimeError("duplicate action keys")
    return table
