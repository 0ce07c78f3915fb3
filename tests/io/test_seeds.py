"""Seeds files: round trip, validation messages, snapping to detections."""

import json
import math

import numpy as np
import pytest

from carapost.io.seeds import (BrimSeed, FaceSeed, Seeds, SeedsFileError, read_seeds, seeds_from_dict, snap_seeds,
                               write_seeds)
from carapost.synth import SynthConfig, generate_take
from carapost.synth.seeds import seeds_for

EXAMPLE = {
    "frame": 3,
    "brim": [{"brim_index": 3, "xy": {"0": [612.4, 88.1], "1": [610.0, 140.25]}}],
    "face": [{"name": "Nose_Tip", "xy": {"0": [640.2, 401.7], "2": [655.0, 398.5]}},
             {"xy": {"1": [100.0, 200.0], "3": [110.0, 210.0]}}],
}


def test_round_trip_and_structure(tmp_path):
    path = tmp_path / "take_seeds.json"
    write_seeds(path, EXAMPLE)
    s = read_seeds(path)
    assert s.frame == 3
    assert s.brim == (BrimSeed(3, {0: (612.4, 88.1), 1: (610.0, 140.25)}),)
    assert s.face[0] == FaceSeed("Nose_Tip", {0: (640.2, 401.7), 2: (655.0, 398.5)})
    assert s.face[1].name is None
    assert s.to_dict() == EXAMPLE  # numbers written exactly; unnamed entries stay unnamed
    assert json.loads(path.read_text())["face"][0]["xy"]["2"] == [655.0, 398.5]
    # atomic write: nothing but the file in the folder
    assert [p.name for p in tmp_path.iterdir()] == ["take_seeds.json"]


def test_reads_the_synthetic_generator_output(tmp_path):
    take = generate_take(SynthConfig(n_markers=35, n_frames=1))
    d = seeds_for(take, 0)
    path = tmp_path / "s.json"
    path.write_text(json.dumps(d))
    s = read_seeds(path)
    assert len(s.face) == len(d["face"]) and len(s.brim) == len(d["brim"])
    assert s.face[0].name == d["face"][0]["name"]
    c0 = sorted(s.face[0].xy)[0]
    assert s.face[0].xy[c0] == tuple(d["face"][0]["xy"][str(c0)])


def test_defaults_and_unknown_keys():
    s = seeds_from_dict({"face": [{"xy": {"0": [1, 2], "1": [3, 4]}, "comment": "x"}], "version": 2})
    assert s.frame == 0 and s.brim == () and len(s.face) == 1


@pytest.mark.parametrize("data, fragment", [
    ([], "top level must be a JSON object"),
    ({"frame": -1}, '"frame" must be a non-negative whole number'),
    ({"frame": 1.5}, '"frame" must be a non-negative whole number'),
    ({"brim": {}}, '"brim" must be a list'),
    ({"brim": [{"xy": {"0": [1, 2]}}]}, 'brim[0]: missing "brim_index"'),
    ({"brim": [{"brim_index": "3", "xy": {"0": [1, 2]}}]}, 'brim[0]: "brim_index" must be'),
    ({"brim": [{"brim_index": 1, "xy": {"0": [1, 2]}}, {"brim_index": 1, "xy": {"0": [1, 2]}}]},
     "brim[1]: brim dot 1 is already seeded by brim[0]"),
    ({"face": [{"name": "A"}]}, 'face[0] ("A"): missing "xy"'),
    ({"face": [{"name": "A", "xy": {}}]}, 'face[0] ("A"): "xy" names no camera'),
    ({"face": [{"name": "A", "xy": {"left": [1, 2]}}]}, "camera key 'left' is not a channel number"),
    ({"face": [{"name": "A", "xy": {"-1": [1, 2]}}]}, "camera key '-1' is not a channel number"),
    ({"face": [{"name": "A", "xy": {"0": [1]}}]}, "camera 0: position must be [x, y]"),
    ({"face": [{"name": "A", "xy": {"0": ["1", 2]}}]}, "camera 0: position must be [x, y]"),
    ({"face": [{"name": "A", "xy": {"0": [math.nan, 2]}}]}, "camera 0: position must be finite"),
    ({"face": [{"name": 5, "xy": {"0": [1, 2]}}]}, '"name" must be a non-empty string'),
    ({"face": [{"name": "A", "xy": {"0": [1, 2]}}, {"name": "A", "xy": {"0": [1, 2]}}]},
     "the name is already used by face[0]"),
])
def test_validation_messages_name_file_and_entry(data, fragment):
    with pytest.raises(SeedsFileError) as e:
        seeds_from_dict(data, source="take_seeds.json")
    msg = str(e.value)
    assert msg.startswith("take_seeds.json: ")
    assert fragment in msg


