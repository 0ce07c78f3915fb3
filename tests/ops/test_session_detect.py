import numpy as np
import pytest

from carapost.ops.change import take_diff
from carapost.ops.detect import detect_blobs, read_blob_parameters_from_pico, remove_unused_detections
from carapost.ops.session import Session



def test_session_from_sources(session, tiny_take_files):
    synth, _ = tiny_take_files
    take = session.take
    assert take.n_cameras == 4 and take.n_frames == 4
    assert [c.channel for c in take.cameras] == [0, 1, 2, 3]
    assert np.isfinite(take.R).all()
    img = session.image(2, 1)
    assert img.shape == (360, 640)
    assert take.params.blobs.find_black_blobs


def test_detect_current_frame_and_range_undo(session, tiny_take_files, undo_check):
    synth, _ = tiny_take_files
    take = session.take
    params = take.params.blobs.from_dict({**take.params.blobs.to_dict(), "black_min_radius": 1.5,
                                           "white_min_radius": 1.5})
    ch = detect_blobs(take, session.image, [1], workers=1, params=params)
    assert take.detections[0].count(1) == 0  # the op does not touch the take
    before, after = undo_check(session, ch)
    assert all(d.detected[1] and not d.detected[0] for d in session.take.detections)
    from carapost.core.blobs import detect_blobs as core_detect

    for c in range(4):
        direct = core_detect(session.image(c, 1), params)
        np.testing.assert_array_equal(session.take.detections[c].frame(1)["x"], direct["x"])
    assert sum(d.count(1) for d in session.take.detections) > 50
    ch2 = detect_blobs(take, session.image, range(4), cameras=[0, 3], workers=2)
    undo_check(session, ch2)
    assert session.take.detections[3].detected.all() and not session.take.detections[1].detected[0]


def test_detect_cancel_keeps_finished_frames(session):
    calls = []

    def cancel():
        return len(calls) >= 1

    ch = detect_blobs(session.take, session.image, range(4), cameras=[0], workers=1,
                      progress=lambda d, t: calls.append(d), cancel=cancel)
    session.apply(ch)
    det = session.take.detections[0]
    assert 1 <= det.detected.sum() < 4


def test_remove_unused_detections_keeps_attached(session, undo_check):
    take = session.take
    session.apply(detect_blobs(take, session.image, [0], workers=1))
    # attach detection 2 of camera 1 to a new point by hand
    take.add_points(1)
    take.obs_det[0, 0, 1] = 2
    take.obs_xy[0, 0, 1] = take.detections[1].xy(0)[2]
    xy_attached = take.detections[1].xy(0)[2].copy()
    ch = remove_unused_detections(take)
    undo_check(session, ch)
    det = session.take.detections[1]
    assert det.count(0) == 1
    assert session.take.obs_det[0, 0, 1] == 0
    np.testing.assert_array_equal(det.xy(0)[0], xy_attached)


def test_read_blob_parameters(session, undo_check):
    take = session.take
    take.params.blobs.black_threshold = 0.9
    ch = read_blob_parameters_from_pico(take, session.sources[0].meta.blob_parameters)
    undo_check(session, ch)
    assert session.take.params.blobs.black_threshold == 0.4
    with pytest.raises(ValueError, match="no blob parameters"):
        read_blob_parameters_from_pico(take, {})


def test_save_and_open_roundtrip(session, tmp_path):
    session.apply(detect_blobs(session.take, session.image, [0], workers=1))
    assert session.modified
    p = session.save(tmp_path / "t.cara")
    assert not session.modified
    again = Session.open(p)
    assert take_diff(again.take, session.take, ignore_sources=True) == []
    assert again.take.cameras[0].source.relpath == "Tiny_0.pico" or again.take.cameras[0].source.relpath
    assert again.missing == []
    again.close()
