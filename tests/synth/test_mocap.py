"""Synthetic labelled marker trajectories for the labelling tests and benchmarks."""

import numpy as np
import pytest

from carapost.synth.mocap import body_motion, corrupt, face_motion


def test_face_motion_is_deterministic_and_smooth():
    a = face_motion(40, 120, 60.0, seed=1)
    b = face_motion(40, 120, 60.0, seed=1)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert a.xyz.shape == (120, 40, 3) and len(a.names) == 40 and len(set(a.names)) == 40
    step = np.linalg.norm(np.diff(a.xyz, axis=0), axis=-1)
    assert step.max() < 5.0  # mm per frame at 60 Hz
    d = np.linalg.norm(a.xyz[0][:, None] - a.xyz[0][None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d.min() > 2.0
    with pytest.raises(ValueError):
        face_motion(10)


def test_body_motion_spacing():
    m = body_motion(100, 120.0, seed=0)
    d = np.linalg.norm(m.xyz[0][:, None] - m.xyz[0][None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d.min() >= 35.0 and m.sticks.shape[1] == 2


def test_corrupt_swaps_gaps_and_spurious():
    m = face_motion(40, 300, 60.0, seed=2)
    c = corrupt(m, seed=3, n_swaps=2, gap_rate=0.01, spurious_rate=0.5, ghost_tracks=2)
    assert len(c.swaps) == 2
    gaps = np.isnan(c.clean_labels_xyz[..., 0])
    assert 0.01 < gaps.mean() < 0.2
    np.testing.assert_array_equal(np.isnan(c.xyz[..., 0]).sum(), gaps.sum())
    a, b, s, e = c.swaps[0]
    np.testing.assert_array_equal(c.xyz[s:e, a], c.clean_labels_xyz[s:e, b])
    assert np.isfinite(c.spurious[..., 0]).sum() > 100
