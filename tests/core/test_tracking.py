"""The automatic tracker on synthetic takes with ground truth.

Detections are the truth (every visible dot's image centroid + 0.05 px noise, plus clutter),
so these tests measure the tracker alone; the frame-0 points are the truth (a perfect
Initialize 3D). ``track_cases`` scores a result by the identity of every attached detection.
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from track_cases import apply_result, build_take, evaluate, truth_case, truth_detections  # noqa: E402

from carapost.core.track_cameras import CameraSet, bundle_frame, loo_residuals, triangulate_uv  # noqa: E402
from carapost.core.track_match import greedy_assign, size_compatible  # noqa: E402
from carapost.core.tracking import track  # noqa: E402
from carapost.model.params import TrackingParameters, sparse_35_preset  # noqa: E402
from carapost.model.take import ObsSource, Recon  # noqa: E402
from carapost.ops.change import take_diff  # noqa: E402
from carapost.synth import SynthConfig  # noqa: E402
from carapost.synth.evaluate import score_points  # noqa: E402

CONFIG = SynthConfig(n_markers=80, n_frames=40, width=640, height=360, high_motion=True, blinks=True, seed=3)


@pytest.fixture(scope="module")
def case():
    return truth_case(CONFIG)


@pytest.fixture(scope="module")
def tracked(case):
    """The whole clip tracked forwards with default parameters, applied to a copy of the take."""
    res = track(case.take, 0)
    take = copy.deepcopy(case.take)
    apply_result(take, res)
    return res, take


def _score(case, res):
    take = copy.deepcopy(case.take)
    apply_result(take, res)
    return evaluate(take, case.truth, case.labels, res.frames), take


# --------------------------------------------------------------------------- accuracy


def test_forwards_coverage_identity_and_accuracy(case, tracked):
    res, take = tracked
    assert res.frames == list(range(1, 40))
    s = evaluate(take, case.truth, case.labels, res.frames)
    assert s.coverage >= 0.99
    assert s.wrong_frames == 0 and s.swapped_points == 0
    # a few stray detections lie within a pixel or two of where a hidden marker projects
    n_obs = int((take.obs_det[res.frames] >= 0).sum())
    assert s.mismatched_obs <= 0.002 * n_obs
    # 640 x 360 pixels are twice the size of the targets' 1280 x 720: errors scale with them
    assert s.median_mm <= 0.15 and s.p95_mm <= 0.5
    # the project's own scorer agrees: no point changes identity
    ps = score_points(take, case.truth, res.frames)
    assert ps.swaps == 0
    assert ps.coverage >= 0.99


def test_camera_poses_follow_the_flex(case, tracked):
    res, take = tracked
    tr = case.truth
    cams = CameraSet(tr.intrinsics)
    for k, f in enumerate(res.frames[::6]):
        i = res.frames.index(f)
        # reprojection of the true markers with the estimated poses against the true poses, px
        p_est = cams.to_pixels(cams.project_uv(tr.xyz[f], res.R[i], res.t[i]))
        p_true = cams.to_pixels(cams.project_uv(tr.xyz[f], tr.R[f], tr.t[f]))
        assert np.nanmax(np.linalg.norm(p_est - p_true, axis=-1)) < 0.3
    # the nominal poses (what the take held) are several tenths of a pixel off
    assert res.cameras_updated


def test_backwards_from_the_last_frame(case):
    last = case.truth.n_frames - 1
    tables, labels = truth_detections(case.truth, range(40), brim_polarity=case.synth.brim.polarity)
    take = build_take(case.synth, tables, labels, start=last)
    res = track(take, last, direction=-1)
    assert res.frames == list(range(38, -1, -1))
    apply_result(take, res)
    s = evaluate(take, case.truth, labels, res.frames)
    assert s.coverage >= 0.99 and s.wrong_frames == 0
    assert s.median_mm <= 0.15 and s.p95_mm <= 0.5


def test_eyelids_leave_gaps_in_blinks_and_come_back(case, tracked):
    res, take = tracked
    tr = case.truth
    blink = np.flatnonzero(tr.blink_frames)
    assert len(blink) >= 3, "the test clip should contain a blink"
    for m in tr.eyelid_indices:
        hidden = [f for f in res.frames if tr.visible[f, m].sum() == 0]
        # hidden: a gap, not a wrong position
        assert np.isnan(take.xyz[hidden, m]).all()
        after = [f for f in res.frames if f > blink.max() + 3 and tr.visible[f, m].sum() >= 2]
        assert after, "eyelid should be visible after the blink"
        assert np.isfinite(take.xyz[after, m]).all(-1).mean() >= 0.9
        err = np.linalg.norm(take.xyz[after, m] - tr.xyz[after, m], axis=-1)
        assert np.nanmax(err) < 0.5


def test_is_pure_and_reports(tracked):
    _, take = tracked
    before = copy.deepcopy(take)
    calls = []
    res = track(take, 5, n_frames=4, progress=lambda d, t: calls.append((d, t)))
    assert take_diff(take, before) == []
    assert res.frames == [6, 7, 8, 9]
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]
    rep = res.report
    assert rep["frames"] == 4 and not rep["cancelled"] and len(rep["per_frame"]) == 4
    assert rep["totals"]["multi_view"] > 0.9 * 4 * 80 * 0.8
    T = len(res.points)
    assert res.xyz.shape == (4, T, 3) and res.obs_det.shape == (4, T, 4) and res.R.shape == (4, 4, 3, 3)


def test_cancel_keeps_finished_frames(case):
    done = []
    res = track(case.take, 0, progress=lambda d, t: done.append(d), cancel=lambda: len(done) >= 5)
    assert res.frames == [1, 2, 3, 4, 5]
    assert res.report["cancelled"]
    assert res.xyz.shape[0] == 5
    assert np.isfinite(res.xyz).all(-1).mean() > 0.8


def test_subset_leaves_other_points_alone(case, tracked):
    _, full = tracked
    take = copy.deepcopy(full)
    face = take.face_points()
    # keep frame 0; clear a few points after it and re-track only them
    sel = face[[3, 20, 41, 60]]
    for name, fill in (("xyz", np.nan), ("obs_det", -1), ("obs_xy", np.nan)):
        getattr(take, name)[1:, sel] = fill
    res = track(take, 0, points=sel)
    assert set(res.points) == set(sel)
    # the others' detections were not taken
    others = np.setdiff1d(np.arange(take.n_points), sel)
    for k, f in enumerate(res.frames):
        for c in range(4):
            od = res.obs_det[k, :, c]
            mine = od[od >= 0]
            theirs = take.obs_det[f, others, c]
            assert not np.isin(mine, theirs[theirs >= 0]).any()
    apply_result(take, res)
    err = np.linalg.norm(take.xyz[1:, sel] - case.truth.xyz[1:, sel], axis=-1)
    multi = take.recon[1:, sel] == Recon.MULTI_VIEW
    assert np.nanmedian(err[multi]) < 0.2 and np.nanmax(err[multi]) < 1.0 and np.isfinite(err).mean() > 0.9


def test_without_brim_the_take_poses_are_used(case):
    take = copy.deepcopy(case.take)
    take.R[:] = case.truth.R          # a take whose poses are known for every frame
    take.t[:] = case.truth.t
    face = take.face_points()
    res = track(take, 0, points=face, n_frames=15)
    assert not res.cameras_updated
    np.testing.assert_array_equal(res.R, case.truth.R[1:16])
    apply_result(take, res)
    s = evaluate(take, case.truth, case.labels, res.frames)
    assert s.coverage >= 0.99 and s.wrong_frames == 0


# --------------------------------------------------------------------------- parameters


def test_tiny_face_tracking_distance_loses_points(case, tracked):
    res, take = tracked
    base = evaluate(take, case.truth, case.labels, res.frames)
    p = TrackingParameters(face_point_tracking_distance=0.3, face_point_max_elastic_prediction_distance=0.3)
    s, _ = _score(case, track(case.take, 0, params=p))
    assert s.coverage < base.coverage - 0.1


def test_elastic_distance_limits_elastic_matches(tracked):
    # a third of the points start with a wrong velocity (their previous frame is 6 mm off):
    # their own prediction misleads them, their neighbours' elastic prediction does not -- as
    # far as the Face Point Max Elastic Prediction Distance lets it
    _, take = tracked
    take = copy.deepcopy(take)
    bad = take.face_points()[::3]
    take.xyz[4, bad] += np.array([6.0, 0.0, 0.0])
    found = []
    for dist in (15.0, 0.05):
        r = track(take, 5, n_frames=1, params=TrackingParameters(face_point_max_elastic_prediction_distance=dist))
        found.append(np.isfinite(r.xyz[0, np.isin(r.points, bad)]).all(-1).mean())
    assert found[1] < found[0] - 0.1


def test_tiny_brim_distance_loses_the_brim(case):
    res = track(case.take, 0, n_frames=5, params=TrackingParameters(brim_point_tracking_distance=0.01))
    brim = np.isin(res.points, case.take.brim_points())
    ok = track(case.take, 0, n_frames=5)
    assert (res.obs_det[:, brim] >= 0).sum() < 0.1 * (ok.obs_det[:, brim] >= 0).sum()


def _planted(case, frame: int, camera: int, marker: int, *, dx: float = 0.0, scale: float = 1.0):
    """A copy of the take with one marker's detection moved by ``dx`` px / resized."""
    take = copy.deepcopy(case.take)
    det = take.detections[camera]
    tb = {k: v.copy() for k, v in det.frame(frame).items()}
    i = int(np.flatnonzero(case.labels[camera][frame] == marker)[0])
    tb["x"][i] += dx
    tb["major"][i] *= scale
    tb["minor"][i] *= scale
    take.detections[camera] = det.with_frames({frame: tb})
    return take, i


