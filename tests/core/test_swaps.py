"""Swap detection and repair on labelled trajectories."""

import numpy as np
import pytest

from carapost.core.swaps import (Relabel, apply_relabel, detect_swaps, invert_relabels, jump_scores,
                                 relabel_points, stable_neighbours)
from carapost.synth.mocap import body_motion, corrupt, face_motion


def _repaired(c, rep):
    fixed = apply_relabel(c.xyz, rep.relabels)
    ok = np.isfinite(c.clean_labels_xyz[..., 0])
    return int((ok & ~(fixed[..., 0] == c.clean_labels_xyz[..., 0])).sum())


@pytest.mark.parametrize("kind, rate", [("face", 60.0), ("face", 240.0), ("body", 60.0), ("body", 120.0)])
def test_every_injected_swap_is_repaired(kind, rate):
    m = face_motion(60, 900, rate, seed=2) if kind == "face" else body_motion(900, rate, seed=2)
    c = corrupt(m, seed=5, n_swaps=5, gap_rate=0.002, spurious_rate=0.0, swap_length=(5, 200))
    rep = detect_swaps(c.xyz)
    assert _repaired(c, rep) == 0
    found = {frozenset(p) for r in rep.relabels for p in r.pairs}
    assert found == {frozenset((a, b)) for a, b, _, _ in c.swaps}
    scores = [r.score for r in rep.relabels]
    assert scores == sorted(scores, reverse=True)  # worst first
    assert len(rep.jump_size) >= 2 * len(c.swaps) - 2


def test_clean_data_is_left_alone():
    m = face_motion(60, 900, 60.0, seed=3)
    c = corrupt(m, seed=1, gap_rate=0.003)
    rep = detect_swaps(c.xyz)
    assert rep.relabels == []


def test_one_frame_outlier_swap_and_a_swap_to_the_end():
    m = face_motion(40, 400, 60.0, seed=6)
    x = m.xyz.copy()
    x[200, [3, 4]] = x[200, [4, 3]]
    x[350:, [10, 11]] = x[350:, [11, 10]]
    rep = detect_swaps(x)
    got = sorted((r.start, r.end, tuple(sorted(r.pairs[0]))) for r in rep.relabels)
    assert got == [(200, 201, (3, 4)), (350, 400, (10, 11))]
    # with frame 399 declared right, the first 350 frames are the ones relabelled instead
    rep = detect_swaps(x, reference_frame=399)
    assert sorted((r.start, r.end) for r in rep.relabels) == [(0, 350), (200, 201)]


def test_apply_invert_and_points():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(6, 4, 3))
    r = Relabel(2, 5, np.array([0, 2, 3, 1]), 1.0)
    y = apply_relabel(x, [r])
    np.testing.assert_array_equal(y[:2], x[:2])
    np.testing.assert_array_equal(y[3, 1], x[3, 2])
    np.testing.assert_array_equal(apply_relabel(y, invert_relabels([r])), x)
    assert r.pairs == [(1, 2, 3)] and r.markers == [1, 2, 3]
    labels = np.tile(np.array([3, 2, 1, 0, -1]), (6, 1))  # point k holds marker labels[f, k]
    lab2 = relabel_points(labels, [r])
    # the point that was marker 2 becomes marker 1 (new[1] = old[perm[1]] = old[2])
    assert lab2[3, 1] == 1 and lab2[0, 1] == 2 and lab2[3, 4] == -1
    with pytest.raises(ValueError):
        apply_relabel(x[:, :3], [r])


def test_jump_scores_and_neighbours():
    m = face_motion(30, 200, 60.0, seed=1)
    x = m.xyz.copy()
    x[100:, 5] += [8.0, 0.0, 0.0]
    nb = stable_neighbours(x)
    assert nb.shape == (30, 6) and 5 not in nb[5]
    J3, J1 = jump_scores(x, nb)
    assert int(np.nanargmax(J3[:, 5])) == 100 and J3[100, 5] == pytest.approx(8.0, abs=0.5)
    assert np.isnan(J3[0]).all() and np.isnan(J1[0]).all()


@pytest.mark.parametrize("rel", ["ezc3d/Vicon.c3d", "ezc3d/Qualisys.c3d", "opensim-core/walking2.c3d",
                                 "kineticstoolkit/kinematics_tennis_serve.c3d"])
def test_real_files_clean_and_with_injected_swaps(real_data, rel):
    from carapost.io.c3d import read_c3d
    d = read_c3d(real_data / rel)
    x = d.xyz[:, d.marker_indices()]
    assert detect_swaps(x).relabels == []  # no false alarm on a well-labelled take
    if "tennis" in rel:
        return
    rng = np.random.default_rng(3)
    y = x.copy()
    F, M, _ = x.shape
    med = np.nanmedian(x, axis=0)
    injected = []
    for a in rng.choice(M, 3, replace=False):
        dist = np.linalg.norm(med - med[a], axis=1)
        dist[a] = np.inf
        b = int(np.argmin(dist))
        s = int(rng.integers(20, F - 80))
        y[s:s + 60, [a, b]] = y[s:s + 60, [b, a]]
        injected.append((a, b))
    rep = detect_swaps(y)
    fixed = apply_relabel(y, rep.relabels)
    ok = np.isfinite(x[..., 0])
    assert (fixed[..., 0][ok] == x[..., 0][ok]).all()
