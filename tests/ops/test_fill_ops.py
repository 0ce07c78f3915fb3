"""Interpolate Gaps, Stabilize Data [Manual]/[Assisted] and Align Data as undoable operations."""

import copy

import numpy as np
import pytest

from carapost.core.camera import project
from carapost.model.params import GapFillingParameters, StabilizationParameters
from carapost.model.take import BrimModel, CameraInfo, ObsSource, PointKind, Recon, Take
from carapost.ops.fill import (
    align_data,
    evaluate_fill,
    face_model_for,
    interpolate_gaps,
    stabilize_assisted,
    stabilize_manual,
)
from carapost.ops.session import Session


def take_from_truth(tr, noise=0.05, seed=0):
    """A tracked take made from synthetic ground truth: cameras with the true poses, 2D
    observations where a marker is visible, 3D positions (with noise) where it is seen by two
    or more cameras; a brim of four points."""
    F, M, C = tr.visible.shape
    cams = [CameraInfo(f"cam{c}", c, tr.intrinsics[c], tuple(tr.image_size)) for c in range(C)]
    take = Take.new(cams, F, tr.frame_rate, R=tr.R, t=tr.t)
    take.add_points(M, labels=list(tr.names))
    rng = np.random.default_rng(seed)
    vis = tr.visible
    take.obs_xy[...] = np.where(vis[..., None], tr.xy, np.nan).astype(np.float32)
    take.obs_src[vis] = ObsSource.BLOB
    multi = vis.sum(-1) >= 2
    take.xyz[multi] = tr.xyz[multi] + rng.normal(scale=noise, size=(int(multi.sum()), 3))
    take.recon[multi] = Recon.MULTI_VIEW
    bx = tr.brim_xyz[:4]
    take.brim = BrimModel("test", tr.brim_xyz.copy(), np.ones(len(tr.brim_xyz)), -np.ones(len(tr.brim_xyz), np.int8))
    cols = take.add_points(4, kind=PointKind.BRIM, brim_index=np.arange(4))
    take.xyz[:, cols] = bx
    take.recon[:, cols] = Recon.MULTI_VIEW
    return take


@pytest.fixture(scope="module")
def synth():
    from carapost.synth import SynthConfig, generate_take

    return generate_take(SynthConfig(n_markers=35, n_frames=60, blinks=True, high_motion=True, seed=2)).truth


@pytest.fixture(scope="module")
def c3d(real_data):
    from carapost.io.c3d_take import take_from_c3d

    return take_from_c3d(real_data / "c3d.org-samples" / "sample_29" / "Facial-Sing.c3d")


@pytest.fixture
def sing(c3d):
    return Session(copy.deepcopy(c3d))


def col(take, label):
    return take.points.labels.index(label)


# ----------------------------------------------------------------------------- Interpolate Gaps
def test_interpolate_all_gaps(sing, undo_check):
    take = sing.take
    gaps = ~np.isfinite(take.xyz).all(-1)
    ch = interpolate_gaps(take)
    assert ch.report["filled"] == gaps.sum() and ch.report["unfilled"] == 0
    assert "filled" in ch.text
    before, after = undo_check(sing, ch)
    assert np.isfinite(take.xyz).all()
    assert (take.recon[gaps] == Recon.INTERPOLATED).all()
    np.testing.assert_array_equal(take.xyz[~gaps], before.xyz[~gaps])
    assert (take.recon[~gaps] == Recon.MULTI_VIEW).all()


def test_selected_points_and_active_range(sing):
    take = sing.take
    take.active_range = (1700, 1999)
    p = col(take, "section5-1")          # gaps at 1722-1787 and 1936-2123
    before = copy.deepcopy(take)
    sing.apply(interpolate_gaps(take, [p]))
    changed = ~(np.isfinite(before.xyz).all(-1)) & np.isfinite(take.xyz).all(-1)
    f, q = np.nonzero(changed)
    assert set(q.tolist()) == {p}
    assert f.min() == 1722 and f.max() == 1999
    assert np.isnan(take.xyz[2000:2124, p]).all()


