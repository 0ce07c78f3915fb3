"""Small take changes the GUI needs that the operations layer does not provide yet.

Each builds a :class:`~carapost.ops.change.Change` from the existing change types and leaves the
take untouched, exactly like an ``ops`` function; they belong in ``carapost/ops`` and will move
there (the command line needs them too). Nothing here computes anything beyond copying values.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

import numpy as np

from carapost.io.calibration import Calibration
from carapost.model.take import Take
from carapost.ops.change import ArrayPatch, AttributeChange, Change, Composite

__all__ = ["ops", "apply_calibration", "set_rom_path", "rename_label"]


def ops(module: str) -> Any:
    """``carapost.ops.<module>``, imported when an action first runs (operation modules being
    written in parallel cannot break the start of the application)."""
    return importlib.import_module(f"carapost.ops.{module}")


def apply_calibration(take: Take, calib: Calibration) -> Composite:
    """"Import XCP": the calibration's intrinsics and (per-frame) poses replace the take's.

    Raises
    ------
    ValueError
        If the calibration has a different number of cameras.
    """
    if len(calib.cameras) != take.n_cameras:
        raise ValueError(f"{calib.source}: calibration has {len(calib.cameras)} cameras, the take has "
                         f"{take.n_cameras}")
    R, t = calib.poses(take.n_frames)
    changes: list[Change] = [AttributeChange.capture(take, f"cameras.{c}.intrinsics", cam.intrinsics)
                             for c, cam in enumerate(calib.cameras)]
    changes.append(ArrayPatch.capture(take, "R", (slice(None),), np.asarray(R, float)))
    changes.append(ArrayPatch.capture(take, "t", (slice(None),), np.asarray(t, float)))
    return Composite(changes, f"Import XCP {os.path.basename(calib.source)}")


def set_rom_path(take: Take, path: str) -> AttributeChange:
    """"Load ROM": remember the ROM take used by Initialize from ROM."""
    return AttributeChange.capture(take, "rom_path", str(path), f"Load ROM {os.path.basename(path)}")


def rename_label(take: Take, old: str, new: str) -> Composite:
    """Rename a label of the Labelling pane's list (and on the point holding it).

    Raises
    ------
    ValueError
        If ``old`` is not a label, ``new`` is empty, contains white space or already exists.
    """
    new = new.strip()
    if old not in take.labels:
        raise ValueError(f"Rename label: there is no label {old!r}")
    if not new or any(ch.isspace() for ch in new):
        raise ValueError(f"Rename label: {new!r} is not a valid label (no spaces, not empty)")
    if new in take.labels:
        raise ValueError(f"Rename label: {new!r} already exists")
    labels = [new if lab == old else lab for lab in take.labels]
    pts = take.points.copy()
    pts.labels = [new if lab == old else lab for lab in pts.labels]
    return Composite([AttributeChange.capture(take, "labels", labels), AttributeChange.capture(take, "points", pts)],
                     f"Rename label {old} to {new}")
