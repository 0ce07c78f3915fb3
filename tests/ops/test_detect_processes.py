"""Detect Blobs over a range runs in worker processes when the session's sources are given, with
exactly the detections of the threaded path, progress, cancel and one undoable change."""

import numpy as np
import pytest

from carapost.ops import detect as detect_ops
from carapost.ops.change import take_diff
from carapost.ops.session import Session


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from carapost.synth import SynthConfig, generate_take, write_take

    synth = generate_take(SynthConfig(n_markers=35, n_frames=8, width=640, height=360, seed=9))
    return write_take(synth, tmp_path_factory.mktemp("dp"), "D")


def _session(files):
    return Session.from_sources([files[f"pico_{c}"] for c in range(4)], files["xcp"])


def test_processes_match_threads(files, monkeypatch):
    import carapost.ops.split_detect as split

    used = []
    real = split.detect_blobs_split
    monkeypatch.setattr(split, "detect_blobs_split", lambda *a, **k: used.append(k["workers"]) or real(*a, **k))
    with _session(files) as s:
        frames = range(s.take.n_frames)                                    # 8 frames x 4 cameras = 32 images
        seen = []
        by_processes = detect_ops.detect_blobs(s.take, s.image, frames, sources=s.sources,
                                               progress=lambda d, t: seen.append((d, t)))
        by_threads = detect_ops.detect_blobs(s.take, s.image, frames)
        assert used == [2] and seen[-1] == (32, 32)
        assert by_processes.text == by_threads.text
        for a, b in zip(by_processes.changes, by_threads.changes):
            assert a.camera == b.camera and sorted(a.new) == sorted(b.new)
            for f in a.new:
                for key in ("x", "y", "major", "minor", "score"):
                    np.testing.assert_array_equal(a.new[f][key], b.new[f][key])
        import copy

        before = copy.deepcopy(s.take)
        s.apply(by_processes)
        assert all(d.detected.all() for d in s.take.detections)
        s.stack.undo()
        assert take_diff(s.take, before) == []


def test_short_ranges_stay_in_threads(files, monkeypatch):
    import carapost.ops.split_detect as split

    monkeypatch.setattr(split, "detect_blobs_split", lambda *a, **k: pytest.fail("no processes for one frame"))
    with _session(files) as s:
        change = detect_ops.detect_blobs(s.take, s.image, [0], sources=s.sources)
        assert change.text.startswith("Detect Blobs [Current Frame]")


def test_cancel_keeps_finished_chunks(files):
    from carapost.ops.split_detect import detect_blobs_split

    with _session(files) as s:
        calls = []

        def cancel():
            calls.append(1)
            return len(calls) > 1                                            # stop after the first chunk

        change = detect_blobs_split(s.take, range(s.take.n_frames), sources=s.sources, cancel=cancel,
                                    chunk_frames=1)             # one frame a chunk: cancel acts between them
        done = {f for ch in change.changes for f in ch.new}
        assert 0 < len(done) < s.take.n_frames
