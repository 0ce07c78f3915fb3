"""Lazy access to the operations modules, and the one GUI-only change left (Load ROM's path)."""

from __future__ import annotations

import importlib
import os
from typing import Any

from carapost.model.take import Take
from carapost.ops.change import AttributeChange

__all__ = ["ops", "set_rom_path"]


def ops(module: str) -> Any:
    """``carapost.ops.<module>``, imported when an action first runs (operation modules being
    written in parallel cannot break the start of the application)."""
    return importlib.import_module(f"carapost.ops.{module}")


def set_rom_path(take: Take, path: str) -> AttributeChange:
    """"Load ROM": remember the ROM take used by Initialize from ROM."""
    return AttributeChange.capture(take, "rom_path", str(path), f"Load ROM {os.path.basename(path)}")


