"""Target Tracker operations on a rendered synthetic take whose cameras are the true ones."""

import copy
import dataclasses

import numpy as np
import pytest

from carapost.core.camera import project
from carapost.model.take import CameraInfo, ObsSource, Recon, Take
from carapost.ops import target as T
from carapost.ops.change import take_diff
from carapost.ops.session import Session
from carapost.synth import SynthConfig, generate_take


@pytest.fixture(scope="module")
def synth():
    return generate_take(SynthConfig(n_markers=35, n_frames=40, width=640, height=360))


@pytest.fixture(scope="module")
def image(synth):
    cache = {}

    def get(c, f):
        if (c, f) not in cache:
            cache[(c, f)] = synth.image(f, c)
        return cache[(c, f)]
    return get


@pytest.fixture
def ses(synth):
    tr = synth.truth
    cams = [CameraInfo(f"cam{c}", c, tr.intrinsics[c], (640, 360)) for c in range(4)]
    return Session(Take.new(cams, synth.n_frames, 60.0, R=tr.R, t=tr.t))


def settings(take, **kw):
    return dataclasses.replace(take.params.tracker, **kw)


def _clean(synth, cams, frames):
    tr = synth.truth
    ok = np.ones(tr.visible.shape[1], bool)
    for c in cams:
        ok &= tr.visible[frames][:, :, c].all(0) & ~tr.partly_hidden[frames][:, :, c].any(0)
    return np.flatnonzero(ok)


def _new_point(ses, synth, m, frame, cams):
    """Add Target Track in the first camera, Edit Target Track in the others (at the truth)."""
    tr = synth.truth
    ses.apply(T.add_target_track(ses.take, cams[0], frame, tr.centroid_xy[frame, m, cams[0]]))
    col = ses.take.n_points - 1
    for c in cams[1:]:
        ses.apply(T.edit_target_track(ses.take, col, c, frame, tr.centroid_xy[frame, m, c]))
    return col


def _set_obs(take, frames, col, cam, xy, src=ObsSource.BLOB):
    take.obs_xy[frames, col, cam] = xy
    take.obs_src[frames, col, cam] = src


# ------------------------------------------------------------------- keyframe editing
def test_add_and_edit_target_track(ses, synth, undo_check):
    tr = synth.truth
    take = ses.take
    m = int(_clean(synth, (0, 1), np.arange(0, 1))[0])
    before, after = undo_check(ses, T.add_target_track(take, 0, 0, tr.centroid_xy[0, m, 0]))
    assert take.n_points == 1 and take.points.ids.tolist() == [0] and take.next_point_id == 1
    assert take.obs_src[0, 0, 0] == ObsSource.KEYFRAME and take.obs_q[0, 0, 0] == 1.0
    assert np.allclose(take.obs_xy[0, 0, 0], tr.centroid_xy[0, m, 0])
    kf = take.keyframes
    assert kf.frame.tolist() == [0] and kf.point_id.tolist() == [0] and kf.camera.tolist() == [0]
    # Default boxes: Patch Match Size (15 px) wide, search 2 x 7.5 px larger on each side.
    assert np.allclose(kf.pattern[0] - np.tile(kf.xy[0], 2), [-7.5, -7.5, 7.5, 7.5])
    assert np.allclose(kf.search[0] - np.tile(kf.xy[0], 2), [-15, -15, 15, 15])
    assert np.isnan(take.xyz[0, 0]).all()  # one view: no 3D yet

    undo_check(ses, T.edit_target_track(take, 0, 1, 0, tr.centroid_xy[0, m, 1]))
    assert take.keyframes.camera.tolist() == [0, 1]
    assert take.recon[0, 0] == Recon.MULTI_VIEW
    assert np.linalg.norm(take.xyz[0, 0] - tr.xyz[0, m]) < 0.5   # mm (keyed at the exact centroids)

    # Editing again in camera 1 moves that keyframe (with its boxes); a blob there is replaced.
    take.obs_det[0, 0, 1] = 0
    take.obs_src[0, 0, 1] = ObsSource.BLOB
    new = tr.centroid_xy[0, m, 1] + [1.0, -0.5]
    undo_check(ses, T.edit_target_track(take, 0, 1, 0, new))
    r = 1
    assert np.allclose(take.keyframes.xy[r], new) and len(take.keyframes) == 2
    assert np.allclose(take.keyframes.pattern[r] - np.tile(take.keyframes.xy[r], 2), [-7.5, -7.5, 7.5, 7.5])
    assert take.obs_det[0, 0, 1] == -1 and take.obs_src[0, 0, 1] == ObsSource.KEYFRAME

    # Nudge a keyframe / resize its boxes.
    undo_check(ses, T.adjust_keyframe(take, 0, 0, 0, xy=tr.centroid_xy[0, m, 0] + [0.25, 0.0]))
    assert np.allclose(take.obs_xy[0, 0, 0], tr.centroid_xy[0, m, 0] + [0.25, 0.0])
    assert np.allclose(take.keyframes.pattern[0] - np.tile(take.keyframes.xy[0], 2), [-7.5, -7.5, 7.5, 7.5])
    x, y = take.keyframes.xy[0]
    undo_check(ses, T.adjust_keyframe(take, 0, 0, 0, search=[x - 30, y - 20, x + 30, y + 20]))
    assert np.allclose(take.keyframes.search[0], [x - 30, y - 20, x + 30, y + 20])
    with pytest.raises(ValueError, match="no keyframe"):
        T.adjust_keyframe(take, 0, 2, 0, xy=(10, 10))


