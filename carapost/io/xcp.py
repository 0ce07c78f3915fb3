"""Vicon XCP camera calibration files (XML): read and write.

What is read (reference guide, "About calibration data (XCP) files"; ``docs/formats/xcp.md``):

* ``<Cameras>`` root with ``<Camera>`` children: ``NAME``, ``DEVICEID``, ``USERID``,
  ``PIXEL_ASPECT_RATIO`` (default 1), ``SENSOR_SIZE`` (default unknown), ``SKEW`` (default 0);
* each camera's ``<KeyFrames>/<KeyFrame>``: ``FRAME`` (may be omitted for a single keyframe),
  ``FOCAL_LENGTH`` (pixels), ``PRINCIPAL_POINT``, ``ORIENTATION`` (quaternion x y z w, real
  part last, world to camera), ``POSITION`` (the camera *centre* in world mm, so
  ``t = -R @ POSITION``), ``VICON_RADIAL="w0 w1"`` or
  ``VICON_RADIAL2="Vicon3Parameter cx cy k1 k2 k3"``, ``IMAGE_ERROR``, ``WORLD_ERROR``.

Everything else (other attributes, ``ThresholdGrid``, ``Calibration``, ``Capture``,
``ControlFrames``, comments, ...) is kept in ``extra`` and written back unchanged, in place.
Numbers are written with ``repr`` so poses round-trip to machine precision.

A number split across lines with its exponent (``"2.6e-\\n 016"``, as in the guide's printed
example) is re-joined when read.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from lxml import etree

from carapost.core.camera import Intrinsics, matrix_to_quat, quat_to_matrix
from carapost.io.calibration import (
    Calibration,
    CalibrationError,
    CameraCalibration,
    atomic_write_bytes,
    read_bytes,
)

__all__ = ["read_xcp", "parse_xcp", "write_xcp", "xcp_bytes"]

_CAMERA_KNOWN = ("DEVICEID", "NAME", "PIXEL_ASPECT_RATIO", "SENSOR_SIZE", "SKEW", "USERID")
_KEYFRAME_KNOWN = ("FOCAL_LENGTH", "FRAME", "IMAGE_ERROR", "ORIENTATION", "POSITION",
                   "PRINCIPAL_POINT", "VICON_RADIAL", "VICON_RADIAL2", "WORLD_ERROR")
_SPLIT_EXPONENT = re.compile(r"(?<=[0-9.][eE][+-])\s+(?=\d)|(?<=[0-9.][eE])\s+(?=[+-]?\d)")


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


class _Ctx:
    """Where we are in the file, for error messages."""

    def __init__(self, fname: str) -> None:
        self.fname = fname
        self.where = ""

    def error(self, msg: str) -> CalibrationError:
        return CalibrationError(f"{self.fname}: {self.where}{msg}")


def _parse(ctx: _Ctx, attr: str, raw: str, n: int | None, *, finite: bool = True) -> list[float]:
    """Numbers of attribute ``attr`` whose text is ``raw`` (exactly ``n`` of them if given)."""
    parts = _SPLIT_EXPONENT.sub("", raw.strip()).split()
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ctx.error(f'{attr} must hold numbers, got "{raw}"') from None
    if n is not None and len(vals) != n:
        word = "number" if n == 1 else "numbers"
        raise ctx.error(f'{attr} must have {n} {word}, got "{raw}"')
    if finite and not all(np.isfinite(vals)):
        raise ctx.error(f'{attr} must be finite, got "{raw}"')
    return vals


def _numbers(ctx: _Ctx, el: Any, attr: str, n: int | None, *, required: bool = True,
             finite: bool = True) -> list[float] | None:
    raw = el.get(attr)
    if raw is None:
        if required:
            raise ctx.error(f"{attr} is missing")
        return None
    return _parse(ctx, attr, raw, n, finite=finite)


def _serialise(child: Any) -> tuple[str, str]:
    if isinstance(child, etree._Comment):
        return ("comment", child.text or "")
    if isinstance(child, etree._ProcessingInstruction):
        return ("pi", etree.tostring(child, encoding="unicode", with_tail=False))
    return ("xml", etree.tostring(child, encoding="unicode", with_tail=False))


def _read_keyframe(ctx: _Ctx, kf: Any, cam_attr: dict[str, Any], single: bool) -> tuple[Any, ...]:
    if kf.get("FRAME") is None and single:
        frame = 0
    else:
        fr = _numbers(ctx, kf, "FRAME", 1)
        assert fr is not None
        if fr[0] != int(fr[0]):
            raise ctx.error(f'FRAME must be an integer, got "{kf.get("FRAME")}"')
        frame = int(fr[0])
    f = _numbers(ctx, kf, "FOCAL_LENGTH", 1)
    pp = _numbers(ctx, kf, "PRINCIPAL_POINT", 2)
    q = _numbers(ctx, kf, "ORIENTATION", 4)
    pos = _numbers(ctx, kf, "POSITION", 3)
    assert f is not None and pp is not None and q is not None and pos is not None
    if f[0] <= 0:
        raise ctx.error(f'FOCAL_LENGTH must be positive, got "{kf.get("FOCAL_LENGTH")}"')
    if np.linalg.norm(q) < 1e-12:
        raise ctx.error(f'ORIENTATION is a zero quaternion: "{kf.get("ORIENTATION")}"')
    radial = (0.0, 0.0, 0.0)
    centre: tuple[float, float] | None = None
    extra_attr = {k: v for k, v in kf.attrib.items() if k not in _KEYFRAME_KNOWN}
    if kf.get("VICON_RADIAL2") is not None:
        raw = kf.get("VICON_RADIAL2")
        parts = raw.split()
        if not parts or parts[0] != "Vicon3Parameter":
            raise ctx.error(f'VICON_RADIAL2 must start with "Vicon3Parameter", got "{raw}"')
        if len(parts) != 6:
            raise ctx.error(f'VICON_RADIAL2 must have "Vicon3Parameter" and 5 numbers, got "{raw}"')
        vals = _parse(ctx, "VICON_RADIAL2", " ".join(parts[1:]), 5)
        centre = (vals[0], vals[1])
        radial = (vals[2], vals[3], vals[4])
        if kf.get("VICON_RADIAL") is not None:  # both present: VICON_RADIAL2 wins, keep the other
            extra_attr["VICON_RADIAL"] = kf.get("VICON_RADIAL")
    elif kf.get("VICON_RADIAL") is not None:
        w = _numbers(ctx, kf, "VICON_RADIAL", 2)
        assert w is not None
        radial = (w[0], w[1], 0.0)
    img = _numbers(ctx, kf, "IMAGE_ERROR", 1, required=False, finite=False)
    wld = _numbers(ctx, kf, "WORLD_ERROR", 1, required=False, finite=False)
    try:
        intr = Intrinsics(focal_length=f[0], principal_point=(pp[0], pp[1]),
                          sensor_size=cam_attr["sensor_size"], aspect=cam_attr["aspect"],
                          skew=cam_attr["skew"], radial=radial, distortion_centre=centre)
    except ValueError as e:
        raise ctx.error(str(e)) from None
    R = quat_to_matrix(np.asarray(q))
    C = np.asarray(pos)
    t = -R @ C
    # the pose text as read: written back unchanged while R and t are unchanged
    pose_text = (kf.get("ORIENTATION"), kf.get("POSITION"), R, t)
    return (frame, R, t, img[0] if img else np.nan, wld[0] if wld else np.nan, intr, extra_attr,
            pose_text)


def _read_camera(ctx: _Ctx, index: int, cam: Any) -> CameraCalibration:
    name = cam.get("NAME", "")
    dev = cam.get("DEVICEID", "")
    label = name or (f"DEVICEID {dev}" if dev else "unnamed")
    ctx.where = f"camera {index} ({label}): "
    aspect = _numbers(ctx, cam, "PIXEL_ASPECT_RATIO", 1, required=False)
    skew = _numbers(ctx, cam, "SKEW", 1, required=False)
    size = _numbers(ctx, cam, "SENSOR_SIZE", 2, required=False)
    if size is not None and (any(s < 0 or s != int(s) for s in size)):
        raise ctx.error(f'SENSOR_SIZE must be two non-negative integers, got "{cam.get("SENSOR_SIZE")}"')
    if aspect is not None and aspect[0] <= 0:
        raise ctx.error(f'PIXEL_ASPECT_RATIO must be positive, got "{cam.get("PIXEL_ASPECT_RATIO")}"')
    cam_attr = {"aspect": aspect[0] if aspect else 1.0, "skew": skew[0] if skew else 0.0,
                "sensor_size": (int(size[0]), int(size[1])) if size else (0, 0)}
    children: list[tuple[str, str] | None] = []
    kfs_el = None
    for child in cam:
        if child.tag == "KeyFrames" and kfs_el is None:
            kfs_el = child
            children.append(None)
        else:
            children.append(_serialise(child))
    if kfs_el is None:
        raise ctx.error("has no <KeyFrames> element")
    kf_list = [k for k in kfs_el if k.tag == "KeyFrame"]
    if not kf_list:
        raise ctx.error("has no <KeyFrame>")
    other_kfs = [_serialise(k) for k in kfs_el if k.tag != "KeyFrame"]
    rows = []
    base_where = ctx.where
    for j, kf in enumerate(kf_list):
        if len(kf_list) > 1:
            ctx.where = f"camera {index} ({label}), KeyFrame {j}: "
        rows.append(_read_keyframe(ctx, kf, cam_attr, single=len(kf_list) == 1))
    ctx.where = base_where
    frames = [r[0] for r in rows]
    if len(set(frames)) != len(frames):
        raise ctx.error(f"two KeyFrames have the same FRAME ({sorted(frames)})")
    intrs = [r[5] for r in rows]
    extra: dict[str, Any] = {
        "xcp_attrib": {k: v for k, v in cam.attrib.items() if k not in _CAMERA_KNOWN},
        "xcp_attrib_order": list(cam.attrib.keys()),
        "xcp_children": children,
        "xcp_keyframes_attrib": dict(kfs_el.attrib),
        "xcp_keyframes_other": other_kfs,
        "xcp_keyframe_order": [list(k.attrib.keys()) for k in kf_list],
    }
    # keyframe extras are stored in *sorted* frame order, as the arrays will be
    order = np.argsort(frames, kind="stable")
    extra["xcp_keyframe_extra"] = [rows[i][6] for i in order]
    extra["xcp_keyframe_pose"] = [rows[i][7] for i in order]
    extra["xcp_keyframe_order"] = [extra["xcp_keyframe_order"][i] for i in order]
    same = all(i == intrs[0] for i in intrs)
    return CameraCalibration(
        name=name, device_id=dev, user_id=cam.get("USERID", ""), intrinsics=intrs[0],
        frames=np.array(frames), R=np.stack([r[1] for r in rows]), t=np.stack([r[2] for r in rows]),
        image_error=np.array([r[3] for r in rows]), world_error=np.array([r[4] for r in rows]),
        keyframe_intrinsics=() if same else tuple(intrs), extra=extra)


def parse_xcp(data: bytes | str, *, source: str = "<string>") -> Calibration:
    """Parse XCP text.

    Parameters
    ----------
    data : bytes or str
        The XML.
    source : str
        File name (or path) used in error messages and stored as ``Calibration.source``.

    Returns
    -------
    Calibration
        ``format == "xcp"``; cameras in file order.

    Raises
    ------
    CalibrationError
        Not XML, not a ``<Cameras>`` document, no cameras, or a malformed camera/keyframe.
    """
    fname = Path(source).name
    ctx = _Ctx(fname)
    if isinstance(data, str):  # lxml refuses str with an encoding declaration: drop it
        data = re.sub(r"^\s*<\?xml[^>]*\?>", "", data).encode("utf-8")
    parser = etree.XMLParser(resolve_entities=False, no_network=True, remove_blank_text=True,
                             huge_tree=True)
    try:
        root = etree.fromstring(data, parser)
    except etree.XMLSyntaxError as e:
        raise CalibrationError(f"{fname}: not a valid XML file ({e})") from None
    if root.tag != "Cameras":
        raise CalibrationError(f"{fname}: not an XCP file (the root element is <{root.tag}>, "
                               "expected <Cameras>)")
    cams: list[CameraCalibration] = []
    layout: list[tuple[str, str] | None] = []
    for child in root:
        if child.tag == "Camera":
            cams.append(_read_camera(ctx, len(cams), child))
            layout.append(None)
        else:
            layout.append(_serialise(child))
    if not cams:
        raise CalibrationError(f"{fname}: the file has no <Camera> element")
    extra = {"xcp_root_attrib": dict(root.attrib), "xcp_layout": layout}
    return Calibration(cameras=cams, source=str(source), format="xcp", extra=extra)


def read_xcp(path: str | os.PathLike) -> Calibration:
    """Read an ``.xcp`` file (see :func:`parse_xcp`)."""
    return parse_xcp(read_bytes(path), source=str(path))


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _num(x: float) -> str:
    """Shortest text that reads back as exactly ``x`` (integers without ``.0``)."""
    x = float(x)
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


def _nums(xs: Any) -> str:
    return " ".join(_num(v) for v in np.ravel(xs))


def _deserialise(item: tuple[str, str]) -> Any:
    kind, text = item
    if kind == "comment":
        return etree.Comment(text)
    return etree.fromstring(text)


def _ordered(values: dict[str, str], order: list[str] | None) -> list[tuple[str, str]]:
    keys = [k for k in (order or []) if k in values]
    keys += sorted(k for k in values if k not in keys)
    return [(k, values[k]) for k in keys]


def _keyframe_attrib(cam: CameraCalibration, k: int) -> list[tuple[str, str]]:
    intr = cam.intrinsics_at(k)
    q = matrix_to_quat(cam.R[k])
    centre = -cam.R[k].T @ cam.t[k]
    q_text, c_text = _nums(q), _nums(centre)
    poses = cam.extra.get("xcp_keyframe_pose")
    if poses is not None and k < len(poses):
        q0, c0, R0, t0 = poses[k]
        if np.array_equal(R0, cam.R[k]) and np.array_equal(t0, cam.t[k]):
            q_text, c_text = q0, c0
    vals: dict[str, str] = {
        "FOCAL_LENGTH": _num(intr.focal_length),
        "FRAME": str(int(cam.frames[k])),
        "ORIENTATION": q_text,
        "POSITION": c_text,
        "PRINCIPAL_POINT": _nums(intr.principal_point),
    }
    if intr.distortion_centre is None and intr.radial[2] == 0.0:
        vals["VICON_RADIAL"] = _nums(intr.radial[:2])
    else:
        c = intr.centre
        vals["VICON_RADIAL2"] = "Vicon3Parameter " + _nums([c[0], c[1], *intr.radial])
    if np.isfinite(cam.image_error[k]):
        vals["IMAGE_ERROR"] = _num(cam.image_error[k])
    if np.isfinite(cam.world_error[k]):
        vals["WORLD_ERROR"] = _num(cam.world_error[k])
    kx = cam.extra.get("xcp_keyframe_extra")
    korder = cam.extra.get("xcp_keyframe_order")
    order = None
    if kx is not None and len(kx) == cam.n_keyframes:
        for a, v in kx[k].items():
            vals.setdefault(a, v)
        order = korder[k] if korder and len(korder) == cam.n_keyframes else None
    return _ordered(vals, order)


def _camera_element(cam: CameraCalibration) -> Any:
    intr = cam.intrinsics
    vals = {
        "DEVICEID": cam.device_id,
        "NAME": cam.name,
        "PIXEL_ASPECT_RATIO": _num(intr.aspect),
        "SENSOR_SIZE": _nums(intr.sensor_size) if any(intr.sensor_size) else "",
        "SKEW": _num(intr.skew),
        "USERID": cam.user_id,
    }
    if not vals["SENSOR_SIZE"]:  # unknown: leave it out
        del vals["SENSOR_SIZE"]
    for a, v in cam.extra.get("xcp_attrib", {}).items():
        vals.setdefault(a, v)
    el = etree.Element("Camera")
    for a, v in _ordered(vals, cam.extra.get("xcp_attrib_order")):
        el.set(a, v)
    children = cam.extra.get("xcp_children") or [None]
    for item in children:
        if item is not None:
            el.append(_deserialise(item))
            continue
        kfs = etree.SubElement(el, "KeyFrames")
        for a, v in cam.extra.get("xcp_keyframes_attrib", {}).items():
            kfs.set(a, v)
        for k in range(cam.n_keyframes):
            kf = etree.SubElement(kfs, "KeyFrame")
            for a, v in _keyframe_attrib(cam, k):
                kf.set(a, v)
        for other in cam.extra.get("xcp_keyframes_other", []):
            kfs.append(_deserialise(other))
    return el


def xcp_bytes(calib: Calibration) -> bytes:
    """The XCP document (UTF-8 bytes) for ``calib``.

    Unknown attributes and elements read from an XCP are written back in place. A camera
    uses ``VICON_RADIAL`` when its correction has no ``r^6`` term and is centred on the
    principal point, else ``VICON_RADIAL2``. Image/world errors that are NaN are omitted.
    """
    if not calib.cameras:
        raise CalibrationError("cannot write an XCP file without cameras")
    root = etree.Element("Cameras")
    attrib = calib.extra.get("xcp_root_attrib")
    if attrib is None:
        radial2 = any(c.intrinsics_at(k).distortion_centre is not None or c.intrinsics_at(k).radial[2] != 0
                      for c in calib.cameras for k in range(c.n_keyframes))
        attrib = {"SOURCE": "CaraPost for Python", "VERSION": "2.0" if radial2 else "1.0"}
    for a, v in attrib.items():
        root.set(a, v)
    layout = list(calib.extra.get("xcp_layout") or [None] * len(calib.cameras))
    n_slots = sum(1 for item in layout if item is None)
    layout += [None] * max(0, len(calib.cameras) - n_slots)
    ci = 0
    for item in layout:
        if item is None:
            if ci < len(calib.cameras):
                root.append(_camera_element(calib.cameras[ci]))
                ci += 1
        else:
            root.append(_deserialise(item))
    etree.indent(root, space="  ")
    # The declaration as Vicon Nexus writes it (double quotes), then the tree.
    return (b'<?xml version="1.0" encoding="UTF-8" standalone="no" ?>\n'
            + etree.tostring(root, encoding="UTF-8", pretty_print=True))


def write_xcp(path: str | os.PathLike, calib: Calibration) -> None:
    """Write ``calib`` to ``path`` as XCP, atomically (see :func:`xcp_bytes`)."""
    try:
        data = xcp_bytes(calib)
    except CalibrationError as e:
        raise CalibrationError(f"{Path(path).name}: {e}") from None
    atomic_write_bytes(path, data)
