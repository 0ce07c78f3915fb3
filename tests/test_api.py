"""The scripting API (``carapost.api``): time conversions, logging, Pico, CaraExport, CaraProcess.

The take is the demo written by ``examples/make_demo_take.py`` (shared with
``tests/test_examples.py`` through the session's base temporary folder).
"""

from __future__ import annotations

import inspect
import logging
import pydoc
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import carapost.api as cp
from carapost.core.camera import camera_centre
from carapost.io.pico import PicoReader

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.fixture(scope="session")
def demo(tmp_path_factory) -> Path:
    folder = tmp_path_factory.getbasetemp() / "api_demo"
    if not (folder / "Example.cara").exists():
        proc = subprocess.run([sys.executable, str(EXAMPLES / "make_demo_take.py"), str(folder)], capture_output=True,
                              text=True, timeout=300)
        assert proc.returncode == 0, proc.stdout + proc.stderr
    return folder


# ------------------------------------------------------------------------------ timecode
@pytest.mark.parametrize("rate, count, tc", [
    (30, 0, "00:00:00:00"), (30, 1799, "00:00:59:29"), (30, 1800, "00:01:00:00"), (25, 90000, "01:00:00:00"),
    (60, 216000, "01:00:00:00"), (24, 24 * 86400 - 1, "23:59:59:23"),
    # drop-frame (SMPTE 12M): 2 labels skipped per minute at 29.97, 4 at 59.94, except every 10th minute
    (29.97, 1799, "00:00:59;29"), (29.97, 1800, "00:01:00;02"), (29.97, 17981, "00:09:59;29"),
    (29.97, 17982, "00:10:00;00"), (29.97, 107892, "01:00:00;00"), (30000 / 1001, 1800, "00:01:00;02"),
    (59.94, 3599, "00:00:59;59"), (59.94, 3600, "00:01:00;04"), (59.94, 35964, "00:10:00;00"),
])
def test_timecode_known_values(rate, count, tc):
    assert cp.count_to_timecode(count, rate) == tc
    assert cp.timecode_to_count(tc, rate) == count


@pytest.mark.parametrize("rate, day", [(29.97, 2589408), (59.94, 5178816), (25.0, 2160000), (23.976, 2073600)])
def test_timecode_round_trip_over_a_day(rate, day):
    counts = np.arange(0, day, 997)
    codes = cp.count_to_timecode(counts, rate)
    assert len(set(codes)) == len(codes)
    assert [cp.timecode_to_count(c, rate) for c in codes] == counts.tolist()
    assert cp.count_to_timecode(day, rate) == cp.count_to_timecode(0, rate)     # 24-hour wrap
    # Labels increase with time (sorting the strings sorts the frames).
    assert codes == sorted(codes)


def test_timecode_rules():
    assert cp.is_drop_frame_rate(29.97) and cp.is_drop_frame_rate(60000 / 1001) and not cp.is_drop_frame_rate(30)
    assert cp.nominal_rate(23.976) == 24 and cp.nominal_rate(59.94) == 60
    assert cp.count_to_timecode(1800, 29.97, drop_frame=False) == "00:01:00:00"
    assert cp.timecode_to_count("00:01:00:02", 29.97) == 1800          # ':' accepted for drop-frame
    for bad in ("00:01:00;00", "00:01:00;01"):                          # labels drop-frame skips
        with pytest.raises(cp.TimecodeError, match="drop-frame"):
            cp.timecode_to_count(bad, 29.97)
    assert cp.timecode_to_count("00:10:00;00", 29.97) == 17982          # ...but not at a 10th minute
    for bad in ("1:2:3", "24:00:00:00", "00:60:00:00", "00:00:00:30", 12):
        with pytest.raises(cp.TimecodeError):
            cp.timecode_to_count(bad, 30)
    with pytest.raises(cp.TimecodeError, match="positive"):
        cp.TimeBase(0)
    with pytest.raises(cp.TimecodeError, match="29.97 or 59.94"):
        cp.count_to_timecode(5, 25, drop_frame=True)


