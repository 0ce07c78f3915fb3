"""Lazy access to the operations modules."""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["ops"]


def ops(module: str) -> Any:
    """``carapost.ops.<module>``, imported when an action first runs (operation modules being
    written in parallel cannot break the start of the application)."""
    return importlib.import_module(f"carapost.ops.{module}")