def test_bad_input_is_rejected(ses):
    take = ses.take
    with pytest.raises(ValueError, match="camera 7"):
        T.add_target_track(take, 7, 0, (10, 10))
    with pytest.raises(ValueError, match="frame 99"):
        T.add_target_track(take, 0, 99, (10, 10))
    with pytest.raises(ValueError, match="outside camera 0's 640 x 360"):
        T.add_target_track(take, 0, 0, (700, 10))
    with pytest.raises(ValueError, match="does not contain"):
        T.add_target_track(take, 0, 0, (100, 100), pattern=(0, 0, 10, 10))
    with pytest.raises(ValueError, match="select at least one point"):
        T.add_keyframes(take, [], 0)
    with pytest.raises(ValueError, match="does not exist"):
        T.track_forward_one_frame(take, [3], 0, lambda c, f: None)
    ses.apply(T.add_target_track(take, 0, 5, (100, 100)))
    with pytest.raises(ValueError, match="no 2D position in frame 0"):
        T.track_forward_one_frame(take, [0], 0, lambda c, f: None)
    with pytest.raises(ValueError, match="direction"):
        T.track(take, [0], 5, lambda c, f: None, direction=2)


def test_add_keyframes_gaps_to_keys_and_navigation(ses, undo_check):
    take = ses.take
    take.add_points(2)
    # Point 0: camera 0 has positions in 0..4 and 10..19 (a gap 5..9); camera 2 in 3..6 only.
    _set_obs(take, np.r_[0:5, 10:20], 0, 0, (100.0, 120.0))
    _set_obs(take, np.arange(3, 7), 0, 2, (200.0, 150.0))
    # Attached to a blob of radius 2 px: the keyframe replaces the connection, its boxes fit the blob.
    take.detections[0] = take.detections[0].with_frames({2: {"x": [100.0], "y": [120.0], "major": [2.0],
                                                             "minor": [2.0], "polarity": [-1], "score": [1.0]}})
    take.obs_det[2, 0, 0] = 0
    # Point 1: camera 1 has positions in 2..3, 6..6 and 30..35.
    _set_obs(take, np.r_[2:4, 6, 30:36], 1, 1, (300.0, 200.0))

    before, after = undo_check(ses, T.add_keyframes(take, [0], 2))
    assert take.keyframes.frame.tolist() == [2] and take.keyframes.camera.tolist() == [0]
    assert take.obs_src[2, 0, 0] == ObsSource.KEYFRAME and take.obs_det[2, 0, 0] == -1
    rel = np.tile(take.keyframes.xy[0], 2)
    assert np.allclose(take.keyframes.pattern[0] - rel, [-5, -5, 5, 5])    # 2.5 blob diameters wide
    assert np.allclose(take.keyframes.search[0] - rel, [-11, -11, 11, 11])  # + 6 px
    assert T.add_keyframes(take, [0], 2).changes == []  # already keyed
    with pytest.raises(ValueError, match="no 2D position in frame 25"):
        T.add_keyframes(take, [0, 1], 25)

    undo_check(ses, T.gaps_to_keys(take, [0, 1]))
    kf = take.keyframes
    got = sorted(zip(kf.point_id.tolist(), kf.camera.tolist(), kf.frame.tolist()))
    # Either side of every interior gap; nothing at the start or the end of a track.
    assert got == [(0, 0, 2), (0, 0, 4), (0, 0, 10), (1, 1, 3), (1, 1, 6), (1, 1, 30)]
    assert (take.obs_src[[4, 10], 0, 0] == ObsSource.KEYFRAME).all()
    assert take.obs_src[3, 0, 2] == ObsSource.BLOB  # camera 2 has no interior gap

    # Next/Prev Key Frame over the selected points' keyframes in any camera, wrapping.
    assert T.next_keyframe(take, [0], 4) == 10 and T.next_keyframe(take, [0], 10) == 2
    assert T.prev_keyframe(take, [0], 4) == 2 and T.prev_keyframe(take, [0], 2) == 10
    assert T.next_keyframe(take, [0, 1], 10) == 30 and T.prev_keyframe(take, [1], 0) == 30
    assert T.next_keyframe(take, [], 5) == 6 and T.prev_keyframe(take, [], 0) == 0
    assert T.next_keyframe(take, [], 39) == 39

    # Clear Tracked Points: every 2D observation and keyframe of the point goes, 3D resting on them too.
    take.xyz[3, 0] = (1.0, 2.0, 3.0)
    take.recon[3, 0] = Recon.MULTI_VIEW
    take.xyz[7, 0] = (1.0, 2.0, 3.0)
    take.recon[7, 0] = Recon.INTERPOLATED
    undo_check(ses, T.clear_tracked_points(take, [0]))
    assert np.isnan(take.obs_xy[:, 0]).all() and (take.obs_src[:, 0] == 0).all()
    assert set(take.keyframes.point_id.tolist()) == {1}
    assert take.recon[3, 0] == Recon.NONE and np.isnan(take.xyz[3, 0]).all()
    assert take.recon[7, 0] == Recon.INTERPOLATED
    assert np.isfinite(take.obs_xy[2, 1, 1]).all()


