"""Qt undo integration: every :class:`~carapost.ops.change.Change` becomes a ``QUndoCommand``.

The operations layer builds changes without touching the take; pushing a :class:`ChangeCommand`
onto the document's ``QUndoStack`` applies it (``push`` calls ``redo``). The History pane is a
view of that stack.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from PySide6.QtGui import QUndoCommand

from carapost.ops.change import Change

if TYPE_CHECKING:  # pragma: no cover
    from .document import Document

__all__ = ["ChangeCommand"]

log = logging.getLogger("carapost.ui")


class ChangeCommand(QUndoCommand):
    """A take change on the undo stack.

    Parameters
    ----------
    doc : Document
        Owner of the take; told after every redo/undo so views refresh.
    change : Change
        Applied by :meth:`redo` (also on ``push``), reverted by :meth:`undo`.

    If applying the change fails on ``push`` the error is logged and the command is made
    obsolete, so Qt drops it instead of keeping a broken history entry.
    """

    def __init__(self, doc: "Document", change: Change) -> None:
        super().__init__(change.text or type(change).__name__)
        self.doc = doc
        self.change = change
        self.failed = False

    def redo(self) -> None:
        try:
            self.change.redo(self.doc.take)
        except Exception as exc:  # noqa: BLE001 - reported to the user, never a raw traceback
            self.failed = True
            log.error("%s failed: %s", self.text(), exc)
            self.setObsolete(True)
        self.doc.notify_take_changed()

    def undo(self) -> None:
        self.change.undo(self.doc.take)
        self.doc.notify_take_changed()
