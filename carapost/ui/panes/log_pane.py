"""Log pane: time, level, category and text of every message of the ``carapost`` logger.

A :class:`QtLogHandler` turns log records (from any thread) into a queued Qt signal; the pane
shows information in the normal text colour, warnings in yellow and errors in red.
"""

from __future__ import annotations

import datetime as _dt
import logging
from collections import deque

from PySide6.QtCore import QObject, Signal
from PySide6.QtGui import QColor
from PySide6.QtWidgets import QAbstractItemView, QHeaderView, QPushButton, QTableWidget, QTableWidgetItem, \
    QVBoxLayout, QWidget

__all__ = ["QtLogHandler", "LogPane", "LEVEL_COLOURS"]

LEVEL_COLOURS = {logging.WARNING: QColor(240, 220, 40), logging.ERROR: QColor(235, 70, 70),
                 logging.CRITICAL: QColor(235, 70, 70)}
LEVEL_NAMES = {logging.DEBUG: "Debug", logging.INFO: "Default", logging.WARNING: "Warn", logging.ERROR: "Error",
               logging.CRITICAL: "Error"}
MAX_ROWS = 5000


class _Emitter(QObject):
    record = Signal(object)


class QtLogHandler(logging.Handler):
    """A logging handler that forwards records as a Qt signal (thread-safe) and keeps the last
    ``MAX_ROWS`` for panes created later."""

    def __init__(self, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.emitter = _Emitter()
        self.records: deque[tuple[str, str, str, str, int]] = deque(maxlen=MAX_ROWS)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
        except Exception:  # noqa: BLE001 - a bad format string must not break logging
            text = str(record.msg)
        when = _dt.datetime.fromtimestamp(record.created).strftime("%Y.%m.%d %H:%M:%S.%f")[:-3]
        cat = record.name.split(".")[-1] if record.name != "carapost" else "Cara"
        row = (when, LEVEL_NAMES.get(record.levelno, record.levelname), cat.capitalize() if cat != "Cara" else cat,
               text, record.levelno)
        self.records.append(row)
        try:
            self.emitter.record.emit(row)
        except RuntimeError:  # the emitter was deleted while the application quits
            pass


class LogPane(QWidget):
    def __init__(self, handler: QtLogHandler, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.handler = handler
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        self.table = QTableWidget(0, 4)
        self.table.setObjectName("logTable")
        self.table.setHorizontalHeaderLabels(["Time", "Level", "Category", "Text"])
        self.table.verticalHeader().setVisible(False)
        self.table.verticalHeader().setDefaultSectionSize(self.fontMetrics().height() + 4)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        hh = self.table.horizontalHeader()
        hh.setSectionResizeMode(3, QHeaderView.ResizeMode.Stretch)
        self.table.setColumnWidth(0, 170)
        self.table.setColumnWidth(1, 60)
        self.table.setColumnWidth(2, 80)
        self.table.setWordWrap(False)
        lay.addWidget(self.table, 1)
        clear = QPushButton("Clear Log")
        clear.clicked.connect(self.clear)
        lay.addWidget(clear)
        for row in list(handler.records):
            self.add(row)
        handler.emitter.record.connect(self.add)

    def add(self, row: tuple[str, str, str, str, int]) -> None:
        if self.table.rowCount() >= MAX_ROWS:
            self.table.removeRow(0)
        r = self.table.rowCount()
        self.table.insertRow(r)
        colour = LEVEL_COLOURS.get(row[4])
        for c, value in enumerate(row[:4]):
            item = QTableWidgetItem(value)
            if colour is not None:
                item.setForeground(colour)
            self.table.setItem(r, c, item)
        self.table.scrollToBottom()

    def clear(self) -> None:
        self.table.setRowCount(0)
        self.handler.records.clear()

    def detach(self) -> None:
        try:
            self.handler.emitter.record.disconnect(self.add)
        except (RuntimeError, TypeError):
            pass
