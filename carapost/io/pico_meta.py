"""Capture metadata of a ``.pico`` file (and of any camera source): :class:`PicoMetadata`."""

from __future__ import annotations

import copy
import json
import math
import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PICO_VERSION", "PicoMetadata", "meta_to_json", "meta_from_json"]

PICO_VERSION = (1, 0)
_TIMECODE = re.compile(r"^\d{2}:[0-5]\d:[0-5]\d[:;]\d{2}$")


@dataclass
class PicoMetadata:
    """Capture metadata of one camera's recording (names from the reference guide).

    Attributes
    ----------
    logger_name, logger_description, logger_id : str
        Name, description and unique id of the logger at capture time.
    camera_name : str
        Name of the camera (sensor).
    channel : int
        0-based camera channel (the number after the last ``_`` of the file name).
    frame_rate : float
        Frames per second, > 0.
    start_timecode : str
        SMPTE timecode of frame 0, ``"HH:MM:SS:FF"`` (``;`` before the frames for drop-frame).
    width, height : int
        Image size in pixels (0 = not yet known; the writer fills it from the first frame).
    rotation : int
        Display rotation in degrees clockwise, one of 0, 90, 180, 270.
    blob_parameters : dict
        The Blob Parameters section at capture (``BlobParameters.to_dict()``).
    extra : dict
        Free JSON-serialisable keys (also keeps unknown keys written by newer versions).
    format_version : str
        ``"major.minor"`` of the container that holds this metadata.
    """

    logger_name: str = ""
    logger_description: str = ""
    logger_id: str = ""
    camera_name: str = ""
    channel: int = 0
    frame_rate: float = 60.0
    start_timecode: str = "00:00:00:00"
    width: int = 0
    height: int = 0
    rotation: int = 0
    blob_parameters: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    format_version: str = f"{PICO_VERSION[0]}.{PICO_VERSION[1]}"

    def __post_init__(self) -> None:
        for name in ("logger_name", "logger_description", "logger_id", "camera_name",
                     "start_timecode", "format_version"):
            if not isinstance(getattr(self, name), str):
                raise ValueError(f"PicoMetadata.{name} must be text, got {getattr(self, name)!r}")
        for name in ("channel", "width", "height", "rotation"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise ValueError(f"PicoMetadata.{name} must be a whole number >= 0, got {v!r}")
            setattr(self, name, int(v))
        if self.rotation not in (0, 90, 180, 270):
            raise ValueError(f"PicoMetadata.rotation must be 0, 90, 180 or 270, got {self.rotation!r}")
        try:
            rate = float(self.frame_rate)
        except (TypeError, ValueError):
            raise ValueError(f"PicoMetadata.frame_rate must be a number, got {self.frame_rate!r}") from None
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"PicoMetadata.frame_rate must be > 0, got {self.frame_rate!r}")
        self.frame_rate = rate
        if not _TIMECODE.match(self.start_timecode):
            raise ValueError(f"PicoMetadata.start_timecode must be SMPTE 'HH:MM:SS:FF', "
                             f"got {self.start_timecode!r}")
        for name in ("blob_parameters", "extra"):
            if not isinstance(getattr(self, name), dict):
                raise ValueError(f"PicoMetadata.{name} must be a dict, got {getattr(self, name)!r}")

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready deep copy."""
        return copy.deepcopy(asdict(self))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "PicoMetadata":
        """Build from :meth:`to_dict` output; unknown keys are kept in ``extra``."""
        known = {f.name for f in fields(cls)}
        kw = {k: copy.deepcopy(v) for k, v in d.items() if k in known}
        unknown = {k: copy.deepcopy(v) for k, v in d.items() if k not in known}
        if unknown:
            kw["extra"] = {**unknown, **kw.get("extra", {})}
        return cls(**kw)

    def copy(self) -> "PicoMetadata":
        return PicoMetadata.from_dict(self.to_dict())


def meta_to_json(path: Path, meta: PicoMetadata, codec: str, quality: int) -> bytes:
    """The UTF-8 JSON document stored in a pico header and footer (``path`` names errors)."""
    doc = {"format": "carapost-pico", "codec": codec, "quality": quality, "metadata": meta.to_dict()}
    try:
        return json.dumps(doc, ensure_ascii=False, allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: metadata is not JSON-serialisable: {exc}") from None


def meta_from_json(raw: bytes) -> tuple[PicoMetadata, dict[str, Any]]:
    """Parse :func:`meta_to_json` output: (metadata, whole document). ValueError if invalid."""
    doc = json.loads(raw.decode("utf-8"))
    if not isinstance(doc, dict) or not isinstance(doc.get("metadata"), dict):
        raise ValueError("metadata JSON has no 'metadata' object")
    return PicoMetadata.from_dict(doc["metadata"]), doc
