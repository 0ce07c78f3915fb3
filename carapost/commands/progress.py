"""Terminal progress bars for long command-line work (tqdm on stderr)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from tqdm import tqdm

__all__ = ["progress_bar", "ENABLED"]

#: Set to False by ``--no-progress`` (farm logs).
ENABLED = True


@contextmanager
def progress_bar(description: str, unit: str = "frame") -> Iterator[Callable[[int, int], None]]:
    """A ``progress(done, total)`` callback drawing a bar while the block runs."""
    bar: tqdm | None = None

    def update(done: int, total: int) -> None:
        nonlocal bar
        if not ENABLED:
            return
        if bar is None:
            bar = tqdm(total=total, desc=description, unit=unit, file=sys.stderr, leave=False,
                       dynamic_ncols=True, disable=None)  # None: no bar when stderr is not a terminal
        bar.total = total
        bar.n = done
        bar.refresh()

    try:
        yield update
    finally:
        if bar is not None:
            bar.close()
