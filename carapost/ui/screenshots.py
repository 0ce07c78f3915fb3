"""The screenshots of ``docs/gui.md``, taken offscreen from a processed take.

``python -m carapost.ui.screenshots TAKE.cara OUTDIR [WIDTHxHEIGHT]`` (make the take with
``carapost demo --out DIR``) writes ``gui_main.png`` (four sensor views, one point selected),
``gui_views.png`` (3D view with labels, continuity chart with one point expanded per sensor,
graph view, a sensor) and ``gui_camera.png`` (one sensor zoomed in on the face with blob preview
and all labels).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["take_screenshots"]


def _pump(app, seconds: float = 0.3, until: Callable[[], bool] | None = None, timeout: float = 120.0) -> None:  # type: ignore[no-untyped-def]
    start = time.time()
    while True:
        app.processEvents()
        done = until() if until is not None else time.time() - start >= seconds
        if done:
            return
        if time.time() - start > timeout:
            raise TimeoutError("the window did not finish loading the take")
        time.sleep(0.01)


def take_screenshots(take: str | os.PathLike, out: str | os.PathLike, size: tuple[int, int] = (1600, 1000)) -> list[Path]:
    """Open ``take`` in a main window of ``size`` and save the three screenshots into ``out``."""
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtCore import QStandardPaths

    from .app import application, apply_theme

    QStandardPaths.setTestModeEnabled(True)   # never touch the user's settings
    app = application()
    apply_theme(app)
    from .main_window import MainWindow
    from .settings import Settings

    Settings().q.clear()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    w = MainWindow()
    try:
        return _shoot(app, w, take, out, size)
    finally:
        w.doc.set_display("blob_preview", False)
        w.doc.dirty_base = False
        w.doc.undo.setClean()
        w.close()
        _pump(app, 0.1)


def _shoot(app, w, take, out: Path, size: tuple[int, int]) -> list[Path]:  # type: ignore[no-untyped-def]
    w.resize(*size)
    w.show()
    w.open_path(str(take), ask=False)
    _pump(app, until=lambda: w.doc.has_take and not w.jobs.busy)
    doc = w.doc
    t = doc.take
    labelled = [c for c in range(t.n_points) if t.points.labels[c]]
    points = labelled[:1] or list(range(min(t.n_points, 1)))
    doc.set_frame(min(30, doc.n_frames - 1))
    doc.select_columns(points)
    _pump(app, 0.5)
    saved = []
    path = out / "gui_main.png"
    w.grab().save(str(path))
    saved.append(path)

    slots = w.workspace.visible_slots()
    v3 = slots[0].set_view("3d")
    v3.options["Point Labels :All"] = True
    v3.yaw, v3.pitch = 0.35, 0.15
    cont = slots[1].set_view("continuity")
    cont.expanded.update(int(t.points.ids[c]) for c in points)
    cont.on_take()
    slots[2].set_view("graph", 0)
    slots[3].set_view("sensor", 1 % max(t.n_cameras, 1))
    _pump(app, 0.6)
    path = out / "gui_views.png"
    w.grab().save(str(path))
    saved.append(path)

    w.workspace.set_layout(1)
    cam = slots[0].set_view("sensor", 0)
    _pump(app, 0.3)
    cam.set_option("Point Labels: All", True)
    doc.set_display("blob_preview", True)
    cam.fit_to_window()
    cam.center_selection()
    cam.zoom_at(2.2, cam.rect().center().toPointF())
    _pump(app, until=lambda: w.previewer.get(0, doc.frame) is not None, timeout=60)
    _pump(app, 0.5)
    path = out / "gui_camera.png"
    w.grab().save(str(path))
    saved.append(path)
    w.workspace.set_layout(4)
    return saved


if __name__ == "__main__":
    if len(sys.argv) < 3:
        print(__doc__)
        raise SystemExit(2)
    wh = tuple(int(v) for v in sys.argv[3].split("x")) if len(sys.argv) > 3 else (1600, 1000)
    for p in take_screenshots(sys.argv[1], sys.argv[2], wh):  # type: ignore[arg-type]
        print(p)
