"""Helpers of the GUI tests: dialogs answered without modal loops, loading the tiny take, and
points built from the synthetic truth."""

from __future__ import annotations

import numpy as np

__all__ = ["FakePrompts", "load_take", "inject_truth"]


class FakePrompts:
    """Answers the GUI's questions from ``answers`` (a value or a callable) and records them."""

    def __init__(self) -> None:
        self.answers: dict[str, object] = {"save_discard_cancel": "discard"}
        self.calls: list[tuple] = []

    def _get(self, name: str, *args: object) -> object:
        self.calls.append((name, *args))
        a = self.answers.get(name)
        return a(*args) if callable(a) else a

    def open_file(self, title, filters, folder=""):  # noqa: ANN001, ANN201
        return self._get("open_file", title)

    def open_files(self, title, filters, folder=""):  # noqa: ANN001, ANN201
        return self._get("open_files", title)

    def open_folder(self, title, folder=""):  # noqa: ANN001, ANN201
        return self._get("open_folder", title)

    def save_file(self, title, filters, folder=""):  # noqa: ANN001, ANN201
        return self._get("save_file", title)

    def get_int(self, title, label, value, lo, hi):  # noqa: ANN001, ANN201
        return self._get("get_int", title)

    def get_text(self, title, label, text=""):  # noqa: ANN001, ANN201
        return self._get("get_text", title)

    def get_colour(self, title, colour):  # noqa: ANN001, ANN201
        return self._get("get_colour", title)

    def save_discard_cancel(self, text):  # noqa: ANN001, ANN201
        return self._get("save_discard_cancel")

    def info(self, title, text):  # noqa: ANN001, ANN201
        self.calls.append(("info", title, text))


def load_take(qtbot, w, files) -> None:  # noqa: ANN001
    """Import the tiny take into a window and wait for the worker."""
    synth, paths = files
    w.import_sources([str(paths["pico_0"])])
    qtbot.waitUntil(lambda: w.doc.has_take and not w.jobs.busy, timeout=30000)


def inject_truth(w, synth, markers=10) -> None:  # noqa: ANN001
    """Give the open take the exact truth projections as detections (before any history), then
    build ``markers`` points through the Merge operation in every frame (undoable entries)."""
    from carapost.ops.points import merge

    take = w.doc.take
    tr = synth.truth
    F, M, C = tr.visible.shape
    for c in range(C):
        frames = {}
        for f in range(F):
            vis = np.flatnonzero(tr.visible[f, :, c])
            frames[f] = {"x": tr.xy[f, vis, c, 0], "y": tr.xy[f, vis, c, 1], "major": np.full(len(vis), 3.0),
                         "minor": np.full(len(vis), 2.5), "angle": np.zeros(len(vis)),
                         "polarity": np.full(len(vis), -1), "score": np.ones(len(vis))}
        take.detections[c] = take.detections[c].with_frames(frames)
    w.doc.notify_take_changed()
    done = 0
    for m in range(M):
        if done == markers:
            break
        if not tr.visible[:, m, :2].all():
            continue
        col = None
        for f in range(F):
            dets = [(c, f, int(np.flatnonzero(np.flatnonzero(tr.visible[f, :, c]) == m)[0]))
                    for c in range(C) if tr.visible[f, m, c]]
            w.doc.apply(merge(take, [] if col is None else [col], dets, frame=f))
            col = take.n_points - 1 if col is None else col
        done += 1
