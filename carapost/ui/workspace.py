"""The workspace: 1, 2 or 4 view slots, each showing a sensor, the 3D view, a graph or the
continuity chart (chosen from the slot's header buttons or its context menu)."""

from __future__ import annotations

from PySide6.QtCore import QPoint, Qt, Signal
from PySide6.QtGui import QAction
from PySide6.QtWidgets import QFrame, QGridLayout, QHBoxLayout, QLabel, QMenu, QToolButton, QVBoxLayout, QWidget

from .document import Document
from .views.base import BaseView
from .views.blob_preview import BlobPreviewer
from .views.camera_view import CameraView
from .views.continuity import ContinuityView
from .views.graph_view import GraphView
from .views.view3d import View3D

__all__ = ["ViewSlot", "Workspace", "FloatingWorkspace", "VIEW_KINDS"]

VIEW_KINDS = ("sensor", "3d", "graph", "continuity")


class ViewSlot(QFrame):
    """One pane of the workspace: a header (title, view buttons) above a view."""

    viewChanged = Signal()

    def __init__(self, doc: Document, previewer: BlobPreviewer | None, kind: str = "3d", camera: int = 0,
                 parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        self.previewer = previewer
        self.setFrameShape(QFrame.Shape.StyledPanel)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(1, 1, 1, 1)
        lay.setSpacing(0)
        head = QHBoxLayout()
        head.setContentsMargins(4, 1, 2, 1)
        self.title = QLabel()
        self.title.setMinimumWidth(1)   # a long sensor name is clipped, it does not widen the window
        head.addWidget(self.title, 1)
        self.sensor_button = QToolButton()
        self.sensor_button.setText("Sensor")
        self.sensor_button.setPopupMode(QToolButton.ToolButtonPopupMode.InstantPopup)
        self.sensor_button.setMenu(QMenu(self.sensor_button))
        self.sensor_button.menu().aboutToShow.connect(self._fill_sensor_button)
        head.addWidget(self.sensor_button)
        for k, text in (("3d", "3D"), ("graph", "Graph"), ("continuity", "Continuity")):
            b = QToolButton()
            b.setText(text)
            b.setObjectName(f"slot_{k}")
            b.clicked.connect(lambda _c=False, kk=k: self.set_view(kk, self.camera))
            head.addWidget(b)
        lay.addLayout(head)
        self.view: BaseView | None = None
        self.kind, self.camera = kind, camera
        self.set_view(kind, camera)

    # ------------------------------------------------------------------ views
    def set_view(self, kind: str, camera: int | None = None) -> BaseView:
        """Show a view of ``kind`` (``"sensor"``, ``"3d"``, ``"graph"``, ``"continuity"``)."""
        if kind not in VIEW_KINDS:
            raise ValueError(f"unknown view kind {kind!r}; choose from {', '.join(VIEW_KINDS)}")
        camera = self.camera if camera is None else int(camera)
        old = self.view
        if old is not None:
            old.detach()
            self.layout().removeWidget(old)
            old.hide()
            old.deleteLater()
        if kind == "sensor":
            view: BaseView = CameraView(self.doc, camera, self.previewer, self)
        elif kind == "graph":
            view = GraphView(self.doc, camera, self)
        elif kind == "continuity":
            view = ContinuityView(self.doc, self)
        else:
            view = View3D(self.doc, self)
        view.contextRequested.connect(self.show_context_menu)
        self.layout().addWidget(view)
        self.view, self.kind, self.camera = view, kind, camera
        view.on_session()
        self._update_title()
        self.viewChanged.emit()
        return view

    def _update_title(self) -> None:
        text = self.view.title() if self.view is not None else ""
        self.title.setText(text)
        self.title.setToolTip(text)

    def n_cameras(self) -> int:
        return self.doc.take.n_cameras if self.doc.has_take else 4

    def set_sensor(self, camera: int) -> None:
        """Sensor > Sensor N: the camera of a sensor or graph view (other views become sensors)."""
        if self.kind == "graph":
            self.camera = camera
            self.view.set_camera(camera)  # type: ignore[union-attr]
            self._update_title()
        else:
            self.set_view("sensor", camera)

    def _fill_sensor_button(self) -> None:
        menu = self.sensor_button.menu()
        menu.clear()
        for c in range(self.n_cameras()):
            menu.addAction(f"Sensor {c}").triggered.connect(lambda _c=False, cc=c: self.set_sensor(cc))

    # ------------------------------------------------------------------ context menu
    def context_menu(self) -> QMenu:
        """The view's context menu: View and Sensor submenus, then the view's own entries."""
        menu = QMenu(self)
        views = menu.addMenu("View")
        for kind, text in (("3d", "3D"), ("graph", "Graph"), ("continuity", "Continuity")):
            act: QAction = views.addAction(text)
            act.setCheckable(True)
            act.setChecked(self.kind == kind)
            act.triggered.connect(lambda _c=False, k=kind: self.set_view(k))
        for c in range(self.n_cameras()):
            act = views.addAction(f"Sensor {c}")
            act.setCheckable(True)
            act.setChecked(self.kind == "sensor" and self.camera == c)
            act.triggered.connect(lambda _c=False, cc=c: self.set_view("sensor", cc))
        sensors = menu.addMenu("Sensor")
        for c in range(self.n_cameras()):
            act = sensors.addAction(f"Sensor {c}")
            act.setCheckable(True)
            act.setChecked(self.kind in ("sensor", "graph") and self.camera == c)
            act.triggered.connect(lambda _c=False, cc=c: self.set_sensor(cc))
        menu.addSeparator()
        if self.view is not None:
            self.view.fill_context_menu(menu)
        return menu

    def show_context_menu(self, global_pos: QPoint) -> None:
        menu = self.context_menu()
        menu.exec(global_pos)
        menu.deleteLater()

    def detach(self) -> None:
        if self.view is not None:
            self.view.detach()


class Workspace(QWidget):
    """1, 2 or 4 view slots in a grid."""

    def __init__(self, doc: Document, previewer: BlobPreviewer | None, *, n_views: int = 4,
                 default: str = "sensors", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        self.previewer = previewer
        self.default = default
        self.grid = QGridLayout(self)
        self.grid.setContentsMargins(0, 0, 0, 0)
        self.grid.setSpacing(2)
        self.slots = [ViewSlot(doc, previewer, *self._default_kind(i), parent=self) for i in range(4)]
        self.n_views = 0
        self.set_layout(n_views)
        doc.sessionChanged.connect(self._session_changed)
        self._cameras = doc.take.n_cameras if doc.has_take else -1

    def _default_kind(self, i: int) -> tuple[str, int]:
        n = self.doc.take.n_cameras if self.doc.has_take else 4
        if self.default == "3d":
            return ("3d", 0) if i == 0 else (("sensor", i - 1) if i - 1 < n else ("continuity", 0))
        if i < n:
            return ("sensor", i)
        return ("3d", 0) if i == n else ("continuity", 0)

    def _session_changed(self) -> None:
        n = self.doc.take.n_cameras if self.doc.has_take else -1
        if n != self._cameras:  # a different rig: back to the default views
            self._cameras = n
            for i, slot in enumerate(self.slots):
                slot.set_view(*self._default_kind(i))
        for slot in self.slots:
            slot._update_title()

    def set_layout(self, n: int) -> None:
        """Show 1, 2 or 4 views; camera views return to their default zoom (fit to window)."""
        if n not in (1, 2, 4):
            raise ValueError(f"a workspace shows 1, 2 or 4 views, not {n}")
        for slot in self.slots:
            self.grid.removeWidget(slot)
            slot.hide()
        pos = {1: [(0, 0)], 2: [(0, 0), (0, 1)], 4: [(0, 0), (0, 1), (1, 0), (1, 1)]}[n]
        for slot, (r, c) in zip(self.slots, pos):
            self.grid.addWidget(slot, r, c)
            slot.show()
        for r in range(2):
            self.grid.setRowStretch(r, 1 if r < (2 if n == 4 else 1) else 0)
            self.grid.setColumnStretch(r, 1 if r < (1 if n == 1 else 2) else 0)
        self.n_views = n
        for v in self.camera_views():
            v.fit_to_window()

    def visible_slots(self) -> list[ViewSlot]:
        return self.slots[:self.n_views]

    def camera_views(self) -> list[CameraView]:
        return [s.view for s in self.visible_slots() if isinstance(s.view, CameraView)]

    def detach(self) -> None:
        try:
            self.doc.sessionChanged.disconnect(self._session_changed)
        except (RuntimeError, TypeError):
            pass
        for s in self.slots:
            s.detach()


class FloatingWorkspace(QWidget):
    """View > New Floating Workspace: a separate window with a workspace (3D view first)."""

    closed = Signal(object)

    def __init__(self, doc: Document, previewer: BlobPreviewer | None, actions: list[QAction],
                 parent: QWidget | None = None) -> None:
        super().__init__(parent, Qt.WindowType.Window)
        self.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose, True)
        self.setWindowTitle("CaraPost - Workspace")
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        bar = QHBoxLayout()
        self.workspace = Workspace(doc, previewer, n_views=1, default="3d", parent=self)
        for n in (1, 2, 4):
            b = QToolButton()
            b.setText(f"{n}")
            b.setToolTip(f"{n} view{'s' if n > 1 else ''}")
            b.clicked.connect(lambda _c=False, nn=n: self.workspace.set_layout(nn))
            bar.addWidget(b)
        bar.addStretch(1)
        lay.addLayout(bar)
        lay.addWidget(self.workspace, 1)
        self.addActions(actions)   # the main window's shortcuts work here too
        self.resize(720, 520)

    def closeEvent(self, event) -> None:  # type: ignore[no-untyped-def]  # noqa: N802
        self.workspace.detach()
        self.closed.emit(self)
        super().closeEvent(event)
