"""The GUI's model: the open session, the undo stack, the current frame and the selection.

Views and panes take a :class:`Document` in their constructor and connect to its signals; they
never hold take data of their own. Selections name points by their stable ids, so a selection
survives deleting or adding other points.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence

import numpy as np
from PySide6.QtCore import QObject, Signal
from PySide6.QtGui import QUndoStack

from carapost.io.sources import FrameCache
from carapost.model.take import Take
from carapost.ops.change import Change, Composite
from carapost.ops.points import DetectionRef
from carapost.ops.session import Session

from .undo import ChangeCommand

__all__ = ["Document"]

log = logging.getLogger("carapost")

CACHE_BYTES = 768 * 2**20  #: frame cache budget shared by all cameras
PREFETCH = 12              #: frames decoded ahead of the current one


class Document(QObject):
    """One open take with everything the views share.

    Signals
    -------
    sessionChanged()
        A take was opened, imported or closed (views rebuild).
    takeChanged()
        The take's data changed (push, undo, redo, reload).
    frameChanged(int)
        The current frame moved.
    selectionChanged()
        Selected points, detections or cameras changed.
    displayChanged()
        A shared display toggle changed (blob preview, stabilized, lock to point).
    busyChanged(bool)
        A long operation started or finished (editing is disabled meanwhile).
    """

    sessionChanged = Signal()
    takeChanged = Signal()
    frameChanged = Signal(int)
    selectionChanged = Signal()
    displayChanged = Signal()
    busyChanged = Signal(bool)
    activeCameraChanged = Signal()

    def __init__(self, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.session: Session | None = None
        self.undo = QUndoStack(self)
        self.frame = 0
        self.sel_points: list[int] = []          # point ids
        self.sel_detections: list[DetectionRef] = []
        self.sel_cameras: list[int] = []         # explicit camera selection (Selection pane)
        self.active_camera: int | None = None    # the camera view last clicked
        self.caches: list[FrameCache | None] = []
        self.busy = False
        self.blob_preview = False
        self.show_stabilized = False
        self.lock_to_point = False
        self.rom: Take | None = None
        self.dirty_base = False                  # modified before the history was cleared
        self._direction = 1

    # ------------------------------------------------------------------------ session
    @property
    def take(self) -> Take:
        if self.session is None:
            raise ValueError("no take is open: open a .cara file or import pico files first")
        return self.session.take

    @property
    def has_take(self) -> bool:
        return self.session is not None

    def set_session(self, session: Session | None) -> None:
        """Replace the open session (the old one's files are closed); clears the history."""
        self.close_session()
        self.session = session
        if session is not None:
            per = CACHE_BYTES // max(1, session.take.n_cameras)
            self.caches = [FrameCache(s, max_bytes=per) if s is not None else None for s in session.sources]
            self.frame = int(np.clip(session.take.current_frame, 0, session.take.n_frames - 1))
            for m in session.messages:
                log.warning("%s", m)
        self.sessionChanged.emit()
        self.takeChanged.emit()
        self.frameChanged.emit(self.frame)
        self.selectionChanged.emit()

    def close_session(self) -> None:
        for c in self.caches:
            if c is not None:
                c.close()
        self.caches = []
        if self.session is not None:
            self.session.close()
        self.session = None
        self.undo.clear()
        self.dirty_base = False
        self.sel_points, self.sel_detections, self.sel_cameras = [], [], []
        self.active_camera = None
        self.rom = None
        self.frame = 0

    @property
    def modified(self) -> bool:
        return self.session is not None and (self.dirty_base or not self.undo.isClean())

    def mark_saved(self) -> None:
        self.dirty_base = False
        self.undo.setClean()

    def clear_history(self) -> None:
        """"Clear History": forget every command (frees their memory), keep the modified flag."""
        self.dirty_base = self.modified
        self.undo.clear()

    # ------------------------------------------------------------------------ changes
    def apply(self, change: Change | None, *, force: bool = False) -> bool:
        """Push a change onto the undo stack (applying it). Empty changes are reported, not pushed.

        While a long operation runs (``busy``) changes are refused unless ``force`` (the
        operation's own result). Returns True if the change was applied.
        """
        if change is None:
            return False
        if self.busy and not force:
            log.error("%s: wait for the running operation to finish (or cancel it)", change.text or "Change")
            return False
        if isinstance(change, Composite) and not change.changes:
            log.info("%s", change.text or "Nothing to change")
            return False
        cmd = ChangeCommand(self, change)
        self.undo.push(cmd)
        if cmd.failed:
            return False
        log.info("%s", cmd.text())
        return True

    def notify_take_changed(self) -> None:
        """Called after the take changed: sync sources, drop stale selections, tell the views."""
        if self.session is None:
            return
        take = self.take
        for c, src in enumerate(self.session.sources):
            if src is None or c >= take.n_cameras:
                continue
            off = take.cameras[c].frame_offset
            if src.offset != off:
                src.offset = off
                cache = self.caches[c] if c < len(self.caches) else None
                if cache is not None:
                    cache.clear()
        ids = set(take.points.ids.tolist())
        pts = [p for p in self.sel_points if p in ids]
        dets = [d for d in self.sel_detections if d[0] < take.n_cameras and d[2] < take.detections[d[0]].count(d[1])]
        changed = pts != self.sel_points or dets != self.sel_detections
        self.sel_points, self.sel_detections = pts, dets
        self.takeChanged.emit()
        if changed:
            self.selectionChanged.emit()

    # ------------------------------------------------------------------------ frames
    @property
    def n_frames(self) -> int:
        return self.take.n_frames if self.session is not None else 1

    def set_frame(self, frame: int) -> None:
        """Move the current frame (clamped to the take) and prefetch images ahead."""
        if self.session is None:
            return
        f = int(np.clip(frame, 0, self.take.n_frames - 1))
        if f == self.frame:
            return
        self._direction = 1 if f > self.frame else -1
        self.frame = f
        self.take.current_frame = f
        self.frameChanged.emit(f)
        self.prefetch()

    def prefetch(self) -> None:
        f, n = self.frame, self.n_frames
        if self._direction > 0:
            ahead = range(f + 1, min(n, f + 1 + PREFETCH))
        else:
            ahead = range(f - 1, max(-1, f - 1 - PREFETCH), -1)
        for cache in self.caches:
            if cache is not None:
                cache.prefetch(ahead)

    def image(self, camera: int, frame: int | None = None) -> np.ndarray | None:
        """Grayscale image ``(H, W)`` uint8 of a camera (un-rotated), or None without a source."""
        if self.session is None or camera >= len(self.caches) or self.caches[camera] is None:
            return None
        f = self.frame if frame is None else frame
        try:
            return self.caches[camera].get(f)  # type: ignore[union-attr]
        except (IndexError, ValueError, OSError) as exc:
            log.error("camera %d frame %d: %s", camera, f, exc)
            return None

    # ------------------------------------------------------------------------ selection
    def selected_columns(self) -> list[int]:
        """Column indices of the selected points, in selection order."""
        if self.session is None or not self.sel_points:
            return []
        ids = self.take.points.ids
        if len(ids) == 0:
            return []
        order = np.argsort(ids)
        pos = np.clip(np.searchsorted(ids[order], self.sel_points), 0, len(ids) - 1)
        ok = ids[order][pos] == np.asarray(self.sel_points)
        return [int(c) for c in order[pos][ok]]

    def select(self, points: Iterable[int] = (), detections: Iterable[DetectionRef] = (), *, add: bool = False,
               toggle: bool = False) -> None:
        """Select points (by id) and detections; ``add`` extends, ``toggle`` flips membership."""
        pts = [int(p) for p in points]
        dets = [tuple(int(v) for v in d) for d in detections]
        if toggle:
            new_p = [p for p in self.sel_points if p not in pts] + [p for p in pts if p not in self.sel_points]
            new_d = [d for d in self.sel_detections if d not in dets] + \
                [d for d in dets if d not in self.sel_detections]  # type: ignore[misc]
        elif add:
            new_p = self.sel_points + [p for p in pts if p not in self.sel_points]
            new_d = self.sel_detections + [d for d in dets if d not in self.sel_detections]  # type: ignore[misc]
        else:
            new_p, new_d = list(dict.fromkeys(pts)), list(dict.fromkeys(dets))  # type: ignore[arg-type]
        if new_p != self.sel_points or new_d != self.sel_detections:
            self.sel_points, self.sel_detections = new_p, new_d  # type: ignore[assignment]
            self.selectionChanged.emit()

    def select_columns(self, cols: Sequence[int], *, add: bool = False) -> None:
        ids = self.take.points.ids
        self.select([int(ids[c]) for c in cols], self.sel_detections if add else (), add=add)

    def clear_selection(self) -> None:
        self.select()

    def set_camera_selection(self, cameras: Iterable[int]) -> None:
        cams = sorted({int(c) for c in cameras})
        if cams != self.sel_cameras:
            self.sel_cameras = cams
            self.selectionChanged.emit()

    def set_active_camera(self, camera: int | None) -> None:
        """The camera view last clicked (what camera-wise commands use without a selection)."""
        if camera != self.active_camera:
            self.active_camera = camera
            self.activeCameraChanged.emit()

    def toggle_camera(self, camera: int) -> None:
        cams = set(self.sel_cameras)
        cams ^= {int(camera)}
        self.set_camera_selection(cams)

    def target_cameras(self) -> list[int] | None:
        """The explicit camera selection, else the active camera view, else None (all)."""
        if self.sel_cameras:
            return list(self.sel_cameras)
        if self.active_camera is not None:
            return [self.active_camera]
        return None

    # ------------------------------------------------------------------------ display
    def set_display(self, name: str, value: bool) -> None:
        if getattr(self, name) != value:
            setattr(self, name, bool(value))
            self.displayChanged.emit()

    def set_busy(self, busy: bool) -> None:
        if busy != self.busy:
            self.busy = busy
            self.busyChanged.emit(busy)
