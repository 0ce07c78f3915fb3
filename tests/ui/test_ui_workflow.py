"""End to end through the GUI: import a synthetic take, detect blobs from the Process menu in a
worker, merge detections into a point with the M shortcut, undo everything and compare."""

import copy

import numpy as np
from PySide6.QtCore import Qt

from carapost.model.take import Recon
from carapost.ops.change import take_diff


def press(qtbot, w, key, mods=Qt.KeyboardModifier.NoModifier):
    target = w.workspace.slots[0].view
    qtbot.keyClick(target, key, mods)


def test_detect_merge_undo_redo(qtbot, loaded, tiny_files):
    w = loaded
    synth, _ = tiny_files
    take = w.doc.take
    before = copy.deepcopy(take)
    assert w.windowTitle().startswith("Tiny (not saved)") and not w.isWindowModified()

    # Properties pane: a smaller Black Min Radius for the 640x360 images (one undoable edit).
    editor = w.panes["properties"].sections["blobs"].editors["black_min_radius"]
    editor.setValue(1.5)
    assert take.params.blobs.black_min_radius == 1.5
    assert w.doc.undo.count() == 1 and w.isWindowModified()

    # Process > Detect Blobs [Active Range] runs in a worker with the progress panel showing.
    w.actions["process.detect_range"].trigger()
    assert w.jobs.busy and w.doc.busy
    assert not w.actions["edit.merge"].isEnabled()          # editing is off while it runs
    qtbot.waitUntil(lambda: not w.jobs.busy, timeout=60000)
    assert not w.timebar.progress.isVisible()
    assert all(d.detected.all() for d in take.detections)
    assert all(d.count(f) >= 15 for d in take.detections for f in range(take.n_frames))
    assert w.doc.undo.count() == 2 and w.doc.undo.text(1).startswith("Detect Blobs [Active Range]")

    # Pick the detections of one marker in cameras 0, 1 and 2 of frame 0 (truth within 1 px).
    tr = synth.truth
    m = next(m for m in range(tr.visible.shape[1]) if tr.visible[0, m, :3].all())
    dets = []
    for c in range(3):
        d = np.linalg.norm(take.detections[c].xy(0) - tr.xy[0, m, c], axis=1)
        assert d.min() < 1.0
        dets.append((c, 0, int(np.argmin(d))))
    w.doc.select((), dets)
    press(qtbot, w, Qt.Key.Key_M)
    assert w.last_action == "edit.merge"
    assert take.n_points == 1 and take.recon[0, 0] == Recon.MULTI_VIEW
    assert np.linalg.norm(take.xyz[0, 0] - tr.xyz[0, m]) < 2.0      # mm, nominal calibration (flex ignored)
    assert w.doc.sel_points == [int(take.points.ids[0])]           # the new point is selected
    after = copy.deepcopy(take)
    n = w.doc.undo.count()
    assert n == 3

    # Undo everything with Ctrl+Z: the take is exactly the imported one again.
    for _ in range(n):
        press(qtbot, w, Qt.Key.Key_Z, Qt.KeyboardModifier.ControlModifier)
    assert w.doc.undo.index() == 0
    assert take_diff(take, before) == []
    assert not w.isWindowModified()
    # The History pane shows all three entries as undone (red).
    hist = w.panes["history"]
    assert [applied for _, applied in hist.entries()] == [False, False, False]
    # Redo everything with Ctrl+Y.
    for _ in range(n):
        press(qtbot, w, Qt.Key.Key_Y, Qt.KeyboardModifier.ControlModifier)
    assert take_diff(take, after) == []


def test_cancel_keeps_finished_frames(qtbot, loaded):
    """Cancel stops a worker; what was finished is applied as one undoable change."""
    w = loaded
    calls = {"n": 0}

    def slow_op(progress, cancel):
        from carapost.ops.detect import detect_blobs

        def image(c, f):
            calls["n"] += 1
            if calls["n"] == 2:
                w.jobs.cancel()          # the user presses Cancel while frames are running
            return w.doc.session.image(c, f)

        return detect_blobs(w.doc.take, image, range(3), cameras=[0], workers=1, progress=progress, cancel=cancel)

    w.run_job("Detect Blobs [Active Range]", slow_op, lambda ch, cancelled: w.apply(ch, force=True))
    qtbot.waitUntil(lambda: not w.jobs.busy, timeout=30000)
    det = w.doc.take.detections[0]
    assert 1 <= det.detected.sum() < 3
    assert w.doc.undo.count() == 1
    w.doc.undo.undo()
    assert not w.doc.take.detections[0].detected.any()


def test_cancel_button(qtbot, loaded):
    import threading

    w = loaded
    gate = threading.Event()

    def job(progress, cancel):
        progress(0, 10)
        while not cancel():
            gate.wait(0.01)
        return None

    w.run_job("Waiting", job, lambda r, c: None)
    qtbot.waitUntil(lambda: w.timebar.progress.isVisible(), timeout=5000)
    qtbot.mouseClick(w.timebar.progress.cancel_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: not w.jobs.busy, timeout=5000)
    assert not w.doc.busy and w.actions["edit.merge"].isEnabled()


def test_close_while_a_job_runs_cancels_it(qtbot, window):
    import threading

    gate = threading.Event()
    stopped = []

    def job(progress, cancel):
        while not cancel():
            gate.wait(0.01)
        stopped.append(True)
        return None

    window.run_job("Waiting", job, lambda r, c: None)
    assert window.jobs.busy
    window.close()
    assert stopped == [True]