def _isolated_marker(case, f: int, c: int, min_px: float = 15.0) -> int:
    """A marker seen by three or more cameras whose detection in camera c is isolated."""
    xy = case.take.detections[c].xy(f)
    lab = case.labels[c][f]
    for m in np.flatnonzero(case.truth.visible[f].sum(-1) >= 3):
        if m not in lab:
            continue
        d = np.linalg.norm(xy - xy[lab == m][0], axis=1)
        if np.sort(d)[1] > min_px:
            return int(m)
    raise AssertionError("no isolated marker")


def test_remove_bad_2d_projections_detaches_a_planted_outlier(case):
    c, f = 1, 6
    m = _isolated_marker(case, f, c)
    take, i = _planted(case, f, c, m, dx=4.0)
    col = [m]  # tracked alone: nothing but the motion model to go by
    on = track(take, 0, points=col, n_frames=f, params=TrackingParameters(max_allowed_2d_projection_error=1.5))
    off = track(take, 0, points=col, n_frames=f, params=TrackingParameters(max_allowed_2d_projection_error=1.5,
                                                                          remove_bad_2d_projections=False))
    k = on.frames.index(f)
    assert on.obs_det[k, 0, c] == -1
    assert off.obs_det[k, 0, c] == i
    # with the outlier kept the point is pulled off its true position
    e_on = np.linalg.norm(on.xyz[k, 0] - case.truth.xyz[f, m])
    e_off = np.linalg.norm(off.xyz[k, 0] - case.truth.xyz[f, m])
    assert e_on < 0.3 < e_off


