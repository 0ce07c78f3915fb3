import copy

import numpy as np
import pytest

from carapost.ops.change import take_diff
from carapost.ops.points import (
    clear_active_range,
    clear_points,
    create_points_from_detections,
    delete_detections,
    delete_points,
    merge,
    remove_interpolated,
    split_point,
)
from carapost.ops.session import Session
from carapost.model.take import ObsSource, Recon


def marker_dets(det_of, f, m):
    return [(c, f, int(det_of[f, m, c])) for c in range(det_of.shape[2]) if det_of[f, m, c] >= 0]


def visible_marker(det_of, f, n_cams=3):
    return int(np.flatnonzero((det_of[f] >= 0).sum(-1) >= n_cams)[0])


@pytest.fixture
def sess(truth_take):
    take, det_of = truth_take
    return Session(take), det_of


def test_merge_detections_creates_point(sess, tiny_synth, undo_check):
    s, det_of = sess
    m = visible_marker(det_of, 2)
    ch = merge(s.take, detections=marker_dets(det_of, 2, m))
    undo_check(s, ch)
    take = s.take
    assert take.n_points == 1
    np.testing.assert_allclose(take.xyz[2, 0], tiny_synth.truth.xyz[2, m], atol=1e-3)
    assert take.recon[2, 0] == Recon.MULTI_VIEW
    assert (take.obs_src[2, 0] == ObsSource.BLOB).sum() == len(marker_dets(det_of, 2, m))
    assert np.isnan(take.xyz[1, 0]).all()


def test_merge_point_with_detection_and_two_points(sess, undo_check):
    s, det_of = sess
    m = visible_marker(det_of, 0)
    dets = marker_dets(det_of, 0, m)
    s.apply(merge(s.take, detections=dets[:2]))
    undo_check(s, merge(s.take, points=[0], detections=dets[2:]))
    assert (s.take.obs_det[0, 0] >= 0).sum() == len(dets)
    # a second point from the same marker in frame 1, merged into the first
    s.apply(merge(s.take, detections=marker_dets(det_of, 1, m)))
    assert s.take.n_points == 2
    undo_check(s, merge(s.take, points=[0, 1]))
    assert s.take.n_points == 1
    assert (s.take.obs_det[1, 0] >= 0).sum() == len(marker_dets(det_of, 1, m))


def test_merge_steals_detection_from_other_point(sess, undo_check):
    s, det_of = sess
    m0, m1 = np.flatnonzero((det_of[0] >= 0).sum(-1) >= 3)[:2]
    s.apply(merge(s.take, detections=marker_dets(det_of, 0, m0)))
    wrong = marker_dets(det_of, 0, m0)[0]
    s.apply(merge(s.take, detections=[wrong] + marker_dets(det_of, 0, m1)[1:2]))
    assert s.take.obs_det[0, 0, wrong[0]] == -1  # detached from the first point
    assert s.take.obs_det[0, 1, wrong[0]] == wrong[2]


def test_merge_errors(sess):
    s, det_of = sess
    with pytest.raises(ValueError, match="at least two detections"):
        merge(s.take, detections=[(0, 0, 0)])
    with pytest.raises(ValueError, match="does not exist"):
        merge(s.take, detections=[(0, 0, 9999), (1, 0, 0)])
    with pytest.raises(ValueError, match="one detection per camera"):
        merge(s.take, detections=[(0, 0, 0), (0, 0, 1)])


def test_delete_split_clear_create(sess, undo_check):
    s, det_of = sess
    for f in range(6):
        m = visible_marker(det_of, f)
        if f == 0:
            s.apply(merge(s.take, detections=marker_dets(det_of, 0, m)))
        else:
            s.apply(merge(s.take, points=[0], detections=marker_dets(det_of, f, m)))
    assert np.isfinite(s.take.xyz[:, 0]).all()
    undo_check(s, split_point(s.take, 0, 3))
    assert s.take.n_points == 2
    assert np.isnan(s.take.xyz[3:, 0]).all() and np.isfinite(s.take.xyz[3:, 1]).all()
    undo_check(s, clear_points(s.take, [0], [1], cameras=[0]))
    assert s.take.obs_det[1, 0, 0] == -1
    undo_check(s, clear_points(s.take, [0], [2]))
    assert np.isnan(s.take.xyz[2, 0]).all() and (s.take.obs_det[2, 0] == -1).all()
    undo_check(s, delete_points(s.take, [1]))
    assert s.take.n_points == 1
    d = marker_dets(det_of, 0, visible_marker(det_of, 0))
    undo_check(s, delete_detections(s.take, d[:1]))
    assert s.take.obs_det[0, 0, d[0][0]] == -1
    undo_check(s, create_points_from_detections(s.take, [(2, 4, 0), (3, 4, 1)]))
    assert s.take.n_points == 3
    undo_check(s, clear_active_range(s.take))
    assert (s.take.obs_det == -1).all()


def test_remove_interpolated(sess, undo_check):
    s, det_of = sess
    s.take.add_points(2)
    s.take.xyz[:, :] = 1.0
    s.take.recon[:, 0] = Recon.INTERPOLATED
    s.take.recon[:, 1] = Recon.MULTI_VIEW
    undo_check(s, remove_interpolated(s.take))
    assert np.isnan(s.take.xyz[:, 0]).all() and np.isfinite(s.take.xyz[:, 1]).all()
