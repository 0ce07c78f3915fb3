"""Fixtures for operation tests: a tiny synthetic take written to disk and opened as a session."""

import copy

import pytest

from carapost.ops.session import Session
from carapost.synth import SynthConfig, generate_take, write_take


@pytest.fixture(scope="session")
def tiny_take_files(tmp_path_factory):
    synth = generate_take(SynthConfig(n_markers=35, n_frames=4, width=640, height=360, seed=3))
    out = tmp_path_factory.mktemp("tiny")
    paths = write_take(synth, out, "Tiny")
    return synth, paths


@pytest.fixture
def session(tiny_take_files):
    synth, paths = tiny_take_files
    picos = [paths[f"pico_{c}"] for c in range(4)]
    s = Session.from_sources(picos, paths["xcp"], name="Tiny")
    yield s
    s.close()


@pytest.fixture
def undo_check():
    return check_undo_redo


def check_undo_redo(session, change):
    """Apply ``change`` through the stack, undo, compare with before, redo, compare with after."""
    from carapost.ops.change import take_diff

    before = copy.deepcopy(session.take)
    session.apply(change)
    after = copy.deepcopy(session.take)
    session.stack.undo()
    assert take_diff(session.take, before) == []
    session.stack.redo()
    assert take_diff(session.take, after) == []
    return before, after


@pytest.fixture(scope="session")
def tiny_synth():
    return generate_take(SynthConfig(n_markers=35, n_frames=6, width=640, height=360, seed=5))


@pytest.fixture
def truth_take(tiny_synth):
    """A take whose detections are the exact truth projections (marker m of camera c in frame f
    is detection ``order[f, c][m]``), with no points yet. Returns (take, det_of) where
    ``det_of[f, m, c]`` is the detection index of marker m (-1 if invisible)."""
    import numpy as np

    from carapost.core.camera import Intrinsics  # noqa: F401
    from carapost.model.take import CameraInfo, Take

    tr = tiny_synth.truth
    F, M, C = tr.visible.shape
    cams = [CameraInfo(f"cam{c}", c, tr.intrinsics[c], (640, 360)) for c in range(C)]
    take = Take.new(cams, F, 60.0, R=tr.R, t=tr.t)
    det_of = np.full((F, M, C), -1, np.int32)
    for c in range(C):
        frames = {}
        for f in range(F):
            vis = np.flatnonzero(tr.visible[f, :, c])
            rng = np.random.default_rng(f * 10 + c)
            order = rng.permutation(len(vis))
            m = vis[order]
            det_of[f, m, c] = np.arange(len(m))
            frames[f] = {"x": tr.xy[f, m, c, 0], "y": tr.xy[f, m, c, 1], "major": np.full(len(m), 3.0),
                         "minor": np.full(len(m), 3.0), "polarity": np.full(len(m), -1), "score": np.ones(len(m))}
        take.detections[c] = take.detections[c].with_frames(frames)
    return take, det_of
