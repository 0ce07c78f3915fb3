"""Long-range shape check (re-identification against the shape around the reference frame)."""

from pathlib import Path

import numpy as np
import pytest

from carapost.core.label_assign import label_assignment
from carapost.core.label_shape import rigid_over_take, shape_costs, shape_model, shape_relabels, take_rigidity
from carapost.core.labelling import label_accuracy, points_from_trajectories
from carapost.core.swaps import apply_relabel, detect_swaps
from carapost.synth.mocap import body_motion, face_motion

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"


def _pieces(x: np.ndarray) -> np.ndarray:
    """Tracklet id of every sample: each marker's runs of valid samples."""
    valid = np.isfinite(x[..., 0])
    F, M = valid.shape
    brk = np.zeros((F, M), bool)
    brk[0] = valid[0]
    brk[1:] = valid[1:] & ~valid[:-1]
    cum = np.cumsum(brk.T.ravel()).reshape(M, F).T - 1
    return np.where(valid, cum, -1)


def _nearest_pair(x: np.ndarray, f: int) -> tuple[int, int]:
    d = np.linalg.norm(x[f][:, None] - x[f][None], axis=-1)
    np.fill_diagonal(d, np.inf)
    a, b = np.unravel_index(np.argmin(d), d.shape)
    return int(a), int(b)


@pytest.mark.parametrize("kind", ["body", "face"])
def test_swap_after_a_common_gap_is_repaired(kind):
    # two neighbouring markers vanish together and come back with each other's labels: no
    # jump to see (a gap on both sides), only the shape says which is which
    m = body_motion(600, 120.0, seed=1) if kind == "body" else face_motion(40, 600, 60.0, seed=1)
    truth = m.xyz.copy()
    a, b = _nearest_pair(truth, 300)
    x = truth.copy()
    x[290:300, [a, b]] = np.nan
    x[300:, [a, b]] = x[300:, [b, a]]
    rel = shape_relabels(x, 0, pieces=_pieces(x))
    fixed = apply_relabel(x, rel)
    ok = np.isfinite(x[..., 0])
    assert (fixed[ok] == np.where(np.isfinite(x[..., :1]), truth, np.nan)[ok]).all()
    assert {frozenset(p) for r in rel for p in r.pairs} == {frozenset((a, b))}
    assert all(r.start >= 290 for r in rel)


@pytest.mark.parametrize("kind", ["body", "face"])
def test_clean_trajectories_are_left_alone(kind):
    m = body_motion(900, 60.0, seed=2) if kind == "body" else face_motion(80, 900, 60.0, seed=2)
    x = m.xyz.copy()
    rng = np.random.default_rng(0)
    x += rng.normal(0, 0.2, x.shape)
    x[rng.random(x.shape[:2]) < 0.01] = np.nan
    assert shape_relabels(x, 450, pieces=_pieces(x)) == []


def test_reference_frame_and_fixed_markers_are_never_moved():
    m = body_motion(400, 120.0, seed=3)
    x = m.xyz.copy()
    a, b = _nearest_pair(x, 0)
    x[:, [a, b]] = x[:, [b, a]]  # "wrong" from the start: the reference frame says otherwise
    assert shape_relabels(x, 0, pieces=_pieces(x)) == []
    y = m.xyz.copy()
    y[200:, [a, b]] = y[200:, [b, a]]
    y[195:200, [a, b]] = np.nan
    assert shape_relabels(y, 0, pieces=_pieces(y), fixed=[a]) == []
    assert len(shape_relabels(y, 0, pieces=_pieces(y))) == 1


def test_model_and_costs_shapes():
    m = face_motion(30, 200, 60.0, seed=4)
    mod = shape_model(m.xyz, np.arange(0, 100, 5), k=5)
    assert mod.partners.shape == mod.dist.shape == mod.spread.shape == (30, 5)
    assert (mod.partners != np.arange(30)[:, None]).all()
    c = shape_costs(m.xyz, mod)
    assert c.shape == (200, 30) and np.median(c[:100]) < 1.0
    with pytest.raises(ValueError, match="frames, markers, 3"):
        shape_relabels(m.xyz[..., :2], 0)
    with pytest.raises(ValueError, match="reference frame"):
        shape_relabels(m.xyz, 500)
    with pytest.raises(ValueError, match="pieces"):
        shape_relabels(m.xyz, 0, pieces=np.zeros((3, 3), int))


def _real(rel: str):
    from carapost.io.c3d import read_c3d
    from carapost.ops.label_file import UNLABELLED_NAME
    p = REAL / rel
    if not p.exists():
        pytest.skip(f"{p} not available")
    d = read_c3d(p)
    idx = d.marker_indices()
    named = np.array([not UNLABELLED_NAME.match(d.labels[i]) for i in idx], bool)
    x, extra = d.xyz[:, idx[named]], d.xyz[:, idx[~named]]
    valid = np.isfinite(x).all(-1)
    f0 = int(np.flatnonzero(valid.all(1))[0])
    pts, truth = points_from_trajectories(x, extra, seed=1)
    h = np.full(truth.shape, -1, np.int32)
    h[f0] = truth[f0]
    return x, pts, truth, h


