"""What every workspace view shares: the document, its signals, shuttling time, option menus."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from PySide6.QtCore import QRectF, Qt, Signal
from PySide6.QtGui import QAction, QColor, QPainter, QWheelEvent
from PySide6.QtWidgets import QMenu, QWidget

from ..document import Document

__all__ = ["BaseView", "add_toggle", "add_action", "plain_right_click", "draw_hint", "NO_TAKE"]

#: What an empty view says (an artist opening the program sees how to start).
NO_TAKE = "No take open\nFile > Open (Ctrl+O): a .cara project or one .pico file of a take"


def draw_hint(p: QPainter, rect: QRectF, text: str, *, top: bool = False) -> None:
    """Grey hint text in an empty view or pane: centred, or at the top (over a drawing)."""
    p.setPen(QColor(175, 178, 185))
    align = (Qt.AlignmentFlag.AlignHCenter | Qt.AlignmentFlag.AlignTop) if top else Qt.AlignmentFlag.AlignCenter
    p.drawText(rect.adjusted(8, 8, -8, -8), int(align | Qt.TextFlag.TextWordWrap), text)


def add_toggle(menu: QMenu, text: str, checked: bool, slot: Callable[[bool], None]) -> QAction:
    """A checkable menu entry calling ``slot(checked)``."""
    act = menu.addAction(text)
    act.setCheckable(True)
    act.setChecked(bool(checked))
    act.toggled.connect(slot)
    return act


def add_action(menu: QMenu, text: str, slot: Callable[[], None], enabled: bool = True) -> QAction:
    act = menu.addAction(text)
    act.triggered.connect(lambda _checked=False: slot())
    act.setEnabled(enabled)
    return act


class BaseView(QWidget):
    """A view of the document shown in a workspace slot.

    Subclasses set ``kind`` and implement :meth:`fill_context_menu` and the ``on_*`` hooks. The
    document's signals are connected here and disconnected by :meth:`detach` (called when the
    view is replaced or its window closes).

    Signals
    -------
    contextRequested(QPoint)
        Global position of a plain right-click (the slot shows the view's context menu).
    """

    kind = ""
    contextRequested = Signal(object)

    def __init__(self, doc: Document, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.doc = doc
        self._connections: list[tuple[object, Callable]] = []
        self._listen(doc.sessionChanged, self.on_session)
        self._listen(doc.takeChanged, self.on_take)
        self._listen(doc.frameChanged, self.on_frame)
        self._listen(doc.selectionChanged, self.on_selection)
        self._listen(doc.displayChanged, self.on_display)

    def _listen(self, signal: object, slot: Callable) -> None:
        signal.connect(slot)  # type: ignore[attr-defined]
        self._connections.append((signal, slot))

    def detach(self) -> None:
        """Disconnect from the document (the view is going away)."""
        for signal, slot in self._connections:
            try:
                signal.disconnect(slot)  # type: ignore[attr-defined]
            except (RuntimeError, TypeError):  # already gone with its sender
                pass
        self._connections.clear()

    # -- hooks ----------------------------------------------------------------------------
    def on_session(self) -> None:
        self.update()

    def on_take(self) -> None:
        self.update()

    def on_frame(self, frame: int) -> None:
        self.update()

    def on_selection(self) -> None:
        self.update()

    def on_display(self) -> None:
        self.update()

    def fill_context_menu(self, menu: QMenu) -> None:
        """Add the view's own entries (after the View and Sensor submenus)."""

    def title(self) -> str:
        return self.kind

    # -- shared interaction ---------------------------------------------------------------
    def shuttle(self, steps: int) -> None:
        if self.doc.has_take and steps:
            self.doc.set_frame(self.doc.frame + steps)

    def wheelEvent(self, event: QWheelEvent) -> None:  # noqa: N802 - Qt override
        """Mouse wheel shuttles time (the guide's "Shuttle time")."""
        dy = event.angleDelta().y()
        steps = int(dy / 120) or int(np.sign(dy))
        self.shuttle(-steps)
        event.accept()

    def request_context_menu(self, global_pos: object) -> None:
        self.contextRequested.emit(global_pos)


def plain_right_click(modifiers: Qt.KeyboardModifier) -> bool:
    """A right-click without Shift/Alt opens the context menu (with them it zooms)."""
    return not (modifiers & (Qt.KeyboardModifier.ShiftModifier | Qt.KeyboardModifier.AltModifier))
