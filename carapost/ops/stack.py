"""A plain (Qt-free) undo stack for the command line and the scripting API.

The GUI wraps the same :class:`~carapost.ops.change.Change` objects in ``QUndoCommand``s; this
class gives scripts the same semantics: ``push`` applies, ``undo``/``redo`` step through the
history, ``is_clean`` tells whether the take matches its last save.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from carapost.model.take import Take

from .change import Change

__all__ = ["UndoStack"]


@dataclass
class UndoStack:
    take: Take
    changes: list[Change] = field(default_factory=list)
    index: int = 0          # number of applied changes
    clean_index: int | None = 0

    def push(self, change: Change) -> Change:
        """Apply ``change`` and record it (dropping anything that had been undone)."""
        change.redo(self.take)
        del self.changes[self.index:]
        if self.clean_index is not None and self.clean_index > self.index:
            self.clean_index = None
        self.changes.append(change)
        self.index += 1
        return change

    def can_undo(self) -> bool:
        return self.index > 0

    def can_redo(self) -> bool:
        return self.index < len(self.changes)

    def undo(self) -> None:
        if not self.can_undo():
            raise IndexError("nothing to undo")
        self.index -= 1
        self.changes[self.index].undo(self.take)

    def redo(self) -> None:
        if not self.can_redo():
            raise IndexError("nothing to redo")
        self.changes[self.index].redo(self.take)
        self.index += 1

    def set_clean(self) -> None:
        self.clean_index = self.index

    def is_clean(self) -> bool:
        return self.clean_index == self.index

    def clear(self) -> None:
        """"Clear History": forget every change (frees their memory)."""
        self.changes.clear()
        self.clean_index = 0 if self.is_clean() else None
        self.index = 0

    def history(self) -> list[tuple[str, bool]]:
        """(text, applied) for every entry, oldest first — the History pane's list."""
        return [(c.text, i < self.index) for i, c in enumerate(self.changes)]
