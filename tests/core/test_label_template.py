"""Marker-set templates and Label From Template."""

import numpy as np
import pytest

from carapost.core.template import MarkerTemplate, label_from_template, similarity_fit, template_from_frame
from carapost.synth.mocap import _rot, face_motion


@pytest.fixture(scope="module")
def face():
    return face_motion(80, 1200, 60.0, seed=4)


def _scene(X, seed, drop=5, spurious=5, scale=1.0):
    rng = np.random.default_rng(seed)
    R = _rot(rng.normal(size=3))
    P = scale * X @ R.T + rng.normal(size=3) * 200
    M = len(X)
    keep = np.ones(M, bool)
    keep[rng.choice(M, drop, replace=False)] = False
    truth = np.concatenate([np.flatnonzero(keep), -np.ones(spurious, int)])
    P = np.concatenate([P[keep], rng.uniform(P.min(0), P.max(0), (spurious, 3))])
    P = np.concatenate([P, np.full((2, 3), np.nan)])  # empty slots
    truth = np.concatenate([truth, [-1, -1]])
    o = rng.permutation(len(P))
    return P[o], truth[o], keep


@pytest.mark.parametrize("frame", [0, 400, 1100])
def test_other_expression_any_pose(face, frame):
    tpl = template_from_frame(face.xyz[0], face.names, face.sticks, source="synthetic frame 0")
    for seed in range(3):
        P, truth, keep = _scene(face.xyz[frame], seed)
        fit = label_from_template(P, tpl)
        real = truth >= 0
        # no marker gets another marker's name; a spurious point may rarely sit nearer to a
        # marker's place than the marker itself
        assert not (real & (fit.labels >= 0) & (fit.labels != truth)).any()
        assert (fit.labels[real] == truth[real]).mean() >= 0.98
        if (fit.labels == truth).all():
            np.testing.assert_array_equal(np.sort(fit.missing), np.flatnonzero(~keep))
            assert len(fit.unlabelled) == 5


def test_scale_and_rigid_options(face):
    P, truth, _ = _scene(face.xyz[300], 7, scale=1.1)
    fit = label_from_template(P, face.xyz[0])
    assert (fit.labels == truth).all() and fit.scale == pytest.approx(1.1, rel=0.03)
    fit = label_from_template(P, face.xyz[0], nonrigid=False)
    assert (fit.labels[truth >= 0] == truth[truth >= 0]).mean() >= 0.95


def test_real_face_template(real_data):
    from carapost.io.c3d import read_c3d
    x = read_c3d(real_data / "c3d.org-samples/sample_29/Facial-Sing.c3d").xyz[:, :37]
    for f in (500, 1500, 2500):
        P, truth, _ = _scene(x[f], f, drop=3, spurious=3)
        assert (label_from_template(P, x[422]).labels == truth).all()


def test_similarity_fit():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(10, 3))
    R = _rot(np.array([0.3, -0.2, 0.5]))
    b = 2.0 * a @ R.T + [1.0, 2.0, 3.0]
    s, R2, t = similarity_fit(a, b)
    assert s == pytest.approx(2.0) and np.allclose(R2, R) and np.allclose(t, [1.0, 2.0, 3.0])


def test_template_validation():
    with pytest.raises(ValueError, match="unique"):
        MarkerTemplate(["a", "a"], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="positions of shape"):
        MarkerTemplate(["a", "b"], np.zeros((3, 3)))
    with pytest.raises(ValueError, match="sticks"):
        MarkerTemplate(["a", "b"], np.zeros((2, 3)), np.array([[0, 5]]))
    with pytest.raises(ValueError, match="no marker position"):
        template_from_frame(np.full((2, 3), np.nan), ["a", "b"])
    with pytest.raises(ValueError, match="at least 3"):
        label_from_template(np.zeros((2, 3)), np.zeros((5, 3)))
