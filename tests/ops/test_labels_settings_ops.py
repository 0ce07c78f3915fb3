import numpy as np
import pytest

from carapost.model.params import Parameters
from carapost.ops.labels import (
    assign_label,
    clear_all_labels,
    create_stick,
    create_stick_mesh,
    delete_labels,
    delete_sticks,
    edit_stick_colour,
    import_labels_from_text,
    unlabel_points,
)
from carapost.ops.session import Session
from carapost.ops.settings import (
    apply_preset,
    distance_between_points,
    increment_image_sequence_offset,
    point_information,
    restore_properties,
    rotate_sensors,
    set_active_range,
    set_caddies,
    set_property,
)


@pytest.fixture
def sess(truth_take, tiny_synth):
    take, _ = truth_take
    take.add_points(12)
    take.xyz[:] = tiny_synth.truth.xyz[:, :12]
    return Session(take)


def test_labels(sess, tmp_path, undo_check):
    s = sess
    f = tmp_path / "labels.txt"
    f.write_text("Nose_Tip Chin\nBrow_L\n")
    undo_check(s, import_labels_from_text(s.take, f))
    undo_check(s, import_labels_from_text(s.take, f))
    assert s.take.labels == ["Nose_Tip", "Chin", "Brow_L", "Nose_Tip - Copy", "Chin - Copy", "Brow_L - Copy"]
    undo_check(s, assign_label(s.take, 0, "Nose_Tip"))
    undo_check(s, assign_label(s.take, 1, "Nose_Tip"))  # moves the label
    assert s.take.points.labels[:2] == ["", "Nose_Tip"]
    undo_check(s, assign_label(s.take, 2, "New_One"))
    assert "New_One" in s.take.labels
    with pytest.raises(ValueError, match="spaces"):
        assign_label(s.take, 2, "a b")
    undo_check(s, unlabel_points(s.take, [1]))
    assert s.take.points.labels[1] == ""
    undo_check(s, delete_labels(s.take, ["New_One"]))
    assert s.take.points.labels[2] == "" and "New_One" not in s.take.labels
    undo_check(s, clear_all_labels(s.take))
    assert s.take.labels == []


def test_sticks(sess, undo_check):
    s = sess
    undo_check(s, create_stick(s.take, 0, 1))
    with pytest.raises(ValueError, match="already joined"):
        create_stick(s.take, 1, 0)
    undo_check(s, create_stick_mesh(s.take, 0))
    n = len(s.take.sticks)
    assert n > 12
    undo_check(s, edit_stick_colour(s.take, [0, 1], (255, 0, 0)))
    assert s.take.stick_colours[1].tolist() == [255, 0, 0]
    undo_check(s, delete_sticks(s.take, [0]))
    assert len(s.take.sticks) == n - 1
    ids_removed = s.take.points.ids[3]
    s.take.remove_points([3])
    assert not np.isin(s.take.sticks, ids_removed).any()


def test_settings(sess, undo_check):
    s = sess
    undo_check(s, set_property(s.take, "Tracking Parameters", "Max Allowed 3D Point Error", 7))
    assert s.take.params.tracking.max_allowed_3d_point_error == 7
    with pytest.raises(ValueError, match="range"):
        set_property(s.take, "tracking", "patch_match_threshold", 2)
    undo_check(s, apply_preset(s.take, "sparse"))
    assert s.take.params.init3d.max_allowed_depth == 60
    undo_check(s, restore_properties(s.take))
    assert s.take.params == Parameters()
    undo_check(s, set_active_range(s.take, 1, 3))
    assert s.take.active_range == (1, 3)
    with pytest.raises(ValueError, match="within"):
        set_active_range(s.take, 3, 99)
    undo_check(s, rotate_sensors(s.take, [0, 2]))
    assert s.take.cameras[2].rotation == 90
    with pytest.raises(ValueError, match="2D information"):
        increment_image_sequence_offset(s.take, [0])


def test_caddies(sess, undo_check):
    s = sess
    undo_check(s, set_caddies(s.take, []))           # cameras around a room: no caddies
    assert s.take.caddies == []
    undo_check(s, set_caddies(s.take, [(0, 2), (1, 3)]))
    assert s.take.caddies == [(0, 2), (1, 3)]
    for bad in ([(0, 4)], [(1, 1)], [(0, 1), (1, 2)]):
        with pytest.raises(ValueError, match="caddies"):
            set_caddies(s.take, bad)
    assert s.take.caddies == [(0, 2), (1, 3)]


def test_offset_on_fresh_camera(sess, undo_check):
    s = sess
    s.take.detections[1] = type(s.take.detections[1]).empty(s.take.n_frames)
    undo_check(s, increment_image_sequence_offset(s.take, [1]))
    assert s.take.cameras[1].frame_offset == 1


def test_point_information(sess, tiny_synth):
    s = sess
    info = point_information(s.take, 0, 0)
    assert info["xyz_mm"] == pytest.approx(tiny_synth.truth.xyz[0, 0].tolist())
    assert "distance_to_caddy_0_mm" in info and 100 < info["distance_to_cameras_mm"] < 400
    d = distance_between_points(s.take, 0, 1, 0)
    assert d == pytest.approx(np.linalg.norm(tiny_synth.truth.xyz[0, 0] - tiny_synth.truth.xyz[0, 1]))
