"""Qualisys ``.qca`` / ``.qca.txt`` camera calibrations (XML): read.

Layout (one ``<camera>`` per device under ``<calibration><cameras>``)::

    <camera active="1" serial="cam01" model="..." avg-residual="0.40" viewrotation="0">
      <fov_video left="0" top="0" right="1087" bottom="1919"/>
      <transform x="..." y="..." z="..." r11="..." ... r33="..."/>
      <intrinsic focalLengthU="..." focalLengthV="..." centerPointU="..." centerPointV="..."
                 skew="..." radialDistortion1..3="..." tangentalDistortion1..2="..."
                 sensorMinU/MaxU/MinV/MaxV="..." focallength="(mm)"/>
    </camera>

Conventions, established on the real Pose2Sim demo file (``docs/camera-model.md``):

* **Intrinsics** are in sensor *sub-pixels* (1/64 pixel): ``f = focalLengthU / 64``,
  principal point ``centerPointU / 64 - fov_video.left`` (likewise V with ``top``), all divided
  by the ``binning`` factor. The image is ``right - left + 1`` by ``bottom - top + 1`` pixels.
  ``PIXEL_ASPECT_RATIO = focalLengthU / focalLengthV``.
* **Distortion** ``radialDistortion1..3`` / ``tangentalDistortion1..2`` are OpenCV/Brown
  coefficients on *normalised* coordinates (not scaled by 64: a checkerboard fit on the demo's
  intrinsic images with the file's K gives ``k1 = -0.03..-0.07, k2 = 0.05..0.24`` against the
  file's ``-0.047, 0.137``). They are converted to the XCP radial correction by least squares
  (:func:`carapost.core.lens_models.fit_radial_correction`); the tangential terms cannot be
  represented as such: they are dropped, and by default the correction's own centre is fitted
  as well, which absorbs most of their effect. The fit's largest residual over the image is in
  ``extra["distortion_fit"]["max_residual_px"]``; the original coefficients are in
  ``extra["opencv_distortion"]``.
* **Pose**: the ``transform`` matrix ``M = [[r11 r12 r13], [r21 ...], ...]`` rotates world to
  the Qualisys camera frame, whose camera looks along ``-z`` with ``y`` up; ``x, y, z`` is the
  camera centre in mm. Hence ``R = diag(1, -1, -1) @ M`` and ``t = -R @ (x, y, z)``.
* ``avg-residual`` (mm) becomes ``world_error``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from lxml import etree

from carapost.core.camera import Intrinsics
from carapost.core.lens_models import brown_undistort, fit_radial_correction
from carapost.io.calibration import Calibration, CalibrationError, CameraCalibration, read_bytes

__all__ = ["read_qca", "parse_qca", "QUALISYS_TO_CAMERA"]

#: Qualisys camera frame (looks along -z, y up) to our camera frame (+z forward, y down).
QUALISYS_TO_CAMERA = np.diag([1.0, -1.0, -1.0])

_SUBPIXEL = 64.0


def _attr(fname: str, where: str, el: Any, name: str, default: float | None = None,
          alt: tuple[str, ...] = ()) -> float:
    raw = el.get(name)
    for a in alt:
        if raw is None:
            raw = el.get(a)
    if raw is None:
        if default is not None:
            return default
        raise CalibrationError(f"{fname}: {where}<{el.tag}> {name} is missing")
    try:
        v = float(raw)
    except ValueError:
        raise CalibrationError(f'{fname}: {where}<{el.tag}> {name} must be a number, got "{raw}"') from None
    if not np.isfinite(v):
        raise CalibrationError(f'{fname}: {where}<{el.tag}> {name} must be finite, got "{raw}"')
    return v


def _read_camera(fname: str, index: int, cam: Any, binning: float, fit_centre: bool) -> CameraCalibration:
    serial = cam.get("serial", "")
    where = f"camera {index} ({serial or 'unnamed'}): "
    fov = cam.find("fov_video")
    if fov is None:
        fov = cam.find("fov_marker")
    intr_el = cam.find("intrinsic")
    tr = cam.find("transform")
    for el, tag in ((intr_el, "intrinsic"), (tr, "transform")):
        if el is None:
            raise CalibrationError(f"{fname}: {where}has no <{tag}> element")
    assert intr_el is not None and tr is not None
    if fov is not None:
        left, top = _attr(fname, where, fov, "left", 0.0), _attr(fname, where, fov, "top", 0.0)
        right, bottom = _attr(fname, where, fov, "right"), _attr(fname, where, fov, "bottom")
    else:  # no field of view: the whole sensor
        left = top = 0.0
        right = _attr(fname, where, intr_el, "sensorMaxU") / _SUBPIXEL
        bottom = _attr(fname, where, intr_el, "sensorMaxV") / _SUBPIXEL
    width = int(round((right - left + 1) / binning))
    height = int(round((bottom - top + 1) / binning))
    if width <= 0 or height <= 0:
        raise CalibrationError(f"{fname}: {where}empty field of view "
                               f"(left {left:g}, top {top:g}, right {right:g}, bottom {bottom:g})")
    fu = _attr(fname, where, intr_el, "focalLengthU") / _SUBPIXEL / binning
    fv = _attr(fname, where, intr_el, "focalLengthV") / _SUBPIXEL / binning
    if fu <= 0 or fv <= 0:
        raise CalibrationError(f"{fname}: {where}<intrinsic> focal lengths must be positive")
    cu = (_attr(fname, where, intr_el, "centerPointU") / _SUBPIXEL - left) / binning
    cv = (_attr(fname, where, intr_el, "centerPointV") / _SUBPIXEL - top) / binning
    skew = _attr(fname, where, intr_el, "skew", 0.0) / _SUBPIXEL / binning
    k = [_attr(fname, where, intr_el, f"radialDistortion{i}", 0.0) for i in (1, 2, 3)]
    p = [_attr(fname, where, intr_el, f"tangentalDistortion{i}", 0.0, alt=(f"tangentialDistortion{i}",))
         for i in (1, 2)]
    coeffs = [k[0], k[1], p[0], p[1], k[2]]
    linear = Intrinsics(focal_length=fu, principal_point=(cu, cv), sensor_size=(width, height),
                        aspect=fu / fv, skew=skew)
    extra: dict[str, Any] = {
        "qca_attrib": dict(cam.attrib),
        "qca_elements": {child.tag: dict(child.attrib) for child in cam},
        "opencv_distortion": {"coefficients": coeffs, "fisheye": False},
    }
    if any(c != 0.0 for c in coeffs):
        try:
            intr, report = fit_radial_correction(linear, lambda xy: brown_undistort(xy, coeffs),
                                                 fit_centre=fit_centre and any(v != 0.0 for v in p))
        except ValueError as e:
            raise CalibrationError(f"{fname}: {where}{e}") from None
        extra["distortion_fit"] = {**report, "from": "qualisys radial k1 k2 k3",
                                   "dropped_tangential": p}
    else:
        intr = linear
    extra["opencv_distortion"]["intrinsics"] = intr
    M = np.array([[_attr(fname, where, tr, f"r{i}{j}") for j in (1, 2, 3)] for i in (1, 2, 3)])
    if np.abs(M @ M.T - np.eye(3)).max() > 1e-5 or np.linalg.det(M) <= 0:
        raise CalibrationError(f"{fname}: {where}<transform> r11..r33 is not a rotation matrix")
    centre = np.array([_attr(fname, where, tr, a) for a in ("x", "y", "z")])
    R = QUALISYS_TO_CAMERA @ M
    t = -R @ centre
    res = cam.get("avg-residual")
    try:
        world_error = float(res) if res is not None else np.nan
    except ValueError:
        world_error = np.nan
    return CameraCalibration(name=serial, device_id=serial, user_id="", intrinsics=intr,
                             frames=np.array([0]), R=R[None], t=t[None],
                             image_error=np.array([np.nan]), world_error=np.array([world_error]),
                             extra=extra)


def parse_qca(data: bytes | str, *, source: str = "<string>", binning: float = 1,
              fit_centre: bool = True) -> Calibration:
    """Parse Qualisys calibration XML.

    Parameters
    ----------
    data : bytes or str
    source : str
        File name or path for messages and ``Calibration.source``.
    binning : float
        Video binning factor (2 when a 1080p sensor filmed at 540p); intrinsics and image
        size are divided by it.
    fit_centre : bool
        When the file has tangential terms, fit the radial correction's own centre too
        (written as ``VICON_RADIAL2``): it absorbs most of the decentring distortion
        (max residual 1.0 px instead of 2.2 px on the demo file). ``False`` keeps the
        principal point as centre.

    Returns
    -------
    Calibration
        ``format == "qca"``, cameras in file order (inactive ones included; see
        ``extra["qca_attrib"]["active"]``).

    Raises
    ------
    CalibrationError
        Not XML, no ``<camera>``, a missing or malformed attribute, a transform that is not
        a rotation, or a distortion that cannot be inverted over the image.
    """
    fname = Path(source).name
    if not binning or binning <= 0:
        raise CalibrationError(f"{fname}: binning must be positive, got {binning}")
    if isinstance(data, str):
        data = data.encode("utf-8")
    parser = etree.XMLParser(resolve_entities=False, no_network=True, remove_blank_text=True)
    try:
        root = etree.fromstring(data, parser)
    except etree.XMLSyntaxError as e:
        raise CalibrationError(f"{fname}: not a valid XML file ({e})") from None
    if root.tag != "calibration":
        raise CalibrationError(f"{fname}: not a Qualisys calibration (the root element is "
                               f"<{root.tag}>, expected <calibration>)")
    cams_el = root.findall("cameras/camera")
    if not cams_el:
        raise CalibrationError(f"{fname}: the file has no <cameras>/<camera> element")
    cams = [_read_camera(fname, i, c, float(binning), fit_centre) for i, c in enumerate(cams_el)]
    extra = {"qca_root_attrib": dict(root.attrib), "qca_binning": binning}
    return Calibration(cameras=cams, source=str(source), format="qca", extra=extra)


def read_qca(path: str | os.PathLike, *, binning: float = 1, fit_centre: bool = True) -> Calibration:
    """Read a ``.qca`` / ``.qca.txt`` file (see :func:`parse_qca`)."""
    return parse_qca(read_bytes(path), source=str(path), binning=binning, fit_centre=fit_centre)
