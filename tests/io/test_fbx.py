"""FBX export, proved by independent readers: the ufbx loader (always) and Blender's FBX and BVH
importers (slow tests, when a Python with ``bpy`` is available)."""

from __future__ import annotations

import ctypes
import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from carapost.core.camera import camera_centre, quat_to_matrix
from carapost.io.c3d_take import take_from_c3d
from carapost.io.export import axis_matrix, export_take
from carapost.io.fbx import export_fbx, fbx_bytes, time_mode
from carapost.io.fbx_binary import FOOTER_ID, FOOTER_MAGIC, HEADER_MAGIC, KTIME_PER_SECOND
from carapost.model.params import ExportParameters

sys.path.insert(0, str(Path(__file__).parent))
from test_exports import FIRST, FPS, make_take  # noqa: E402

ufbx = pytest.importorskip("ufbx")

NAMES = ["Nose_Tip", "Chin", "Point_2", "Nose_Tip_2", "Brim_4", "Brim_5"]
#: FBX camera axes (looks along +X, +Y up) in our camera frame (+z forward, +y down).
CAM_AXES = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


class U:
    """A proxy for ufbx objects that works around a reference-counting bug of ufbx 0.0.5's
    Python binding.

    The binding keeps one Python wrapper per scene element and hands the cached wrapper out
    again *without* incrementing its reference count, so every later access steals a reference
    and the wrapper is freed while still in use (a segmentation fault a few lines later). The
    proxy takes one extra reference on every ufbx object it hands out; the few wrappers of a
    test scene then live as long as the process (a deliberate, harmless leak).
    """

    __slots__ = ("_obj",)

    def __init__(self, obj) -> None:
        object.__setattr__(self, "_obj", obj)

    @staticmethod
    def wrap(obj):
        if type(obj) is tuple:  # e.g. AnimValue.curves; NamedTuples (Vec3, Transform) hold values
            return tuple(U.wrap(x) for x in obj)
        if type(obj).__module__.startswith("ufbx") and not isinstance(obj, (int, float, str, tuple)):
            ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))
            return U(obj)
        return obj

    def __getattr__(self, name: str):
        value = getattr(self._obj, name)
        if callable(value) and not isinstance(value, type):  # a method: wrap what it returns
            return U(value)
        return U.wrap(value)

    def __getitem__(self, i):
        return U.wrap(self._obj[i])

    def __len__(self) -> int:
        return len(self._obj)

    def __call__(self, *args, **kw):
        return U.wrap(self._obj(*(unwrap(a) for a in args), **kw))

    def __bool__(self) -> bool:
        return True

    def __eq__(self, other) -> bool:
        return unwrap(self) is unwrap(other) or unwrap(self) == unwrap(other)

    __hash__ = None  # type: ignore[assignment]


def unwrap(obj):
    return obj._obj if isinstance(obj, U) else obj


def uf(name: str, *args):
    """Call the ufbx module function ``name`` on (unwrapped) arguments."""
    return U.wrap(getattr(ufbx, name)(*(unwrap(a) for a in args)))


def items(lst) -> list:
    """Elements of a ufbx list (by index: the binding's iterators are unsafe too)."""
    return [lst[i] for i in range(len(lst))]


def load(path: Path, **kw) -> U:
    return U(ufbx.load_file(str(path), **kw))


def translation_curves(scene, layer, name: str):
    node = scene.find_node(name)
    prop = layer.find_anim_prop(node, "Lcl Translation")
    return node, (None if unwrap(prop) is None else prop.anim_value.curves)


def seconds(frame: int, rate: float = FPS) -> float:
    return (FIRST + frame) / rate


@pytest.fixture(scope="module")
def take():
    return make_take()


# ----------------------------------------------------------------------- points and time
@pytest.mark.parametrize("version,up,units", [(7400, "Y", "mm"), (7500, "Z", "cm"), (7400, "Z", "mm"),
                                              (7500, "Y", "cm")])
