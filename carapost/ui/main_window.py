"""The main window: menus from the action table, the workspace and timebar, the dock panes,
window title and unsaved-changes handling, settings, long operations."""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt
from PySide6.QtGui import QAction, QCloseEvent, QKeySequence
from PySide6.QtWidgets import QDockWidget, QMainWindow, QMenu, QVBoxLayout, QWidget

from carapost.io.sources import FrameCache, OffsetSource, open_source
from carapost.ops.change import Change
from carapost.ops.session import Session

from . import cmd_file
from .actions import ACTIONS, MENUS, PANELS, RECENT, SEP, Act, OpContext, action_table
from .document import CACHE_BYTES, Document
from .panes.history import HistoryPane
from .panes.labelling import LabellingPane
from .panes.log_pane import LogPane, QtLogHandler
from .panes.properties import PropertiesPane
from .panes.selected_point import SelectedPointPane
from .panes.selection import SelectionPane
from .panes.tracker import TrackerPane
from .prompts import Prompts
from .settings import Settings
from .timebar import Timebar
from .views.blob_preview import BlobPreviewer
from .views.camera_view import CameraView
from .workers import JobFn, JobRunner
from .workspace import FloatingWorkspace, Workspace

__all__ = ["MainWindow", "PANES"]

log = logging.getLogger("carapost")

STATE_VERSION = 1
#: Dock panes: key -> (title, area).
PANES = {"properties": ("Properties", Qt.DockWidgetArea.RightDockWidgetArea),
         "selection": ("Selection", Qt.DockWidgetArea.RightDockWidgetArea),
         "tracker": ("Tracker", Qt.DockWidgetArea.RightDockWidgetArea),
         "labelling": ("Labelling", Qt.DockWidgetArea.LeftDockWidgetArea),
         "history": ("History", Qt.DockWidgetArea.LeftDockWidgetArea),
         "selected_point": ("Selected Point", Qt.DockWidgetArea.BottomDockWidgetArea),
         "log": ("Log", Qt.DockWidgetArea.BottomDockWidgetArea)}


