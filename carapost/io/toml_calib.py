"""OpenCV-style calibration TOML (aniposelib, Pose2Sim): read and write.

Layout (aniposelib ``CameraGroup.dump`` and Pose2Sim ``Calib_*.toml``)::

    [cam_0]                       # any table holding a "matrix" is a camera, in file order
    name = "A"
    size = [ 1920, 1080,]         # width, height (Pose2Sim writes floats)
    matrix = [ [ fx, 0.0, cx,], [ 0.0, fy, cy,], [ 0.0, 0.0, 1.0,],]
    distortions = [ k1, k2, p1, p2, k3,]   # OpenCV, normalised coordinates (4, 5 or 8 values)
    rotation = [ rx, ry, rz,]     # Rodrigues vector, world -> camera (a 3x3 matrix is accepted)
    translation = [ tx, ty, tz,]  # X_cam = R X + t, in the file's length unit
    fisheye = false               # optional; true: 4 OpenCV fisheye coefficients

    [metadata]                    # optional, kept as is
    adjusted = false
    error = 0.17

Units: aniposelib writes whatever unit the board was measured in (often mm); Pose2Sim writes
metres. ``units="auto"`` (default) takes metres when every camera centre lies within 20 units
of the origin (no stage is 20 m across, no camera rig fits in 2 cm) and millimetres otherwise;
pass ``units="mm"``, ``"cm"`` or ``"m"`` to decide. The unit used is kept in
``extra["toml_units"]`` and used again when writing.

Distortion: our model is the XCP radial correction, so the OpenCV coefficients are converted
by a least-squares fit over the image (:func:`carapost.core.lens_models.fit_radial_correction`;
the residual is in ``CameraCalibration.extra["distortion_fit"]``). Writing gives ``K``, ``R``
and ``t`` exactly, and the original coefficients when the camera's intrinsics are still those
that were read; otherwise OpenCV ``k1, k2, k3`` fitted to our correction
(:func:`carapost.core.lens_models.fit_brown_distortion`, approximate; ``p1 = p2 = 0``).

Section names written are ``cam_0``, ``cam_1``, ... zero-padded so that a lexical sort (which
aniposelib applies) keeps the camera order; sections read from a TOML keep their names.
"""

from __future__ import annotations

import json
import math
import os
import re
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from carapost.core.camera import Intrinsics, matrix_to_quat, rodrigues
from carapost.core.lens_models import (
    brown_undistort,
    fisheye_undistort,
    fit_brown_distortion,
    fit_radial_correction,
)
from carapost.io.calibration import (
    Calibration,
    CalibrationError,
    CameraCalibration,
    atomic_write_bytes,
    read_bytes,
)

__all__ = ["read_toml", "parse_toml", "write_toml", "toml_text", "rotation_vector", "UNITS_MM"]

#: Millimetres per unit.
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}

#: ``units="auto"``: camera centres all closer than this to the origin means metres.
AUTO_METRES_BELOW = 20.0

