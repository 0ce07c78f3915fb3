"""Naming pieces by the marker set's distances learnt over the take (label_ranges)."""

from pathlib import Path

import numpy as np
import pytest

from carapost.core.label_assign import label_assignment
from carapost.core.label_ranges import learn_ranges, range_relabel, range_tiebreak, take_groups
from carapost.core.label_rigid import rigid_relabel
from carapost.core.labelling import label_accuracy, points_from_trajectories

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"
CHAIR, ARM, FORE, HEAD = range(0, 4), range(4, 8), range(8, 11), range(11, 14)


def _rot(axis, ang):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    ang = np.asarray(ang, float)[..., None, None]
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * (K @ K)


def _arm_take(F=900, rate=60.0, seed=0, gap=(300, 600)):
    """A seated athlete's left side, mm: a still chair (4 markers), an upper-arm cluster (4),
    a forearm cluster of 3 markers in a near-isosceles triangle (49, 50 and 76 mm: it cannot
    tell two of its markers apart by itself) whose long side runs along the forearm, and a
    head (3). The elbow flexes and the arm swings. The forearm is absent over ``gap``; the
    head vanishes for good at its start (its rigid partners never come back)."""
    rng = np.random.default_rng(seed)
    t = np.arange(F) / rate
    chair = np.array([[0, 0, 0], [400, 0, 0], [0, 300, 0], [400, 300, 50.0]])
    arm_cfg = np.array([[0, 0, 0], [60, 0, 0], [0, 55, 0], [20, 25, 45.0]])
    a, b, c = 49.0, 50.0, 76.0
    x = (a * a - b * b + c * c) / (2 * c)
    fore_cfg = np.array([[0, 0, 0], [0, np.sqrt(a * a - x * x), -x], [0, 0, -c]])  # long side along -z
    head_cfg = np.array([[0, 0, 0], [90, 0, 0], [40, 70, 10.0]])
    shoulder = np.array([200, 150, 600.0])
    R_arm = _rot([0, 1, 0], 0.6 * np.sin(2 * np.pi * 0.25 * t))
    arm = (shoulder + np.einsum("fij,j->fi", R_arm, [0, 0, -150.0]))[:, None] + np.einsum(
        "fij,mj->fmi", R_arm, arm_cfg - arm_cfg.mean(0))
    elbow = shoulder + np.einsum("fij,j->fi", R_arm, [0, 0, -300.0])
    R_fore = R_arm @ _rot([0, 1, 0], 0.8 + 0.5 * np.sin(2 * np.pi * 0.4 * t + 1.0))
    fore = (elbow + np.einsum("fij,j->fi", R_fore, [0, 40.0, -60.0]))[:, None] + np.einsum(
        "fij,mj->fmi", R_fore, fore_cfg)
    R_head = _rot([0, 0, 1], 0.3 * np.sin(2 * np.pi * 0.1 * t))
    head = (shoulder + [-100, 0, 350])[None, None] + np.einsum("fij,mj->fmi", R_head, head_cfg - head_cfg.mean(0))
    xyz = np.concatenate([np.broadcast_to(chair, (F, 4, 3)), arm, fore, head], axis=1).copy()
    xyz += rng.normal(scale=0.2, size=xyz.shape)
    xyz[gap[0]:gap[1], FORE] = np.nan
    xyz[gap[0]:, HEAD] = np.nan
    return xyz


def _labelled(xyz, back=600):
    """Points (not shuffled), true labels and tracklets (one per marker; the forearm's points
    after the gap on new tracklets)."""
    pts, truth = points_from_trajectories(xyz, seed=0, shuffle=False)
    tid = np.where(np.isfinite(pts[..., 0]), truth, -1).astype(np.int32)
    tid[back:, list(FORE)] += 100
    return pts, truth, tid