def test_read_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.json"
    with pytest.raises(SeedsFileError, match="nope.json: cannot read"):
        read_seeds(missing)
    bad = tmp_path / "bad.json"
    bad.write_text('{"frame": 0,\n "face": [}')
    with pytest.raises(SeedsFileError, match=r"bad.json: not valid JSON: .* line 2"):
        read_seeds(bad)
    binary = tmp_path / "bin.json"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(SeedsFileError, match="bin.json: not UTF-8"):
        read_seeds(binary)


def test_write_rejects_invalid_and_unwritable(tmp_path):
    with pytest.raises(SeedsFileError, match="s.json: face"):
        write_seeds(tmp_path / "s.json", {"face": [{"xy": {"0": [1, "x"]}}]})
    assert not (tmp_path / "s.json").exists()
    with pytest.raises(SeedsFileError, match="cannot write"):
        write_seeds(tmp_path / "no_such_dir" / "s.json", EXAMPLE)


def _dets():
    return [np.array([[612.0, 88.0], [640.0, 401.0], [700.0, 500.0]]),
            np.array([[610.5, 140.0], [100.5, 200.5]]),
            np.array([[655.3, 398.2], [900.0, 900.0]]),
            np.array([[111.0, 209.0], [400.0, 400.0]])]


def test_snap_exact_and_named():
    s = snap_seeds(EXAMPLE, _dets(), radius_px=3.0)
    assert s.brim == {3: {0: 0, 1: 0}}
    assert s.face == [("Nose_Tip", {0: 1, 2: 0}), (None, {1: 1, 3: 0})]
    assert s.face_seeds == [{0: 1, 2: 0}, {1: 1, 3: 0}]
    assert s.face_names == ["Nose_Tip", None]
    assert s.messages == [] and s.misses == []


def test_snap_reports_misses_with_distance_and_drops_one_camera_faces():
    dets = _dets()
    dets[2] = np.array([[660.2, 398.5]])  # Nose_Tip's camera-2 detection is 5.2 px away
    s = snap_seeds(EXAMPLE, dets, radius_px=3.0)
    assert len(s.misses) == 1
    m = s.misses[0]
    assert (m.kind, m.entry, m.label, m.camera) == ("face", 0, "Nose_Tip", 2)
    assert m.distance == pytest.approx(5.2, abs=1e-9)
    assert any("Nose_Tip: camera 2: no detection within 3 px" in x and "5.2 px away" in x for x in s.messages)
    # left with one camera: dropped, and said so
    assert [n for n, _ in s.face] == [None]
    assert any("Nose_Tip: matched in 1 camera(s)" in x for x in s.messages)


def test_snap_conflicts_and_missing_cameras():
    seeds = {"face": [{"name": "A", "xy": {"0": [10, 10], "1": [50, 50], "5": [1, 1]}},
                      {"name": "B", "xy": {"0": [11, 11], "1": [80, 80]}}]}
    dets = [np.array([[10.5, 10.5]]), np.array([[50, 50], [80, 80]]), np.zeros((0, 2))]
    s = snap_seeds(seeds, dets)
    assert any("camera 5 does not exist" in x for x in s.messages)
    assert any("detection 0 is the nearest to several seeds (A, B)" in x for x in s.messages)
    assert s.face == []  # both lost camera 0, leaving one camera each
    empty = snap_seeds({"face": [{"xy": {"2": [1, 1], "1": [50, 50]}}]}, dets)
    assert empty.misses[0].camera == 2 and math.isinf(empty.misses[0].distance)
    assert "no detections" in empty.messages[0]


def test_snap_accepts_detection_tables_and_checks_radius():
    dets = [{"x": d[:, 0], "y": d[:, 1]} for d in _dets()]
    assert snap_seeds(Seeds(face=(FaceSeed("N", {0: (640.2, 401.7), 2: (655.0, 398.5)}),)), dets).face == [
        ("N", {0: 1, 2: 0})]
    with pytest.raises(ValueError, match="radius_px must be positive"):
        snap_seeds(EXAMPLE, dets, radius_px=0)
