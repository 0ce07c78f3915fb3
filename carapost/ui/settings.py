"""Persistent GUI settings (``QSettings``): window layout, recent files, preferences.

Settings are versioned (``SETTINGS_VERSION``): a newer major layout is ignored rather than
misread. Tests isolate them with ``QStandardPaths.setTestModeEnabled(True)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from PySide6.QtCore import QByteArray, QSettings

__all__ = ["ORG", "APP", "SETTINGS_VERSION", "MAX_RECENT", "Settings"]

ORG = "CaraPost"
APP = "CaraPost for Python"
SETTINGS_VERSION = 1
MAX_RECENT = 8


class Settings:
    """Typed access to the application's ``QSettings``."""

    def __init__(self) -> None:
        self.q = QSettings(ORG, APP)
        if int(self.q.value("version", SETTINGS_VERSION)) > SETTINGS_VERSION:
            self.q = QSettings(ORG, f"{APP} v{SETTINGS_VERSION}")  # do not misread a newer layout
        self.q.setValue("version", SETTINGS_VERSION)

    # -- recent files ---------------------------------------------------------------------
    def recent_files(self) -> list[str]:
        v = self.q.value("recent/files", [])
        if isinstance(v, str):
            v = [v]
        return [str(x) for x in (v or [])][:MAX_RECENT]

    def add_recent(self, path: str | Path) -> list[str]:
        p = str(Path(path).resolve())
        files = [p] + [f for f in self.recent_files() if f != p]
        files = files[:MAX_RECENT]
        self.q.setValue("recent/files", files)
        return files

    def clear_recent(self) -> None:
        self.q.setValue("recent/files", [])

    # -- window ---------------------------------------------------------------------------
    def window_state(self) -> tuple[QByteArray | None, QByteArray | None]:
        geo, state = self.q.value("window/geometry"), self.q.value("window/state")
        return (geo if isinstance(geo, QByteArray) else None, state if isinstance(state, QByteArray) else None)

    def save_window_state(self, geometry: QByteArray, state: QByteArray) -> None:
        self.q.setValue("window/geometry", geometry)
        self.q.setValue("window/state", state)

    # -- preferences ----------------------------------------------------------------------
    def get(self, key: str, default: Any) -> Any:
        v = self.q.value(f"prefs/{key}", default)
        if isinstance(default, bool):
            return v in (True, "true", "1", 1)
        if isinstance(default, int):
            try:
                return int(v)
            except (TypeError, ValueError):
                return default
        if isinstance(default, list):
            return list(v) if isinstance(v, (list, tuple)) else ([v] if v else [])
        return v

    def set(self, key: str, value: Any) -> None:
        self.q.setValue(f"prefs/{key}", value)

    def sync(self) -> None:
        self.q.sync()
