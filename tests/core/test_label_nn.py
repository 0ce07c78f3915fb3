"""Seed 002's nearest-neighbour labeller and its hand heuristics."""

import numpy as np
import pytest

from carapost.core.label_hands import hand_model, hand_skeleton, hand_swaps, segment_crossing
from carapost.core.label_nn import label_nearest, skeleton_order
from carapost.core.labelling import label_accuracy, points_from_trajectories, skeleton_from_sticks
from carapost.synth.mocap import corrupt, face_motion


def _hints(truth, frames=(0,)):
    h = np.full(truth.shape, -1, np.int32)
    for f in frames:
        h[f] = truth[f]
    return h


def _still(M=3, F=4, spacing=50.0):
    return np.tile(np.stack([np.arange(M) * spacing, np.zeros(M), np.zeros(M)], 1), (F, 1, 1))


def test_face_with_skeleton():
    m = face_motion(40, 400, 120.0, seed=1, head_motion=0.5)
    c = corrupt(m, seed=1, gap_rate=0.002, spurious_rate=0.1)
    pts, truth = points_from_trajectories(c.clean_labels_xyz, c.spurious, seed=1)
    r = label_nearest(pts, _hints(truth), m.n_markers, skeleton=skeleton_from_sticks(m.sticks, m.n_markers))
    a = label_accuracy(r.labels, truth)
    assert a["accuracy"] >= 0.99, a


def test_distance_thresholds():
    x = _still()
    x[2:, 0, 0] += 20.0  # marker 0 jumps 20 mm at frame 2: beyond 15 mm
    pts, truth = points_from_trajectories(x, shuffle=False)
    r = label_nearest(pts, _hints(truth), 3)
    assert r.labels[2, 0] == -1
    # missing in frame 2, so frame 3 allows 30 mm: found again
    assert r.labels[3, 0] == 0
    r = label_nearest(pts, _hints(truth), 3, dist_thresh=25.0)
    assert r.labels[2, 0] == 0


def test_only_the_nearest_marker_gets_a_point():
    # markers at x = 0 and x = 10; in frame 1 a single point is left: it goes to the marker
    # nearest to it, the other one is missing
    for where, owner in ((4.0, 0), (7.0, 1)):
        x = _still(M=2, spacing=10.0)
        x[1:, 0] = np.nan
        x[1:, 1, 0] = where
        pts, truth = points_from_trajectories(x, shuffle=False)
        r = label_nearest(pts, _hints(truth), 2)
        j = np.flatnonzero(truth[1] == 1)[0]
        assert r.labels[1, j] == owner
        assert (r.labels[1] >= 0).sum() == 1


def test_points_outside_the_bounding_box_are_ignored():
    x = _still(M=3)
    x[1:, 2] = np.nan
    extra = np.full((4, 1, 3), np.nan)
    extra[1:, 0] = [100.0 + 35.0, 0.0, 0.0]  # 35 mm beyond the box of frame 0 grown by 30 mm
    pts, truth = points_from_trajectories(x, extra, shuffle=False)
    j = np.flatnonzero((truth[2] == -1) & np.isfinite(pts[2, :, 0]))[0]
    r = label_nearest(pts, _hints(truth), 3, missing_thresh=100.0)
    assert r.labels[2, j] == -1
    r = label_nearest(pts, _hints(truth), 3, missing_thresh=100.0, bbox_margin=40.0)
    assert r.labels[2, j] == 2


def test_skeleton_carries_a_missing_marker():
    # a chain 0-1-2 translating 10 mm per frame; marker 1 missing for frames 1-3
    F = 6
    x = _still(M=3, F=F) + (np.arange(F) * 10.0)[:, None, None] * np.array([1.0, 0.0, 0.0])
    x[1:4, 1] = np.nan
    pts, truth = points_from_trajectories(x, shuffle=False)
    sk = skeleton_from_sticks(np.array([[0, 1], [1, 2]]), 3)
    with_sk = label_nearest(pts, _hints(truth), 3, skeleton=sk)
    assert with_sk.labels[4, 1] == 1
    without = label_nearest(pts, _hints(truth), 3, dist_thresh=5.0, missing_thresh=25.0)
    assert without.labels[4, 1] == -1  # stayed 40 mm behind: too far


