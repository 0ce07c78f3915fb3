"""Process > Load ROM, Initialize from ROM and Initialize from ROM [Brim Only] through the GUI
(file prompt, worker thread, undo)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "core"))

from rom_cases import rom_take  # noqa: E402

from carapost.io.cara import save_take  # noqa: E402
from carapost.model.take import PointKind  # noqa: E402
from carapost.synth import SynthConfig  # noqa: E402


def wait(qtbot, w):
    qtbot.waitUntil(lambda: not w.jobs.busy, timeout=60000)


@pytest.fixture(scope="module")
def rom_file(tmp_path_factory):
    """A solved ROM of the same rig as the UI's tiny take (640 x 360, 35 markers, another seed)."""
    path = tmp_path_factory.mktemp("ui_rom") / "ROM.cara"
    save_take(rom_take(SynthConfig(n_markers=35, n_frames=1, width=640, height=360, seed=1)), path)
    return path


@pytest.mark.parametrize("brim_only", [False, True])
def test_load_rom_then_initialize(qtbot, loaded, rom_file, brim_only):
    w = loaded
    take = w.doc.take
    take.params.blobs.black_min_radius = 2.0           # the tiny take's small markers
    w.prompts.answers["open_file"] = str(rom_file)
    w.actions["process.load_rom"].trigger()
    wait(qtbot, w)
    assert take.rom_path == str(rom_file) and w.doc.rom is not None and w.doc.rom.n_points == 53
    n, n_points = w.doc.undo.count(), take.n_points
    w.doc.set_frame(1)
    w.actions["process.init_rom_brim" if brim_only else "process.init_rom"].trigger()
    wait(qtbot, w)
    assert w.doc.undo.count() == n + 1
    brim = take.brim_points()
    assert len(brim) == 18 and (take.n_views()[1, brim] >= 2).sum() >= 16
    face = take.face_points()
    if brim_only:
        assert len(face) == 0
    else:
        assert len(face) == 35 and np.isfinite(take.xyz[1, face]).all(-1).sum() >= 20
        assert [take.points.labels[i] for i in face] == [w.doc.rom.points.labels[i] for i in w.doc.rom.face_points()]
    assert all(d.detected[1] for d in take.detections)   # detected first
    w.doc.undo.undo()
    assert take.n_points == n_points and not (take.points.kind == PointKind.BRIM).any()


def test_load_rom_bad_file_logs_error(qtbot, loaded, tmp_path):
    w = loaded
    bad = tmp_path / "bad.cara"
    bad.write_text("no")
    rows = []
    w.log_handler.emitter.record.connect(rows.append)
    w.prompts.answers["open_file"] = str(bad)
    w.actions["process.load_rom"].trigger()
    wait(qtbot, w)
    assert w.doc.take.rom_path == "" and w.doc.rom is None
    assert any(r[1] == "Error" and "bad.cara" in r[3] for r in rows)