def _model(pts, labels, tid, M=14):
    F = len(pts)
    xyz = np.full((F, M, 3), np.nan)
    pieces = np.full((F, M), -1)
    f, j = np.nonzero(labels >= 0)
    xyz[f, labels[f, j]] = pts[f, j]
    pieces[f, labels[f, j]] = tid[f, j]
    return xyz, pieces


def test_learnt_ranges_tell_rigid_pairs_from_loose_ones():
    pts, truth, tid = _labelled(_arm_take())
    model = learn_ranges(*_model(pts, truth, tid))
    assert abs(model.dist[8, 10] - 76.0) < 1.0 and model.spread[8, 10] < 2.5  # one segment
    assert model.spread[4, 8] > 10.0  # across the elbow
    assert np.isnan(model.dist[0, 0]) and np.isclose(model.dist[3, 9], model.dist[9, 3])
    assert model.count[8, 9] == model.count[9, 8] > 0


def test_a_piece_back_after_a_long_gap_is_named_by_the_learnt_distances():
    """After the gap the forearm's marker 9 comes back unnamed and marker 8's point under the
    name of head marker 12 (the head is gone for good: no rigid partner of that name can
    object, and none of marker 8's own is under its name). The distances learnt over the take
    name both."""
    pts, truth, tid = _labelled(_arm_take())
    lab = truth.copy()
    after = np.zeros_like(lab, bool)
    after[600:] = True
    lab[after & (truth == 9)] = -1
    lab[after & (truth == 8)] = 12
    out, named, unnamed, model = range_relabel(pts, lab, tid, 14)
    assert named == 2 and unnamed == 0
    assert np.array_equal(out, truth)
    # already right: nothing to do
    same, named, unnamed, _ = range_relabel(pts, truth, tid, 14, model=model)
    assert named == unnamed == 0 and np.array_equal(same, truth)
    # a hinted point keeps its piece
    prot = np.zeros_like(lab, bool)
    prot[700][truth[700] == 8] = True
    kept, _, _, _ = range_relabel(pts, lab, tid, 14, model=model, protected=prot)
    assert (kept[after & (truth == 8)] == 12).all() and (kept[after & (truth == 9)] == 9).all()


def test_a_returning_symmetric_cluster_is_told_apart_by_the_learnt_distances():
    """All three forearm points come back unnamed after the gap. The forearm is a rigid group
    over the take, but its triangle fits two ways; the distances learnt over the take (to the
    upper arm and the chair) decide which."""
    pts, truth, tid = _labelled(_arm_take())
    lab = truth.copy()
    lab[600:][np.isin(truth[600:], list(FORE))] = -1
    xyz, pieces = _model(pts, lab, tid)
    groups = take_groups(xyz, pieces)
    assert any(set(g.tolist()) == set(FORE) for g in groups.members)
    plain, _ = rigid_relabel(pts, lab, tid, groups, stride=1, min_votes=1)
    assert (plain[600:][np.isin(truth[600:], list(FORE))] == -1).all()  # ambiguous alone
    out, rep = rigid_relabel(pts, lab, tid, groups, stride=1, min_votes=1,
                             tiebreak=range_tiebreak(learn_ranges(xyz, pieces)))
    assert rep["pieces_renamed"] == 3
    assert np.array_equal(out, truth)


def test_the_labeller_with_the_take_check_on_the_arm_take():
    """End to end (shuffled points, frame 0 labelled): every sample right, and the take check
    changes nothing that was right."""
    xyz = _arm_take(seed=1)
    pts, truth = points_from_trajectories(xyz, seed=1)
    h = np.full(truth.shape, -1, np.int32)
    h[0] = truth[0]
    on = label_assignment(pts, h, 14)
    off = label_assignment(pts, h, 14, take_check=False)
    assert "range_named" in on.report  # the forearm was absent for 300 frames: the check ran
    ok_on = (on.labels == truth)[truth >= 0].mean()
    assert ok_on == 1.0 and ok_on >= (off.labels == truth)[truth >= 0].mean()