def test_max_allowed_3d_point_error(case):
    tight = TrackingParameters(max_allowed_3d_point_error=0.001)
    res = track(case.take, 0, n_frames=8, params=tight)
    ok = track(case.take, 0, n_frames=8)
    assert res.report["totals"]["multi_view"] < 0.6 * ok.report["totals"]["multi_view"]
    assert res.report["totals"]["rejected_3d"] > 0
    off = track(case.take, 0, n_frames=8, params=TrackingParameters(max_allowed_3d_point_error=0.001,
                                                                   remove_bad_3d_points=False))
    assert off.report["totals"]["multi_view"] > 0.8 * ok.report["totals"]["multi_view"]


def test_single_sensor_tracking(case, tracked):
    res, _ = tracked
    assert (res.recon == Recon.SINGLE_SENSOR).sum() > 0
    # single-sensor points lie on their detection's ray within the threshold of the truth-ish
    off = track(case.take, 0, params=TrackingParameters(allow_single_sensor_tracking=False))
    assert (off.recon == Recon.SINGLE_SENSOR).sum() == 0
    tight = track(case.take, 0, params=TrackingParameters(single_sensor_tracking_threshold=1e-6))
    assert (tight.recon == Recon.SINGLE_SENSOR).sum() < 0.2 * (res.recon == Recon.SINGLE_SENSOR).sum()
    face = ~np.isin(res.points, case.take.brim_points())
    ss = (res.recon == Recon.SINGLE_SENSOR) & face[None, :]
    k, j = np.nonzero(ss)
    f = np.asarray(res.frames)[k]
    err = np.linalg.norm(res.xyz[k, j] - case.truth.xyz[f, res.points[j]], axis=-1)
    assert np.median(err) < 1.0
    assert (res.obs_det[k, j] >= 0).sum(-1).max() == 1