def test_overwrite_existing_filled_gaps(sing):
    take = sing.take
    p = col(take, "section4-1")          # gap 821-862
    sing.apply(interpolate_gaps(take, [p]))
    first = take.xyz[821:863, p].copy()
    take.xyz[840, p] += 25.0             # spoil one interpolated sample
    assert not interpolate_gaps(take, [p]).changes           # nothing left to fill
    ch = interpolate_gaps(take, [p], params=GapFillingParameters(overwrite_existing_filled_gaps=True))
    sing.apply(ch)
    np.testing.assert_allclose(take.xyz[821:863, p], first, atol=1e-9)
    assert ch.report["filled"] == 42


def test_options_and_errors(sing):
    take = sing.take
    with pytest.raises(ValueError, match="Forwards.*Backwards"):
        interpolate_gaps(take, params=GapFillingParameters(use_forwards_prediction=False,
                                                           use_backwards_prediction=False))
    with pytest.raises(ValueError, match="unknown gap-filling method"):
        interpolate_gaps(take, method="spline")
    with pytest.raises(ValueError, match="point indices"):
        interpolate_gaps(take, [999])
    # forwards only: the first gap of Unlabeled1 (frames 0-421) has nothing before it
    ch = interpolate_gaps(take, params=GapFillingParameters(use_backwards_prediction=False))
    assert ch.report["unfilled"] >= 422


def test_single_sensor_gap_filling(synth, undo_check):
    take = take_from_truth(synth)
    s = Session(take)
    n_obs = np.isfinite(take.obs_xy[..., 0]).sum(-1)
    single = (n_obs == 1) & ~np.isfinite(take.xyz).all(-1)
    assert single.sum() >= 5
    ch = interpolate_gaps(take)
    assert ch.report["single_sensor"] == single.sum()
    undo_check(s, ch)
    assert (take.recon[single] == Recon.SINGLE_SENSOR).all()
    f, p = np.nonzero(single)
    c = np.argmax(np.isfinite(take.obs_xy[f, p, :, 0]), axis=1)
    for cam in np.unique(c):
        k = c == cam
        xy = project(take.xyz[f[k], p[k]], take.cameras[cam].intrinsics, take.R[f[k], cam], take.t[f[k], cam])
        np.testing.assert_allclose(xy, take.obs_xy[f[k], p[k], cam], atol=2e-3)   # float32 observations
    # with the option off the same samples are plain interpolations, and less accurate
    t2 = take_from_truth(synth)
    ch2 = interpolate_gaps(t2, params=GapFillingParameters(allow_single_sensor_tracking_gap_filling=False))
    ch2.redo(t2)
    assert ch2.report["single_sensor"] == 0 and (t2.recon[single] == Recon.INTERPOLATED).all()
    err = np.linalg.norm(take.xyz[f, p] - synth.xyz[f, p], axis=-1)
    err_plain = np.linalg.norm(t2.xyz[f, p] - synth.xyz[f, p], axis=-1)
    assert np.median(err) < np.median(err_plain)


def test_face_model_method_and_evaluation(sing, undo_check):
    take = sing.take
    take.active_range = (0, 999)
    ch = interpolate_gaps(take, method="face_model")
    assert ch.report["method"] == "face_model" and ch.report["unfilled"] == 0
    undo_check(sing, ch)
    sing.stack.undo()
    nb = evaluate_fill(take, "neighbours", seed=3)
    fm = evaluate_fill(take, "face_model", seed=3)
    assert nb.n_hidden == fm.n_hidden and nb.n_filled == nb.n_hidden and nb.hidden.shape[0] == 1000
    np.testing.assert_array_equal(nb.hidden, fm.hidden)
    assert 0.045 < nb.n_hidden / np.isfinite(take.xyz[:1000]).all(-1).sum() < 0.06
    # measured (frames 0-999): neighbours 0.15 / 1.2 mm, face model 0.4 / 2.0 mm (median / p95)
    assert nb.median < 0.25 and nb.p95 < 1.6
    assert fm.median < 0.5 and fm.p95 < 3.0
    assert set(nb.summary()) == {"method", "hidden", "filled", "median_mm", "p95_mm"}


