"""The learned face model (carapost.core.face_model): basis choice, bounded fit, filling."""

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from carapost.core.camera import rodrigues
from carapost.core.face_model import (
    bounded_quadratic,
    build_face_model,
    face_model_fill,
    fit_face_model,
    procrustes_align,
)
from carapost.core.gapfill import hide_runs


def linear_faces(F=200, P=30, K=3, seed=0):
    """Faces ``neutral + sum a_k E_k`` (amplitudes 0..1) under random head motion."""
    rng = np.random.default_rng(seed)
    neutral = rng.normal(scale=40, size=(P, 3))
    E = rng.normal(scale=4, size=(K, P, 3))
    a = np.stack([np.clip(1.2 * np.sin(np.linspace(0, 6 + k, F) + k), 0, 1) for k in range(K)], axis=1)
    shapes = neutral + np.einsum("fk,kpd->fpd", a, E)
    R = rodrigues(rng.normal(scale=0.2, size=(F, 3)))
    t = rng.normal(scale=20, size=(F, 3))
    return np.einsum("fij,fpj->fpi", R, shapes) + t[:, None], shapes


def test_bounded_quadratic_matches_bvls():
    rng = np.random.default_rng(0)
    N, K, R = 60, 12, 80
    A = 100 + rng.normal(size=(N, R, 1)) + rng.normal(scale=2, size=(N, R, K))   # nearly collinear columns
    y = np.einsum("nrk,nk->nr", A, rng.uniform(-0.3, 0.6, (N, K))) + rng.normal(scale=0.5, size=(N, R))
    w = bounded_quadratic(np.einsum("nrk,nrl->nkl", A, A), np.einsum("nrk,nr->nk", A, y))
    ref = np.array([lsq_linear(A[n], y[n], bounds=(0, 1), method="bvls").x for n in range(N)])
    assert w.min() >= 0 and w.max() <= 1
    np.testing.assert_allclose(w, ref, atol=1e-6)
    # a warm start from a nearby point reaches the same solution
    G, h = np.einsum("nrk,nrl->nkl", A, A), np.einsum("nrk,nr->nk", A, y)
    w2 = bounded_quadratic(G, h, init=np.clip(ref + rng.normal(scale=0.2, size=ref.shape), 0, 1))
    np.testing.assert_allclose(w2, ref, atol=1e-6)


def test_procrustes_removes_head_motion():
    rng = np.random.default_rng(4)
    shape = rng.normal(scale=40, size=(25, 3))
    R = rodrigues(rng.normal(scale=0.5, size=(20, 3)))
    X = np.einsum("fij,pj->fpi", R, shape) + rng.normal(scale=30, size=(20, 1, 3))
    aligned, mean = procrustes_align(X)
    np.testing.assert_allclose(aligned, np.repeat(aligned[:1], 20, 0), atol=1e-9)
    np.testing.assert_allclose(mean.mean(0), 0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(mean - mean[0], axis=1), np.linalg.norm(shape - shape[0], axis=1))


def test_basis_is_the_most_extreme_faces():
    """The basis faces are the frames with the largest projections on the principal
    components of the aligned shapes (seed 001: "a measure of extremeness")."""
    X, _ = linear_faces()
    for both in (False, True):
        m = build_face_model(X, n_components=3, both_ends=both)
        aligned, _ = procrustes_align(X)
        D = aligned.reshape(len(X), -1)
        D = D - D.mean(0)
        Vt = np.linalg.svd(D, full_matrices=False)[2][:3]
        proj = D @ Vt.T
        expect = set(np.argmax(np.abs(proj), 0).tolist())
        if both:
            expect |= set(np.argmax(proj, 0).tolist()) | set(np.argmin(proj, 0).tolist())
        assert set(m.frames.tolist()) == expect
        assert m.components == 3 and m.explained > 0.999
        np.testing.assert_allclose(m.basis, aligned[np.sort(m.frames)], atol=1e-6)


def test_fit_recovers_hidden_markers():
    X, _ = linear_faces()
    m = build_face_model(X)
    hid = np.zeros(X.shape[:2], bool)
    hid[:, :5] = True                                   # five markers occluded in every frame
    res = face_model_fill(np.where(hid[..., None], np.nan, X), hid, m, anchor_blend=False)
    assert res.filled[hid].all()
    err = np.linalg.norm(res.xyz[hid] - X[hid], axis=-1)
    assert np.median(err) < 0.1                         # deformations are ~6.5 mm
    fit = fit_face_model(m, np.where(hid[..., None], np.nan, X), np.arange(len(X)))
    assert fit.weights.min() >= 0 and fit.weights.max() <= 1
    assert np.median(fit.rms) < 0.05


def test_too_few_complete_frames():
    X, _ = linear_faces(F=30)
    X[::2, 0] = np.nan
    X[1::2, 1] = np.nan
    with pytest.raises(ValueError, match="frames with all 4 model markers"):
        build_face_model(X, points=[0, 1, 2, 3])
    m = build_face_model(X)             # the default leaves out one of the two never-together markers
    assert len(m.points) == X.shape[1] - 1 and not (0 in m.points and 1 in m.points)
    assert m.n_complete == 15


def test_synthetic_rom_model():
    """A model from a range-of-motion take (all markers, seed 7) fills the gaps of another
    take: better than the neighbour method on the jaw markers hidden whenever the jaw opens.

    Measured (60-frame takes): ROM model median ~0.3 mm."""
    from carapost.synth import SynthConfig, generate_take

    cfg = SynthConfig(n_markers=35, n_frames=60, blinks=False, high_motion=True)
    rom = generate_take(cfg, seed=7).truth
    take = generate_take(cfg, seed=0).truth
    rng = np.random.default_rng(1)
    X = take.xyz + rng.normal(scale=0.05, size=take.xyz.shape)
    hid = hide_runs(np.ones(X.shape[:2], bool), 0.1, seed=2)
    m = build_face_model(rom.xyz)
    assert len(m.points) == X.shape[1]
    res = face_model_fill(np.where(hid[..., None], np.nan, X), hid, m)
    err = np.linalg.norm(res.xyz[hid] - take.xyz[hid], axis=-1)
    assert res.filled[hid].all()
    assert np.median(err) < 0.6 and np.percentile(err, 95) < 2.0


def test_real_c3d_face_model(real_data):
    from carapost.io.c3d_take import take_from_c3d

    take = take_from_c3d(real_data / "c3d.org-samples" / "sample_29" / "Facial-Sing.c3d")
    X = take.xyz[:1500]
    hid = hide_runs(np.isfinite(X).all(-1), 0.05, seed=0)
    Xh = np.where(hid[..., None], np.nan, X)
    m = build_face_model(Xh)
    assert len(m.points) == 37                          # the sparse "Unlabeled1" is left out
    res = face_model_fill(Xh, hid, m)
    err = np.linalg.norm(res.xyz[hid] - X[hid], axis=-1)
    assert res.filled[hid][np.isin(np.nonzero(hid)[1], m.points)].all()
    # measured: median 0.29 mm, p95 1.4 mm, max 4 mm
    assert np.nanmedian(err) < 0.4 and np.nanpercentile(err, 95) < 2.0
