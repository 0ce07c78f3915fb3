"""Rigid-group re-identification (returning rigid clusters named as a whole)."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carapost.core.label_assign import label_assignment
from carapost.core.label_rigid import fit_groups, rigid_groups, rigid_relabel
from carapost.core.labelling import label_accuracy, points_from_trajectories
from carapost.io.c3d import read_c3d


def _clusters(F: int = 900, rate: float = 120.0, seed: int = 0, noise: float = 0.2):
    """Three rigid 4-marker clusters (irregular tetrahedra, 60-120 mm) on independent smooth
    motions, plus two lone markers wandering near them. Returns xyz (F, 14, 3) and the
    clusters' marker indices."""
    rng = np.random.default_rng(seed)
    t = np.arange(F) / rate
    xyz = np.zeros((F, 14, 3))
    groups = []
    for c in range(3):
        shape = rng.normal(0, 45, (4, 3))
        shape -= shape.mean(0)
        centre = np.array([c * 400.0, 0, 1000]) + 150 * np.stack(
            [np.sin(2 * np.pi * (0.3 + 0.1 * c) * t + k) for k in range(3)], 1)
        rv = np.stack([0.8 * np.sin(2 * np.pi * (0.2 + 0.05 * c) * t + k + c) for k in range(3)], 1)
        R = Rotation.from_rotvec(rv).as_matrix()  # (F, 3, 3)
        xyz[:, 4 * c:4 * c + 4] = np.einsum("fij,mj->fmi", R, shape) + centre[:, None]
        groups.append(list(range(4 * c, 4 * c + 4)))
    for k in range(2):
        xyz[:, 12 + k] = np.array([200.0 + 400 * k, 250, 1000]) + 100 * np.stack(
            [np.sin(2 * np.pi * 0.5 * t + 2 * k + j) for j in range(3)], 1)
    xyz += rng.normal(0, noise, xyz.shape)
    return xyz, groups


def test_rigid_groups_finds_the_clusters():
    xyz, groups = _clusters()
    g = rigid_groups(xyz, np.arange(0, 300, 3))
    assert sorted(sorted(m.tolist()) for m in g.members) == groups
    for D, cfg in zip(g.dist, g.config):
        assert np.allclose(np.linalg.norm(cfg[:, None] - cfg[None], axis=-1), D, atol=2.0)


def test_rigid_groups_rejects_a_face_that_only_looks_rigid_near_the_reference():
    # near the reference frame nothing moves relative to anything: everything looks rigid,
    # but over the take the lone markers do not keep their distances
    xyz, groups = _clusters()
    still = xyz.copy()
    still[:100] = xyz[0]
    g = rigid_groups(still, np.arange(0, 100, 2))
    assert max(len(m) for m in g.members) > 4  # fooled by the still window
    g = rigid_groups(still, np.arange(0, 100, 2), check_frames=np.arange(0, 900, 5))
    assert sorted(sorted(m.tolist()) for m in g.members) == groups


def test_fit_groups_names_a_shuffled_frame():
    xyz, groups = _clusters(seed=1)
    g = rigid_groups(xyz, np.arange(0, 200, 2))
    rng = np.random.default_rng(2)
    for f in (350, 600, 899):
        order = rng.permutation(14)
        P = xyz[f, order]
        P = np.concatenate([P, rng.normal(500, 300, (3, 3))])  # spurious points
        names = fit_groups(P, g)
        grouped = np.isin(order, np.concatenate(groups))
        assert (names[:14][grouped] == order[grouped]).all()
        assert (names[:14][~grouped] == -1).all()


def test_rigid_relabel_renames_a_returning_cluster_and_leaves_right_labels_alone():
    xyz, groups = _clusters(seed=3)
    pts, truth = points_from_trajectories(xyz, seed=0)
    tid = np.where(truth >= 0, truth, -1)  # one tracklet per marker ...
    tid[500:] = np.where(truth[500:] >= 0, truth[500:] + 14, -1)  # ... cut at frame 500
    g = rigid_groups(xyz, np.arange(0, 200, 2))
    lab = truth.copy()
    # cluster 1 came back at 500 under the names of cluster 2 and a lone marker
    wrong = {4: 8, 5: 9, 6: 12, 7: 4}
    late = lab[500:]
    lab[500:] = np.vectorize(lambda v: wrong.get(int(v), v))(late)
    lab[500:][np.isin(truth[500:], [8, 9, 12])] = -1  # ... whose points were unnamed
    new, rep = rigid_relabel(pts, lab, tid, g)
    acc = label_accuracy(new, truth)
    assert rep["pieces_renamed"] >= 4
    assert acc["wrong"] == 0
    assert acc["missed"] <= int((truth[500:] == 12).sum())  # the lone marker is no group's
    # right labels stay as they are
    same, rep = rigid_relabel(pts, truth, tid, g)
    assert (same == truth).all() and rep["pieces_renamed"] == 0


def test_label_assignment_reidentifies_clusters_returning_after_a_common_gap():
    # two clusters vanish together for 150 frames; cluster 2's markers never come back, and
    # cluster 0 returns moved and turned far from where it left
    xyz, groups = _clusters(F=900, seed=4)
    x = xyz.copy()
    x[400:550, 0:4] = np.nan
    x[400:, 8:12] = np.nan
    pts, truth = points_from_trajectories(x, seed=1)
    h = np.full(truth.shape, -1, np.int32)
    h[100] = truth[100]
    res = label_assignment(pts, h, 14)
    acc = label_accuracy(res.labels, truth)
    assert acc["wrong"] == 0, acc
    assert acc["accuracy"] >= 0.999


def test_keeps_rigid_groups_vetoes_undecidable_permutations():
    from carapost.core.label_rigid import keeps_rigid_groups
    from carapost.core.swaps import Relabel
    xyz, groups = _clusters(seed=5)
    g = rigid_groups(xyz, np.arange(0, 200, 2))
    swap01 = np.arange(14)
    swap01[[0, 1]] = [1, 0]
    x = xyz.copy()
    x[300:400, 2:4] = np.nan  # only markers 0 and 1 of their cluster are seen here
    assert not keeps_rigid_groups(x, Relabel(300, 400, swap01), g)
    # with the rest of the cluster present, the shape check's evidence decides
    assert keeps_rigid_groups(xyz, Relabel(300, 400, swap01), g)
    x[300:330, 2:4] = xyz[300:330, 2:4]  # ... present in too few of the frames
    assert not keeps_rigid_groups(x, Relabel(300, 400, swap01), g)
    # markers of no group are not its business
    swap_lone = np.arange(14)
    swap_lone[[12, 13]] = [13, 12]
    assert keeps_rigid_groups(xyz, Relabel(300, 400, swap_lone), g)


def test_real_basket_sprint_returning_clusters():
    # the wheelchair, wheel and arm clusters vanish together and come back (75.5 % before
    # the rigid-group check)
    p = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "kineticstoolkit" / \
        "kinematics_basket_sprint.c3d"
    if not p.exists():
        pytest.skip("real data not available")
    d = read_c3d(p)
    x = d.xyz[:, d.marker_indices()]
    M = x.shape[1]
    valid = np.isfinite(x).all(-1)
    f0 = int(np.flatnonzero(valid.all(1))[0]) if valid.all(1).any() else int(np.argmax(valid.sum(1)))
    pts, truth = points_from_trajectories(x, seed=1)
    h = np.full(truth.shape, -1, np.int32)
    h[f0] = truth[f0]
    res = label_assignment(pts, h, M)
    assert res.report["rigid_renamed"] > 20
    assert label_accuracy(res.labels, truth)["accuracy"] >= 0.91