def test_timebase():
    tb = cp.TimeBase(29.97, "00:59:59:28", first_frame_number=100)
    assert tb.drop_frame and tb.start_timecode == "00:59:59;28"
    assert tb.frame_to_timecode(2) == "01:00:00;00"
    assert tb.frame_to_timecode([0, 1, 2]) == ["00:59:59;28", "00:59:59;29", "01:00:00;00"]
    assert tb.timecode_to_frame("01:00:00;00") == 2
    np.testing.assert_array_equal(tb.timecode_to_frame(["01:00:00;00", "00:59:59;27"]), [2, -1])
    assert tb.frame_to_number(2) == 102 and tb.number_to_frame(102) == 2
    np.testing.assert_array_equal(tb.frame_to_number(np.array([0, 5])), [100, 105])
    assert tb.number_to_timecode(102) == "01:00:00;00" and tb.timecode_to_number("01:00:00;00") == 102
    assert tb.frame_to_seconds(2997) == pytest.approx(100.0)
    with pytest.raises(cp.TimecodeError, match="whole"):
        tb.frame_to_timecode(1.5)
    # A take running through midnight.
    late = cp.TimeBase(25, "23:59:59:24")
    assert late.frame_to_timecode(1) == "00:00:00:00" and late.timecode_to_frame("00:00:00:00") == 1
    assert late.timecode_to_frame("23:59:59:23") == -1


# ------------------------------------------------------------------------------- logging
def test_log_verbosity(caplog):
    logger = logging.getLogger("carapost")
    old = logger.level
    try:
        cp.set_log_verbosity("warning")
        assert cp.get_log_verbosity() == "warning" and logger.level == logging.WARNING
        with caplog.at_level(logging.NOTSET, logger="carapost.io"):
            logging.getLogger("carapost.io.pico").info("hidden")
            logging.getLogger("carapost.io.pico").warning("shown")
        assert [r.getMessage() for r in caplog.records] == ["shown"]
        cp.set_log_verbosity("DEBUG")
        assert cp.get_log_verbosity() == "debug"
        cp.set_log_verbosity("off")
        assert not logger.isEnabledFor(logging.CRITICAL)
        cp.set_log_verbosity(logging.INFO)
        assert cp.get_log_verbosity() == "info"
        for bad in ("loud", -1, True, 2.5):
            with pytest.raises(ValueError, match="verbosity"):
                cp.set_log_verbosity(bad)
    finally:
        logger.setLevel(old)


