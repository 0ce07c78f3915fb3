"""Scrubbing speed of the GUI: a 4-camera 1280x720 take with overlays, offscreen.

The main window shows the four sensor views (fitted, 1600x1000 window) with detections, points,
projections and labels of 80 markers; every step moves the current frame and repaints all four
views synchronously (image decode through the frame cache + overlay + painting).

* ``sequential``: scrubbing forward one frame at a time (the cache prefetches ahead);
* ``random``: jumping to random frames (every frame decoded on demand: decode-bound);
* ``cached``: revisiting decoded frames (overlay and painting alone).

Rates are reported by wall time and by CPU time of the whole process (decode threads
included: the rate one core doing all the work would reach, robust to a busy machine).
Target: sequential scrubbing >= 30 frames/s, judged on the CPU-time rate. Prints one JSON line.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit  # noqa: E402

N_FRAMES, N_MARKERS = 48, 80


def build_take(folder: Path):
    from carapost.synth import SynthConfig, generate_take, write_take

    synth = generate_take(SynthConfig(n_markers=N_MARKERS, n_frames=N_FRAMES, seed=1))
    paths = write_take(synth, folder, "Scrub")
    return synth, paths


def add_overlays(take, synth) -> None:
    """Truth detections in every frame and one point per marker (obs + 3D), written directly."""
    tr = synth.truth
    F, M, C = tr.visible.shape
    for c in range(C):
        frames = {}
        for f in range(F):
            vis = np.flatnonzero(tr.visible[f, :, c])
            frames[f] = {"x": tr.xy[f, vis, c, 0], "y": tr.xy[f, vis, c, 1], "major": np.full(len(vis), 4.0),
                         "minor": np.full(len(vis), 3.0), "angle": np.zeros(len(vis)),
                         "polarity": np.full(len(vis), -1), "score": np.ones(len(vis))}
        take.detections[c] = take.detections[c].with_frames(frames)
    take.add_points(M, labels=list(tr.names))
    take.xyz[:] = tr.xyz
    take.recon[:] = 3
    vis = tr.visible
    take.obs_xy[:] = np.where(vis[..., None], tr.xy, np.nan).astype(np.float32)
    take.obs_src[:] = np.where(vis, 1, 0)
    for c in range(C):
        for f in range(F):
            idx = np.full(M, -1, np.int32)
            v = np.flatnonzero(vis[f, :, c])
            idx[v] = np.arange(len(v))
            take.obs_det[f, :, c] = idx


def main() -> None:
    from PySide6.QtCore import QStandardPaths
    from PySide6.QtWidgets import QApplication

    from carapost.ops.session import Session
    from carapost.ui.app import application
    from carapost.ui.main_window import MainWindow

    QStandardPaths.setTestModeEnabled(True)
    app = application()
    with tempfile.TemporaryDirectory() as tmp:
        synth, paths = build_take(Path(tmp))
        session = Session.from_sources([paths[f"pico_{c}"] for c in range(4)], paths["xcp"], name="Scrub")
        add_overlays(session.take, synth)
        session.take.params.display.point_labels_all = True
        # Decode cost alone (one camera, uncached reads).
        t0 = time.perf_counter()
        for f in range(N_FRAMES):
            session.sources[0].read(f)
        decode_ms = (time.perf_counter() - t0) / N_FRAMES * 1000
        w = MainWindow()
        w.resize(1600, 1000)
        w.show()
        w.doc.set_session(session)
        w.doc.select(session.take.points.ids[:5].tolist())
        app.processEvents()
        views = w.workspace.camera_views()

        def step(f: int) -> None:
            w.doc.set_frame(f)
            app.processEvents()          # the event loop paints every dirty widget once

        for cache in w.doc.caches:       # cold start: nothing decoded yet
            cache.clear()  # type: ignore[union-attr]
        w.doc.frame = -1
        t0, c0 = time.perf_counter(), time.process_time()
        for f in range(N_FRAMES):
            step(f)
        for cache in w.doc.caches:       # count the decoding prefetched meanwhile too
            cache.wait(10)  # type: ignore[union-attr]
        seq = N_FRAMES / (time.perf_counter() - t0)
        seq_cpu = N_FRAMES / (time.process_time() - c0)
        rng = np.random.default_rng(0)
        order = rng.permutation(N_FRAMES)
        for cache in w.doc.caches:
            cache.clear()  # type: ignore[union-attr]
        t0, c0 = time.perf_counter(), time.process_time()
        for f in order:
            for cache in w.doc.caches:   # no prefetch help: every jump decodes
                cache.prefetch([])  # type: ignore[union-attr]
            step(int(f))
        rnd = N_FRAMES / (time.perf_counter() - t0)
        rnd_cpu = N_FRAMES / (time.process_time() - c0)
        for f in range(N_FRAMES):        # warm the cache completely
            step(f)
        t0, c0 = time.perf_counter(), time.process_time()
        for f in order:
            step(int(f))
        cached = N_FRAMES / (time.perf_counter() - t0)
        cached_cpu = N_FRAMES / (time.process_time() - c0)
        t0 = time.perf_counter()
        for _ in range(20):
            views[0].repaint()           # one view, idle quality (antialiased)
        paint_ms = (time.perf_counter() - t0) / 20 * 1000
        w.doc.undo.setClean()
        w.close()
        app.processEvents()
        QApplication.processEvents()
    emit("scrub_4x1280x720", frames=N_FRAMES, cameras=4, markers=N_MARKERS, window="1600x1000",
         sequential_fps=round(seq, 1), sequential_fps_cpu=round(seq_cpu, 1), random_fps=round(rnd, 1),
         random_fps_cpu=round(rnd_cpu, 1), cached_fps=round(cached, 1), cached_fps_cpu=round(cached_cpu, 1),
         paint_ms_per_view=round(paint_ms, 2), decode_ms_per_image=round(decode_ms, 2),
         target_fps=30, ok=seq_cpu >= 30)


if __name__ == "__main__":
    main()
