"""Blink gaps: the pulse model of carapost.core.gapfill_blink against known excursions."""

import numpy as np
import pytest

from carapost.core.gapfill import fill_gaps, gap_runs
from carapost.core.gapfill_blink import blink_pulse, excursion_depths, fill_blink_gaps

FPS = 60.0
DEPTH = 7.5
#: (onset frame, rise, hold, fall) of the toy take's blinks, frames
BLINKS = ((30.3, 3.4, 2.5, 6.2), (100.7, 4.0, 1.8, 5.0), (160.1, 3.1, 3.3, 7.0))


def toy_take(noise=0.05, seed=0):
    """20 points moving with a rigid head (smooth rotation and translation) and a little
    non-rigid motion; point 0 is an "eyelid" whose own excursion is a blink pulse of depth
    ``DEPTH`` along a fixed direction, hidden while more than half closed.

    Returns (truth (F, P, 3), observed with NaN where hidden, lid-hidden mask (F, P))."""
    rng = np.random.default_rng(seed)
    F, P = 200, 20
    rest = rng.uniform(-35, 35, size=(P, 3)) * np.array([1.0, 1.0, 0.4])
    rest[0] = [30.0, 8.0, 7.0]
    t = np.arange(F) / FPS
    ang = 0.08 * np.sin(2 * np.pi * 0.7 * t)
    c, s = np.cos(ang), np.sin(ang)
    R = np.zeros((F, 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    trans = np.stack([3 * np.sin(2 * np.pi * 0.4 * t), 2 * np.sin(2 * np.pi * 0.9 * t), t], -1)
    local = rest[None] + 0.3 * np.sin(2 * np.pi * 1.3 * t)[:, None, None] * rng.normal(size=(1, P, 3))
    amp = np.max([blink_pulse(np.arange(F), *b) for b in BLINKS], axis=0)
    v = np.array([0.0, -1.0, 0.125])
    v /= np.linalg.norm(v)
    local[:, 0] += DEPTH * amp[:, None] * v
    truth = np.einsum("fij,fpj->fpi", R, local) + trans[:, None]
    hidden = np.zeros((F, P), bool)
    hidden[:, 0] = amp >= 0.5
    obs = truth + rng.normal(scale=noise, size=truth.shape)
    obs[hidden] = np.nan
    return truth, obs, hidden


def per_blink_median(err, hidden):
    _, a, b = gap_runs(hidden[:, [0]])
    return [float(np.median(err[f0:f1 + 1, 0])) for f0, f1 in zip(a, b)]


def test_blink_pulse_shape():
    f = np.arange(-2.0, 20.0, 0.25)
    a = blink_pulse(f, 0.0, 4.0, 2.0, 8.0)
    assert a.min() == 0.0 and a.max() == 1.0
    np.testing.assert_allclose(blink_pulse(np.array([2.0, 5.0, 10.0, 15.0]), 0.0, 4.0, 2.0, 8.0),
                               [0.5, 1.0, 0.5, 0.0], atol=1e-12)
    assert (np.diff(a[(f >= 0) & (f <= 4)]) >= 0).all() and (np.diff(a[(f >= 6) & (f <= 14)]) <= 0).all()


def test_excursion_depth_measured_on_a_complete_take():
    truth, _, _ = toy_take()
    d = excursion_depths(truth, np.array([0, 5]))
    assert d[0] == pytest.approx(DEPTH, abs=0.05)
    assert d[1] < 1.0                                  # an ordinary point: its non-rigid wobble only


def test_known_depth_fills_every_blink_within_a_millimetre():
    truth, obs, hidden = toy_take()
    base = fill_gaps(obs, hidden)
    res, fits = fill_blink_gaps(obs, hidden, frame_rate=FPS, depths={0: DEPTH})
    assert [f.point for f in fits] == [0] and len(fits[0].pulses) == len(BLINKS)
    assert abs(fits[0].direction @ np.array([0, -1, 0.125]) / np.linalg.norm([0, -1, 0.125])) > 0.98
    err = np.linalg.norm(res.xyz - truth, axis=-1)
    err_nb = np.linalg.norm(base.xyz - truth, axis=-1)
    blinks = per_blink_median(err, hidden)
    assert len(blinks) == 3 and max(blinks) < 1.0 and np.mean(blinks) < 0.6, blinks
    assert min(per_blink_median(err_nb, hidden)) > 3.0   # the guide's method misses the closure
    assert res.filled[hidden].all() and not res.filled[~hidden].any()
    np.testing.assert_array_equal(res.xyz[~hidden], obs[~hidden])


def test_fitted_depth_without_rom_still_beats_the_neighbours():
    truth, obs, hidden = toy_take(seed=1)
    base = fill_gaps(obs, hidden)
    res, fits = fill_blink_gaps(obs, hidden, frame_rate=FPS)
    assert fits and fits[0].depth_mm > 3.2             # at least as deep as the lid was seen
    ours = per_blink_median(np.linalg.norm(res.xyz - truth, axis=-1), hidden)
    theirs = per_blink_median(np.linalg.norm(base.xyz - truth, axis=-1), hidden)
    assert all(a < b for a, b in zip(ours, theirs)), (ours, theirs)


def test_ordinary_gaps_keep_the_neighbour_fill():
    truth, obs, hidden = toy_take()
    gap = hidden.copy()
    gap[50:70, 7] = True                                # a point that moves with its neighbours
    obs = obs.copy()
    obs[50:70, 7] = np.nan
    base = fill_gaps(obs, gap)
    res, fits = fill_blink_gaps(obs, gap, frame_rate=FPS, base=base, depths={0: DEPTH})
    assert [f.point for f in fits] == [0]
    np.testing.assert_array_equal(res.xyz[:, 7], base.xyz[:, 7])
    assert np.median(np.linalg.norm(res.xyz[50:70, 7] - truth[50:70, 7], axis=-1)) < 0.3


def test_a_known_depth_smaller_than_what_is_seen_is_not_used():
    _, obs, hidden = toy_take()
    base = fill_gaps(obs, hidden)
    res, fits = fill_blink_gaps(obs, hidden, frame_rate=FPS, base=base, depths={0: 1.0})
    assert fits == []
    np.testing.assert_array_equal(res.xyz, base.xyz)


def test_bad_input():
    _, obs, hidden = toy_take()
    with pytest.raises(ValueError, match="frame_rate"):
        fill_blink_gaps(obs, hidden, frame_rate=0)
    with pytest.raises(ValueError, match="fill mask"):
        fill_blink_gaps(obs, hidden[:, :3], frame_rate=FPS)
    with pytest.raises(ValueError, match=r"\(F, P, 3\)"):
        fill_blink_gaps(obs[..., :2], hidden, frame_rate=FPS)
    with pytest.raises(ValueError, match="window_s"):
        fill_blink_gaps(obs, hidden, frame_rate=FPS, window_s=0)