# ------------------------------------------------------------------------- tracking
def test_track_forward_follows_truth_in_2d_and_3d(ses, synth, image, undo_check):
    tr = synth.truth
    take = ses.take
    markers = _clean(synth, (0, 1), np.arange(0, 21))[:4]
    cols = [_new_point(ses, synth, m, 0, (0, 1)) for m in markers]
    calls = []
    s = settings(take, stop_after_n_frames=True, n_frames=20, break_threshold=0.8)
    pre = copy.deepcopy(take)
    ch = T.track_forward_to_end(take, cols, 0, image, settings=s, progress=lambda d, n: calls.append((d, n)))
    assert take_diff(take, pre) == []  # building the change leaves the take alone
    assert calls[-1] == (20, 20) and len(calls) == 20
    rep = ch.report
    assert rep.points.tolist() == [0, 0, 1, 1, 2, 2, 3, 3] and rep.cameras.tolist() == [0, 1] * 4
    assert rep.n_tracked.tolist() == [20] * 8 and rep.keyframes_added == 0 and not rep.cancelled
    before, after = undo_check(ses, ch)
    f = np.arange(1, 21)
    assert (take.obs_src[f][:, cols][..., :2] == ObsSource.TARGET).all()
    assert (take.obs_det[f][:, cols][..., :2] == -1).all()
    q = take.obs_q[f][:, cols][..., :2]
    assert ((q >= 0.8) & (q <= 1.0)).all()
    assert np.isnan(take.obs_xy[21:, cols]).all()  # Stop after N Frames, N = 20
    err2 = np.linalg.norm(take.obs_xy[f][:, cols][..., :2, :] - tr.centroid_xy[f][:, markers][..., :2, :], axis=-1)
    assert np.median(err2) < 0.3   # px
    assert (take.recon[f][:, cols] == Recon.MULTI_VIEW).all()
    err3 = np.linalg.norm(take.xyz[f][:, cols] - tr.xyz[f][:, markers], axis=-1)
    assert np.median(err3) < 1.0   # mm: one caddy's short baseline magnifies 2D error in depth
    # Cameras 2 and 3 had nothing in frame 0: untouched.
    assert np.isnan(take.obs_xy[:, cols, 2:]).all()