def test_ufbx_reads_points_time_and_settings(take, tmp_path, version, up, units):
    path = tmp_path / "t.fbx"
    export_fbx(take, path, options=ExportParameters(units=units, up_axis=up), version=version)
    scene = load(path)
    assert scene.metadata.version == version and not scene.metadata.ascii
    assert scene.metadata.creator.startswith("CaraPost for Python")
    assert len(scene.metadata.warnings) == 0
    s = scene.settings
    assert s.frames_per_second == FPS and s.time_mode == 3          # eFrames60
    assert s.unit_meters == pytest.approx({"mm": 0.001, "cm": 0.01}[units])
    assert tuple(s.axes) == tuple(ufbx.axes_right_handed_y_up if up == "Y" else ufbx.axes_right_handed_z_up)
    # hierarchy: scene root > take root > one null per point (+ Cameras > camera nodes)
    root = scene.find_node("Test Take")
    assert root.parent.is_root
    children = [c.name for c in items(root.children)]
    assert children == NAMES + ["Cameras"]
    assert all(scene.find_node(n).attrib_type == ufbx.ElementType.EMPTY for n in NAMES)
    # animation stack: the take's time span
    stack = items(scene.anim_stacks)[0]
    assert stack.name == "Test Take"
    assert stack.time_begin == pytest.approx(seconds(0), abs=1e-9)
    assert stack.time_end == pytest.approx(seconds(29), abs=1e-9)
    # key values at every frame: <= 1e-4 mm after unit conversion
    expect = take.xyz @ axis_matrix(up).T
    to_mm = {"mm": 1.0, "cm": 10.0}[units]
    anim = scene.anim
    worst = 0.0
    for k, name in enumerate(NAMES[:5]):
        node = scene.find_node(name)
        for f in range(take.n_frames):
            if np.isfinite(expect[f, k]).all():
                tr = uf("evaluate_transform", anim, node, seconds(f))
                worst = max(worst, float(np.abs(np.array(tr.translation) * to_mm - expect[f, k]).max()))
    assert worst <= 1e-4


def test_gaps_are_missing_keys_and_invisibility(take, tmp_path):
    path = tmp_path / "gaps.fbx"
    export_fbx(take, path)
    scene = load(path)
    layer = items(items(scene.anim_stacks)[0].layers)[0]
    node, curves = translation_curves(scene, layer, "Chin")            # gap at frames 5..8
    for curve in curves:
        keys = items(curve.keyframes)
        frames = np.rint(np.array([kf.time for kf in keys]) * FPS).astype(int) - FIRST
        assert np.array_equal(frames, np.r_[0:5, 9:30])                 # no key in the gap
        interp = {f: kf.interpolation for f, kf in zip(frames, keys)}
        assert interp[4] == ufbx.Interpolation.CONSTANT_PREV            # holds across the gap
        assert interp[3] == interp[9] == ufbx.Interpolation.LINEAR
    vis = layer.find_anim_prop(node, "Visibility").anim_value
    assert [vis.evaluate_real(seconds(f)) for f in range(3, 11)] == [1, 1, 0, 0, 0, 0, 1, 1]
    # the position does not drift towards the next run inside the gap
    tr = uf("evaluate_transform", scene.anim, node, seconds(6.5))
    assert np.allclose(tr.translation, take.xyz[4, 1], atol=1e-4)
    _, lead = translation_curves(scene, layer, "Point_2")               # leading gap (frames 0..2)
    assert np.rint(items(lead[0].keyframes)[0].time * FPS) - FIRST == 3
    p2 = scene.find_node("Point_2")
    assert layer.find_anim_prop(p2, "Visibility").anim_value.evaluate_real(seconds(0)) == 0.0
    # a point without any position: no animation, hidden
    never, curves5 = translation_curves(scene, layer, "Brim_5")
    assert curves5 is None and not never.visible
    # a point without gaps has no visibility curve
    assert layer.find_anim_prop(scene.find_node("Nose_Tip_2"), "Visibility") is None


