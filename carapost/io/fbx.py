"""FBX export: a take's points as animated nulls (binary FBX 7.4 / 7.5, written by CaraPost).

No FBX SDK is available from the package registries, so CaraPost writes the format itself
(``docs/formats/fbx.md`` documents every record written; :mod:`carapost.io.fbx_binary` encodes
them). The file holds:

* a root null named after the take (``CaraPost`` when unnamed) under the scene root;
* one null per exported point under it, named by label, else ``Point_<id>`` / ``Brim_<id>``
  (unique: repeats get ``_2``...), its ``Lcl Translation`` animated with one key per frame;
* optionally (*Include Cameras*) a ``Cameras`` null holding one camera node per take camera
  with a solved pose: its position and orientation (animated when the rig moves), a 36 mm-wide
  film back and the equivalent focal length, so the field of view is the camera's;
* one animation stack (named like the root) and layer spanning the exported frames; the
  global settings carry the frame rate (``TimeMode``, ``CustomFrameRate``), the time span,
  the units (``UnitScaleFactor``: 0.1 for mm, 1 for cm) and the up axis.

Gaps: a point has keys only at frames where it has a position. The last key before each gap
has constant interpolation (the curve holds still across the gap instead of sliding towards
the next run), and the null's ``Visibility`` is keyed 0 at the first frame of each gap and 1
where data resume (constant keys). Points never reconstructed are static and invisible.

Times: take frame ``f`` is keyed at ``(first_frame_number + f) / frame_rate`` seconds in FBX
ticks (46186158000 per second), rounded to the nearest tick. Key values are float32 (the
format's only key type): about 1e-7 relative, i.e. <= 1e-4 mm for coordinates within 1.6 m.
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

import numpy as np

from carapost import __version__
from carapost.model.params import ExportParameters
from carapost.model.take import Take

from .atomic import atomic_write_bytes
from .export import UNIT_SCALE, ExportData, axis_matrix, prepare_export, unique_names
from .fbx_binary import (
    CREATION_TIME,
    FILE_ID,
    KTIME_PER_SECOND,
    FbxNode,
    Prop,
    encode_fbx,
    p_array,
    p_bool,
    p_float64,
    p_int32,
    p_int64,
    p_raw,
    p_string,
)

__all__ = ["export_fbx", "fbx_bytes", "fbx_time", "time_mode", "KTIME_PER_SECOND", "FILM_WIDTH_MM"]

#: Film-back width given to exported cameras (mm); the focal length is scaled to match.
FILM_WIDTH_MM = 36.0
#: FBX ``TimeMode`` values of the standard rates (``14`` = custom, see ``CustomFrameRate``).
_TIME_MODES = ((120.0, 1), (100.0, 2), (60.0, 3), (50.0, 4), (48.0, 5), (30.0, 6), (30000 / 1001, 9),
               (25.0, 10), (24.0, 11), (24000 / 1001, 13), (96.0, 15), (72.0, 16), (60000 / 1001, 17),
               (120000 / 1001, 18))
_CUSTOM_TIME_MODE = 14
#: ``KeyAttrFlags``: FbxAnimCurveDef interpolation bits.
_KEY_CONSTANT = 0x00000002
_KEY_LINEAR = 0x00000004
#: FBX axis settings (UpAxis, UpAxisSign, FrontAxis, FrontAxisSign, CoordAxis, CoordAxisSign):
#: right-handed Y-up (Maya, MotionBuilder) and right-handed Z-up (3ds Max, Blender).
_AXES = {"Y": (1, 1, 2, 1, 0, 1), "Z": (2, 1, 1, -1, 0, 1)}
#: FBX camera axes (looks along +X, +Y up, +Z right) in our camera frame (+z forward, +y down).
_CAM_AXES = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


def time_mode(frame_rate: float) -> int:
    """FBX ``TimeMode`` enum of a frame rate (14 = custom)."""
    for rate, mode in _TIME_MODES:
        if abs(frame_rate - rate) <= 1e-9 * rate:
            return mode
    return _CUSTOM_TIME_MODE


def fbx_time(seconds: np.ndarray | float) -> np.ndarray:
    """Seconds to FBX ticks (int64, nearest tick)."""
    return np.rint(np.asarray(seconds, dtype=np.float64) * KTIME_PER_SECOND).astype(np.int64)


def _ticks(numbers: np.ndarray, frame_rate: float) -> np.ndarray:
    """FBX ticks of frame numbers, exact when the rate divides the tick rate."""
    numbers = np.asarray(numbers, dtype=np.int64)
    if float(frame_rate).is_integer() and KTIME_PER_SECOND % int(frame_rate) == 0:
        return numbers * (KTIME_PER_SECOND // int(frame_rate))
    return fbx_time(numbers / float(frame_rate))


# --------------------------------------------------------------------------- properties
def _P(name: str, ptype: str, label: str, flags: str, *values: Prop) -> FbxNode:
    """A ``P`` record of a ``Properties70`` block."""
    return FbxNode("P", [p_string(name), p_string(ptype), p_string(label), p_string(flags), *values])


def _p_int(name: str, v: int) -> FbxNode:
    return _P(name, "int", "Integer", "", p_int32(v))


def _p_enum(name: str, v: int) -> FbxNode:
    return _P(name, "enum", "", "", p_int32(v))


def _p_bool(name: str, v: bool) -> FbxNode:
    return _P(name, "bool", "", "", p_int32(1 if v else 0))


def _p_double(name: str, v: float) -> FbxNode:
    return _P(name, "double", "Number", "", p_float64(v))


def _p_number(name: str, v: float, flags: str = "A") -> FbxNode:
    return _P(name, "Number", "", flags, p_float64(v))


def _p_ktime(name: str, v: int) -> FbxNode:
    return _P(name, "KTime", "Time", "", p_int64(v))


def _p_kstring(name: str, v: str, label: str = "", flags: str = "") -> FbxNode:
    return _P(name, "KString", label, flags, p_string(v))


def _p_vec(name: str, v: np.ndarray | tuple[float, ...], ptype: str = "Vector3D", label: str = "Vector",
           flags: str = "") -> FbxNode:
    return _P(name, ptype, label, flags, *(p_float64(x) for x in v))


def _p_color(name: str, v: tuple[float, float, float]) -> FbxNode:
    return _P(name, "ColorRGB", "Color", "", *(p_float64(x) for x in v))


def _p_lcl(name: str, v: np.ndarray | tuple[float, ...], animated: bool) -> FbxNode:
    return _P(name, name, "", "A+" if animated else "A", *(p_float64(x) for x in v))


def _props70(*entries: FbxNode) -> FbxNode:
    return FbxNode("Properties70", [], list(entries))


class _Ids:
    """Unique, deterministic object ids (0 is the scene root)."""

    def __init__(self) -> None:
        self._next = 1_000_000_000

    def __call__(self) -> int:
        self._next += 1
        return self._next


# ---------------------------------------------------------------------------- animation
def _key_attributes(constant: np.ndarray) -> tuple[Prop, Prop, Prop]:
    """``KeyAttrFlags``, ``KeyAttrDataFloat``, ``KeyAttrRefCount`` for keys that are linear or
    constant (``constant (n,) bool``): run-length encoded, one attribute set per run."""
    n = constant.shape[0]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(constant.astype(np.int8))) + 1])
    counts = np.diff(np.concatenate([starts, [n]]))
    flags = np.where(constant[starts], _KEY_CONSTANT, _KEY_LINEAR).astype(np.int32)
    return (p_array(flags, np.int32), p_array(np.zeros(4 * len(starts)), np.float32),
            p_array(counts, np.int32))


def _curve(oid: int, times: np.ndarray, values: np.ndarray, constant: np.ndarray) -> FbxNode:
    """An ``AnimationCurve`` object with keys at ``times`` (ticks)."""
    node = FbxNode("AnimationCurve", [p_int64(oid), p_string("\x00\x01AnimCurve"), p_string("")])
    node.add("Default", p_float64(float(values[0]) if len(values) else 0.0))
    node.add("KeyVer", p_int32(4008))
    node.add("KeyTime", p_array(times, np.int64))
    node.add("KeyValueFloat", p_array(values, np.float32))
    flags, data, refs = _key_attributes(constant)
    node.add("KeyAttrFlags", flags)
    node.add("KeyAttrDataFloat", data)
    node.add("KeyAttrRefCount", refs)
    return node


class _Scene:
    """Objects and connections being built."""

    def __init__(self) -> None:
        self.ids = _Ids()
        self.objects: list[FbxNode] = []
        self.connections: list[FbxNode] = []
        self.counts: dict[str, int] = {}
        self.layer = 0

    def obj(self, node: FbxNode) -> None:
        self.objects.append(node)
        self.counts[node.name] = self.counts.get(node.name, 0) + 1

    def oo(self, child: int, parent: int) -> None:
        self.connections.append(FbxNode("C", [p_string("OO"), p_int64(child), p_int64(parent)]))

    def op(self, child: int, parent: int, prop: str) -> None:
        self.connections.append(FbxNode("C", [p_string("OP"), p_int64(child), p_int64(parent), p_string(prop)]))

    def null(self, name: str, parent: int, props: list[FbxNode], kind: str = "Null") -> int:
        """A Model (``kind`` "Null" or "Camera") under ``parent``; returns its id."""
        mid = self.ids()
        model = FbxNode("Model", [p_int64(mid), p_string(f"{name}\x00\x01Model"), p_string(kind)])
        model.add("Version", p_int32(232))
        model.children.append(_props70(_p_enum("RotationOrder", 0), _p_bool("RotationActive", True),
                                       _p_enum("InheritType", 1), _p_int("DefaultAttributeIndex", 0),
                                       *props))
        model.add("Shading", p_bool(True))
        model.add("Culling", p_string("CullingOff"))
        self.obj(model)
        self.oo(mid, parent)
        return mid

    def null_attribute(self, model: int) -> None:
        aid = self.ids()
        attr = FbxNode("NodeAttribute", [p_int64(aid), p_string("\x00\x01NodeAttribute"), p_string("Null")])
        attr.children.append(_props70(_P("Look", "enum", "", "", p_int32(1))))
        attr.add("TypeFlags", p_string("Null"))
        self.obj(attr)
        self.oo(aid, model)

    def animate(self, model: int, prop: str, node_name: str, channels: list[str], ticks: np.ndarray,
                values: np.ndarray, constant: np.ndarray) -> None:
        """An ``AnimationCurveNode`` driving ``prop`` of ``model`` with one curve per channel
        (``values (n, len(channels))``)."""
        cid = self.ids()
        cn = FbxNode("AnimationCurveNode", [p_int64(cid), p_string(f"{node_name}\x00\x01AnimCurveNode"),
                                            p_string("")])
        cn.children.append(_props70(*(_p_number(f"d|{ch}", float(values[0, k]))
                                      for k, ch in enumerate(channels))))
        self.obj(cn)
        self.oo(cid, self.layer)
        self.op(cid, model, prop)
        for k, ch in enumerate(channels):
            kid = self.ids()
            self.obj(_curve(kid, ticks, values[:, k], constant))
            self.op(kid, cid, f"d|{ch}")


def _runs_end(valid: np.ndarray) -> np.ndarray:
    """For each valid sample, whether it is the last of its run (``valid (n,)``)."""
    nxt = np.concatenate([valid[1:], [False]])
    return valid & ~nxt


def _animate_point(scene: _Scene, model: int, ticks: np.ndarray, xyz: np.ndarray, valid: np.ndarray) -> None:
    if not valid.any():
        return
    scene.animate(model, "Lcl Translation", "T", ["X", "Y", "Z"], ticks[valid], xyz[valid],
                  _runs_end(valid)[valid])
    if valid.all():
        return
    change = np.concatenate([[True], valid[1:] != valid[:-1]])
    vis = valid[change].astype(np.float64)[:, None]
    scene.animate(model, "Visibility", "Visibility", ["Visibility"], ticks[change], vis,
                  np.ones(int(change.sum()), bool))


# ------------------------------------------------------------------------------ cameras
def euler_xyz(M: np.ndarray) -> np.ndarray:
    """Euler angles (degrees, ``(..., 3)``) of rotations ``M (..., 3, 3)`` in FBX's default
    ``eEulerXYZ`` order: ``M = Rz(c) @ Ry(b) @ Rx(a)`` (x applied first)."""
    M = np.asarray(M, dtype=float)
    sb = np.clip(-M[..., 2, 0], -1.0, 1.0)
    b = np.arcsin(sb)
    cb = np.hypot(M[..., 0, 0], M[..., 1, 0])
    lock = cb < 1e-9
    a = np.where(lock, 0.0, np.arctan2(M[..., 2, 1], M[..., 2, 2]))
    c = np.where(lock, np.arctan2(-M[..., 0, 1], M[..., 1, 1]), np.arctan2(M[..., 1, 0], M[..., 0, 0]))
    return np.degrees(np.stack([a, b, c], axis=-1))


def _camera_props(take: Take, c: int) -> list[FbxNode]:
    cam = take.cameras[c]
    intr = cam.intrinsics
    W, H = (int(v) for v in (cam.image_size if any(cam.image_size) else intr.sensor_size))
    if W <= 0 or H <= 0:
        W, H = max(int(round(2 * intr.principal_point[0])), 1), max(int(round(2 * intr.principal_point[1])), 1)
    mm_per_px = FILM_WIDTH_MM / W
    film_w = FILM_WIDTH_MM / 25.4
    film_h = film_w * H / W
    focal_mm = intr.focal_length * mm_per_px
    fov = float(np.degrees(2 * np.arctan(W / (2 * intr.focal_length))))
    props = [_p_color("Color", (0.8, 0.8, 0.8)), _p_enum("AspectRatioMode", 2),
             _p_double("AspectWidth", W), _p_double("AspectHeight", H),
             _p_double("PixelAspectRatio", intr.aspect), _p_double("FilmWidth", film_w),
             _p_double("FilmHeight", film_h), _p_double("FilmAspectRatio", W / H),
             _p_enum("ApertureMode", 3), _p_enum("GateFit", 2),
             _P("FieldOfView", "FieldOfView", "", "A", p_float64(fov)),
             _P("FocalLength", "Number", "", "A", p_float64(focal_mm)),
             _p_double("NearPlane", 1.0), _p_double("FarPlane", 100000.0)]
    return props


def _add_cameras(scene: _Scene, take: Take, data: ExportData, parent: int, ticks: np.ndarray) -> None:
    Q = axis_matrix(data.up_axis)
    scale = UNIT_SCALE[data.units]
    fr = data.frames
    names = unique_names([cam.name or f"Camera_{c}" for c, cam in enumerate(take.cameras)])
    for c in range(take.n_cameras):
        R, t = take.R[fr, c], take.t[fr, c]
        valid = np.isfinite(R).all((1, 2)) & np.isfinite(t).all(1)
        if not valid.any():
            continue
        centre = np.full((len(fr), 3), np.nan)
        M = np.full((len(fr), 3, 3), np.nan)
        Rt = np.swapaxes(R[valid], 1, 2)
        centre[valid] = -np.einsum("nij,nj->ni", Rt, t[valid]) @ Q.T * scale
        M[valid] = Q @ Rt @ _CAM_AXES
        euler = np.full((len(fr), 3), np.nan)
        euler[valid] = np.degrees(np.unwrap(np.radians(euler_xyz(M[valid])), axis=0))
        k0 = int(np.argmax(valid))
        moving = not (np.allclose(centre[valid], centre[k0], rtol=0, atol=1e-9)
                      and np.allclose(euler[valid], euler[k0], rtol=0, atol=1e-9))
        props = [_p_lcl("Lcl Translation", centre[k0], moving), _p_lcl("Lcl Rotation", euler[k0], moving)]
        mid = scene.null(names[c], parent, props, kind="Camera")
        aprops = _camera_props(take, c)
        aid = scene.ids()
        attr = FbxNode("NodeAttribute", [p_int64(aid), p_string(f"{names[c]}\x00\x01NodeAttribute"),
                                         p_string("Camera")])
        attr.children.append(_props70(*aprops))
        attr.add("TypeFlags", p_string("Camera"))
        attr.add("GeometryVersion", p_int32(124))
        look = M[k0][:, 0]
        up = M[k0][:, 1]
        attr.add("Position", *(p_float64(v) for v in centre[k0]))
        attr.add("Up", *(p_float64(v) for v in up))
        attr.add("LookAt", *(p_float64(v) for v in centre[k0] + look))
        attr.add("ShowInfoOnMoving", p_int32(1))
        attr.add("ShowAudio", p_int32(0))
        attr.add("AudioColor", p_float64(0.0), p_float64(1.0), p_float64(0.0))
        attr.add("CameraOrthoZoom", p_float64(1.0))
        scene.obj(attr)
        scene.oo(aid, mid)
        if moving:
            ends = _runs_end(valid)[valid]
            scene.animate(mid, "Lcl Translation", "T", ["X", "Y", "Z"], ticks[valid], centre[valid], ends)
            scene.animate(mid, "Lcl Rotation", "R", ["X", "Y", "Z"], ticks[valid], euler[valid], ends)


# ---------------------------------------------------------------------------- sections
def _header(take: Take, path: Path, version: int, now: _dt.datetime) -> list[FbxNode]:
    creator = f"CaraPost for Python {__version__}"
    head = FbxNode("FBXHeaderExtension")
    head.add("FBXHeaderVersion", p_int32(1003))
    head.add("FBXVersion", p_int32(version))
    head.add("EncryptionType", p_int32(0))
    ts = head.add("CreationTimeStamp")
    ts.add("Version", p_int32(1000))
    for name, v in (("Year", now.year), ("Month", now.month), ("Day", now.day), ("Hour", now.hour),
                    ("Minute", now.minute), ("Second", now.second),
                    ("Millisecond", now.microsecond // 1000)):
        ts.add(name, p_int32(v))
    head.add("Creator", p_string(creator))
    info = head.add("SceneInfo", p_string("GlobalInfo\x00\x01SceneInfo"), p_string("UserData"))
    info.add("Type", p_string("UserData"))
    info.add("Version", p_int32(100))
    meta = info.add("MetaData")
    meta.add("Version", p_int32(100))
    for name, v in (("Title", take.name), ("Subject", "Facial motion capture"), ("Author", ""),
                    ("Keywords", ""), ("Revision", ""), ("Comment", "")):
        meta.add(name, p_string(v))
    stamp = now.strftime("%d/%m/%Y %H:%M:%S.") + f"{now.microsecond // 1000:03d}"
    info.children.append(_props70(
        _p_kstring("DocumentUrl", str(path), "Url"), _p_kstring("SrcDocumentUrl", str(path), "Url"),
        _P("Original", "Compound", "", ""),
        _p_kstring("Original|ApplicationVendor", "CaraPost"),
        _p_kstring("Original|ApplicationName", "CaraPost for Python"),
        _p_kstring("Original|ApplicationVersion", str(__version__)),
        _P("Original|DateTime_GMT", "DateTime", "", "", p_string(stamp)),
        _p_kstring("Original|FileName", path.name),
        _P("LastSaved", "Compound", "", ""),
        _p_kstring("LastSaved|ApplicationVendor", "CaraPost"),
        _p_kstring("LastSaved|ApplicationName", "CaraPost for Python"),
        _p_kstring("LastSaved|ApplicationVersion", str(__version__)),
        _P("LastSaved|DateTime_GMT", "DateTime", "", "", p_string(stamp))))
    return [head, FbxNode("FileId", [p_raw(FILE_ID)]), FbxNode("CreationTime", [p_string(CREATION_TIME)]),
            FbxNode("Creator", [p_string(creator)])]


def _global_settings(data: ExportData, start: int, stop: int) -> FbxNode:
    up, up_s, front, front_s, coord, coord_s = _AXES[data.up_axis]
    unit_cm = UNIT_SCALE["cm"] / UNIT_SCALE[data.units]  # centimetres per file unit
    gs = FbxNode("GlobalSettings")
    gs.add("Version", p_int32(1000))
    gs.children.append(_props70(
        _p_int("UpAxis", up), _p_int("UpAxisSign", up_s), _p_int("FrontAxis", front),
        _p_int("FrontAxisSign", front_s), _p_int("CoordAxis", coord), _p_int("CoordAxisSign", coord_s),
        _p_int("OriginalUpAxis", up), _p_int("OriginalUpAxisSign", up_s),
        _p_double("UnitScaleFactor", unit_cm), _p_double("OriginalUnitScaleFactor", unit_cm),
        _p_color("AmbientColor", (0.0, 0.0, 0.0)),
        _p_kstring("DefaultCamera", "Producer Perspective"),
        _p_enum("TimeMode", time_mode(data.frame_rate)), _p_enum("TimeProtocol", 2),
        _p_enum("SnapOnFrameMode", 0), _p_ktime("TimeSpanStart", start), _p_ktime("TimeSpanStop", stop),
        _p_double("CustomFrameRate", data.frame_rate)))
    return gs


def _templates(counts: dict[str, int], cameras: bool) -> FbxNode:
    defs = FbxNode("Definitions")
    defs.add("Version", p_int32(100))
    defs.add("Count", p_int32(1 + sum(counts.values())))
    gs = defs.add("ObjectType", p_string("GlobalSettings"))
    gs.add("Count", p_int32(1))

    def otype(name: str, template: str | None, props: list[FbxNode]) -> FbxNode | None:
        if not counts.get(name):
            return None
        ot = defs.add("ObjectType", p_string(name))
        ot.add("Count", p_int32(counts[name]))
        if template is not None:
            ot.add("PropertyTemplate", p_string(template)).children.append(_props70(*props))
        return ot

    zero3 = (0.0, 0.0, 0.0)
    otype("Model", "FbxNode", [
        _p_enum("QuaternionInterpolate", 0), _p_vec("RotationOffset", zero3), _p_vec("RotationPivot", zero3),
        _p_vec("ScalingOffset", zero3), _p_vec("ScalingPivot", zero3), _p_bool("TranslationActive", False),
        _p_enum("RotationOrder", 0), _p_bool("RotationSpaceForLimitOnly", False),
        _p_vec("PreRotation", zero3), _p_vec("PostRotation", zero3), _p_bool("RotationActive", False),
        _p_enum("InheritType", 0), _p_bool("ScalingActive", False), _p_vec("GeometricTranslation", zero3),
        _p_vec("GeometricRotation", zero3), _p_vec("GeometricScaling", (1.0, 1.0, 1.0)),
        _p_int("DefaultAttributeIndex", -1), _p_bool("Show", True), _p_bool("Freeze", False),
        _p_lcl("Lcl Translation", zero3, False), _p_lcl("Lcl Rotation", zero3, False),
        _p_lcl("Lcl Scaling", (1.0, 1.0, 1.0), False),
        _P("Visibility", "Visibility", "", "A", p_float64(1.0)),
        _P("Visibility Inheritance", "Visibility Inheritance", "", "", p_int32(1))])
    na = otype("NodeAttribute", "FbxNull", [_p_color("Color", (0.8, 0.8, 0.8)), _p_double("Size", 100.0),
                                            _p_enum("Look", 1)])
    if na is not None and cameras:
        na.add("PropertyTemplate", p_string("FbxCamera")).children.append(_props70(
            _p_color("Color", (0.8, 0.8, 0.8)), _p_double("FilmWidth", 0.816), _p_double("FilmHeight", 0.612),
            _P("FocalLength", "Number", "", "A", p_float64(34.89327621672628)), _p_enum("ApertureMode", 2),
            _p_enum("GateFit", 0)))
    otype("AnimationStack", "FbxAnimStack", [
        _p_kstring("Description", ""), _p_ktime("LocalStart", 0), _p_ktime("LocalStop", 0),
        _p_ktime("ReferenceStart", 0), _p_ktime("ReferenceStop", 0)])
    otype("AnimationLayer", "FbxAnimLayer", [
        _P("Weight", "Number", "", "A", p_float64(100.0)), _p_bool("Mute", False), _p_bool("Solo", False),
        _p_bool("Lock", False), _p_color("Color", (0.8, 0.8, 0.8)), _p_enum("BlendMode", 0),
        _p_enum("RotationAccumulationMode", 0), _p_enum("ScaleAccumulationMode", 0),
        _P("BlendModeBypass", "ULongLong", "", "", p_int64(0))])
    otype("AnimationCurveNode", "FbxAnimCurveNode", [_P("d", "Compound", "", "")])
    otype("AnimationCurve", None, [])
    return defs


# ---------------------------------------------------------------------------------- API
def fbx_bytes(take: Take, *, options: ExportParameters | None = None,
              selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
              points: np.ndarray | list[int] | None = None, version: int = 7400, path: str | os.PathLike = "",
              timestamp: _dt.datetime | None = None) -> bytes:
    """The binary FBX document of a take (see :func:`export_fbx`)."""
    opts = take.params.export if options is None else options
    data = prepare_export(take, options=opts, selection=selection, points=points, frames=frames)
    if int(version) not in (7400, 7500):
        raise ValueError(f"FBX version must be 7400 or 7500, got {version}")
    now = timestamp or _dt.datetime.now()
    ticks = _ticks(data.frame_numbers, data.frame_rate)
    start, stop = int(ticks[0]), int(ticks[-1])
    root_name = take.name.strip() or "CaraPost"

    scene = _Scene()
    stack_id = scene.ids()
    stack = FbxNode("AnimationStack", [p_int64(stack_id), p_string(f"{root_name}\x00\x01AnimStack"), p_string("")])
    stack.children.append(_props70(_p_ktime("LocalStart", start), _p_ktime("LocalStop", stop),
                                   _p_ktime("ReferenceStart", start), _p_ktime("ReferenceStop", stop)))
    scene.obj(stack)
    scene.layer = scene.ids()
    scene.obj(FbxNode("AnimationLayer", [p_int64(scene.layer), p_string("BaseLayer\x00\x01AnimLayer"),
                                         p_string("")]))
    scene.oo(scene.layer, stack_id)

    root_props = [_p_lcl("Lcl Translation", (0.0, 0.0, 0.0), False),
                  _P("CaraPost_FirstFrameNumber", "int", "Integer", "U", p_int32(int(take.first_frame_number))),
                  _P("CaraPost_StartTimecode", "KString", "", "U", p_string(take.start_timecode)),
                  _P("CaraPost_Units", "KString", "", "U", p_string(data.units)),
                  _P("CaraPost_Stabilized", "bool", "", "U", p_int32(int(data.stabilized)))]
    root = scene.null(root_name, 0, root_props)
    scene.null_attribute(root)
    for k in range(data.n_points):
        valid = data.valid[:, k]
        xyz = data.xyz[:, k]
        first = xyz[int(np.argmax(valid))] if valid.any() else np.zeros(3)
        props = [_p_lcl("Lcl Translation", first, bool(valid.any())),
                 _P("Visibility", "Visibility", "", "A+" if 0 < valid.sum() < len(valid) else "A",
                    p_float64(1.0 if valid.any() else 0.0)),
                 _P("CaraPost_PointId", "int", "Integer", "U", p_int32(int(data.ids[k])))]
        mid = scene.null(data.names[k], root, props)
        scene.null_attribute(mid)
        _animate_point(scene, mid, ticks, xyz, valid)
    fr = data.frames
    posed = (np.isfinite(take.R[fr]).all((2, 3)) & np.isfinite(take.t[fr]).all(2)).any(0)   # (C,)
    has_cameras = bool(opts.include_cameras and posed.any())
    if has_cameras:
        group = scene.null("Cameras", root, [])
        scene.null_attribute(group)
        _add_cameras(scene, take, data, group, ticks)

    doc_id = scene.ids()
    documents = FbxNode("Documents")
    documents.add("Count", p_int32(1))
    doc = documents.add("Document", p_int64(doc_id), p_string(""), p_string("Scene"))
    doc.children.append(_props70(_P("SourceObject", "object", "", ""),
                                 _p_kstring("ActiveAnimStackName", root_name)))
    doc.add("RootNode", p_int64(0))

    takes = FbxNode("Takes")
    takes.add("Current", p_string(root_name))
    tk = takes.add("Take", p_string(root_name))
    tk.add("FileName", p_string(f"{root_name.replace(' ', '_')}.tak"))
    tk.add("LocalTime", p_int64(start), p_int64(stop))
    tk.add("ReferenceTime", p_int64(start), p_int64(stop))

    nodes = _header(take, Path(path) if path else Path(f"{root_name}.fbx"), int(version), now)
    nodes += [_global_settings(data, start, stop), documents, FbxNode("References"),
              _templates(scene.counts, has_cameras), FbxNode("Objects", [], scene.objects),
              FbxNode("Connections", [], scene.connections), takes]
    return encode_fbx(nodes, int(version))


def export_fbx(take: Take, path: str | os.PathLike, *, options: ExportParameters | None = None,
               selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
               points: np.ndarray | list[int] | None = None, version: int = 7400,
               timestamp: _dt.datetime | None = None) -> None:
    """Write a take's points (and cameras) to a binary FBX file, atomically.

    Parameters
    ----------
    take : Take
    path : path-like
        Destination ``.fbx``; its folder must exist.
    options : ExportParameters, optional
        Units (mm / cm), up axis (Y / Z), raw or stabilized data, selected points only,
        brim points, cameras. Default ``take.params.export``.
    selection : int array, optional
        Selected point columns (used when *Selected Points Only* is on).
    frames : (int, int), optional
        Inclusive range of take frame indices (default: all).
    points : int array, optional
        Explicit point columns (overrides the point options).
    version : {7400, 7500}
        FBX 7.4 (32-bit offsets, read by every FBX 2014+ application) or 7.5 (64-bit).
    timestamp : datetime, optional
        Creation time written in the header (default: now).

    Raises
    ------
    ValueError
        No points to export, bad range or selection, stabilized data missing; the message
        names the file.
    """
    path = Path(path)
    try:
        data = fbx_bytes(take, options=options, selection=selection, frames=frames, points=points,
                         version=version, path=path.resolve(), timestamp=timestamp)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    if not path.parent.is_dir():
        raise ValueError(f"{path}: cannot write, the folder {path.parent} does not exist")
    atomic_write_bytes(path, data)