@pytest.mark.slow
@pytest.mark.parametrize("rel, before, now", [
    ("kineticstoolkit/kinematics_tennis_serve.c3d", 0.925, 0.9995),  # confused during each serve
    ("c3d.org-samples/sample_29/Facial-Sing.c3d", 0.92, 0.999),  # file's own labels jump at 820-870
])
def test_real_files_recover_after_confusion(rel, before, now):
    x, pts, truth, h = _real(rel)
    M = x.shape[1]
    off = label_accuracy(label_assignment(pts, h, M, shape_check=False).labels, truth)["accuracy"]
    on = label_accuracy(label_assignment(pts, h, M).labels, truth)["accuracy"]
    assert off < before and on >= now, (off, on)


def test_well_labelled_real_file_unchanged():
    x, pts, truth, h = _real("ezc3d/Vicon.c3d")
    r = label_assignment(pts, h, x.shape[1])
    assert label_accuracy(r.labels, truth)["accuracy"] == 1.0
    assert r.report["shape_repairs"] == 0
    assert detect_swaps(x).relabels == []


def test_frame_level_runs_repair_a_two_frame_confusion():
    # a confusion of two frames (fast motion) is too short for the default runs; the
    # labeller's last pass (every frame, runs of one frame, the same gain test) repairs it
    m = body_motion(400, 120.0, seed=3)
    truth = m.xyz.copy()
    a, b = _nearest_pair(truth, 200)
    x = truth.copy()
    x[200:202, [a, b]] = x[200:202, [b, a]]
    assert shape_relabels(x, 0) == []
    rel = shape_relabels(x, 0, stride=1, min_run=1, iterations=2)
    assert {frozenset(p) for r in rel for p in r.pairs} == {frozenset((a, b))}
    assert np.array_equal(apply_relabel(x, rel), truth, equal_nan=True)


def test_take_rigidity_tells_a_resting_joint_from_a_rigid_pair():
    # markers 0-2 on one segment, 3-4 on another joined to it; still for the first 100
    # frames (everything looks rigid there), then the joint bends by 45-135 degrees (an elbow)
    F = 600
    t = np.arange(F)
    s = np.maximum(t - 100, 0)
    ang = np.radians(90) * (1 - np.exp(-s / 10.0)) * (1 + 0.5 * np.sin(s / 30.0))
    seg1 = np.array([[0.0, 0, 0], [50, 0, 0], [0, 40, 0]])
    seg2 = np.array([[150.0, 0, 0], [200, 10, 0]])
    rot = np.stack([np.stack([np.cos(ang), -np.sin(ang), 0 * ang], 1), np.stack([np.sin(ang), np.cos(ang), 0 * ang], 1),
                    np.tile([0.0, 0, 1], (F, 1))], 1)  # (F, 3, 3) about the joint at x = 100
    joint = np.array([100.0, 0, 0])
    x = np.concatenate([np.tile(seg1, (F, 1, 1)), np.einsum("fij,mj->fmi", rot, seg2 - joint) + joint], 1)
    x += np.random.default_rng(0).normal(0, 0.2, x.shape)
    model = shape_model(x, np.arange(0, 100, 2), k=4)
    share = take_rigidity(model, x)
    same = np.array([[(m < 3) == (p < 3) for p in row] for m, row in enumerate(model.partners)])
    assert (share[same] > 0.9).all() and (share[~same] < 0.5).all()
    rigid = rigid_over_take(model, x)
    kept = rigid.partners >= 0
    assert kept.sum() == same.sum()
    assert all((m < 3) == (p < 3) for m, row in enumerate(rigid.partners) for p in row if p >= 0)
    # wrong labels over a third of the take do not make a rigid pair look non-rigid
    y = x.copy()
    y[300:500, [0, 1]] = y[300:500, [1, 0]]
    assert take_rigidity(model, y)[0][model.partners[0] == 2] > 0.6


def test_neighbour_segments_follow_the_pieces():
    from carapost.core.label_shape import _neighbour_segments
    from carapost.core.swaps import Relabel
    F, M = 100, 4
    pieces = np.tile(np.arange(M), (F, 1))
    pieces[40:, 1] = 10  # marker 1 changes tracklet at 40 and 70, marker 2 at 55
    pieces[70:, 1] = 11
    pieces[55:, 2] = 12
    perm = np.array([0, 2, 1, 3])
    assert _neighbour_segments(pieces, Relabel(40, 55, perm), F, 99) == [(55, 70), (0, 40)]
    # never over the reference frame
    assert _neighbour_segments(pieces, Relabel(40, 55, perm), F, 20) == [(55, 70)]


def test_propagation_carries_a_repair_over_tracklet_segments():
    # a swap carried on over three tracklet segments: with propagation, the repair of one
    # segment is tried on the next; the result is the same full repair
    m = body_motion(600, 120.0, seed=1)
    truth = m.xyz.copy()
    a, b = _nearest_pair(truth, 300)
    x = truth.copy()
    x[290:300, [a, b]] = np.nan
    x[300:, [a, b]] = x[300:, [b, a]]
    pc = _pieces(x)
    pc[400:, [a, b]] += 1000  # new tracklets at 400 and 500
    pc[500:, [a, b]] += 1000
    for prop in (False, True):
        rel = shape_relabels(x, 0, pieces=pc, propagate=prop)
        assert np.array_equal(apply_relabel(x, rel), np.where(np.isfinite(x), truth, np.nan), equal_nan=True)
