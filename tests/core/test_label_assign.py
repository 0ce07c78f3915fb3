"""The default labeller (tracklets + global assignment) on synthetic and real data."""

import numpy as np
import pytest

from carapost.core.label_assign import AssignmentParams, kabsch, label_assignment, motion_scales
from carapost.core.labelling import label_accuracy, points_from_trajectories
from carapost.synth.mocap import body_motion, corrupt, face_motion


def _case(motion, *, ref=0, seed=0, **kw):
    c = corrupt(motion, seed=seed, **kw)
    pts, truth = points_from_trajectories(c.clean_labels_xyz, c.spurious, seed=seed)
    h = np.full(truth.shape, -1, np.int32)
    h[ref] = truth[ref]
    return pts, truth, h


@pytest.fixture(scope="module")
def face():
    return face_motion(60, 600, 60.0, seed=3)


@pytest.fixture(scope="module")
def body():
    return body_motion(600, 120.0, seed=3)


def test_face_with_dropouts_noise_spurious_and_ghosts(face):
    pts, truth, h = _case(face, noise_mm=0.1, gap_rate=0.003, spurious_rate=0.2, ghost_tracks=4)
    r = label_assignment(pts, h, face.n_markers)
    a = label_accuracy(r.labels, truth)
    assert a["accuracy"] >= 0.999, a
    assert a["wrong"] == 0 and a["spurious_labelled"] <= 5
    assert r.report["reference_frame"] == 0 and r.report["unlabelled_points"] >= 100


def test_body_at_60_hz(body):
    fast = body_motion(600, 60.0, seed=4)
    pts, truth, h = _case(fast, noise_mm=0.3, gap_rate=0.002, spurious_rate=0.1)
    a = label_accuracy(label_assignment(pts, h, fast.n_markers).labels, truth)
    assert a["accuracy"] >= 0.999 and a["wrong"] == 0, a


def test_reference_in_the_middle_labels_backwards_too(body):
    pts, truth, h = _case(body, ref=300, spurious_rate=0.05)
    r = label_assignment(pts, h, body.n_markers)
    a = label_accuracy(r.labels[:300], truth[:300])
    assert a["accuracy"] >= 0.999, a
    assert r.report["reference_frame"] == 300


def test_hints_always_win(face):
    pts, truth, h = _case(face, gap_rate=0.0, spurious_rate=0.0)
    M = face.n_markers
    # a "fully labelled" marker 5 hinted everywhere, and a user mapping in frame 100 that says
    # markers 7 and 8 are the other way round: labelling continues from the mapping
    h[truth == 5] = 5
    j7 = np.flatnonzero(truth[100] == 7)[0]
    j8 = np.flatnonzero(truth[100] == 8)[0]
    h[100, j7], h[100, j8] = 8, 7
    r = label_assignment(pts, h, M, repair_swaps=False)
    assert (r.labels[truth == 5] == 5).all()
    assert r.labels[100, j7] == 8 and r.labels[100, j8] == 7
    assert label_accuracy(r.labels[:100], truth[:100])["accuracy"] >= 0.999
    remapped = np.where(truth == 7, 8, np.where(truth == 8, 7, truth))
    assert label_accuracy(r.labels[100:], remapped[100:])["accuracy"] >= 0.999


def test_ignored_markers_keep_hints_and_are_not_reused(face):
    pts, truth, h = _case(face, gap_rate=0.004, spurious_rate=0.3)
    h[truth == 3] = 3
    r = label_assignment(pts, h, face.n_markers, ignore=[3])
    assert (r.labels[truth == 3] == 3).all()
    assert ((r.labels == 3) == (truth == 3)).all()


def test_template_instead_of_hints(face):
    pts, truth, _ = _case(face, gap_rate=0.002, spurious_rate=0.05)
    r = label_assignment(pts, None, face.n_markers, template=face.xyz[0] + np.array([5.0, -3.0, 2.0]))
    assert label_accuracy(r.labels, truth)["accuracy"] >= 0.999