def test_break_threshold_on_blink_keeps_quality_and_stops(ses, synth, image):
    tr = synth.truth
    take = ses.take
    first_hidden = int(np.flatnonzero(tr.blink_frames)[0])
    f0 = first_hidden - 8
    m = int(tr.eyelid_indices[0])
    col = _new_point(ses, synth, m, f0, (0, 1))
    ch = T.track_forward_to_end(take, [col], f0, image)          # defaults: Break Threshold 0.9
    assert ch.report.stop_reason == ["break threshold"] * 2
    assert (ch.report.stop_frame <= first_hidden).all()
    ses.apply(ch)
    last = int(ch.report.stop_frame.min())
    assert np.isnan(take.obs_xy[last:, col, :2]).all() and np.isnan(take.obs_q[last:, col]).all()
    q = take.obs_q[f0 + 1:last, col, :2]
    assert (q >= 0.9).all() and (q <= 1.0).all()
    ses.stack.undo()
    low = T.track_forward_to_end(take, [col], f0, image, settings=settings(take, break_threshold=0.3,
                                                                          stop_after_n_frames=True, n_frames=12))
    assert (low.report.n_tracked == 12).all()  # straight through the blink


def test_tracker_settings_have_effects(ses, synth, image):
    tr = synth.truth
    take = ses.take
    m = int(_clean(synth, (0, 1, 2), np.arange(0, 40))[0])
    col = _new_point(ses, synth, m, 10, (0, 1))
    base = settings(take, stop_after_n_frames=True, n_frames=4, break_threshold=0.7)

    # Stop after N Frames (N) / one frame / to the end.
    assert T.track_forward_to_end(take, [col], 10, image, settings=base).report.n_tracked.tolist() == [4, 4]
    assert T.track_back_to_start(take, [col], 10, image, settings=base).report.frames.tolist() == [9, 8, 7, 6]
    assert T.track_forward_one_frame(take, [col], 10, image, settings=base).report.frames.tolist() == [11]
    assert T.track_back_one_frame(take, [col], 10, image, settings=base).report.frames.tolist() == [9]
    _set_obs(take, 34, col, 0, tr.centroid_xy[34, m, 0])
    full = T.track_forward_to_end(take, [col], 34, image, settings=dataclasses.replace(base, stop_after_n_frames=False))
    assert full.report.frames.tolist() == list(range(35, 40))

    # Stop On Next Keyframe: a keyframe of the point at frame 13 (in camera 0 only).
    ses.apply(T.edit_target_track(take, col, 0, 13, tr.centroid_xy[13, m, 0]))
    s = dataclasses.replace(base, n_frames=6)
    on = T.track_forward_to_end(take, [col], 10, image, settings=dataclasses.replace(s, overwrite_existing_tracks=True))
    assert on.report.frames.tolist() == [11, 12]
    off = T.track_forward_to_end(take, [col], 10, image, settings=dataclasses.replace(
        s, stop_on_next_keyframe=False, overwrite_existing_tracks=True))
    assert off.report.frames.tolist() == [11, 12, 13, 14, 15, 16] and off.report.n_tracked.tolist() == [5, 6]
    # Without overwriting, the point's own keyframe is passed too (it is not overwritten).
    kept = T.track_forward_to_end(take, [col], 10, image, settings=dataclasses.replace(s, stop_on_next_keyframe=False))
    assert kept.report.n_tracked.tolist() == [5, 6] and kept.report.stop_reason == ["end of frames"] * 2
    ses.apply(off)
    assert take.obs_src[13, col, 0] == ObsSource.KEYFRAME and np.allclose(take.obs_xy[13, col, 0],
                                                                           tr.centroid_xy[13, m, 0])
    assert take.obs_src[13, col, 1] == ObsSource.TARGET and take.obs_src[14, col, 0] == ObsSource.TARGET

    # Overwrite Existing Tracks: blob data in camera 1 at frames 18.. blocks tracking unless overwritten.
    _set_obs(take, np.arange(18, 22), col, 1, tr.centroid_xy[18:22, m, 1])
    s = dataclasses.replace(base, n_frames=6, stop_on_next_keyframe=False)
    keep = T.track_forward_to_end(take, [col], 16, image, settings=s)
    assert keep.report.stop_reason[1] == "existing track" and keep.report.stop_frame[1] == 18
    assert keep.report.n_tracked.tolist() == [6, 1]
    over = T.track_forward_to_end(take, [col], 16, image, settings=dataclasses.replace(s, overwrite_existing_tracks=True))
    assert over.report.n_tracked.tolist() == [6, 6]
    ses.apply(over)
    assert (take.obs_src[18:23, col, 1] == ObsSource.TARGET).all()

    # Automatically Add Keyframes: a keyframe at the start frame in every tracked camera, or none.
    n_kf = len(take.keyframes)
    auto = T.track_forward_to_end(take, [col], 22, image, settings=s)
    assert auto.report.keyframes_added == 2
    ses.apply(auto)
    assert len(take.keyframes) == n_kf + 2 and (take.obs_src[22, col, :2] == ObsSource.KEYFRAME).all()
    ses.stack.undo()
    manual = T.track_forward_to_end(take, [col], 22, image, settings=dataclasses.replace(
        s, automatically_add_keyframes=False))
    assert manual.report.keyframes_added == 0 and manual.report.n_tracked.tolist() == [6, 6]
    ses.apply(manual)
    assert len(take.keyframes) == n_kf and (take.obs_src[22, col, :2] == ObsSource.TARGET).all()

    # Update Timeline / 2D View Every Frame: what the UI is told after each frame.
    for tl, view in ((False, False), (True, False), (False, True)):
        got = []
        T.track_forward_to_end(take, [col], 28, image, settings=dataclasses.replace(
            s, n_frames=3, update_timeline_every_frame=tl, update_2d_view_every_frame=view,
            overwrite_existing_tracks=True), on_frame=got.append)
        if not (tl or view):
            assert got == []
        else:
            assert [g.frame for g in got] == [29, 30, 31]
            assert all(g.update_timeline == tl and g.show_frame == view for g in got)
            assert got[0].quality.shape == (2,) and got[0].points.tolist() == [col, col]


