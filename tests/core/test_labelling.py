"""The labelling array contract: conversions, checks, accuracy, dispatch."""

import numpy as np
import pytest

from carapost.core.labelling import (check_hints, hints_from_frame, label_accuracy, label_points,
                                     points_from_trajectories, skeleton_from_sticks, trajectories_from_labels)


def _traj(F=5, M=4, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(F, M, 3)) * 100
    x[1, 2] = np.nan
    x[3, 0] = np.nan
    return x


def test_points_round_trip_and_truth():
    x = _traj()
    extra = np.full((5, 2, 3), np.nan)
    extra[2, 0] = [1.0, 2.0, 3.0]
    pts, truth = points_from_trajectories(x, extra, seed=3)
    assert pts.shape == (5, 6, 3) and truth.shape == (5, 6)
    # valid points first in every frame, empty slots -1
    valid = np.isfinite(pts).all(-1)
    assert not (valid[:, 1:] & ~valid[:, :-1]).any()
    assert (truth[~valid] == -1).all()
    assert int((truth == -1)[valid].sum()) == 1  # the one extra point
    back = trajectories_from_labels(pts, truth, 4)
    np.testing.assert_array_equal(np.isnan(back), np.isnan(x))
    np.testing.assert_allclose(back[np.isfinite(x)], x[np.isfinite(x)])


def test_points_shuffle_changes_order_but_not_content():
    x = _traj(F=30, M=10)
    a, ta = points_from_trajectories(x, seed=1)
    b, tb = points_from_trajectories(x, shuffle=False)
    assert not np.array_equal(ta, tb)
    np.testing.assert_array_equal(tb[0], np.arange(10))
    np.testing.assert_allclose(trajectories_from_labels(a, ta, 10), trajectories_from_labels(b, tb, 10))


def test_inputs_not_mutated():
    x = _traj()
    x0 = x.copy()
    pts, truth = points_from_trajectories(x)
    p0, t0 = pts.copy(), truth.copy()
    trajectories_from_labels(pts, truth, 4)
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(pts, p0)
    np.testing.assert_array_equal(truth, t0)


def test_check_hints_rejects_bad_input():
    valid = np.ones((2, 3), bool)
    with pytest.raises(ValueError, match="shape"):
        check_hints(np.zeros((2, 2), int), (2, 3), 4, valid)
    with pytest.raises(ValueError, match="marker indices"):
        check_hints(np.array([[0, 1, 9], [-1, -1, -1]]), (2, 3), 4, valid)
    with pytest.raises(ValueError, match="two points in frame 1"):
        check_hints(np.array([[0, 1, 2], [3, -1, 3]]), (2, 3), 4, valid)
    with pytest.raises(ValueError, match="integer"):
        check_hints(np.zeros((2, 3)), (2, 3), 4, valid)
    # hints on empty slots are dropped
    v = valid.copy()
    v[0, 0] = False
    assert check_hints(np.array([[0, 1, 2], [-1, -1, -1]]), (2, 3), 4, v)[0, 0] == -1


def test_trajectories_from_labels_rejects_duplicates():
    pts = np.zeros((1, 2, 3))
    with pytest.raises(ValueError, match="marker 0"):
        trajectories_from_labels(pts, np.array([[0, 0]]), 2)


def test_hints_from_frame():
    h = hints_from_frame([2, -1, 0], 1, 3)
    assert h.shape == (3, 3) and (h[[0, 2]] == -1).all() and list(h[1]) == [2, -1, 0]
    with pytest.raises(ValueError):
        hints_from_frame([0], 5, 3)


def test_skeleton_from_sticks_keeps_first_parent_and_child():
    sk = skeleton_from_sticks(np.array([[0, 1], [1, 2], [0, 3], [4, 2]]), 5)
    assert sk[1].tolist() == [0, 2] and sk[2].tolist() == [1, -1]
    assert sk[3].tolist() == [-1, -1]  # 0 already has a child
    assert sk[4].tolist() == [-1, -1]  # 2 already has a parent
    with pytest.raises(ValueError):
        skeleton_from_sticks(np.array([[0, 7]]), 5)


def test_label_accuracy_counts():
    truth = np.array([[0, 1, 2, -1, -1]])
    lab = np.array([[0, 2, -1, 1, -1]])
    a = label_accuracy(lab, truth)
    assert a == {"accuracy": 1 / 3, "wrong": 1, "missed": 1, "spurious_labelled": 1, "marker_samples": 3}


def test_label_points_dispatch():
    x = _traj(F=6, M=3)
    x[np.isnan(x)] = 0.0
    pts, truth = points_from_trajectories(x * 0 + np.arange(3)[None, :, None] * 100.0, seed=0)
    h = np.full(truth.shape, -1, np.int32)
    h[0] = truth[0]
    for method in ("assignment", "nearest"):
        r = label_points(pts, h, 3, method=method)
        assert (r.labels == truth).all()
    with pytest.raises(ValueError, match="unknown labelling method"):
        label_points(pts, h, 3, method="magic")