def test_evaluate_explicit_hide_and_bad_mask(c3d):
    take = c3d
    hide = np.zeros((take.n_frames, take.n_points), bool)
    hide[500:520, col(take, "section7-1")] = True
    ev = evaluate_fill(take, hide=hide)
    assert ev.n_hidden == 20 and ev.median < 1.0
    bad = hide.copy()
    bad[:, col(take, "Unlabeled1")] = True
    with pytest.raises(ValueError, match="no position"):
        evaluate_fill(take, hide=bad)


def test_face_model_from_rom_matches_by_label(sing):
    take = sing.take
    take.active_range = (0, 799)
    order = np.arange(take.n_points)[::-1]
    rom = Take.new([], 800, take.frame_rate, name="rom")
    rom.add_points(take.n_points, labels=[take.points.labels[i] for i in order])
    rom.xyz[...] = take.xyz[:800, order]
    m_self = face_model_for(take)
    m_rom = face_model_for(take, rom=rom)
    np.testing.assert_array_equal(np.sort(m_rom.points), np.sort(m_self.points))
    # the same faces, whatever the column order
    np.testing.assert_array_equal(m_rom.frames, m_self.frames)
    a = m_rom.basis[:, np.argsort(m_rom.points)]
    b = m_self.basis[:, np.argsort(m_self.points)]
    np.testing.assert_allclose(a, b, atol=1e-6)
    other = Take.new([], 10, 100.0)
    other.add_points(3, labels=["a", "b", "c"])
    with pytest.raises(ValueError, match="fewer than 3"):
        face_model_for(take, rom=other)


# ----------------------------------------------------------------------------- stabilization
@pytest.fixture(scope="module")
def blink_takes():
    """A synthetic take with blinks (35 markers, 200 frames at 60 fps, two blinks) made from
    its ground truth, and a ROM take of the same markers (another seed's truth, lids closing
    fully in view)."""
    from carapost.synth import SynthConfig, generate_take

    cfg = SynthConfig(n_markers=35, n_frames=200, blinks=True, high_motion=True)
    tr = generate_take(cfg, seed=4).truth
    rom_tr = generate_take(cfg, seed=7).truth
    rom = Take.new([], rom_tr.n_frames, rom_tr.frame_rate)
    rom.add_points(len(rom_tr.names), labels=list(rom_tr.names))
    rom.xyz[...] = rom_tr.xyz
    return tr, rom