def test_single_sensor_tracking_puts_the_point_on_the_ray(ses, synth, image):
    tr = synth.truth
    take = ses.take
    m = int(_clean(synth, (2,), np.arange(5, 12))[0])
    col = _new_point(ses, synth, m, 5, (2,))
    take.xyz[5, col] = tr.xyz[5, m]  # a known position to start from (e.g. from earlier tracking)
    s = settings(take, stop_after_n_frames=True, n_frames=6, break_threshold=0.7)
    off = T.track_forward_to_end(take, [col], 5, image, settings=s)
    on = T.track_forward_to_end(take, [col], 5, image, settings=dataclasses.replace(
        s, allow_single_sensor_tracking=True))
    before = copy.deepcopy(take)
    ses.apply(off)
    assert np.isnan(take.xyz[6:12, col]).all() and (take.recon[6:12, col] == Recon.NONE).all()
    ses.stack.undo()
    ses.apply(on)
    f = np.arange(6, 12)
    assert (take.recon[f, col] == Recon.SINGLE_SENSOR).all()
    X = take.xyz[f, col]
    proj = np.stack([project(X[i], tr.intrinsics[2], tr.R[fi, 2], tr.t[fi, 2]) for i, fi in enumerate(f)])
    assert np.allclose(proj, take.obs_xy[f, col, 2], atol=1e-3)          # on camera 2's ray
    assert np.linalg.norm(X - tr.xyz[f, m], axis=-1).max() < 3.0        # near the truth (mm)
    ses.stack.undo()
    assert take_diff(take, before) == []


def test_cancel_keeps_finished_frames(ses, synth, image, undo_check):
    take = ses.take
    m = int(_clean(synth, (0, 1), np.arange(0, 10))[0])
    col = _new_point(ses, synth, m, 0, (0, 1))
    done = []
    ch = T.track_forward_to_end(take, [col], 0, image, progress=lambda d, n: done.append(d),
                                cancel=lambda: len(done) >= 3)
    assert ch.report.cancelled and ch.report.stop_reason == ["cancelled"] * 2
    undo_check(ses, ch)
    assert (take.obs_src[1:4, col, :2] == ObsSource.TARGET).all()
    assert np.isnan(take.obs_xy[4:, col]).all()
