"""The numpy helpers behind the continuity chart and the navigation commands (no Qt)."""

import numpy as np

from carapost.model.take import ObsSource
from carapost.ui import queries as q


def test_continuity_codes_by_camera_count():
    F, P, C = 5, 2, 4
    xyz = np.zeros((F, P, 3))
    obs = np.full((F, P, C, 2), np.nan)
    for f in range(5):
        obs[f, 0, :f] = 1.0             # frame f: f cameras
    xyz[2, 1] = np.nan                  # point 1 has a gap in frame 2
    codes = q.continuity_codes(xyz, obs)
    assert codes[:, 0].tolist() == [q.RED, q.ORANGE, q.YELLOW, q.LIGHT_GREEN, q.DARK_GREEN]
    assert codes[2, 1] == q.GAP and codes[0, 1] == q.RED


def test_sensor_codes_sources_quality_and_keyframes():
    F, P, C = 3, 2, 2
    obs = np.zeros((F, P, C, 2))
    src = np.full((F, P, C), ObsSource.BLOB, np.uint8)
    src[1, 0, 0] = ObsSource.PATCH
    src[2, 0, 0] = ObsSource.TARGET
    qual = np.full((F, P, C), np.nan, np.float32)
    qual[2, 0, 0] = 0.99
    obs[0, 1, 1] = np.nan
    codes = q.sensor_codes(src, qual, obs, (np.array([0]), np.array([7]), np.array([1])), np.array([3, 7]))
    assert codes[0, 0, 0] == q.S_BLOB and codes[1, 0, 0] == q.S_PATCH
    assert codes[2, 0, 0] == q.S_TARGET0 + q.N_TARGET_LEVELS - 1     # good quality = green end
    assert codes[0, 1, 1] == q.S_KEYFRAME                            # keyframe of point id 7, camera 1
    obs[0, 1, 1] = np.nan
    codes = q.sensor_codes(src, qual, obs)
    assert codes[0, 1, 1] == q.S_GAP


def test_reduce_columns_keeps_short_gaps_visible():
    codes = np.full((1, 10000), q.DARK_GREEN, np.uint8)
    codes[0, 5003] = q.GAP
    out = q.reduce_columns(codes, 0, 9999, 100, q.CONTINUITY_PRIORITY)
    assert out.shape == (1, 100) and (out == q.GAP).sum() == 1 and out[0, 50] == q.GAP
    few = q.reduce_columns(codes[:, :4], 0, 3, 8, q.CONTINUITY_PRIORITY)
    assert few.shape == (1, 8) and (few == q.DARK_GREEN).all()


def test_gaps_and_navigation():
    valid = np.ones((10, 3), bool)
    valid[[2, 3, 6], 0] = False          # point 0: two gaps (2-3, 6)
    valid[4, 1] = False                  # point 1: one gap of one frame
    valid[:2, 2] = False                 # point 2: leading missing frames are not a gap
    runs, frames = q.gap_counts(valid)
    assert runs.tolist() == [2, 1, 0] and frames.tolist() == [3, 1, 0]
    assert q.point_with_fewest_gaps(valid) == 1
    assert q.point_with_fewest_gaps(valid[:, 2:]) == -1
    assert q.next_gap_frame(valid[:, 0], 0) == 1 and q.next_gap_frame(valid[:, 0], 1) == 5
    assert q.next_gap_frame(valid[:, 0], 7) == 1          # wraps to the first gap
    assert q.next_gap_frame(valid[:, 2], 0) == -1


def test_polygon_and_outlines():
    poly = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    inside = q.points_in_polygon(np.array([[5, 5], [15, 5], [np.nan, 1]]), poly)
    assert inside.tolist() == [True, False, False]
    ox, oy = q.ellipse_outlines(np.array([1.0]), np.array([2.0]), np.array([3.0]), np.array([1.0]),
                                np.array([np.pi / 2]), n=4)
    np.testing.assert_allclose(np.c_[ox[0], oy[0]][[0, 1, 4]], [[1, 5], [0, 2], [1, 5]], atol=1e-12)