def test_blink_method_fills_eyelid_gaps(blink_takes, undo_check):
    from carapost.core.gapfill import gap_runs
    from carapost.ops.fill import blink_depths_for

    tr, rom = blink_takes
    session = Session(take_from_truth(tr))
    take = session.take
    gap = ~np.isfinite(take.xyz).all(-1)
    depths = blink_depths_for(take, rom)
    for m in tr.eyelid_indices:
        assert depths[int(m)] == pytest.approx(9.29, abs=0.2)     # the synthetic lid marker travels 9.29 mm
    M = len(tr.names)                                                  # the face markers (then 4 brim points)
    medians = {}
    methods = {"neighbours": {}, "blink": {"method": "blink"},
               "blink_fit": {"method": "blink", "blink_depth_model": "fit"},
               "blink_rom": {"method": "blink", "rom": rom},
               "blink_wide_fissure": {"params": GapFillingParameters(method="blink", palpebral_fissure=12.7)}}
    for name, kw in methods.items():
        ch = interpolate_gaps(take, **kw)
        if name == "blink_rom":
            assert ch.report["method"] == "blink" and ch.report["unfilled"] == 0
            _, after = undo_check(session, ch)
            new = after.xyz
            assert (after.recon[gap] != Recon.MULTI_VIEW).all()
            session.stack.undo()
        else:
            ch.redo(take)
            new = take.xyz.copy()
            ch.undo(take)
        err = np.linalg.norm(new[:, :M] - tr.xyz, axis=-1)
        medians[name] = []
        for m in tr.eyelid_indices:
            _, a, b = gap_runs(gap[:, [m]])
            medians[name] += [float(np.median(err[f0:f1 + 1, m])) for f0, f1 in zip(a, b)]
    assert len(medians["neighbours"]) == 4                          # two blinks, two lids
    assert min(medians["neighbours"]) > 3.0                          # the guide's method misses the closure
    assert max(medians["blink_rom"]) <= 1.0, medians                 # issue 4's target, with a ROM depth (0.20-0.53)
    # no ROM, no lower-lid marker in the 35-marker set: the labelled upper lids take the
    # palpebral-fissure prior (9.7 mm for the synthetic 9.29 mm: measured 0.27-0.69 mm per blink)
    assert max(medians["blink"]) < 1.0 and max(medians["blink"]) < min(medians["neighbours"]) - 2.0, medians
    assert max(medians["blink_fit"]) < min(medians["neighbours"]), medians   # measured 1.4-2.2 mm
    # the Gap-Filling Parameters' Palpebral Fissure reaches the fill: 3 mm too wide a fissure
    # closes the lid too far (measured 1.5-2.1 mm per blink against 0.27-0.69)
    assert min(medians["blink_wide_fissure"]) > max(medians["blink"]) + 0.5, medians


def test_lid_priors_defaults_are_the_core_priors():
    from carapost.core.gapfill_lid import LID_MARKER_OFFSET_MM, PALPEBRAL_FISSURE_MM

    gp = GapFillingParameters()
    assert gp.lid_marker_offset == LID_MARKER_OFFSET_MM and gp.palpebral_fissure == PALPEBRAL_FISSURE_MM


def test_upper_lid_columns_by_label():
    from carapost.ops.fill import upper_lid_columns

    take = Take.new([], 3, 60.0)
    take.add_points(6, labels=["Lid_Upper_L", "LUpperLid", "Lid_Lower_L", "R_EYELID_INF", "Brow_L", ""])
    assert upper_lid_columns(take) == {0, 1}


def test_blink_method_leaves_ordinary_gaps_alone(c3d):
    nb = evaluate_fill(c3d, "neighbours", seed=0)
    bl = evaluate_fill(c3d, "blink", seed=0)
    assert bl.n_filled == nb.n_filled
    assert bl.median == pytest.approx(nb.median, abs=0.01) and bl.p95 == pytest.approx(nb.p95, abs=0.05)


def test_stabilize_ops(sing, undo_check):
    take = sing.take
    take.current_frame = 100
    roots = [col(take, f"root-{i}") for i in range(1, 4)]
    raw = take.xyz.copy()
    ch = stabilize_manual(take, roots)
    assert 0 < ch.report["error_mm"] and "stabilization error" in ch.text
    undo_check(sing, ch)
    np.testing.assert_array_equal(take.xyz, raw, strict=True)        # raw data kept
    np.testing.assert_allclose(take.xyz_stabilized[100], raw[100], atol=1e-9)
    ch2 = stabilize_assisted(take, roots, params=StabilizationParameters(max_processing_iterations=5))
    assert ch2.report["iterations"] <= 5 and ch2.report["stable_points_per_frame"] >= 3
    undo_check(sing, ch2)
    with pytest.raises(ValueError, match="section4-1 has a gap at frame 821"):
        stabilize_manual(take, roots[:2] + [col(take, "section4-1")])
    with pytest.raises(ValueError, match="at least three"):
        stabilize_manual(take, roots[:2])
    take.active_range = (200, 300)
    with pytest.raises(ValueError, match="base frame 100 is outside"):
        stabilize_manual(take, roots)


