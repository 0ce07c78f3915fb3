"""The eye's geometry as the blink depth (carapost.core.gapfill_lid) on synthetic takes.

The synthetic lid (carapost.synth.expressions) closes its *margin* 0.97 x the 9.5 mm fissure
(9.2 mm), but moves a marker 2.5 mm above the margin only 7.5 mm (80 markers; 7.0 mm for the
156-marker set's lid markers): its pretarsal skin stretches. The geometry model assumes a rigid
tarsal plate (the marker follows its margin), so on these takes it recovers the margin's travel,
not the marker's: see docs/gap-filling.md.
"""

import numpy as np
import pytest

from carapost.core.gapfill import fill_gaps, gap_runs
from carapost.core.gapfill_blink import fill_blink_gaps


def observed(n_markers, seed, n_frames=150):
    """Truth and the observed take (0.05 mm noise; NaN where fewer than two cameras see a marker)."""
    from carapost.synth import SynthConfig, generate_take

    tr = generate_take(SynthConfig(n_markers=n_markers, n_frames=n_frames, blinks=True, high_motion=True),
                       seed=seed).truth
    rng = np.random.default_rng(seed)
    X = tr.xyz + rng.normal(scale=0.05, size=tr.xyz.shape)
    X[tr.visible.sum(-1) < 2] = np.nan
    return tr, X


def blink_medians(tr, X, res_xyz):
    gap = ~np.isfinite(X).all(-1)
    err = np.linalg.norm(res_xyz - tr.xyz, axis=-1)
    out = []
    for m in tr.eyelid_indices:
        _, a, b = gap_runs(gap[:, [m]])
        out += [float(np.median(err[f0:f1 + 1, m])) for f0, f1 in zip(a, b)]
    return out


@pytest.fixture(scope="module")
def dense():
    return observed(156, 0)


@pytest.fixture(scope="module")
def medium():
    return observed(80, 1)


def test_dense_set_lids_close_onto_their_lower_lid_markers(dense):
    tr, X = dense
    gap = ~np.isfinite(X).all(-1)
    base = fill_gaps(X, gap)
    res, fits = fill_blink_gaps(X, gap, frame_rate=tr.frame_rate, base=base)
    names = list(tr.names)
    pairs = {names[f.point]: names[f.partner] for f in fits}
    assert pairs == {f"Lid_Upper_{s}_{i}": f"Lid_Lower_{s}_{i}" for s in "LR" for i in (1, 2)}
    for f in fits:
        assert f.depth_source == "lower_lid"
        assert 7.3 <= f.depth_mm <= 8.1                 # measured 7.6-7.8 mm; the marker's truth: 7.0 mm
    ours, theirs = blink_medians(tr, X, res.xyz), blink_medians(tr, X, base.xyz)
    assert len(ours) >= 4 and max(ours) <= 1.0, ours     # issue 4's target, without a ROM (measured 0.56-0.92 mm)
    assert min(theirs) > 3.0, theirs


def test_medium_set_recovers_the_lid_margin_travel(medium):
    tr, X = medium
    gap = ~np.isfinite(X).all(-1)
    base = fill_gaps(X, gap)
    res, fits = fill_blink_gaps(X, gap, frame_rate=tr.frame_rate, base=base)
    assert sorted(tr.names[f.point] for f in fits) == ["Lid_Upper_L", "Lid_Upper_R"]
    for f in fits:
        assert tr.names[f.partner] == tr.names[f.point].replace("Upper", "Lower")
        # the synthetic lid margin travels 0.97 * 9.5 = 9.2 mm, the marker 7.5 mm
        assert f.depth_mm == pytest.approx(0.97 * 9.5, abs=0.3)
    ours, theirs = blink_medians(tr, X, res.xyz), blink_medians(tr, X, base.xyz)
    # the 1.8 mm depth excess shows: 0.8-1.8 mm per blink over seeds 0-3 (the target, 1.0 mm,
    # is not met on this marker set without a ROM); the neighbours miss by > 3 mm
    assert max(ours) < 2.0 and all(a < b - 2.0 for a, b in zip(ours, theirs)), (ours, theirs)


def test_non_lid_gaps_keep_the_neighbour_fill(medium):
    tr, X = medium
    gap = ~np.isfinite(X).all(-1)
    base = fill_gaps(X, gap)
    res, fits = fill_blink_gaps(X, gap, frame_rate=tr.frame_rate, base=base)
    lids = set(tr.eyelid_indices.tolist())
    others = [p for p in range(X.shape[1]) if p not in lids]
    np.testing.assert_array_equal(res.xyz[:, others], base.xyz[:, others])
