"""Long operations off the GUI thread, with progress and a working Cancel.

An operation is a plain function ``fn(progress, cancel) -> result`` (the ops layer's
``progress(done, total)`` / ``cancel() -> bool`` callbacks). :class:`JobRunner` runs one at a
time in a ``QThread``; progress arrives on the GUI thread through queued signals, and the
result is handed to a callback on the GUI thread, which applies it as one undoable change.
Cancelling keeps what was finished: the operations return a partial change.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from PySide6.QtCore import QObject, QThread, Signal
from PySide6.QtWidgets import QHBoxLayout, QLabel, QProgressBar, QPushButton, QWidget

__all__ = ["JobRunner", "ProgressPanel", "JobFn"]

log = logging.getLogger("carapost")

JobFn = Callable[[Callable[[int, int], None], Callable[[], bool]], Any]


class _JobThread(QThread):
    progressed = Signal(int, int)
    succeeded = Signal(object)
    errored = Signal(str)

    def __init__(self, fn: JobFn, cancel: threading.Event, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.fn = fn
        self.cancel_event = cancel
        self._last = 0.0

    def _progress(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done >= total or now - self._last > 0.05:  # at most ~20 updates a second
            self._last = now
            self.progressed.emit(int(done), int(total))

    def run(self) -> None:
        try:
            result = self.fn(self._progress, self.cancel_event.is_set)
        except ValueError as exc:
            self.errored.emit(str(exc))
        except Exception as exc:  # noqa: BLE001 - shown in the Log pane, never a raw traceback
            log.debug("job failed", exc_info=True)
            self.errored.emit(f"{type(exc).__name__}: {exc}")
        else:
            self.succeeded.emit(result)


class JobRunner(QObject):
    """Runs one long operation at a time.

    Signals
    -------
    started(str)
        Title of the job that started.
    progress(int, int)
        ``done, total``.
    finished(str)
        The job ended (done, failed or cancelled); its title.
    """

    started = Signal(str)
    progress = Signal(int, int)
    finished = Signal(str)

    def __init__(self, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self._thread: _JobThread | None = None
        self._cancel = threading.Event()
        self.title = ""
        self.cancelled = False
        self._on_done: Callable[[Any, bool], None] = lambda r, c: None
        self._on_error: Callable[[str], None] | None = None

    @property
    def busy(self) -> bool:
        return self._thread is not None

    def run(self, title: str, fn: JobFn, on_done: Callable[[Any, bool], None],
            on_error: Callable[[str], None] | None = None) -> bool:
        """Start ``fn`` in a worker thread; ``on_done(result, cancelled)`` runs on the GUI thread.

        Returns False (and logs) if another job is still running.
        """
        if self._thread is not None:
            log.error("%s: wait for %s to finish (or cancel it)", title, self.title)
            return False
        self._cancel = threading.Event()
        self.cancelled = False
        self.title = title
        th = _JobThread(fn, self._cancel, self)
        self._on_done, self._on_error = on_done, on_error
        # Bound methods of this GUI-thread object: the calls are queued onto the GUI thread.
        th.progressed.connect(self._on_progress)
        th.succeeded.connect(self._on_success)
        th.errored.connect(self._on_failure)
        th.finished.connect(self._on_finished)
        self._thread = th
        self.started.emit(title)
        log.info("%s started", title)
        th.start()
        return True

    def _on_progress(self, done: int, total: int) -> None:
        self.progress.emit(done, total)

    def _on_success(self, result: Any) -> None:
        try:
            self._on_done(result, self.cancelled)
        except ValueError as exc:
            log.error("%s: %s", self.title, exc)

    def _on_failure(self, msg: str) -> None:
        log.error("%s failed: %s", self.title, msg)
        if self._on_error is not None:
            self._on_error(msg)

    def cancel(self) -> None:
        """Ask the running job to stop; what is finished so far is kept."""
        if self._thread is not None:
            self.cancelled = True
            self._cancel.set()
            log.warning("%s: cancelling", self.title)

    def wait(self, ms: int = 30000) -> bool:
        """Block until the job's thread ends (used when closing); True if it ended."""
        if self._thread is None:
            return True
        return self._thread.wait(ms)

    def _on_finished(self) -> None:
        th, self._thread = self._thread, None
        title = self.title
        if th is not None:
            th.deleteLater()
        self.finished.emit(title)


class ProgressPanel(QWidget):
    """Progress bar and Cancel button shown under the play controls while a job runs."""

    def __init__(self, runner: JobRunner, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.runner = runner
        lay = QHBoxLayout(self)
        lay.setContentsMargins(4, 0, 4, 2)
        self.label = QLabel()
        self.bar = QProgressBar()
        self.bar.setTextVisible(True)
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setObjectName("cancelJob")
        lay.addWidget(self.label)
        lay.addWidget(self.bar, 1)
        lay.addWidget(self.cancel_button)
        self.cancel_button.clicked.connect(runner.cancel)
        runner.started.connect(self._started)
        runner.progress.connect(self._progress)
        runner.finished.connect(self._finished)
        self.setVisible(False)

    def _started(self, title: str) -> None:
        self.label.setText(title)
        self.bar.setRange(0, 0)   # busy until the first progress report
        self.cancel_button.setEnabled(True)
        self.setVisible(True)

    def _progress(self, done: int, total: int) -> None:
        self.bar.setRange(0, max(total, 1))
        self.bar.setValue(done)
        self.bar.setFormat("%v / %m")

    def _finished(self, _title: str) -> None:
        self.setVisible(False)