def test_stabilize_with_brim_points(synth):
    take = take_from_truth(synth)
    sel = [col(take, n) for n in ("Forehead_C", "Nose_Bridge", "Nose_Tip")]
    a = stabilize_assisted(take, sel, base_frame=0)
    b = stabilize_assisted(take, sel, base_frame=0, params=StabilizationParameters(use_brim_points=True,
                                                                                   stable_points_percent=1.0))
    assert a.report["error_mm"] > 0 and b.report["stable_points_per_frame"] > a.report["stable_points_per_frame"]


# ----------------------------------------------------------------------------- Align Data
def test_align_stabilized(sing, undo_check):
    take = sing.take
    take.current_frame = 100
    roots = [col(take, f"root-{i}") for i in range(1, 4)]
    sing.apply(stabilize_manual(take, roots))
    ch = align_data(take, roots)
    assert ch.report["data"] == "stabilized"
    before, _ = undo_check(sing, ch)
    q = take.xyz_stabilized[100, roots]
    np.testing.assert_allclose(q[0], 0, atol=1e-9)
    assert q[1, 0] > 0 and abs(q[1, 1]) < 1e-9 and abs(q[1, 2]) < 1e-9
    assert q[2, 1] > 0 and abs(q[2, 2]) < 1e-9
    np.testing.assert_array_equal(take.xyz, before.xyz)
    # rigid: distances unchanged in every frame
    d0 = np.linalg.norm(before.xyz_stabilized[:, 7] - before.xyz_stabilized[:, 12], axis=-1)
    d1 = np.linalg.norm(take.xyz_stabilized[:, 7] - take.xyz_stabilized[:, 12], axis=-1)
    np.testing.assert_allclose(d1, d0, atol=1e-9)


def test_align_raw_keeps_projections(synth, undo_check):
    take = take_from_truth(synth)
    s = Session(take)
    pts = [col(take, n) for n in ("Nose_Bridge", "Forehead_L", "Forehead_R")]
    take.current_frame = 5
    xy0 = project(take.xyz[:, :10], take.cameras[1].intrinsics, take.R[:, None, 1], take.t[:, None, 1])
    ch = align_data(take, pts)
    assert ch.report["data"] == "raw"
    undo_check(s, ch)
    np.testing.assert_allclose(take.xyz[5, pts[0]], 0, atol=1e-9)
    xy1 = project(take.xyz[:, :10], take.cameras[1].intrinsics, take.R[:, None, 1], take.t[:, None, 1])
    np.testing.assert_allclose(xy1, xy0, atol=1e-6, equal_nan=True)
    # the brim model moved with the world: brim points still sit on their dots
    bcols = take.brim_points()
    np.testing.assert_allclose(take.xyz[0, bcols], take.brim.xyz[:4], atol=1e-9)
    with pytest.raises(ValueError, match="exactly three"):
        align_data(take, pts[:2])
    take.xyz[5, col(take, "Chin")] = np.nan
    with pytest.raises(ValueError, match="Chin has no position in frame 5"):
        align_data(take, pts[:2] + [col(take, "Chin")])


def test_method_property_chooses_the_method(synth):
    """The Gap-Filling Parameters' Method is what Interpolate Gaps uses when none is given
    (the GUI's menu entry and the API's default); an unknown method is refused."""
    from carapost.model.params import FILL_METHODS

    take = take_from_truth(synth)
    assert take.params.gapfill.method == "neighbours" and "blink" in FILL_METHODS
    for m in FILL_METHODS:
        t = copy.deepcopy(take)
        t.params.gapfill.method = m
        rep = interpolate_gaps(t).report
        assert rep["method"] == m and rep["filled"] > 0
    with pytest.raises(ValueError, match="Method"):
        GapFillingParameters(method="spline")