def test_log_handler_for_scripts():
    code = ("import logging, carapost.api as cp; cp.set_log_verbosity('info'); cp.set_log_verbosity('info');"
            "logging.getLogger('carapost.x').info('hello'); logging.getLogger('carapost').debug('nope')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr == "INFO carapost: hello\n"


# ---------------------------------------------------------------------------------- Pico
def test_pico(demo):
    path = demo / "Example_2.pico"
    with cp.Pico(path) as pico, PicoReader(path) as ref:
        assert (pico.n_frames, pico.width, pico.height, pico.frame_rate) == (4, 640, 360, 60.0)
        assert pico.channel == 2 and pico.camera_name == ref.meta.camera_name != ""
        assert pico.logger_name == "SynthLogger" and pico.start_timecode == "00:00:00:00" and pico.rotation == 0
        assert pico.metadata == ref.meta and pico.metadata is not pico.metadata   # copies
        assert pico.blob_parameters()["Black Min Radius"] == 4.0
        info = pico.info()
        assert info["channel"] == 2 and info["frames"] == 4 and info["codec"] == ref.codec
        np.testing.assert_array_equal(pico.frame(3), ref.read(3))
        np.testing.assert_array_equal(pico[1], ref.read(1))
        frames = list(pico)
        assert len(frames) == len(pico) == 4 and frames[0].shape == (360, 640) and frames[0].dtype == np.uint8
        assert len(list(pico.frames(1, 2))) == 2
        assert [p.name for p in pico.take_files()] == [f"Example_{c}.pico" for c in range(4)]
        assert pico.verify() == [] and pico.warnings == []
        assert pico.time.frame_to_timecode(3) == "00:00:00:03"
        with pytest.raises(IndexError):
            pico.frame(4)
        with pytest.raises(IndexError):
            list(pico.frames(2, 7))
        assert "channel=2" in repr(pico)
    with pytest.raises(cp.PicoError, match="nothing.pico"):
        cp.Pico(demo / "nothing.pico")


# ---------------------------------------------------------------------------- CaraExport
def test_cara_export_reads_the_take(demo):
    exp = cp.CaraExport(demo / "Example.cara")
    take = exp.take
    F, P, C = exp.n_frames, exp.n_points, exp.n_cameras
    assert (F, C) == (4, 4) and P == take.n_points > 18 and exp.frame_rate == 60.0
    assert exp.xyz.shape == (F, P, 3) and exp.reconstruction.shape == (F, P)
    np.testing.assert_array_equal(exp.xyz, take.xyz)
    np.testing.assert_array_equal(np.sort(np.concatenate([exp.face_points, exp.brim_points])), np.arange(P))
    assert (exp.point_kinds[exp.brim_points] == cp.PointKind.BRIM).all()
    names = exp.point_names
    infos = exp.points()
    nose = next(i for i in infos if i.label)                        # a named seed
    assert len(set(names)) == P and names[exp.point_index(nose.label)] == nose.label
    assert nose.name == nose.label and nose.kind == "face" and nose.brim_index == -1
    b = infos[int(exp.brim_points[3])]
    assert b.kind == "brim" and b.name == f"Brim_{b.id}" and b.label == "" and b.brim_index == exp.brim_indices[b.index]
    np.testing.assert_array_equal(exp.trajectory(nose.label), take.xyz[:, nose.index])
    np.testing.assert_array_equal(exp.positions(2), take.xyz[2])
    np.testing.assert_array_equal(exp.tracks_2d(1), take.obs_xy[:, :, 1])
    np.testing.assert_allclose(exp.camera_positions, camera_centre(take.R, take.t))
    R, t = exp.camera_poses(1)
    np.testing.assert_array_equal(R, take.R[1])
    assert exp.intrinsics(0) == take.cameras[0].intrinsics and exp.camera_names[0] == take.cameras[0].name
    assert exp.source_path(0) == demo / "Example_0.pico"
    assert exp.sticks.shape == (0, 2) and exp.brim is take.brim and len(exp.brim) == 18
    dets = exp.detections(0, 0)
    assert set(dets) >= {"x", "y", "major", "minor", "polarity", "score"} and exp.n_detections(0, 0) == len(dets["x"])
    assert exp.detected_frames(3).tolist() == [0, 1, 2, 3]
    # Multi-view samples really are seen by two or more cameras.
    multi = exp.reconstruction == cp.Recon.MULTI_VIEW
    assert (np.isfinite(exp.observations[..., 0]).sum(-1)[multi] >= 2).all()
    s = exp.summary()
    assert s["face_points"] == len(exp.face_points) and s["brim"] == "v2.0" and s["labelled"] >= 2


def test_cara_export_is_read_only(demo):
    exp = cp.CaraExport(demo / "Example.cara")
    for arr in (exp.xyz, exp.reconstruction, exp.tracks_2d(0), exp.observations, exp.R, exp.point_ids,
                exp.trajectory(0), exp.positions(0)):
        with pytest.raises(ValueError, match="read-only"):
            arr[...] = 0
    with pytest.raises(KeyError, match="Nobody"):
        exp.point_index("Nobody")
    with pytest.raises(KeyError):
        exp.point_index(exp.n_points)
    with pytest.raises(IndexError):
        exp.camera_poses(exp.n_frames)
    with pytest.raises(IndexError):
        exp.tracks_2d(4)


def test_cara_export_time(demo):
    exp = cp.CaraExport(demo / "Example.cara")
    exp.take.start_timecode = "10:00:00:00"      # (in memory only)
    exp.take.first_frame_number = 1000
    assert exp.frame_to_timecode(61) == "10:00:01:01" and exp.frame_to_number(61) == 1061
    assert exp.timecode_to_frame("10:00:01:01") == 61 and exp.number_to_frame(1061) == 61
    assert exp.number_to_timecode(1001) == "10:00:00:01" and exp.timecode_to_number("10:00:00:02") == 1002
    assert not exp.time.drop_frame
    exp.take.frame_rate = 30000 / 1001
    assert exp.time.drop_frame and exp.frame_to_timecode(1800) == "10:01:00;02"


def test_cara_export_export(demo, tmp_path):
    exp = cp.CaraExport(demo / "Example.cara")
    out = exp.export(tmp_path / "take.c3d", properties={"Include Brim Points": False})
    back = cp.CaraExport(out)                      # a C3D opens as a take too
    face = exp.face_points
    assert back.n_points == len(face) and back.point_names == [exp.point_names[p] for p in face]
    np.testing.assert_allclose(back.xyz, exp.xyz[:, face], atol=1e-3, equal_nan=True)
    assert exp.take.params.export.include_brim                       # the take is not changed
    exp.export(tmp_path / "cm.csv", properties={"units": "cm"}, points=[int(face[0])])
    assert (tmp_path / "cm.csv").stat().st_size > 0
    with pytest.raises(ValueError, match="Units"):
        exp.export(tmp_path / "x.fbx", properties={"Units": "furlong"})
    with pytest.raises(ValueError, match="Colour"):
        exp.export(tmp_path / "x.fbx", properties={"Colour": 1})
    with pytest.raises(ValueError, match="x.doc"):
        exp.export(tmp_path / "x.doc")
    with pytest.raises(ValueError, match="missing.cara"):
        cp.CaraExport(tmp_path / "missing.cara")


# ---------------------------------------------------------------------------- CaraProcess
def test_process_from_pico_and_detect(demo, tmp_path):
    with cp.CaraProcess.from_pico(demo / "Example_3.pico") as take:   # any channel stands for the take
        assert (take.name, take.n_cameras, take.n_frames, take.path) == ("Example", 4, 4, None)
        ref = cp.CaraExport(demo / "Example_b.cara")
        assert take.take.cameras[2].intrinsics == ref.take.cameras[2].intrinsics    # Example.xcp found
        assert np.isfinite(take.take.R).all()
        assert not take.modified and take.history() == []
        take.set_property("Blob Parameters", "Black Min Radius", 2)
        assert take.detect_blobs([1, 3], 2, 3) is True
        for c in range(4):
            assert take.data.detected_frames(c).tolist() == ([2, 3] if c in (1, 3) else [])
        np.testing.assert_array_equal(take.data.detections(3, 2)["y"], ref.detections(3, 2)["y"])
        assert take.n_detections(1, 2) == ref.n_detections(1, 2) > 20
        for bad, match in (([5], "sensor 5"), (None, "0..3")):
            with pytest.raises(ValueError, match=match):
                take.detect_blobs(bad, 0, 4 if bad is None else 0)
        with pytest.raises(ValueError, match="start <= end"):
            take.detect_blobs(None, 3, 2)
        assert take.modified and len(take.history()) == 2
        saved = take.save(tmp_path / "Example_b.cara")
        assert not take.modified and take.path == saved
    with cp.CaraProcess(saved) as again:
        assert again.get_property("blobs", "black min radius") == 2.0
        assert again.n_detections() == take.n_detections() and again.missing_sources == []
    # Cancelling keeps what was done and says so.
    with cp.CaraProcess(demo / "Example_0.pico") as take:
        assert take.detect_blobs([0], 0, 3, cancel=lambda: True, workers=1) is False


def test_process_properties_and_undo(demo):
    with cp.CaraProcess.from_pico(demo / "Example_0.pico", find=False) as take:
        assert not np.isfinite(take.take.R).any()                   # no calibration looked for
        assert take.property_groups()[2] == "Blob Parameters"
        props = take.properties()
        assert props == cp.default_properties()                     # the capture's parameters are the defaults
        assert take.get_property("Tracking Parameters", "Max Allowed 3D Point Error") == 5.0
        text = take.set_property("Tracking Parameters", "Max Allowed 3D Point Error", 7)
        assert text == "Tracking Parameters: Max Allowed 3D Point Error = 7"
        assert take.get_property("tracking", "max_allowed_3d_point_error") == 7.0
        assert take.properties("Tracking Parameters")["Max Allowed 3D Point Error"] == 7.0
        info = take.property_info("Tracking Parameters", "Max Allowed 3D Point Error")
        assert (info["value"], info["default"], info["unit"], info["min"], info["max"]) == (7.0, 5.0, "mm", 0, 1000)
        take.undo()
        assert take.get_property("Tracking Parameters", "Max Allowed 3D Point Error") == 5.0
        assert take.can_redo and not take.can_undo
        take.redo()
        assert take.get_property("Tracking Parameters", "Max Allowed 3D Point Error") == 7.0
        # Rejected values leave the take and its history unchanged.
        for group, name, value, match in (("Blob Parameters", "Black Threshold", 1.5, "range 0 to 1"),
                                          ("Blob Parameters", "Find Black Blobs", "maybe", "True or False"),
                                          ("Export", "Units", "inch", "one of"),
                                          ("Nothing", "Black Threshold", 1, "no property group"),
                                          ("Blob Parameters", "Blackness", 1, "no property named")):
            with pytest.raises(ValueError, match=match):
                take.set_property(group, name, value)
        with pytest.raises(ValueError, match="no property named"):
            take.get_property("Blob Parameters", "Blackness")
        assert len(take.history()) == 1
        take.apply_preset("sparse")
        assert take.get_property("Initialize 3D Parameters", "Max Allowed Depth") == 60.0
        take.restore_properties()
        assert take.properties() == cp.default_properties()
        take.set_active_range(1, 2)
        assert take.active_range == (1, 2)
        with pytest.raises(ValueError):
            take.set_active_range(2, 9)
        take.clear_history()
        assert take.history() == [] and not take.can_undo
        with pytest.raises(IndexError):
            take.undo()
        with pytest.raises(ValueError, match="no file name"):
            take.save()
        take.current_frame = 3
        assert take.current_frame == 3
        with pytest.raises(ValueError, match="outside"):
            take.current_frame = 4


def test_process_edits_on_a_solved_take(demo, tmp_path):
    shutil.copy(demo / "Example.cara", tmp_path / "Example.cara")
    with cp.CaraProcess(tmp_path / "Example.cara") as take:
        before = take.data.xyz.copy()
        infos = take.data.points()
        named = next(i.name for i in infos if i.label)
        p, generated = next((i.index, i.name) for i in infos if i.kind == "face" and not i.label)
        assert take.assign_label(p, "Chin") == f"Label {generated} as Chin"
        assert take.data.point_names[p] == "Chin" and "Chin" in take.data.label_list
        n = take.n_points
        take.delete_points(["Chin", named])
        assert take.n_points == n - 2 and named not in take.data.point_names
        take.undo()
        take.undo()
        assert take.n_points == n and take.data.point_names[p] == generated
        np.testing.assert_array_equal(take.data.xyz, before)
        with pytest.raises(ValueError, match="Nobody"):
            take.delete_points("Nobody")
        # Gap filling reports; stabilizing on brim dots (rigid) gives a tiny error.
        rep = take.interpolate_gaps()
        assert {"filled", "unfilled"} <= set(rep)
        dots = take.data.brim_indices
        brim = [int(np.flatnonzero(dots == d)[0]) for d in (0, 6, 12, 16)]    # not collinear
        rep = take.stabilize(brim, assisted=False, base_frame=0)
        assert rep["error_mm"] < 1e-6
        assert np.isfinite(take.data.xyz_stabilized[:, brim]).all()
        # Sticks.
        face = take.data.face_points
        take.create_stick(int(face[0]), take.data.point_names[face[1]])
        assert take.data.sticks.tolist() == [[face[0], face[1]]]
        take.save()
    saved = cp.CaraExport(tmp_path / "Example.cara")
    assert np.isfinite(saved.xyz_stabilized[:, brim]).all() and saved.sticks.shape == (1, 2)


def test_process_target_tracker(demo):
    """Clear a point's tracks, key it again in one camera and target-track it: the template
    tracker finds it again close to where the blob tracking had it."""
    with cp.CaraProcess(demo / "Example.cara") as take:
        tracks = take.data.tracks_2d(0).copy()                       # (F, P, 2)
        seen = np.isfinite(tracks[..., 0]).all(0)
        p = int(next(q for q in take.data.face_points if seen[q]))    # tracked in every frame of camera 0
        take.clear_tracked_points(p)
        assert not np.isfinite(take.data.observations[:, p]).any()
        text = take.add_target_track(0, 0, tracks[0, p])
        q = take.n_points - 1
        assert text.startswith("Add Target Track") and take.data.observation_sources[0, q, 0] == cp.ObsSource.KEYFRAME
        rep = take.target_track([q], 0)
        assert rep["tracked"] == {(q, 0): 3} and not rep["cancelled"]
        found = take.data.tracks_2d(0)[:, q]
        assert (take.data.observation_sources[1:, q, 0] == cp.ObsSource.TARGET).all()
        assert np.abs(found - tracks[:, p]).max() < 1.0                  # px, against the blob centres
        assert take.add_keyframes(q, 2).startswith("Add Keyframe")
        assert take.data.observation_sources[2, q, 0] == cp.ObsSource.KEYFRAME
        assert take.add_keyframes(q, 0) == ""                          # already a keyframe: nothing to do
        take.undo()
        take.undo()
        assert not np.isfinite(take.data.tracks_2d(0)[1:, q]).any()
        with pytest.raises(ValueError, match="finite"):
            take.add_target_track(0, 0, [np.nan, 1.0])


def test_process_pipeline_and_tracking(demo, tmp_path):
    with cp.CaraProcess(demo / "Example_b.cara") as take:
        take.import_brim(demo / "Example_brim.json")
        assert take.n_points == 18 and take.data.brim.name == "v2.0"
        summary = take.run_pipeline(seeds=demo / "Example_seeds.json", detect="none")
        assert summary["points"] >= 5
        face = take.data.face_points
        assert np.isfinite(take.data.xyz[0, face]).all(-1).sum() == summary["points"]
        text = take.track(0, n_frames=1)
        assert text.startswith("Track Forwards [Single Frame]: 1 frames")
        assert np.isfinite(take.data.xyz[1, face]).all(-1).any() and not np.isfinite(take.data.xyz[2, face]).any()
        take.undo()
        assert not np.isfinite(take.data.xyz[1, face]).any()
        with pytest.raises(ValueError, match="direction"):
            take.track(0, direction="sideways")
        with pytest.raises(ValueError, match="no point has a 3D position"):
            take.track(3, direction="backwards", points=face.tolist())
        with pytest.raises(ValueError, match="PipelineOptions|seeds"):
            take.run_pipeline()


def test_process_open_errors(tmp_path):
    with pytest.raises(ValueError, match="missing.cara"):
        cp.CaraProcess(tmp_path / "missing.cara")
    with pytest.raises(ValueError, match="video.mp4"):
        cp.CaraProcess(tmp_path / "video.mp4")
    with pytest.raises(ValueError, match="Nothing"):
        cp.CaraProcess.from_pico(tmp_path / "Nothing_0.pico")
    with pytest.raises(ValueError, match="no camera sources"):
        cp.CaraProcess.from_sources([])


def test_help_documents_the_api():
    """``help()`` on every public object gives its summary and (for the main classes) examples."""
    for name in cp.__all__:
        obj = getattr(cp, name)
        if isinstance(obj, (dict, tuple)) or not getattr(obj, "__module__", "").startswith("carapost.api"):
            continue            # constants, and the model's enums re-exported for convenience
        assert obj.__doc__ and len(obj.__doc__.strip()) > 20, name
    for cls in (cp.CaraProcess, cp.CaraExport, cp.Pico, cp.TimeBase):
        assert "Examples" in cls.__doc__
        for attr, member in inspect.getmembers(cls):          # methods and properties, inherited too
            if attr.startswith("_") or isinstance(member, tuple):
                continue
            doc = member.fget.__doc__ if isinstance(member, property) else member.__doc__
            assert doc, f"{cls.__name__}.{attr}"
    text = pydoc.render_doc(cp.CaraProcess.detect_blobs, renderer=pydoc.plaintext)
    assert "sensors" in text and "start_frame" in text and "Returns" in text
    for attr in ("track", "initialize_3d", "interpolate_gaps", "solve_brim"):          # inherited steps
        assert getattr(cp.CaraProcess, attr).__doc__


def test_process_import_calibration(demo, tmp_path):
    from carapost.io.calibration import load_calibration

    shutil.copy(demo / "Example.cara", tmp_path / "Example.cara")
    xcp = next(demo.glob("*.xcp"))
    with cp.CaraProcess(tmp_path / "Example.cara") as take:
        R0 = take.take.R.copy()
        take.take.R[:] = np.nan                        # as if the take had been imported uncalibrated
        text = take.import_calibration(xcp)
        assert text.startswith("Import XCP")
        R, _ = load_calibration(xcp).poses(take.n_frames)
        np.testing.assert_allclose(take.take.R, R)
        take.undo()
        assert np.isnan(take.take.R).all()
        with pytest.raises(ValueError, match="missing.xcp"):
            take.import_calibration(tmp_path / "missing.xcp")
        take.take.R[:] = R0
