"""Marker-set template files (``.json``): names, neutral positions, sticks.

Schema (version 1)::

    {
      "format": "carapost-marker-template",
      "version": 1,
      "units": "mm",
      "source": "ROM_take.cara frame 120",
      "names": ["Brow_L_1", ...],
      "xyz": [[x, y, z] or null, ...],      one per name; null = unknown position
      "sticks": [[i, j], ...]                indices into names
    }

A reader accepts any version 1 file and rejects newer versions with a message. Writes are
atomic (temporary file in the same folder, then rename).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from carapost.core.template import MarkerTemplate

from .atomic import atomic_write_bytes

__all__ = ["TemplateFileError", "read_marker_template", "write_marker_template", "FORMAT", "VERSION"]

FORMAT = "carapost-marker-template"
VERSION = 1


class TemplateFileError(ValueError):
    """A template file that cannot be read or written; the message names the file."""


def read_marker_template(path: str | os.PathLike) -> MarkerTemplate:
    """Read a marker-set template.

    Raises
    ------
    TemplateFileError
        Unreadable or not JSON, wrong format name, newer version, inconsistent content.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise TemplateFileError(f"{path}: cannot read the marker template ({e})") from e
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise TemplateFileError(f"{path}: not a CaraPost marker template (format {FORMAT!r} expected)")
    ver = doc.get("version")
    if not isinstance(ver, int) or ver < 1:
        raise TemplateFileError(f"{path}: bad template version {ver!r}")
    if ver > VERSION:
        raise TemplateFileError(f"{path}: template version {ver} is newer than this CaraPost reads ({VERSION})")
    if doc.get("units", "mm") != "mm":
        raise TemplateFileError(f"{path}: template units must be 'mm', got {doc.get('units')!r}")
    names = doc.get("names")
    xyz = doc.get("xyz")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise TemplateFileError(f"{path}: 'names' must be a non-empty list of strings")
    if not isinstance(xyz, list) or len(xyz) != len(names):
        raise TemplateFileError(f"{path}: 'xyz' must hold one position (or null) per name")
    try:
        pos = np.array([[np.nan] * 3 if p is None else [float(v) for v in p] for p in xyz], np.float64)
    except (TypeError, ValueError) as e:
        raise TemplateFileError(f"{path}: a position is not three numbers ({e})") from e
    if pos.shape != (len(names), 3):
        raise TemplateFileError(f"{path}: positions must be [x, y, z] triples")
    try:
        sticks = np.array(doc.get("sticks", []), np.int64).reshape(-1, 2)
        return MarkerTemplate(names, pos, sticks, str(doc.get("source", "")))
    except ValueError as e:
        raise TemplateFileError(f"{path}: {e}") from e


def write_marker_template(template: MarkerTemplate, path: str | os.PathLike) -> None:
    """Write a marker-set template, atomically.

    Raises
    ------
    TemplateFileError
        The folder does not exist or cannot be written.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise TemplateFileError(f"{path}: cannot write, the folder {path.parent} does not exist")
    doc = {"format": FORMAT, "version": VERSION, "units": "mm", "source": template.source,
           "names": list(template.names),
           "xyz": [None if not np.isfinite(p).all() else [round(float(v), 6) for v in p] for p in template.xyz],
           "sticks": [[int(a), int(b)] for a, b in template.sticks]}
    data = json.dumps(doc, indent=1).encode("utf-8")
    try:
        atomic_write_bytes(path, data)
    except OSError as e:
        raise TemplateFileError(f"{path}: cannot write ({e})") from e