_KNOWN = ("name", "size", "matrix", "distortions", "rotation", "translation", "fisheye")


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rodrigues (axis-angle) vectors ``(..., 3)`` of rotation matrices ``(..., 3, 3)``."""
    q = matrix_to_quat(np.asarray(R, dtype=float))
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:4])
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0)
    return v * factor


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


def _array(fname: str, where: str, d: dict[str, Any], key: str, shape: tuple[int, ...] | None,
           *, allowed: tuple[tuple[int, ...], ...] = ()) -> np.ndarray:
    if key not in d:
        raise CalibrationError(f"{fname}: {where}{key} is missing")
    try:
        a = np.array(d[key], dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{fname}: {where}{key} must be numbers, got {d[key]!r}") from None
    ok = (a.shape == shape) if shape is not None else False
    ok = ok or a.shape in allowed
    if not ok:
        want = " or ".join(str(s) for s in ((shape,) if shape else ()) + allowed)
        raise CalibrationError(f"{fname}: {where}{key} must have shape {want}, got {a.shape}")
    if not np.isfinite(a).all():
        raise CalibrationError(f"{fname}: {where}{key} must be finite, got {d[key]!r}")
    return a


def _read_camera(fname: str, index: int, key: str, d: dict[str, Any], fit_centre: bool) -> CameraCalibration:
    name = str(d.get("name", key))
    where = f"camera {index} ({name}): "
    K = _array(fname, where, d, "matrix", (3, 3))
    if abs(K[1, 0]) > 1e-9 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{fname}: {where}matrix is not a camera matrix "
                               "[[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    fisheye = bool(d.get("fisheye", False))
    dist = _array(fname, where, d, "distortions", None, allowed=((4,),) if fisheye else
                  ((0,), (4,), (5,), (8,))) if "distortions" in d else np.zeros(0)
    rot = _array(fname, where, d, "rotation", (3,), allowed=((3, 3),))
    if rot.shape == (3, 3):
        R = rot
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
            raise CalibrationError(f"{fname}: {where}rotation is a 3x3 matrix but not a rotation")
    else:
        R = rodrigues(rot)
    t = _array(fname, where, d, "translation", (3,))
    size_note = ""
    if "size" in d:
        size = _array(fname, where, d, "size", (2,))
        if (size <= 0).any():
            raise CalibrationError(f"{fname}: {where}size must be positive, got {d['size']!r}")
        wh = (int(round(size[0])), int(round(size[1])))
    else:  # only needed for the distortion fit: assume a centred principal point
        wh = (int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1)))
        size_note = "size missing: estimated as 2 * principal point + 1"
    linear = Intrinsics(focal_length=float(K[0, 0]), principal_point=(float(K[0, 2]), float(K[1, 2])),
                        sensor_size=wh, aspect=float(K[0, 0] / K[1, 1]), skew=float(K[0, 1]))
    extra: dict[str, Any] = {"toml_section": key,
                             "toml_other": {k: v for k, v in d.items() if k not in _KNOWN}}
    coeffs = [float(c) for c in dist]
    if any(c != 0.0 for c in coeffs):
        if fisheye:
            undist = (lambda xy: fisheye_undistort(xy, coeffs))
            tangential = False
        else:
            undist = (lambda xy: brown_undistort(xy, coeffs))
            tangential = len(coeffs) >= 4 and (coeffs[2] != 0.0 or coeffs[3] != 0.0)
        try:
            intr, report = fit_radial_correction(linear, undist, fit_centre=fit_centre and tangential)
        except ValueError as e:
            raise CalibrationError(f"{fname}: {where}{e}") from None
        extra["distortion_fit"] = {**report, "from": "opencv fisheye" if fisheye else "opencv"}
        if size_note:
            extra["distortion_fit"]["note"] = size_note
    else:
        intr = linear
    if size_note:
        intr = intr.with_(sensor_size=(0, 0))
    extra["opencv_distortion"] = {"coefficients": coeffs, "fisheye": fisheye, "intrinsics": intr}
    return CameraCalibration(name=name, device_id="", user_id="", intrinsics=intr, frames=np.array([0]),
                             R=R[None], t=t[None], extra=extra)


def parse_toml(text: str | bytes, *, source: str = "<string>", units: str = "auto",
               fit_centre: bool = True) -> Calibration:
    """Parse an OpenCV-style calibration TOML.

    Parameters
    ----------
    text : str or bytes
    source : str
        File name or path for messages and ``Calibration.source``.
    units : {"auto", "mm", "cm", "m"}
        Length unit of ``translation`` (see the module docstring for ``"auto"``).
    fit_centre : bool
        When a camera has tangential terms, also fit the radial correction's own centre.

    Returns
    -------
    Calibration
        ``format == "toml"``; translations converted to mm; cameras in file order.

    Raises
    ------
    CalibrationError
        Invalid TOML, no camera table, a missing or malformed key, or an unknown unit.
    """
    fname = Path(source).name
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise CalibrationError(f"{fname}: not a UTF-8 text file") from None
    if units != "auto" and units not in UNITS_MM:
        raise CalibrationError(f"{fname}: unknown units {units!r} (use 'auto', 'mm', 'cm' or 'm')")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise CalibrationError(f"{fname}: not a valid TOML file ({e})") from None
    cams: list[CameraCalibration] = []
    other: dict[str, Any] = {}
    for key, val in doc.items():
        if isinstance(val, dict) and "matrix" in val:
            cams.append(_read_camera(fname, len(cams), key, val, fit_centre))
        else:
            other[key] = val
    if not cams:
        raise CalibrationError(f"{fname}: no camera table (a table with a 'matrix' key) in the file")
    detected = units == "auto"
    if detected:
        reach = max(float(np.linalg.norm(c.centres[0])) for c in cams)
        units = "m" if 0.0 < reach < AUTO_METRES_BELOW else "mm"
    scale = UNITS_MM[units]
    for c in cams:
        c.t = c.t * scale
    extra = {"toml_units": units, "toml_units_detected": detected, "toml_other": other}
    return Calibration(cameras=cams, source=str(source), format="toml", extra=extra)


def read_toml(path: str | os.PathLike, *, units: str = "auto", fit_centre: bool = True) -> Calibration:
    """Read a calibration ``.toml`` file (see :func:`parse_toml`)."""
    return parse_toml(read_bytes(path), source=str(path), units=units, fit_centre=fit_centre)


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k, ensure_ascii=False)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        x = float(v)
        if math.isnan(x):
            return "nan"
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return repr(x)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, np.ndarray):
        return _value(v.tolist())
    if isinstance(v, (list, tuple)):
        return "[ " + ", ".join(_value(x) for x in v) + ",]" if v else "[]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    if hasattr(v, "isoformat"):
        return v.isoformat()
    raise CalibrationError(f"cannot write a value of type {type(v).__name__} to TOML")


def _section_names(calib: Calibration) -> list[str]:
    n = len(calib.cameras)
    width = len(str(n - 1))
    names = [f"cam_{i:0{width}d}" for i in range(n)]
    if calib.format == "toml":
        kept = [c.extra.get("toml_section") for c in calib.cameras]
        if all(isinstance(k, str) for k in kept) and len(set(kept)) == n:
            names = [str(k) for k in kept]
    return names


def toml_text(calib: Calibration, *, units: str | None = None, frame: int | None = None,
              rational: bool = False) -> tuple[str, list[dict[str, Any]]]:
    """The TOML text for ``calib`` and, per camera, how its distortion was written.

    Parameters
    ----------
    calib : Calibration
    units : {"mm", "cm", "m"} or None
        Unit of ``translation``. ``None``: the unit the calibration was read in if it came
        from a TOML, else metres (Pose2Sim's convention; aniposelib does not mind).
    frame : int or None
        Frame whose pose is written for moving cameras (TOML holds one pose per camera).
    rational : bool
        Fit 8 OpenCV coefficients (rational model) instead of 5 where the distortion has to
        be fitted (see :func:`carapost.core.lens_models.fit_brown_distortion`).

    Returns
    -------
    text : str
    report : list of dict
        Per camera: ``distortion`` ``"original"`` (coefficients as read) or ``"fitted"``
        with the fit report of :func:`carapost.core.lens_models.fit_brown_distortion`.

    Raises
    ------
    CalibrationError
        Unknown unit, or a camera with several keyframes and no ``frame``.
    """
    if units is None:
        units = calib.extra.get("toml_units", "m") if calib.format == "toml" else "m"
    if units not in UNITS_MM:
        raise CalibrationError(f"unknown units {units!r} (use 'mm', 'cm' or 'm')")
    if not calib.cameras:
        raise CalibrationError("cannot write a calibration without cameras")
    scale = UNITS_MM[units]
    lines: list[str] = []
    report: list[dict[str, Any]] = []
    other = calib.extra.get("toml_other", {}) if calib.format == "toml" else {}
    for k, v in other.items():  # top-level plain values must come before any table
        if not isinstance(v, dict):
            lines.append(f"{_key(k)} = {_value(v)}")
    if lines:
        lines.append("")
    for section, cam in zip(_section_names(calib), calib.cameras):
        if cam.n_keyframes > 1 and frame is None:
            raise CalibrationError(f"camera {cam.label} moves ({cam.n_keyframes} keyframes): a TOML "
                                   "calibration holds one pose per camera; pass frame=")
        k = int(cam.keyframe_index(frame if frame is not None else 0))
        intr = cam.intrinsics_at(k)
        od = cam.extra.get("opencv_distortion")
        if od is not None and od.get("intrinsics") == intr:
            coeffs, fisheye = list(od["coefficients"]), bool(od.get("fisheye", False))
            report.append({"distortion": "original"})
        else:
            c5, rep = fit_brown_distortion(intr, rational=rational)
            coeffs, fisheye = [float(c) for c in c5], False
            report.append({"distortion": "fitted", **rep})
        Kmat = intr.K
        w, h = intr.sensor_size
        lines.append(f"[{_key(section)}]")
        lines.append(f"name = {_value(cam.name or cam.label)}")
        lines.append(f"size = {_value([int(w), int(h)])}")
        lines.append(f"matrix = {_value(Kmat.tolist())}")
        lines.append(f"distortions = {_value(coeffs)}")
        lines.append(f"rotation = {_value(rotation_vector(cam.R[k]).tolist())}")
        lines.append(f"translation = {_value((cam.t[k] / scale).tolist())}")
        lines.append(f"fisheye = {_value(fisheye)}")
        extra_keys = cam.extra.get("toml_other", {}) if calib.format == "toml" else {}
        for key, v in extra_keys.items():
            lines.append(f"{_key(key)} = {_value(v)}")
        lines.append("")
    for key, v in other.items():
        if isinstance(v, dict):
            lines.append(f"[{_key(key)}]")
            lines.extend(f"{_key(a)} = {_value(x)}" for a, x in v.items())
            lines.append("")
    return "\n".join(lines), report


def write_toml(path: str | os.PathLike, calib: Calibration, *, units: str | None = None,
               frame: int | None = None, rational: bool = False) -> list[dict[str, Any]]:
    """Write ``calib`` as a calibration TOML, atomically (see :func:`toml_text`).

    Returns
    -------
    list of dict
        Per camera, how the distortion was written (``"original"`` or ``"fitted"`` with its
        ``max_residual_px``).
    """
    try:
        text, report = toml_text(calib, units=units, frame=frame, rational=rational)
    except CalibrationError as e:
        raise CalibrationError(f"{Path(path).name}: {e}") from None
    atomic_write_bytes(path, text.encode("utf-8"))
    return report
