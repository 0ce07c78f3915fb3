import numpy as np
import pytest

from carapost.core.camera import Intrinsics
from carapost.model.detections import Detections
from carapost.model.take import CameraInfo, PointKind, Take


def make_take(F=5, C=4):
    cams = [CameraInfo(f"cam{c}", c, Intrinsics(800.0, (320.0, 240.0), (640, 480))) for c in range(C)]
    return Take.new(cams, F, 60.0)


def test_new_take_shapes():
    take = make_take()
    take.check()
    assert take.xyz.shape == (5, 0, 3)
    assert take.obs_xy.shape == (5, 0, 4, 2)
    assert take.caddies == [(0, 1), (2, 3)]
    assert take.active_range == (0, 4)


def test_zero_and_one_camera_takes_have_no_caddies():
    assert Take.new([], 3, 30.0).caddies == []
    take = make_take(C=1)
    assert take.caddies == []


def test_bad_caddy_rejected():
    cams = [CameraInfo("a", 0, Intrinsics(800.0, (1.0, 1.0)))]
    with pytest.raises(ValueError, match="caddy"):
        Take.new(cams, 3, 30.0, caddies=[(0, 1)])


def test_add_remove_points_keeps_ids_and_sticks():
    take = make_take()
    idx = take.add_points(3, labels=["a", "", "c"])
    take.add_points(2, kind=PointKind.BRIM, brim_index=np.array([0, 1]))
    take.xyz[:, idx, :] = 1.0
    take.sticks = np.array([[0, 1], [1, 2], [0, 2]])
    take.stick_colours = np.zeros((3, 3), np.uint8)
    take.check()
    assert take.points.names() == ["a", "Point_1", "c", "Brim_3", "Brim_4"]
    take.remove_points([1])
    take.check()
    assert list(take.points.ids) == [0, 2, 3, 4]
    assert take.sticks.tolist() == [[0, 2]]
    new = take.add_points(1)
    assert take.points.ids[new[0]] == 5  # ids are never reused
    assert np.isnan(take.xyz[:, new[0]]).all()


def test_detections_csr_replace_and_select():
    det = Detections.empty(4)
    det = det.with_frames({1: {"x": [1, 2, 3], "y": [4, 5, 6]}, 3: {"x": [7], "y": [8]}})
    assert det.counts().tolist() == [0, 3, 0, 1]
    assert det.detected.tolist() == [False, True, False, True]
    np.testing.assert_array_equal(det.xy(1), [[1, 4], [2, 5], [3, 6]])
    det2 = det.with_frames({1: {"x": [9], "y": [9]}})
    assert det2.counts().tolist() == [0, 1, 0, 1]
    assert det2.x.tolist() == [9, 7]
    kept, remap = det.select(np.array([True, False, True, True]))
    assert kept.counts().tolist() == [0, 2, 0, 1]
    assert remap.tolist() == [0, -1, 1, 0]
    assert kept.x.tolist() == [1, 3, 7]