def test_fallback_frames_and_fixed_markers():
    x = _still(M=3, F=6)
    pts, truth = points_from_trajectories(x, seed=4)
    h = _hints(truth, frames=(0, 3))
    h[3][truth[3] == 0], h[3][truth[3] == 1] = 1, 0  # fallback frame 3 says 0 and 1 are swapped
    r = label_nearest(pts, h, 3)
    assert (r.labels[3] == h[3]).all()
    assert (r.labels[4:][truth[4:] == 0] == 1).all()  # and the labelling continues from it


def test_ignored_markers():
    x = _still(M=3, F=4)
    pts, truth = points_from_trajectories(x, seed=4)
    h = _hints(truth)
    h[truth == 2] = 2
    r = label_nearest(pts, h, 3, ignore=[2])
    assert ((r.labels == 2) == (truth == 2)).all()


def test_backward_pass_and_bad_input():
    x = _still(M=3, F=6)
    pts, truth = points_from_trajectories(x, seed=2)
    r = label_nearest(pts, _hints(truth, frames=(4,)), 3)
    assert (r.labels == truth).all() and r.report["reference_frame"] == 4
    r = label_nearest(pts, _hints(truth, frames=(4,)), 3, backward=False)
    assert (r.labels[:4] == -1).all()
    with pytest.raises(ValueError, match="needs hints"):
        label_nearest(pts, None, 3)
    with pytest.raises(ValueError, match="skeleton"):
        label_nearest(pts, _hints(truth), 3, skeleton=np.zeros((2, 2), int))


def test_skeleton_order_parents_first():
    sk = skeleton_from_sticks(np.array([[2, 1], [1, 0]]), 3)
    assert skeleton_order(sk).tolist() == [2, 1, 0]


# ------------------------------------------------------------------------------- hands
def _hand():
    names, pos = [], []
    for fi, f in enumerate("TIMRL"):
        for j in range(1, 5):
            names.append(f"Hands_R_{f}{j}")
            pos.append([fi * 20.0, j * 25.0, 0.0])
    return names, np.array(pos)


def test_hand_model_and_skeleton():
    names, _ = _hand()
    model = hand_model(names + ["Other"])
    assert model.fingers[("R", "I")] == [4, 5, 6, 7]
    assert len(model.neighbour_pairs()) == 4
    sk = hand_skeleton(names)
    assert sk[5].tolist() == [4, 6] and sk[4, 0] == -1 and sk[7, 1] == -1
    assert hand_model(["a", "b"]) is None


def test_segment_crossing():
    d = segment_crossing(np.array([0.0, 0, 0]), np.array([2.0, 2, 0]), np.array([0.0, 2, 1]), np.array([2.0, 0, 1]))
    assert d == pytest.approx(1.0)
    assert segment_crossing(np.zeros(3), np.array([1.0, 0, 0]), np.array([5.0, -1, 0]), np.array([5.0, 1, 0])) == np.inf


def test_crossed_fingertips_are_swapped_back():
    names, X = _hand()
    model = hand_model(names)
    Y = X.copy()
    Y[[7, 11]] = Y[[11, 7]]  # index and middle fingertips exchanged: bones 3-4 cross
    pairs = hand_swaps(Y, model)
    assert pairs == [(7, 11)]
    assert hand_swaps(X, model) == []


def test_backward_fingertip_is_swapped():
    names, X = _hand()
    model = hand_model(names)
    Y = X.copy()
    Y[[2, 3]] = Y[[3, 2]]  # thumb DIP and tip exchanged: the tip bends back 180 degrees
    assert hand_swaps(Y, model) == [(2, 3)]


def test_hand_heuristics_in_the_labeller():
    names, X = _hand()
    F = 5
    x = np.tile(X, (F, 1, 1))
    x[2:, [7, 11]] = x[2:, [11, 7]]  # data where the two fingertips really crossed
    pts, truth = points_from_trajectories(x, shuffle=False)
    h = _hints(truth)
    h[2][truth[2] == 7], h[2][truth[2] == 11] = 7, 11  # and a frame mapping that keeps them crossed
    plain = label_nearest(pts, h, len(names), names=names)
    fixed = label_nearest(pts, h, len(names), names=names, hand_heuristics=True)
    assert plain.report["hand_swaps"] == 0 and fixed.report["hand_swaps"] >= 1
    assert fixed.labels[3][truth[3] == 7] == 11