def test_inputs_not_mutated(face):
    pts, truth, h = _case(face, spurious_rate=0.1)
    p0, h0 = pts.copy(), h.copy()
    label_assignment(pts, h, face.n_markers)
    np.testing.assert_array_equal(pts, p0)
    np.testing.assert_array_equal(h, h0)


def test_bad_input_is_rejected(face):
    pts, truth, h = _case(face)
    with pytest.raises(ValueError, match="hints .* or a template"):
        label_assignment(pts, None, face.n_markers)
    with pytest.raises(ValueError, match="shape"):
        label_assignment(pts[..., :2], h, face.n_markers)
    with pytest.raises(ValueError, match="ignored marker"):
        label_assignment(pts, h, face.n_markers, ignore=[99])
    with pytest.raises(ValueError, match="template must have shape"):
        label_assignment(pts, None, face.n_markers, template=np.zeros((3, 3)))


def test_progress_can_stop_early(face):
    pts, truth, h = _case(face, spurious_rate=0.5)
    calls = []

    def progress(done, total):
        calls.append((done, total))
        return False

    r = label_assignment(pts, h, face.n_markers, progress=progress)
    assert len(calls) == 1 and r.labels.shape == truth.shape


def test_kabsch_recovers_rotation():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    b = a @ R.T + [1.0, 2.0, 3.0]
    R2, ca, cb = kabsch(a, b)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose((a - ca) @ R2.T + cb, b, atol=1e-10)


def test_motion_scales(face):
    pts, truth = points_from_trajectories(face.xyz, shuffle=False)
    links = np.tile(np.arange(pts.shape[1], dtype=np.int32), (len(pts), 1))
    links[0] = -1
    rel, fastest = motion_scales(pts, links)
    steps = np.linalg.norm(np.diff(face.xyz, axis=0), axis=-1)
    assert 0 < rel < fastest <= steps.max() + 1e-9


def test_params_are_tunable(face):
    pts, truth, h = _case(face, spurious_rate=0.1)
    r = label_assignment(pts, h, face.n_markers, params=AssignmentParams(gate=3.0, neighbours=4))
    assert label_accuracy(r.labels, truth)["accuracy"] >= 0.99


# ------------------------------------------------------------------------------- real data
def _real(real_data, rel, seed=1):
    from carapost.io.c3d import read_c3d
    d = read_c3d(real_data / rel)
    x = d.xyz[:, d.marker_indices()]
    valid = np.isfinite(x).all(-1)
    full = np.flatnonzero(valid.all(1))
    f0 = int(full[0]) if len(full) else int(np.argmax(valid.sum(1)))
    pts, truth = points_from_trajectories(x, seed=seed)
    h = np.full(truth.shape, -1, np.int32)
    h[f0] = truth[f0]
    return pts, truth, h, x.shape[1]


@pytest.mark.parametrize("rel, target", [("ezc3d/Vicon.c3d", 0.999), ("ezc3d/Qualisys.c3d", 1.0),
                                         ("opensim-core/walking2.c3d", 0.999)])
def test_real_files_with_hidden_shuffled_labels(real_data, rel, target):
    pts, truth, h, M = _real(real_data, rel)
    a = label_accuracy(label_assignment(pts, h, M).labels, truth)
    assert a["accuracy"] >= target, a


def test_real_face_file(real_data):
    # Facial-Sing.c3d's own labels are inconsistent in places (a marker jumping 60-70 mm for a
    # few dozen frames around frame 820, and a ghost "Unlabeled1"): most of it must agree.
    pts, truth, h, M = _real(real_data, "c3d.org-samples/sample_29/Facial-Sing.c3d")
    a = label_accuracy(label_assignment(pts, h, M).labels, truth)
    assert a["accuracy"] >= 0.9, a
    assert label_accuracy(label_assignment(pts, h, M).labels[:800], truth[:800])["accuracy"] >= 0.999