class MainWindow(QMainWindow):
    """The CaraPost main window.

    Attributes
    ----------
    doc : Document
    actions : dict of str to QAction
        Every menu entry by key (see :mod:`carapost.ui.actions`).
    prompts : Prompts
        The dialogs (tests substitute their own).
    jobs : JobRunner
    workspace : Workspace
    timebar : Timebar
    panes : dict of str to QWidget
    docks : dict of str to QDockWidget
    """

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setObjectName("CaraPostMainWindow")
        self.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose, True)
        self.settings = Settings()
        self.prompts = Prompts(self)
        self.doc = Document(self)
        self.jobs = JobRunner(self)
        self.previewer = BlobPreviewer(self.doc, self)
        self.table = action_table()
        self.last_action = ""
        self.point_edit_mode = ""
        self.floating: list[FloatingWorkspace] = []
        self._hidden_docks: list[QDockWidget] = []
        self._closing = False
        self.log_handler = QtLogHandler()
        self._logger_level = log.level
        log.addHandler(self.log_handler)
        if log.getEffectiveLevel() > logging.INFO:
            log.setLevel(logging.INFO)
        self._build_actions()
        self._build_central()
        self._build_docks()
        self._build_menus()
        self.doc.sessionChanged.connect(self._session_changed)
        self.doc.busyChanged.connect(lambda _b: self.update_actions())
        self.doc.displayChanged.connect(self.update_actions)
        self.doc.undo.cleanChanged.connect(lambda _c: self._update_title())
        self.doc.undo.indexChanged.connect(lambda _i: (self._update_title(), self.update_actions()))
        self.jobs.started.connect(lambda _t: self.doc.set_busy(True))
        self.jobs.finished.connect(lambda _t: self.doc.set_busy(False))
        self.statusBar().showMessage("Ready")
        self.resize(1400, 900)
        self._restore_settings()
        self._update_title()
        self.update_actions()

    # ================================================================== building
    def _build_actions(self) -> None:
        self.actions: dict[str, QAction] = {}
        for a in ACTIONS:
            qa = QAction(a.text, self)
            qa.setObjectName(a.key)
            if a.shortcut:
                qa.setShortcut(QKeySequence(a.shortcut))
                qa.setShortcutContext(Qt.ShortcutContext.WindowShortcut)
            qa.setCheckable(a.checkable)
            tip = a.tip or a.text
            if a.missing:
                tip = f"{a.text}: not available yet ({a.missing})"
            qa.setStatusTip(tip)
            qa.setToolTip(tip)
            qa.triggered.connect(lambda _checked=False, k=a.key: self.dispatch(k))
            self.actions[a.key] = qa
            self.addAction(qa)

    def _build_central(self) -> None:
        central = QWidget()
        lay = QVBoxLayout(central)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(0)
        self.workspace = Workspace(self.doc, self.previewer, n_views=self.settings.get("layout", 4)
                                   if self.settings.get("layout", 4) in (1, 2, 4) else 4)
        lay.addWidget(self.workspace, 1)
        self.timebar = Timebar(self.doc, self.jobs)
        self.timebar.layoutRequested.connect(self.workspace.set_layout)
        self.timebar.buttons["prev_key"].clicked.connect(self.actions["view.prev_key"].trigger)
        self.timebar.buttons["next_key"].clicked.connect(self.actions["view.next_key"].trigger)
        lay.addWidget(self.timebar)
        self.setCentralWidget(central)

    def _build_docks(self) -> None:
        shortcuts = [(a.text, a.shortcut) for a in ACTIONS if a.shortcut]
        self.panes: dict[str, QWidget] = {
            "properties": PropertiesPane(self.doc, shortcuts),
            "selection": SelectionPane(self.doc),
            "tracker": TrackerPane(self.doc, self.actions),
            "labelling": LabellingPane(self.doc, self.actions),
            "history": HistoryPane(self.doc, self.actions),
            "selected_point": SelectedPointPane(self.doc),
            "log": LogPane(self.log_handler),
        }
        self.docks: dict[str, QDockWidget] = {}
        for key, (title, area) in PANES.items():
            dock = QDockWidget(title, self)
            dock.setObjectName(f"dock_{key}")
            dock.setWidget(self.panes[key])
            self.addDockWidget(area, dock)
            self.docks[key] = dock
        self.tabifyDockWidget(self.docks["properties"], self.docks["selection"])
        self.tabifyDockWidget(self.docks["selection"], self.docks["tracker"])
        self.tabifyDockWidget(self.docks["labelling"], self.docks["history"])
        self.splitDockWidget(self.docks["selected_point"], self.docks["log"], Qt.Orientation.Horizontal)
        self.docks["properties"].raise_()
        self.docks["labelling"].raise_()
        self._docks_sized = False

    def _size_docks(self) -> None:
        """Default pane sizes in proportion to the window (a small screen keeps room for the views)."""
        w, h = self.width(), self.height()
        self.resizeDocks([self.docks["properties"], self.docks["labelling"]],
                         [int(min(max(0.26 * w, 200), 420)), int(min(max(0.14 * w, 150), 230))],
                         Qt.Orientation.Horizontal)
        self.resizeDocks([self.docks["log"]], [int(min(max(0.17 * h, 110), 180))], Qt.Orientation.Vertical)

    def showEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        super().showEvent(event)
        if not self._docks_sized:   # once, unless a saved window state placed them
            self._docks_sized = True
            self._size_docks()

    def _build_menus(self) -> None:
        bar = self.menuBar()
        self.menus: dict[str, QMenu] = {}
        for title, keys in MENUS.items():
            menu = bar.addMenu(title)
            self.menus[title.replace("&", "")] = menu
            for key in keys:
                if key == SEP:
                    menu.addSeparator()
                elif key == RECENT:
                    self.recent_menu = menu.addMenu("Recent Files")
                    self.refresh_recent_menu()
                elif key == PANELS:
                    self.panels_menu = menu.addMenu("Panels")
                    for dock in self.docks.values():
                        self.panels_menu.addAction(dock.toggleViewAction())
                else:
                    menu.addAction(self.actions[key])
        bar.setContextMenuPolicy(Qt.ContextMenuPolicy.CustomContextMenu)
        bar.customContextMenuRequested.connect(lambda pos: self.panels_menu.exec(bar.mapToGlobal(pos)))

    def refresh_recent_menu(self) -> None:
        self.recent_menu.clear()
        files = self.settings.recent_files()
        for i, path in enumerate(files):
            act = self.recent_menu.addAction(f"&{i + 1} {Path(path).name}")
            act.setToolTip(path)
            act.setData(path)
            act.triggered.connect(
                lambda _c=False, p=path: self._guard("Recent Files", lambda: cmd_file.open_recent(self, p)))
        self.recent_menu.setEnabled(bool(files))

    # ================================================================== dispatch
    def dispatch(self, key: str) -> None:
        """Run the action ``key`` (menu, shortcut, button); errors go to the Log pane."""
        act: Act = self.table[key]
        self.last_action = key
        qa = self.actions[key]
        if act.missing:
            if act.checkable:
                qa.setChecked(False)
            log.error("%s is not available yet: %s", act.text, act.missing)
            return
        if key == "edit.undo":
            self.doc.undo.undo()
            return
        if key == "edit.redo":
            self.doc.undo.redo()
            return
        if act.needs_take and not self.doc.has_take:
            log.error("%s: open a project or import pico files first", act.text)
            return
        if act.edits and self.doc.busy:
            log.error("%s: wait for %s to finish (or cancel it)", act.text, self.jobs.title)
            return
        self._guard(act.text, lambda: act.run(self) if act.run is not None else self.run_op(act))
        self.update_actions()

    def _guard(self, what: str, fn: Callable[[], Any]) -> None:
        try:
            fn()
        except (ValueError, KeyError, OSError, IndexError) as exc:
            msg = str(exc).strip("'\"")
            head = msg.split(":", 1)[0]
            named = msg.startswith(what.split(" [")[0]) or (":" in msg and head in what)
            log.error("%s", msg if named else f"{what}: {msg}")
            self.statusBar().showMessage(msg, 8000)

    def op_context(self) -> OpContext:
        doc = self.doc
        session = doc.session
        assert session is not None
        return OpContext(take=doc.take, session=session, frame=doc.frame, points=doc.selected_columns(),
                         detections=list(doc.sel_detections), cameras=list(doc.sel_cameras) or None,
                         image=session.image)

    def run_op(self, act: Act) -> None:
        """Run an action's operation (in a worker thread if ``act.worker``) and apply its change."""
        if act.op is None:
            return
        ctx = self.op_context()
        if not act.worker:
            self.apply(act.op(ctx))
            return
        op = act.op

        def job(progress: Callable[[int, int], None], cancel: Callable[[], bool]) -> Change:
            return op(dataclasses.replace(ctx, progress=progress, cancel=cancel))

        def done(change: Change, cancelled: bool) -> None:
            if cancelled and change is not None:
                change.text = f"{change.text} (cancelled)"
            self.apply(change, force=True)

        self.run_job(act.text, job, done)

    def run_job(self, title: str, fn: JobFn, on_done: Callable[[Any, bool], None]) -> bool:
        """Run ``fn(progress, cancel)`` in a worker; ``on_done(result, cancelled)`` on the GUI thread."""
        return self.jobs.run(title, fn, on_done)

    def apply(self, change: Change | None, *, force: bool = False) -> bool:
        return self.doc.apply(change, force=force)

    def apply_sequence(self, text: str, steps: Sequence[Callable[[], Change]]) -> None:
        """Several operations as one history entry; each is built after the previous applied."""
        self.doc.undo.beginMacro(text)
        try:
            for step in steps:
                self.doc.apply(step())
        finally:
            self.doc.undo.endMacro()

    def update_actions(self) -> None:
        has, busy = self.doc.has_take, self.doc.busy
        for key, qa in self.actions.items():
            a = self.table[key]
            qa.setEnabled((has or not a.needs_take) and not (busy and a.edits))
        self.actions["edit.undo"].setEnabled(has and not busy and self.doc.undo.canUndo())
        self.actions["edit.redo"].setEnabled(has and not busy and self.doc.undo.canRedo())
        for key, verb, text in (("edit.undo", "Undo", self.doc.undo.undoText()),
                                ("edit.redo", "Redo", self.doc.undo.redoText())):
            tip = f"{verb}: {text}" if text else f"{verb}: nothing to {verb.lower()}"
            self.actions[key].setStatusTip(tip)   # the status bar names the command (menu text stays the guide's)
            self.actions[key].setToolTip(tip)
        for key, on in (("view.blob_preview", self.doc.blob_preview), ("view.stabilized", self.doc.show_stabilized),
                        ("view.lock", self.doc.lock_to_point), ("view.full_screen", self.isFullScreen()),
                        ("edit.add_target", self.point_edit_mode == "Add Target Track"),
                        ("edit.edit_target", self.point_edit_mode == "Edit Target Track")):
            self.actions[key].setChecked(on)

    # ================================================================== files
    def last_dir(self) -> str:
        return str(self.settings.get("last_dir", str(Path.home())))

    def _remember_dir(self, path: str | os.PathLike) -> None:
        p = Path(path)
        self.settings.set("last_dir", str(p.parent if p.suffix else p))

    def default_save_path(self, ext: str = ".cara") -> str:
        if not self.doc.has_take:
            return self.last_dir()
        s = self.doc.session
        if s is not None and s.path is not None:
            return str(Path(s.path).with_suffix(ext))
        name = self.doc.take.name or "Untitled"
        return str(Path(self.last_dir()) / f"{name}{ext}")

    def open_path(self, path: str | os.PathLike, ask: bool = True) -> None:
        """Open a ``.cara`` project, or import camera files (a ``.pico`` brings its whole take)."""
        if ask and not self.maybe_save():
            return
        p = str(path)
        if p.lower().endswith(".cara"):
            self._remember_dir(p)

            def job(progress, cancel):  # type: ignore[no-untyped-def]
                return Session.open(p)

            def done(session: Session, cancelled: bool) -> None:
                self.doc.set_session(session)
                self.settings.add_recent(p)
                self.refresh_recent_menu()
                log.info("Load file [%s]", p)

            self.run_job(f"Open {Path(p).name}", job, done)
        else:
            self.import_sources([p])

    def import_sources(self, paths: Sequence[str], calibration: str | None = None) -> None:
        """Import camera files (a single ``.pico`` stands for its whole take); a calibration named
        after the take next to the files is used if none is given."""
        from carapost.io.pico import find_calibration, take_files, take_name

        paths = [str(p) for p in paths]
        if len(paths) == 1 and paths[0].lower().endswith(".pico"):
            paths = [str(q) for q in take_files(paths[0])]
        first = Path(paths[0])
        name = take_name(first)
        if calibration is None:
            found = find_calibration(first)
            calibration = str(found) if found is not None else None
        self._remember_dir(first)

        def job(progress, cancel):  # type: ignore[no-untyped-def]
            return Session.from_sources(paths, calibration, name=name)

        def done(session: Session, cancelled: bool) -> None:
            self.doc.set_session(session)
            log.info("Imported %d camera file(s) of %s%s", len(paths), name,
                     f" with calibration {calibration}" if calibration else " (no calibration found)")

        self.run_job(f"Import {name}", job, done)

    def save(self, path: str | os.PathLike | None = None) -> bool:
        """Save (atomically); a new project asks for a file name. Returns True if saved."""
        session = self.doc.session
        if session is None:
            return False
        if path is None and session.path is None:
            path = self.prompts.save_file("Save", cmd_file.CARA_FILTER, self.default_save_path())
            if not path:
                return False
        if path is not None and not str(path).lower().endswith(".cara"):
            path = f"{path}.cara"
        try:
            target = session.save(path)
        except (ValueError, OSError) as exc:
            log.error("Save failed: %s", exc)
            return False
        self.doc.mark_saved()
        self.settings.add_recent(target)
        self._remember_dir(target)
        self.refresh_recent_menu()
        self._update_title()
        log.info("Saved %s", target)
        return True

    def maybe_save(self) -> bool:
        """Ask Save / Discard / Cancel if there are unsaved changes; True to go on."""
        if not self.doc.modified:
            return True
        answer = self.prompts.save_discard_cancel("The project has unsaved changes. Save them?")
        if answer == "save":
            return self.save()
        return answer == "discard"

    def relocate(self, camera: int, path: str) -> None:
        """Relocate Files: use ``path`` as the camera's video from now on."""
        from carapost.io.cara import relocate_source

        doc = self.doc
        session = doc.session
        if session is None:
            raise ValueError("Relocate Files: no project is open")
        take = doc.take
        cam = take.cameras[camera]
        src = OffsetSource(open_source(path), offset=cam.frame_offset, rotation=cam.rotation, n_frames=take.n_frames)
        if cam.image_size[0] > 0 and (src.width, src.height) != tuple(cam.image_size):
            src.close()
            raise ValueError(f"{path}: images are {src.width}x{src.height}, camera {camera} had "
                             f"{cam.image_size[0]}x{cam.image_size[1]}")
        relocate_source(take, camera, path, cara_path=session.path)
        old = session.sources[camera]
        if old is not None:
            old.close()
        session.sources[camera] = src
        if doc.caches[camera] is not None:
            doc.caches[camera].close()  # type: ignore[union-attr]
        doc.caches[camera] = FrameCache(src, max_bytes=CACHE_BYTES // max(1, take.n_cameras))
        doc.dirty_base = True
        self._update_title()
        doc.notify_take_changed()
        log.info("Camera %d now reads %s", camera, path)

    # ================================================================== view helpers
    def camera_views(self) -> list[CameraView]:
        views = list(self.workspace.camera_views())
        for f in self.floating:
            views += f.workspace.camera_views()
        return views

    def selected_labels(self) -> list[str]:
        return self.panes["labelling"].selected_labels()  # type: ignore[attr-defined]

    def set_point_edit_mode(self, mode: str) -> None:
        self.point_edit_mode = mode
        for v in self.camera_views():
            v.mode = mode
            v.update()
        self.update_actions()

    def new_floating_workspace(self) -> FloatingWorkspace:
        w = FloatingWorkspace(self.doc, self.previewer, list(self.actions.values()), self)
        w.closed.connect(lambda obj: self.floating.remove(obj) if obj in self.floating else None)
        self.floating.append(w)
        w.show()
        return w

    def show_svg(self, svg: str, title: str) -> QWidget:
        from .dialogs import SvgWindow

        win = SvgWindow(svg, title, self)
        win.show()
        return win

    def toggle_full_screen(self) -> None:
        if self.isFullScreen():
            self.showNormal()
        else:
            self.showFullScreen()
        self.update_actions()

    def toggle_docks(self) -> None:
        """Ctrl+F: hide every pane (only the workspace and timebar stay), or show them again."""
        visible = [d for d in self.docks.values() if d.isVisible()]
        if visible:
            self._hidden_docks = visible
            for d in visible:
                d.hide()
        else:
            for d in self._hidden_docks or list(self.docks.values()):
                d.show()
            self._hidden_docks = []

    # ================================================================== state
    def _session_changed(self) -> None:
        self.timebar.stop()
        if self.point_edit_mode:
            self.set_point_edit_mode("")
        self._update_title()
        self.update_actions()

    def _update_title(self) -> None:
        s = self.doc.session
        if s is None:
            name = "No project"
        elif s.path is not None:
            name = Path(s.path).name
        else:
            name = (s.take.name or "Untitled") + " (not saved)"
        self.setWindowTitle(f"{name}[*] - CaraPost")
        self.setWindowModified(self.doc.modified)

    def _restore_settings(self) -> None:
        geo, state = self.settings.window_state()
        if geo is not None:
            self.restoreGeometry(geo)
        if state is not None:
            self._docks_sized = self.restoreState(state, STATE_VERSION)

    def save_settings(self) -> None:
        self.settings.save_window_state(self.saveGeometry(), self.saveState(STATE_VERSION))
        self.settings.set("layout", self.workspace.n_views)
        self.settings.sync()

    def closeEvent(self, event: QCloseEvent) -> None:  # noqa: N802
        if not self._closing and not self.maybe_save():
            event.ignore()
            return
        self._closing = True
        self.timebar.stop()
        if self.jobs.busy:
            self.jobs.cancel()
            self.jobs.wait()
        self.save_settings()
        for f in list(self.floating):
            f.close()
        self.workspace.detach()
        self.previewer.shutdown()
        self.panes["log"].detach()  # type: ignore[attr-defined]
        log.removeHandler(self.log_handler)
        log.setLevel(self._logger_level)
        self.doc.set_session(None)
        super().closeEvent(event)