def test_raw_records_through_ufbx_dom(take, tmp_path):
    path = tmp_path / "dom.fbx"
    export_fbx(take, path)
    scene = load(path, retain_dom=True)
    node = scene.find_node("Chin")
    layer = items(items(scene.anim_stacks)[0].layers)[0]
    curve = layer.find_anim_prop(node, "Lcl Translation").anim_value.curves[0]
    dom = curve.dom_node
    ticks = np.array(items(uf("dom_as_int64_list", dom.find("KeyTime"))))
    frames = np.r_[0:5, 9:30]
    assert np.array_equal(ticks, (FIRST + frames) * (KTIME_PER_SECOND // 60))   # exact ticks
    refs = items(uf("dom_as_int32_list", dom.find("KeyAttrRefCount")))
    flags = items(uf("dom_as_int32_list", dom.find("KeyAttrFlags")))
    assert refs == [4, 1, 20, 1] and flags == [4, 2, 4, 2]                # linear / constant runs
    assert sum(refs) == len(ticks)
    values = np.array(items(uf("dom_as_real_list", dom.find("KeyValueFloat"))))  # ufbx keeps doubles
    assert np.array_equal(values, take.xyz[frames, 1, 0].astype(np.float32))
    gs = scene.dom_root.find("GlobalSettings").find("Properties70")
    props = {items(p.values)[0].value_str: items(p.values) for p in items(gs.children)}
    assert props["TimeSpanStart"][4].value_int == FIRST * (KTIME_PER_SECOND // 60)
    assert props["CustomFrameRate"][4].value_float == FPS
    takes = scene.dom_root.find("Takes")
    assert items(takes.find("Current").values)[0].value_str == "Test Take"


@pytest.mark.parametrize("rate,mode", [(60000 / 1001, 17), (30000 / 1001, 9), (25.0, 10), (59.94, 14),
                                       (240.0, 14)])
def test_frame_rates(tmp_path, rate, mode):
    take = make_take(n_frames=15)
    take.frame_rate = rate
    assert time_mode(rate) == mode
    path = tmp_path / "rate.fbx"
    export_fbx(take, path, options=ExportParameters(include_cameras=False))
    scene = load(path)
    # ufbx reports a standard mode's nominal rate as a float32 (59.94 for 60000/1001 fps); the
    # keys are at the exact times either way
    assert scene.settings.frames_per_second == pytest.approx(rate, rel=1.1e-6)
    assert scene.settings.time_mode == mode
    layer = items(items(scene.anim_stacks)[0].layers)[0]
    _, curves = translation_curves(scene, layer, "Nose_Tip")
    times = np.array([kf.time for kf in items(curves[0].keyframes)])
    assert np.allclose(times, (FIRST + np.arange(14)) / rate, atol=0.6 / KTIME_PER_SECOND)  # last: a gap


# ------------------------------------------------------------------------------ options
def test_point_options(take, tmp_path):
    path = tmp_path / "opts.fbx"
    opts = ExportParameters(selected_only=True, use_stabilized=True, include_cameras=False)
    export_fbx(take, path, options=opts, selection=[1, 4])
    scene = load(path)
    root = scene.find_node("Test Take")
    assert [c.name for c in items(root.children)] == ["Chin", "Brim_4"]
    assert len(scene.cameras) == 0
    tr = uf("evaluate_transform", scene.anim, scene.find_node("Chin"), seconds(2))
    assert np.allclose(tr.translation, take.xyz_stabilized[2, 1], atol=1e-4)
    export_fbx(take, path, options=ExportParameters(include_brim=False), frames=(10, 19))
    scene = load(path)
    root = scene.find_node("Test Take")
    assert [c.name for c in items(root.children)] == NAMES[:4] + ["Cameras"]
    stack = items(scene.anim_stacks)[0]
    assert (stack.time_begin, stack.time_end) == (pytest.approx(seconds(10)), pytest.approx(seconds(19)))


def test_cameras(take, tmp_path):
    path = tmp_path / "cams.fbx"
    export_fbx(take, path, options=ExportParameters(units="cm", up_axis="Z"))
    scene = load(path)
    assert [c.name for c in items(scene.find_node("Cameras").children)] == ["cam0", "cam1", "cam2", "cam3"]
    Q = axis_matrix("Z")
    layer = items(items(scene.anim_stacks)[0].layers)[0]
    for c in range(4):
        node = scene.find_node(f"cam{c}")
        assert node.attrib_type == ufbx.ElementType.CAMERA
        cam = node.camera
        assert cam.focal_length_mm == pytest.approx((1000.0 + 10 * c) * 36.0 / 1280.0)
        assert tuple(cam.resolution) == (1280.0, 720.0)
        fov = np.degrees(2 * np.arctan(640.0 / (1000.0 + 10 * c)))
        assert cam.field_of_view_deg.x == pytest.approx(fov, abs=1e-6)
        animated = layer.find_anim_prop(node, "Lcl Translation") is not None
        assert animated == (c == 1)                                       # only camera 1 moves
        for f in (0, 13, 29):
            tr = uf("evaluate_transform", scene.anim, node, seconds(f))
            centre = camera_centre(take.R[f, c], take.t[f, c]) @ Q.T
            assert np.allclose(np.array(tr.translation) * 10.0, centre, atol=1e-4)
            M = quat_to_matrix(np.array(tr.rotation))
            assert np.allclose(M, Q @ take.R[f, c].T @ CAM_AXES, atol=1e-6)
            # the FBX camera looks along its +X: at the camera's optical axis
            assert np.allclose(M[:, 0], Q @ take.R[f, c][2], atol=1e-6)


def test_c3d_take_exports_points_without_cameras(real_data, tmp_path):
    take = take_from_c3d(real_data / "opensim-core" / "walking2.c3d")
    path = tmp_path / "walk.fbx"
    export_take(take, path)
    scene = load(path)
    assert len(scene.cameras) == 0
    root = scene.find_node("walking2")
    names = [c.name for c in items(root.children)]
    assert names == take.points.labels                                      # no "Cameras" group
    k = int(np.argmax(np.isfinite(take.xyz[..., 0]).sum(0)))
    f = int(np.argmax(np.isfinite(take.xyz[:, k, 0])))
    tr = uf("evaluate_transform", scene.anim, scene.find_node(names[k]),
                                 (take.first_frame_number + f) / take.frame_rate)
    scale = max(1.0, float(np.abs(take.xyz[f, k]).max()) / 1600.0)         # float32 keys
    assert np.allclose(tr.translation, take.xyz[f, k], atol=1e-4 * scale)


# --------------------------------------------------------------------------- binary layout
def walk_records(data: bytes, pos: int, wide: bool, depth: int = 0) -> int:
    """Follow sibling records by their end offsets; return the position after the null record."""
    head = struct.Struct("<QQQ" if wide else "<III")
    null = 25 if wide else 13
    while True:
        end, n_props, props_len = head.unpack_from(data, pos)
        if end == 0:
            assert data[pos:pos + null] == b"\x00" * null
            return pos + null
        name_len = data[pos + head.size]
        start_children = pos + head.size + 1 + name_len + props_len
        assert end >= start_children and n_props >= 0
        if end - start_children > null:                      # children, then a null record
            assert walk_records(data, start_children, wide, depth + 1) == end
        pos = end


@pytest.mark.parametrize("version", [7400, 7500])
def test_binary_layout(take, version):
    data = fbx_bytes(take, version=version)
    assert data[:23] == HEADER_MAGIC and struct.unpack_from("<I", data, 23)[0] == version
    after = walk_records(data, 27, version >= 7500)
    assert data[after:after + 16] == FOOTER_ID and data[after + 16:after + 20] == b"\x00" * 4
    pad_end = len(data) - 16 - 120 - 4
    assert pad_end % 16 == 0 and 1 <= pad_end - (after + 20) <= 16
    assert not any(data[after + 20:pad_end])
    assert struct.unpack_from("<I", data, pad_end)[0] == version
    assert data[-16:] == FOOTER_MAGIC and not any(data[-136:-16])


def test_errors_name_the_file(take, tmp_path):
    with pytest.raises(ValueError, match=r"x.fbx: .*no points to export"):
        export_fbx(take, tmp_path / "x.fbx", points=[])
    with pytest.raises(ValueError, match=r"x.fbx: FBX version must be 7400 or 7500"):
        export_fbx(take, tmp_path / "x.fbx", version=7300)
    with pytest.raises(ValueError, match="does not exist"):
        export_fbx(take, tmp_path / "no" / "x.fbx")
    assert not any(tmp_path.iterdir())


def test_deterministic_given_a_timestamp(take):
    import datetime
    ts = datetime.datetime(2024, 5, 6, 7, 8, 9)
    assert fbx_bytes(take, timestamp=ts, path="a.fbx") == fbx_bytes(take, timestamp=ts, path="a.fbx")


# ------------------------------------------------------------------------------- Blender
def blender_python() -> str | None:
    """A Python interpreter with Blender's ``bpy`` module: ``$CARAPOST_BLENDER_PYTHON`` or the
    throwaway venv ``/tmp/bpyvenv`` (``python3.11 -m venv /tmp/bpyvenv; pip install bpy``)."""
    for cand in (os.environ.get("CARAPOST_BLENDER_PYTHON"), "/tmp/bpyvenv/bin/python"):
        if cand and Path(cand).exists():
            ok = subprocess.run([cand, "-c", "import bpy"], capture_output=True, timeout=120)
            if ok.returncode == 0:
                return cand
    return None


BLENDER_FBX = """
import json, sys
import bpy
path, out, f0, f1 = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
bpy.ops.wm.read_factory_settings(use_empty=True)
res = bpy.ops.import_scene.fbx(filepath=path, anim_offset=0.0)
sc = bpy.context.scene
data = {"result": list(res), "fps": sc.render.fps / sc.render.fps_base, "objects": {}}
objs = list(bpy.data.objects)
for fr in range(f0, f1 + 1):
    sc.frame_set(fr)
    for o in objs:
        d = data["objects"].setdefault(o.name, {"type": o.type, "parent": o.parent.name if o.parent else None,
                                                "pos": [], "rot": []})
        d["pos"].append(list(o.matrix_world.translation))
        d["rot"].append([list(r) for r in o.matrix_world.to_3x3()])
json.dump(data, open(out, "w"))
"""

BLENDER_BVH = """
import json, sys
import bpy
path, out = sys.argv[1], sys.argv[2]
bpy.ops.wm.read_factory_settings(use_empty=True)
res = bpy.ops.import_anim.bvh(filepath=path, update_scene_fps=True, update_scene_duration=True)
sc = bpy.context.scene
arm = [o for o in bpy.data.objects if o.type == "ARMATURE"][0]
data = {"result": list(res), "fps": sc.render.fps / sc.render.fps_base, "bones": {}}
for fr in range(1, int(sys.argv[3]) + 1):
    sc.frame_set(fr)
    for pb in arm.pose.bones:
        data["bones"].setdefault(pb.name, []).append(list(arm.matrix_world @ pb.head))
json.dump(data, open(out, "w"))
"""


def run_blender(script: str, *args: str, tmp_path: Path) -> dict:
    py = blender_python()
    if py is None:
        pytest.skip("no Python with Blender's bpy module (set CARAPOST_BLENDER_PYTHON)")
    code = tmp_path / "blender_script.py"
    code.write_text(script)
    out = tmp_path / "blender.json"
    proc = subprocess.run([py, str(code), *args[:1], str(out), *args[1:]], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(out.read_text())


@pytest.mark.slow
@pytest.mark.parametrize("version,up,units", [(7400, "Y", "mm"), (7500, "Z", "cm")])
def test_blender_imports_the_fbx(take, tmp_path, version, up, units):
    path = tmp_path / "blender.fbx"
    export_fbx(take, path, options=ExportParameters(units=units, up_axis=up), version=version)
    d = run_blender(BLENDER_FBX, str(path), str(FIRST), str(FIRST + take.n_frames - 1), tmp_path=tmp_path)
    assert d["result"] == ["FINISHED"] and d["fps"] == pytest.approx(FPS)
    objs = d["objects"]
    assert {n for n in NAMES} <= set(objs) and objs["Chin"]["type"] == "EMPTY"
    assert objs["Chin"]["parent"] == "Test Take"
    assert {f"cam{c}" for c in range(4)} <= set(objs) and objs["cam1"]["type"] == "CAMERA"
    # Blender: Z up, metres. Both files describe the same world: (x, y, z) mm -> (x, -z, y) / 1000.
    to_blender = axis_matrix("Z") / 1000.0
    for k, name in enumerate(NAMES[:5]):
        pos = np.array(objs[name]["pos"])
        expect = take.xyz[:, k] @ to_blender.T
        ok = np.isfinite(expect).all(-1)
        assert np.allclose(pos[ok], expect[ok], atol=1e-7), name            # 1e-4 mm
    for c in range(4):
        centre = camera_centre(take.R[:, c], take.t[:, c]) @ to_blender.T
        assert np.allclose(np.array(objs[f"cam{c}"]["pos"]), centre, atol=1e-7)
        # A Blender camera looks along its local -Z with +Y up: our optical axis and image up.
        rot = np.array(objs[f"cam{c}"]["rot"])                          # (F, 3, 3), scaled
        rot /= np.linalg.norm(rot, axis=1, keepdims=True)
        Qb = axis_matrix("Z")
        assert np.allclose(-rot[:, :, 2], take.R[:, c, 2] @ Qb.T, atol=1e-5)
        assert np.allclose(rot[:, :, 1], -take.R[:, c, 1] @ Qb.T, atol=1e-5)


@pytest.mark.slow
def test_blender_imports_the_bvh(take, tmp_path):
    path = tmp_path / "blender.bvh"
    export_take(take, path)
    d = run_blender(BLENDER_BVH, str(path), str(take.n_frames), tmp_path=tmp_path)
    assert d["result"] == ["FINISHED"] and d["fps"] == pytest.approx(FPS)
    assert list(d["bones"]) == NAMES
    from carapost.io.export import hold_gaps
    held = hold_gaps(take.xyz, np.isfinite(take.xyz[..., 0])) @ axis_matrix("Z").T
    for k, name in enumerate(NAMES):
        assert np.allclose(np.array(d["bones"][name]), held[:, k], atol=1e-3), name
