"""The eye's geometry as the blink depth (carapost.core.gapfill_lid) on synthetic takes.

The synthetic lid (carapost.synth.expressions.blink_displacement) closes its margin 0.97 x the
9.5 mm fissure (9.2 mm) and its pretarsal skin moves with the margin (a rigid tarsal plate, as
the geometry model assumes): an 80-marker lid marker travels 9.29 mm (with the 1.2 mm lift over
the eyeball). The 156-marker set's lid markers sit 6 mm to either side of the middle of the eye,
2.2 mm from their margins where the fissure is 8.4 mm: they travel 8.24 mm. See
docs/gap-filling.md.
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
        # measured 7.6-7.8 mm; the marker's truth: 8.24 mm (its offset from the margin is 2.2 mm,
        # not the prior's 2.5, on both lids: D = S - 2a comes out 0.6 mm short)
        assert 7.3 <= f.depth_mm <= 8.1
    ours, theirs = blink_medians(tr, X, res.xyz), blink_medians(tr, X, base.xyz)
    assert len(ours) >= 4 and max(ours) <= 1.0, ours     # issue 4's target, without a ROM (measured 0.28-0.73 mm)
    assert min(theirs) > 3.0, theirs


def test_medium_set_recovers_the_lid_marker_travel(medium):
    from carapost.synth.expressions import blink_displacement

    tr, X = medium
    gap = ~np.isfinite(X).all(-1)
    base = fill_gaps(X, gap)
    res, fits = fill_blink_gaps(X, gap, frame_rate=tr.frame_rate, base=base)
    assert sorted(tr.names[f.point] for f in fits) == ["Lid_Upper_L", "Lid_Upper_R"]
    for f in fits:
        name = tr.names[f.point]
        assert tr.names[f.partner] == name.replace("Upper", "Lower")
        # the marker's true travel in a full blink (9.29 mm: 9.2 down with its margin, lifted 1.2 mm)
        u, v = tr.marker_uv[f.point]
        travel = float(np.linalg.norm(blink_displacement(u, v, 1 if name.endswith("_L") else -1)))
        assert travel == pytest.approx(9.29, abs=0.01)
        assert f.depth_mm == pytest.approx(travel, abs=0.3)   # measured 9.31-9.32 mm
    ours, theirs = blink_medians(tr, X, res.xyz), blink_medians(tr, X, base.xyz)
    # issue 4's target without a ROM: measured 0.07-0.63 mm per blink (0.50 at worst over the 26
    # blinks of seeds 0-3 in bench_gapfill); the neighbours miss by > 5 mm
    assert max(ours) <= 1.0 and all(a < b - 2.0 for a, b in zip(ours, theirs)), (ours, theirs)


def test_non_lid_gaps_keep_the_neighbour_fill(medium):
    tr, X = medium
    gap = ~np.isfinite(X).all(-1)
    base = fill_gaps(X, gap)
    res, fits = fill_blink_gaps(X, gap, frame_rate=tr.frame_rate, base=base)
    lids = set(tr.eyelid_indices.tolist())
    others = [p for p in range(X.shape[1]) if p not in lids]
    np.testing.assert_array_equal(res.xyz[:, others], base.xyz[:, others])
