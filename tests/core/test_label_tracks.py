"""Frame-to-frame links and tracklets."""

import numpy as np

from carapost.core.label_tracks import build_tracklets, link_frames, segments_from_trajectories
from carapost.core.labelling import points_from_trajectories


def _grid(F=20, speed=0.5):
    base = np.stack(np.meshgrid(np.arange(4) * 20.0, np.arange(3) * 20.0, [0.0]), -1).reshape(-1, 3)
    t = np.arange(F)[:, None, None]
    return base[None] + t * np.array([speed, 0.2, 0.0])


def test_links_follow_shuffled_points():
    x = _grid()
    pts, truth = points_from_trajectories(x, seed=2)
    links, stats = link_frames(pts)
    prev = np.take_along_axis(truth[:-1], np.maximum(links[1:], 0), 1)
    assert (links[0] == -1).all()
    assert (links[1:] >= 0).all()
    assert (prev == truth[1:]).all()
    assert stats.median < 0.6 and stats.n_links == 19 * 12


def test_fast_motion_needs_the_velocity_pass():
    x = _grid(F=30, speed=14.0)  # 14 mm/frame, markers 20 mm apart
    pts, truth = points_from_trajectories(x, seed=5)
    links, _ = link_frames(pts, passes=2)
    ok = links[1:] >= 0
    prev = np.take_along_axis(truth[:-1], np.maximum(links[1:], 0), 1)
    assert (prev[ok] == truth[1:][ok]).all()  # never wrong
    assert ok.mean() > 0.9


def test_ambiguous_and_duplicate_points_stay_unlinked():
    x = _grid(F=6)
    pts, truth = points_from_trajectories(x, shuffle=False)
    extra = np.full((6, 1, 3), np.nan)
    extra[3, 0] = pts[3, 5] + [0.3, 0.0, 0.0]  # a spurious point right next to marker 5
    pts2, truth2 = points_from_trajectories(x, extra, shuffle=False)
    links, _ = link_frames(pts2)
    j5 = np.flatnonzero(truth2[3] == 5)[0]
    js = np.flatnonzero(truth2[3] == -1)
    js = js[np.isfinite(pts2[3, js, 0])][0]
    prev5 = np.flatnonzero(truth2[2] == 5)[0]
    assert links[3, j5] in (-1, prev5)  # linked right (constant velocity) or left to the assignment
    assert links[3, js] == -1
    dup = pts.copy()
    dup[4, 1] = dup[4, 0]  # two identical points
    links, _ = link_frames(dup)
    assert links[4, 0] == -1 and links[4, 1] == -1
    # links are one to one in every frame
    for f in range(1, 6):
        lk = links[f][links[f] >= 0]
        assert len(lk) == len(np.unique(lk))


def test_hints_cut_and_force_links():
    x = _grid(F=4)
    pts, truth = points_from_trajectories(x, shuffle=False)
    h = np.full(truth.shape, -1, np.int32)
    h[1, 0], h[2, 0] = 0, 1  # the same point said to be two markers: never linked
    links, _ = link_frames(pts, hints=h)
    assert links[2, 0] == -1


def test_build_tracklets():
    x = _grid(F=10)
    x[4:6, 2] = np.nan
    pts, truth = points_from_trajectories(x, seed=1)
    links, _ = link_frames(pts)
    tr = build_tracklets(pts, links)
    assert len(tr) == 13  # marker 2 is split by its gap
    assert (np.diff(tr.offsets) == tr.end - tr.start + 1).all()
    for t in range(len(tr)):
        a, b = tr.offsets[t], tr.offsets[t + 1]
        assert len(set(truth[tr.frames[a:b], tr.index[a:b]])) == 1
    t0 = tr.tid[0, 0]
    np.testing.assert_array_equal(tr.sample_at(t0, 0), pts[0, 0])
    assert tr.sample_at(t0, 99) is None


def test_segments_from_trajectories():
    x = _grid(F=8)
    x[3, 1] = np.nan
    cuts = np.zeros((8, 12), bool)
    cuts[5, 0] = True
    tr, owner = segments_from_trajectories(x, cuts)
    assert len(tr) == 14
    assert sorted(owner.tolist()) == sorted(list(range(12)) + [0, 1])
    t = tr.tid[6, 0]
    assert tr.start[t] == 5 and tr.end[t] == 7


def test_tracklets_numbered_by_first_point_and_bad_links_refused():
    import pytest
    nan = np.nan
    pts = np.array([[[0, 0, 0], [5, 0, 0], [nan, nan, nan]],
                    [[5.1, 0, 0], [0.1, 0, 0], [9, 9, 9]],
                    [[9.1, 9, 9], [5.2, 0, 0], [0.2, 0, 0]]])
    links = np.array([[-1, -1, -1], [1, 0, -1], [2, 0, 1]], np.int32)
    tr = build_tracklets(pts, links)
    # chains: (0,0)->(1,1)->(2,2) is tracklet 0, (0,1)->(1,0)->(2,1) is 1, (1,2)->(2,0) is 2
    assert tr.tid.tolist() == [[0, 1, -1], [1, 0, 2], [2, 1, 0]]
    assert tr.start.tolist() == [0, 0, 1] and tr.end.tolist() == [2, 2, 2]
    assert tr.index[tr.offsets[0]:tr.offsets[1]].tolist() == [0, 1, 2]
    bad = links.copy()
    bad[1, 2] = 2  # a link to the empty slot of frame 0
    with pytest.raises(ValueError, match="empty slots"):
        build_tracklets(pts, bad)
