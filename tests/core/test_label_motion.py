"""Short pieces named by the motion of the markers they continue (label_motion)."""

import numpy as np

from carapost.core.label_motion import fitting_samples, motion_bridge, motion_predictions
from carapost.core.labelling import points_from_trajectories


def _moving(F=40, rate=120.0, seed=0):
    """Three markers of a forearm-like triangle (49, 50, 76 mm) moving along a curve and
    turning, mm, plus a far marker. Returns xyz (F, 4, 3)."""
    rng = np.random.default_rng(seed)
    t = np.arange(F) / rate
    a, b, c = 49.0, 50.0, 76.0
    x = (a * a - b * b + c * c) / (2 * c)
    tri = np.array([[0, 0, 0], [0, np.sqrt(a * a - x * x), -x], [0, 0, -c]])  # Marker1, 2, 4
    ang = 1.5 * t
    R = np.stack([np.stack([np.cos(ang), -np.sin(ang), 0 * ang], -1),
                  np.stack([np.sin(ang), np.cos(ang), 0 * ang], -1),
                  np.stack([0 * ang, 0 * ang, 1 + 0 * ang], -1)], 1)  # (F, 3, 3)
    centre = np.stack([1500 * t, 300 * np.sin(4 * t), 700 + 0 * t], -1)  # 12.5 mm per frame
    xyz = np.concatenate([centre[:, None] + np.einsum("fij,mj->fmi", R, tri),
                          (centre + [600, 0, -500])[:, None]], axis=1)
    return xyz + rng.normal(scale=0.2, size=xyz.shape)


def _pieces(xyz, gap_frames, names_in_gap):
    """Points in fixed columns, one long tracklet per marker before and after the gap and a
    one-frame tracklet per point in each gap frame; labels true outside the gap and
    ``names_in_gap`` (per marker) inside it."""
    pts, truth = points_from_trajectories(xyz, shuffle=False)
    F, N = truth.shape
    tid = np.where(np.isfinite(pts[..., 0]), truth, -1).astype(np.int32)
    g0 = min(gap_frames)
    tid[g0:] = np.where(tid[g0:] >= 0, tid[g0:] + 10, -1)
    labels = truth.copy()
    for i, f in enumerate(gap_frames):
        tid[f] = np.where(tid[f] >= 0, 100 + 10 * i + np.arange(N), -1)
        labels[f] = np.where(truth[f] >= 0, np.asarray(names_in_gap)[np.maximum(truth[f], 0)], -1)
    return pts, truth, tid, labels


def test_motion_predictions_exact_for_linear_motion():
    F = 20
    t = np.arange(F, dtype=float)
    xyz = np.stack([np.stack([3 * t, -2 * t, 0 * t + 5], -1), np.stack([t, t, t], -1)], 1)
    gap = np.arange(8, 11)
    both = motion_predictions(xyz, gap, 8, 10, reach=4)
    np.testing.assert_allclose(both, xyz[gap], atol=1e-9)
    one = xyz.copy()
    one[8:] = np.nan  # only frames before: constant velocity from the two nearest
    np.testing.assert_allclose(motion_predictions(one, gap, 8, 10, reach=4), xyz[gap], atol=1e-9)
    far = xyz.copy()
    far[2:14] = np.nan  # nothing within reach
    assert np.isnan(motion_predictions(far, gap, 8, 10, reach=3)).all()


def test_bridge_names_unnamed_and_mirrored_single_frames():
    """Marker1 and Marker4 of the triangle are seen alone (with Marker2) on one-frame
    tracklets: unnamed in one frame, exchanged (the mirror placement) in another, named
    after an absent far marker in a third; their motion across the gap names all of them."""
    xyz = _moving()
    xyz[20:26, 3] = np.nan  # the far marker is absent over the gap: its name is free
    gap = [21, 23, 25]
    pts, truth, tid, labels = _pieces(xyz, gap, [0, 1, 2, 3])
    labels[21, :3] = [-1, 1, -1]          # unnamed
    labels[23, :3] = [2, 1, 0]            # Marker1 / Marker4 exchanged
    labels[25, :3] = [3, 1, -1]           # Marker1 named after the absent far marker
    for f in (22, 24):
        pts[f, :3] = np.nan
        tid[f, :3] = labels[f, :3] = -1
    out, n = motion_bridge(pts, labels, tid, 4)
    ok = np.isfinite(pts[..., 0])
    assert (out[ok] == truth[ok]).all()
    assert n == 6  # two tracklets in each of the three frames


def test_bridge_leaves_ambiguous_pieces():
    """A point midway between two markers' predictions (6 mm apart) is left unnamed."""
    xyz = _moving()
    xyz[:, 2] = xyz[:, 0] + [0.0, 6.0, 0.0]  # Marker4 moved next to Marker1
    pts, truth, tid, labels = _pieces(xyz, [20], [0, 1, 2, 3])
    pts[20, 0] = 0.5 * (xyz[20, 0] + xyz[20, 2])
    pts[20, 2] = np.nan
    tid[20, 2] = labels[20, 2] = -1
    labels[20, 0] = -1
    out, n = motion_bridge(pts, labels, tid, 4)
    assert n == 0 and out[20, 0] == -1


def test_bridge_keeps_a_name_that_keeps_its_tight_pairs():
    """Marker2's point in a gap frame lies where the far marker's motion puts it (the two
    paths cross there), and Marker2 has no motion of its own around the gap: with its name
    confirmed by its tight pairs (fitting_samples) it keeps it; without, the motion wins."""
    xyz = _moving()
    xyz[19, 3], xyz[21, 3] = xyz[19, 1], xyz[21, 1]
    xyz[20, 3] = np.nan
    pts, truth, tid, labels = _pieces(xyz, [20], [0, 1, 2, 3])
    labels[:20, 1] = -1
    labels[21:, 1] = -1
    D = np.linalg.norm(xyz[20, :, None] - xyz[20, None], axis=-1)
    S = np.ones((4, 4))
    S[3, :] = S[:, 3] = 100.0  # the far marker is loose to all
    anchors = fitting_samples(pts, labels, tid >= 100, D, S)
    assert anchors[20, :3].all()
    wrong = labels.copy()
    wrong[20, 1] = 2  # Marker2's point named Marker4: 49 mm from Marker1, where Marker4 is 76
    assert not fitting_samples(pts, wrong, tid >= 100, D, S)[20, 1]
    kept, _ = motion_bridge(pts, labels, tid, 4, anchors=anchors)
    assert kept[20, 1] == 1
    moved, _ = motion_bridge(pts, labels, tid, 4)
    assert moved[20, 1] == 3
