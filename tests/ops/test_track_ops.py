"""Track Forwards / Backwards [Sequence] / [Single Frame]: undoable, exact undo/redo."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "core"))

from track_cases import evaluate, label_detections, truth_case  # noqa: E402

from carapost.model.take import ObsSource, PointKind, Recon  # noqa: E402
from carapost.ops.change import take_diff  # noqa: E402
from carapost.ops.session import Session  # noqa: E402
from carapost.ops.track import (track_backwards_sequence, track_backwards_single_frame,  # noqa: E402
                                track_forwards_sequence, track_forwards_single_frame, track_sequence)
from carapost.synth import SynthConfig  # noqa: E402


@pytest.fixture(scope="module")
def small_case():
    return truth_case(SynthConfig(n_markers=35, n_frames=12, width=640, height=360, seed=4))


@pytest.fixture
def track_session(small_case):
    return Session(copy.deepcopy(small_case.take))


def test_track_forwards_sequence_undo_redo(track_session, small_case, undo_check):
    take = track_session.take
    ch = track_forwards_sequence(take, None, 0)
    assert np.isnan(take.xyz[1:]).all()          # the op does not touch the take
    before, after = undo_check(track_session, ch)
    assert "Track Forwards [Sequence]" in ch.text and "11 frames" in ch.text
    t = track_session.take
    s = evaluate(t, small_case.truth, small_case.labels, range(1, 12))
    assert s.coverage >= 0.98 and s.wrong_frames == 0      # (eyelids start a blink in this clip)
    # poses were re-estimated per frame (they differ from the nominal calibration)
    assert not np.allclose(t.R[5], before.R[5])
    assert set(take_diff(before, after)) <= {"xyz", "recon", "obs_xy", "obs_det", "obs_src", "obs_q", "R", "t"}
    # nothing outside the frames tracked changed
    np.testing.assert_array_equal(after.obs_det[0], before.obs_det[0])


def test_single_frame_steps_and_backwards(track_session, small_case, undo_check):
    s = track_session
    s.apply(track_forwards_sequence(s.take, None, 0, n_frames=6))
    ch = track_forwards_single_frame(s.take, None, 6)
    before, after = undo_check(s, ch)
    changed = np.flatnonzero(np.any(before.obs_det != after.obs_det, axis=(1, 2)))
    assert list(changed) == [7]
    assert (after.recon[7, after.face_points()] == Recon.MULTI_VIEW).mean() > 0.9
    # backwards one frame from 7 re-tracks frame 6 only
    ch = track_backwards_single_frame(s.take, None, 7)
    before, after = undo_check(s, ch)
    assert "Track Backwards [Single Frame]" in ch.text
    diff = np.flatnonzero(np.any(np.isfinite(before.xyz) != np.isfinite(after.xyz), axis=(1, 2))
                          | np.any(np.nan_to_num(before.xyz - after.xyz) != 0, axis=(1, 2)))
    assert set(diff) <= {6}
    # backwards to the start from frame 7
    ch = track_backwards_sequence(s.take, None, 7)
    undo_check(s, ch)
    sc = evaluate(s.take, small_case.truth, small_case.labels, range(0, 7))
    assert sc.coverage >= 0.98 and sc.wrong_frames == 0


def test_selected_points_only(track_session, undo_check):
    s = track_session
    face = s.take.face_points()
    sel = face[:5]
    ch = track_forwards_sequence(s.take, None, 0, points=sel, n_frames=4)
    before, after = undo_check(s, ch)
    others = np.setdiff1d(np.arange(s.take.n_points), sel)
    np.testing.assert_array_equal(after.obs_det[:, others], before.obs_det[:, others])
    assert np.isfinite(after.xyz[1:5, sel]).all(-1).mean() > 0.9
    # no brim points selected: the cameras keep their poses
    np.testing.assert_array_equal(after.R, before.R)


def test_cancel_keeps_finished_frames(track_session):
    s = track_session
    done = []
    ch = track_forwards_sequence(s.take, None, 0, progress=lambda d, t: done.append(d), cancel=lambda: len(done) >= 3)
    assert "(cancelled)" in ch.text
    s.apply(ch)
    known = np.isfinite(s.take.xyz).all(-1).any(1)
    assert list(np.flatnonzero(known)) == [0, 1, 2, 3]


def test_bad_requests(track_session):
    take = track_session.take
    with pytest.raises(ValueError, match="outside the take"):
        track_forwards_sequence(take, None, 99)
    with pytest.raises(ValueError, match="no point has a 3D position"):
        track_forwards_sequence(take, None, 5)
    with pytest.raises(ValueError, match="point columns"):
        track_forwards_sequence(take, None, 0, points=[999])
    # at the last frame there is nothing to track forwards: an empty change
    t2 = copy.deepcopy(take)
    t2.xyz[11] = t2.xyz[0]
    assert not track_forwards_sequence(t2, None, 11).changes


def test_detects_frames_not_detected_yet(session, tiny_take_files, undo_check):
    """With the video, tracking first detects blobs in frames that have none."""
    synth, _ = tiny_take_files
    take = session.take
    take.params.blobs = take.params.blobs.from_dict({**take.params.blobs.to_dict(), "black_min_radius": 1.5,
                                                     "white_min_radius": 1.5})
    from carapost.ops.detect import detect_blobs

    session.apply(detect_blobs(take, session.image, [0], workers=1))
    _init_from_truth(take, synth, 0)
    assert not take.detections[0].detected[1:].any()
    ch = track_sequence(take, session.image, 0)
    before, after = undo_check(session, ch)
    assert all(d.detected.all() for d in after.detections)
    assert not any(d.detected[1:].any() for d in before.detections)
    # the tracked points sit on their markers
    tr = synth.truth
    face = after.face_points()
    M = len(tr.names)
    ok = np.isfinite(after.xyz[1:, face]).all(-1)
    assert ok.mean() > 0.8
    err = np.linalg.norm(after.xyz[1:, face] - tr.xyz[1:, :M], axis=-1)[ok]
    assert np.median(err) < 0.5
    labels = label_detections(tr, after.detections, range(4), match_px=1.5)
    wrong = 0
    for f in range(1, 4):
        for c in range(4):
            od = after.obs_det[f, face, c]
            has = od >= 0
            lab = labels[c][f][od[has]]
            wrong += int(((lab != np.arange(M)[has]) & (lab >= 0)).sum())
    assert wrong == 0
    srcs = after.obs_src[1:, face][after.obs_det[1:, face] >= 0]
    assert (srcs == ObsSource.BLOB).all()


def _init_from_truth(take, synth, f):
    """Points at the truth with the detections near the truth projections attached (a seeded
    Initialize 3D), and brim points on the brim dots; the frame's true poses."""
    tr = synth.truth
    M, B = len(tr.names), len(tr.brim_xyz)
    face = take.add_points(M, labels=list(tr.names))
    brim = take.add_points(B, kind=PointKind.BRIM, brim_index=np.arange(B))
    take.brim = synth.brim
    take.xyz[f, face] = tr.xyz[f]
    take.xyz[f, brim] = tr.brim_xyz
    take.R[f], take.t[f] = tr.R[f], tr.t[f]
    for c in range(4):
        xy = take.detections[c].xy(f)
        if not len(xy):
            continue
        for cols, pts, vis in ((face, tr.centroid_xy[f, :, c], tr.visible[f, :, c]),
                               (brim, tr.brim_centroid_xy[f, :, c], tr.brim_visible[f, :, c])):
            for j in np.flatnonzero(vis):
                d = np.linalg.norm(xy - pts[j], axis=1)
                i = int(np.argmin(d))
                if d[i] < 1.0:
                    take.obs_det[f, cols[j], c] = i
                    take.obs_xy[f, cols[j], c] = xy[i]
                    take.obs_src[f, cols[j], c] = ObsSource.BLOB
    nv = take.n_views()[f]
    take.recon[f] = np.where(nv >= 2, Recon.MULTI_VIEW, Recon.NONE)
