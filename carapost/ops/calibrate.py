"""Calibrate Cameras without CaraLive: target images per camera -> an ``.xcp`` calibration."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from carapost.core.calib_targets import TargetSpec
from carapost.core.calibrate import RigCalibration, calibrate_cameras
from carapost.io.calibration import Calibration, CameraCalibration, save_calibration
from carapost.model.take import Take

from .change import ArrayPatch, AttributeChange, Change, Composite

__all__ = ["read_grey", "parse_target", "calibrate_cameras_to_file", "apply_calibration"]


def read_grey(path: str | os.PathLike) -> np.ndarray:
    """An image file as 8-bit grayscale (H, W); a clear error naming the file if unreadable."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"{path}: cannot read the image")
    return img


def parse_target(spec: str) -> TargetSpec:
    """``"checkerboard:4x7:60"`` (kind : inner corners or dots cols x rows : spacing in mm)."""
    try:
        kind, size, spacing = spec.split(":")
        cols, rows = (int(v) for v in size.lower().split("x"))
        return TargetSpec(kind, cols, rows, float(spacing))
    except ValueError as exc:
        raise ValueError(f"target must look like checkerboard:4x7:60 (kind:COLSxROWS:spacing_mm), got {spec!r}: "
                         f"{exc}") from None


def calibrate_cameras_to_file(image_sets: Sequence[Sequence[str | os.PathLike]], spec: TargetSpec,
                              output: str | os.PathLike, *, names: Sequence[str] | None = None,
                              extrinsics: bool = True,
                              progress: Callable[[int, int], None] | None = None) -> tuple[Calibration, RigCalibration]:
    """Calibrate every camera from its target images and write the result (``.xcp`` or ``.toml``).

    ``image_sets[c]`` are camera ``c``'s images; for extrinsics, image ``k`` of every camera must show
    the target at the same moment (synchronised shots).
    """
    if not image_sets or any(len(s) == 0 for s in image_sets):
        raise ValueError("every camera needs at least one target image")
    rig = calibrate_cameras([[str(p) for p in s] for s in image_sets], spec, load_image=read_grey,
                            names=list(names) if names else [Path(s[0]).parent.name or f"cam{c}"
                                                             for c, s in enumerate(image_sets)],
                            extrinsics=extrinsics, progress=progress)
    calib = Calibration([CameraCalibration(**r) for r in rig.camera_records()], source=str(output), format="xcp")
    save_calibration(output, calib)
    return calib, rig


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
