"""Log verbosity for scripts (the reference guide's PyDebugServices).

Everything CaraPost logs goes to the standard :mod:`logging` logger ``"carapost"`` (and its
children, e.g. ``"carapost.io.pico"``). :func:`set_log_verbosity` sets that logger's level and,
when logging has not been configured (the root logger has no handler), attaches one handler
printing ``LEVEL carapost: message`` to standard error, so a script sees the messages without
configuring :mod:`logging` itself. An application that configures logging its own way keeps
its handlers: only the ``"carapost"`` logger's level is touched.

Examples
--------
>>> import carapost.api as cp
>>> cp.set_log_verbosity("warning")   # hide information messages, show warnings and errors
>>> cp.get_log_verbosity()
'warning'
>>> cp.set_log_verbosity("off")       # show nothing
"""

from __future__ import annotations

import logging
import sys

__all__ = ["LOG_LEVELS", "set_log_verbosity", "get_log_verbosity"]

#: Verbosity names and their :mod:`logging` levels (``"off"`` hides everything).
LOG_LEVELS: dict[str, int] = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING,
                              "error": logging.ERROR, "critical": logging.CRITICAL, "off": logging.CRITICAL + 10}

_LOGGER = "carapost"
_MARK = "_carapost_api_handler"


def set_log_verbosity(level: str | int) -> None:
    """Show log messages of ``level`` and above; hide the others.

    Parameters
    ----------
    level : {"debug", "info", "warning", "error", "critical", "off"} or int
        A name (case-insensitive) or a :mod:`logging` level number.

    Raises
    ------
    ValueError
        Unknown level name, or a negative number.
    """
    if isinstance(level, str):
        key = level.strip().lower()
        if key not in LOG_LEVELS:
            raise ValueError(f"unknown log verbosity {level!r}; choose from {', '.join(LOG_LEVELS)}")
        value = LOG_LEVELS[key]
    elif isinstance(level, int) and not isinstance(level, bool) and level >= 0:
        value = level
    else:
        raise ValueError(f"log verbosity must be a level name or a logging level number >= 0, got {level!r}")
    logger = logging.getLogger(_LOGGER)
    logger.setLevel(value)
    if not logging.getLogger().handlers and not any(getattr(h, _MARK, False) for h in logger.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(levelname)s carapost: %(message)s"))
        setattr(handler, _MARK, True)
        logger.addHandler(handler)


def get_log_verbosity() -> str:
    """The current verbosity name (the nearest name at or below the ``"carapost"`` logger's
    effective level)."""
    value = logging.getLogger(_LOGGER).getEffectiveLevel()
    best = "debug"
    for name, lv in sorted(LOG_LEVELS.items(), key=lambda kv: kv[1]):
        if lv <= value:
            best = name
    return best