@pytest.mark.slow
def test_real_basket_sprint_after_the_body_markers_vanish():
    """kinematics_basket_sprint: after frame 2200 the head, scapula and hand markers never
    come back; the forearm cluster (rigid over the take, not near the reference frame) and
    the arm points seen one or two at a time are named by the take check (96.96 % without;
    99.39 % before the judged coverage, the ungrouped tie-breakers, the exchange, the tied
    fits' common points and the unattached labels)."""
    from carapost.io.c3d import read_c3d
    p = REAL / "kineticstoolkit/kinematics_basket_sprint.c3d"
    if not p.exists():
        pytest.skip(f"{p} not available")
    d = read_c3d(p)
    x = d.xyz[:, d.marker_indices()]
    f0 = int(np.argmax(np.isfinite(x).all(-1).sum(1)))
    pts, truth = points_from_trajectories(x, seed=1)
    h = np.full(truth.shape, -1, np.int32)
    h[f0] = truth[f0]
    r = label_assignment(pts, h, x.shape[1])
    assert label_accuracy(r.labels, truth)["accuracy"] > 0.995
    assert r.report["take_renamed"] > 100


def _with_hand(xyz):
    """The arm take with a hand (14) and a finger (15) beyond the forearm's far end (marker 10,
    61 and 85 mm on along 8 -> 10): they flex by +-12 mm against the forearm, so they are in no
    rigid group and can never be confirmed."""
    F = len(xyz)
    axis = xyz[:, 10] - xyz[:, 8]
    wob = 12.0 * np.sin(2 * np.pi * np.arange(F) / 97.0)[:, None] * np.array([1.0, 0.0, 0.0])
    hand = xyz[:, 10] + 0.8 * axis + wob
    finger = xyz[:, 10] + 1.12 * axis + wob
    return np.concatenate([xyz, hand[:, None], finger[:, None]], axis=1)


def test_a_tie_is_broken_by_markers_of_no_rigid_group():
    """After the gap only the forearm triangle (two placements fit it) and the hand and finger
    are seen. They are in no rigid group, so never confirmed; with the groups given, the
    tie-breaker counts them, and their learnt distances (61 and 137 mm from markers 10 and
    8) name the forearm."""
    xyz = _with_hand(_arm_take())
    xyz[600:, list(CHAIR) + list(ARM)] = np.nan
    pts, truth, tid = _labelled(xyz)
    lab = truth.copy()
    lab[600:][np.isin(truth[600:], list(FORE))] = -1
    xyz_l, pieces = _model(pts, lab, tid, M=16)
    groups = take_groups(xyz_l, pieces)
    assert not any(np.isin(g, [14, 15]).any() for g in groups.members)
    model = learn_ranges(xyz_l, pieces)
    kw = dict(stride=1, min_votes=1)
    alone, _ = rigid_relabel(pts, lab, tid, groups, tiebreak=range_tiebreak(model), **kw)
    assert (alone[600:][np.isin(truth[600:], list(FORE))] == -1).all()  # nothing confirmed outside
    out, rep = rigid_relabel(pts, lab, tid, groups, tiebreak=range_tiebreak(model, groups=groups), **kw)
    assert rep["pieces_renamed"] == 3
    assert np.array_equal(out, truth)