def test_blob_size_difference_threshold(case):
    c, f = 1, 3
    m = _isolated_marker(case, f, c)
    take, i = _planted(case, f, c, m, scale=3.0)
    loose = track(take, 0, points=[m], n_frames=f)
    strict = track(take, 0, points=[m], n_frames=f, params=TrackingParameters(blob_size_difference_threshold=0.1))
    assert loose.obs_det[-1, 0, c] == i
    assert strict.obs_det[-1, 0, c] == -1


def test_sparse_preset_tracks_the_sparse_set():
    c = truth_case(SynthConfig(n_markers=35, n_frames=25, width=640, height=360, high_motion=True, seed=3))
    res = track(c.take, 0, params=sparse_35_preset().tracking)
    assert (res.recon == Recon.SINGLE_SENSOR).sum() == 0
    s, _ = _score(c, res)
    assert s.coverage >= 0.98 and s.wrong_frames == 0


# --------------------------------------------------------------------------- input checking


def test_bad_input_is_rejected(case):
    with pytest.raises(ValueError, match="direction"):
        track(case.take, 0, direction=2)
    with pytest.raises(ValueError, match="outside the take"):
        track(case.take, 40)
    with pytest.raises(ValueError, match="point columns"):
        track(case.take, 0, points=[10_000])
    take = copy.deepcopy(case.take)
    take.R[0] = np.nan
    with pytest.raises(ValueError, match="no camera poses"):
        track(take, 0)
    res = track(case.take, 39)          # nothing after the last frame
    assert res.frames == [] and res.xyz.shape[0] == 0


def test_points_without_a_start_position_are_not_tracked(case):
    take = copy.deepcopy(case.take)
    take.xyz[0, 5] = np.nan
    res = track(take, 0, n_frames=2)
    assert 5 not in res.points and len(res.points) == take.n_points - 1


# --------------------------------------------------------------------------- building blocks


def test_triangulation_and_leave_one_out_residuals(case):
    tr = case.truth
    cams = CameraSet(tr.intrinsics)
    f = 10
    uv = np.stack([cams.normalise(c, tr.centroid_xy[f, :, c]) for c in range(4)])
    w = tr.visible[f].T.astype(float)
    X, res = triangulate_uv(uv, w, tr.R[f], tr.t[f], cams.scale, iterations=1)
    two = w.sum(0) >= 2
    assert np.nanmax(np.linalg.norm(X[two] - tr.xyz[f, two], axis=1)) < 0.03
    assert np.isnan(X[~two]).all()
    # a 5 px error in one view of a four-view point: its leave-one-out residual is the largest
    m = int(np.flatnonzero(w.sum(0) == 4)[0])
    uv2 = uv.copy()
    uv2[0, m, 0] += 5 / cams.f[0]
    X2, _ = triangulate_uv(uv2, w, tr.R[f], tr.t[f], cams.scale)
    loo = loo_residuals(X2, uv2, w, tr.R[f], tr.t[f], cams.scale)
    assert np.argmax(loo[:, m]) == 0 and loo[0, m] > 3.0
    # matches the explicit leave-one-out triangulation to a few hundredths of a pixel
    w3 = w.copy()
    w3[0] = 0
    X3, _ = triangulate_uv(uv2, w3, tr.R[f], tr.t[f], cams.scale, iterations=2)
    p = cams.to_pixels(cams.project_uv(X3[m:m + 1], tr.R[f], tr.t[f]))[0, 0]
    direct = np.linalg.norm(p - cams.to_pixels(uv2[:, m:m + 1])[0, 0])
    assert abs(direct - loo[0, m]) < 0.1 * direct


def test_frame_bundle_adjustment_recovers_the_flex(case):
    tr = case.truth
    cams = CameraSet(tr.intrinsics)
    f = 12
    rng = np.random.default_rng(0)
    buv = np.stack([cams.normalise(c, tr.brim_centroid_xy[f, :, c] + rng.normal(0, 0.05, (len(tr.brim_xyz), 2)))
                    for c in range(4)])
    fuv = np.stack([cams.normalise(c, tr.centroid_xy[f, :, c] + rng.normal(0, 0.05, (80, 2))) for c in range(4)])
    w = tr.visible[f].T.astype(float)
    X0, _ = triangulate_uv(fuv, w, tr.R[f - 1], tr.t[f - 1], cams.scale)
    Xb = np.broadcast_to(tr.brim_xyz, (4,) + tr.brim_xyz.shape)
    R, t, X = bundle_frame(Xb, buv, tr.brim_visible[f].T, fuv, w, X0, tr.R[f - 1], tr.t[f - 1], cams.scale,
                           iterations=2)
    before = np.nanpercentile(np.linalg.norm(X0 - tr.xyz[f], axis=1), 95)
    after = np.nanpercentile(np.linalg.norm(X - tr.xyz[f], axis=1), 95)
    assert after < 0.3 and after < 0.7 * before
    # the poses now put the true markers where the true poses do, within a few tenths of a pixel
    p_est = cams.to_pixels(cams.project_uv(tr.xyz[f], R, t))
    p_true = cams.to_pixels(cams.project_uv(tr.xyz[f], tr.R[f], tr.t[f]))
    assert np.nanmax(np.linalg.norm(p_est - p_true, axis=-1)) < 0.3


