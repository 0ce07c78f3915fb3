"""Long-range shape check (re-identification against the shape around the reference frame)."""

from pathlib import Path

import numpy as np
import pytest

from carapost.core.label_assign import label_assignment
from carapost.core.label_shape import shape_costs, shape_model, shape_relabels
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
    ("kineticstoolkit/kinematics_tennis_serve.c3d", 0.925, 0.998),  # confused during each serve
    ("c3d.org-samples/sample_29/Facial-Sing.c3d", 0.92, 0.994),  # file's own labels jump at 820-870
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