def test_coverage_over_the_judged_frames():
    """After the gap marker 9 comes back under the name of head marker 12 and marker 10 is seen
    in 6 frames only: the forearm is fitted (three points) there alone. Over all its 300
    frames the piece has 6 votes; over the frames a fit could judge, all of them."""
    xyz = _arm_take()
    xyz[600:700, 10] = np.nan
    xyz[706:, 10] = np.nan
    pts, truth, tid = _labelled(xyz)
    lab = truth.copy()
    lab[600:][truth[600:] == 9] = 12
    xyz_t, pieces = _model(pts, truth, tid)
    groups = take_groups(xyz_t, pieces)
    kw = dict(stride=1, min_votes=1, tiebreak=range_tiebreak(learn_ranges(xyz_t, pieces)))
    plain, rep = rigid_relabel(pts, lab, tid, groups, **kw)
    assert rep["pieces_renamed"] == 0 and (plain[600:][truth[600:] == 9] == 12).all()
    out, rep = rigid_relabel(pts, lab, tid, groups, judged=True, **kw)
    assert rep["pieces_renamed"] == 1
    assert np.array_equal(out, truth)


def test_an_exchanged_pair_is_put_back_whole():
    """Chair marker 3 and the hand (in no rigid group) exchanged over frames 100-199: the chair's
    fit names its point; the hand's point, displaced from the chair's name, is left unnamed -
    or, with ``exchange``, takes the name the chair point had (the hand's)."""
    xyz = _with_hand(_arm_take())
    pts, truth, tid = _labelled(xyz)
    lab = truth.copy()
    seg = np.zeros_like(lab, bool)
    seg[100:200] = True
    lab[seg & (truth == 3)] = 14
    lab[seg & (truth == 14)] = 3
    xyz_t, pieces = _model(pts, truth, tid, M=16)
    groups = take_groups(xyz_t, pieces)
    plain, _ = rigid_relabel(pts, lab, tid, groups, stride=1, min_votes=1)
    assert (plain[seg & (truth == 3)] == 3).all() and (plain[seg & (truth == 14)] == -1).all()
    out, rep = rigid_relabel(pts, lab, tid, groups, stride=1, min_votes=1, exchange=True)
    assert np.array_equal(out, truth)


def test_a_tied_fit_names_the_points_both_placements_agree_on():
    """The forearm triangle alone in a frame: markers 8 and 10 cannot be told apart, marker 9
    (the apex, 49 and 50 mm from them) can."""
    from carapost.core.label_rigid import fit_groups
    xyz = _arm_take()
    pts, truth, tid = _labelled(xyz)
    groups = take_groups(*_model(pts, truth, tid))
    P = np.full_like(pts[100], np.nan)
    fore = np.isin(truth[100], list(FORE))
    P[fore] = pts[100][fore]
    assert (fit_groups(P, groups) == -1).all()
    out = fit_groups(P, groups, partial=True)
    assert np.array_equal(np.flatnonzero(out >= 0), np.flatnonzero(truth[100] == 9))
    assert (out[truth[100] == 9] == 9).all()


def test_a_label_attached_to_nothing_is_given_on_its_costs():
    """A sync object (14) swinging 600 mm about a point 1.2 m from the athlete: every distance
    of it varies by a fifth or more, so no partner can confirm it. Its tracklet after frame
    700 comes back unnamed: the take check names it on the learnt distances alone (a body
    marker always has a partner within a few %, and still needs one)."""
    xyz = _arm_take()
    F = len(xyz)
    t = np.arange(F) / 60.0
    sync = np.array([1200.0, 0.0, 300.0]) + 600.0 * np.stack(
        [np.sin(0.7 * t), np.cos(0.3 * t), 0.3 * np.sin(1.1 * t)], axis=1)
    pts, truth, tid = _labelled(np.concatenate([xyz, sync[:, None]], axis=1))
    tid[700:][truth[700:] == 14] += 100
    lab = truth.copy()
    lab[700:][truth[700:] == 14] = -1
    out, named, unnamed, model = range_relabel(pts, lab, tid, 15)
    assert (model.spread[14, :14] > 0.1 * model.dist[14, :14]).all()
    assert named == 1 and unnamed == 0 and np.array_equal(out, truth)
    kept, named, _, _ = range_relabel(pts, lab, tid, 15, unattached_rel=1.0)  # nothing that loose
    assert named == 0 and (kept[700:][truth[700:] == 14] == -1).all()