def test_greedy_assignment_and_size_gate():
    det = np.array([[0, 1], [0, 2], [1, -1]])
    cost = np.array([[1.0, 5.0], [0.5, 3.0], [0.2, np.inf]])
    out = greedy_assign(np.arange(3), det, cost, 3)
    # query 1 wins detection 0 (0.5 < 1.0), query 2 detection 1; query 0 is left with nothing
    assert out[2] == 1 and out[1] == 0 and out[0] == -1
    assert size_compatible(np.array([4.0]), np.array([4.0]), np.array([5.0]), np.array([4.0]), 0.25)[0]
    assert not size_compatible(np.array([4.0]), np.array([4.0]), np.array([6.0]), np.array([4.0]), 0.25)[0]
    assert size_compatible(np.array([np.nan]), np.array([4.0]), np.array([6.0]), np.array([4.0]), 0.0)[0]


# --------------------------------------------------------------------------- appearance (rendered images)


@pytest.fixture(scope="module")
def imaged():
    """A few rendered frames with truth detections (blob appearance is real)."""
    cfg = SynthConfig(n_markers=80, n_frames=6, width=640, height=360, seed=3, high_motion=True)
    c = truth_case(cfg)
    images = np.stack([c.synth.images(f) for f in range(cfg.n_frames)])   # (F, C, H, W)
    return c, images


def _image_fn(images):
    return lambda cam, frame: images[frame, cam]


def test_appearance_keeps_true_matches(imaged):
    c, images = imaged
    res = track(c.take, 0, image=_image_fn(images))
    s, _ = _score(c, res)
    assert s.coverage >= 0.99 and s.wrong_frames == 0
    # Patch Match Threshold 1: "each frame must perfectly match" -- nothing does
    none = track(c.take, 0, image=_image_fn(images), params=TrackingParameters(patch_match_threshold=1.0))
    face = ~np.isin(none.points, c.take.brim_points())
    assert (none.recon[:, face] != Recon.NONE).sum() < 0.05 * (res.recon[:, face] != Recon.NONE).sum()


def test_patch_tracking_fills_a_missing_detection(imaged):
    c, images = imaged
    f, cam = 3, 0
    vis = np.flatnonzero(c.truth.visible[f, :, cam] & (c.truth.visible[f].sum(-1) == 4))
    m = int(vis[len(vis) // 2])
    take = copy.deepcopy(c.take)
    det = take.detections[cam]
    tb = {k: v.copy() for k, v in det.frame(f).items()}
    keep = c.labels[cam][f] != m
    take.detections[cam] = det.with_frames({f: {k: v[keep] for k, v in tb.items()}})
    res = track(take, 0, image=_image_fn(images), n_frames=f)
    k, j = res.frames.index(f), int(np.flatnonzero(res.points == m)[0])
    assert res.obs_src[k, j, cam] == ObsSource.PATCH and res.obs_det[k, j, cam] == -1
    assert np.linalg.norm(res.obs_xy[k, j, cam] - c.truth.centroid_xy[f, m, cam]) < 1.0
    q15 = res.obs_q[k, j, cam]
    assert 0.8 <= q15 <= 1.0
    # Patch Match Size changes the comparison (and so the score) ...
    small = track(take, 0, image=_image_fn(images), n_frames=f, params=TrackingParameters(patch_match_size=7))
    assert small.obs_src[k, j, cam] == ObsSource.PATCH and small.obs_q[k, j, cam] != q15
    # ... and a Patch Match Threshold above what the patch reaches leaves a gap in that camera
    strict = track(take, 0, image=_image_fn(images), n_frames=f,
                   params=TrackingParameters(patch_match_threshold=min(0.9999, float(q15) + 0.01)))
    assert strict.obs_src[k, j, cam] != ObsSource.PATCH
