"""Process menu commands that need a dialog or a file (the rest are one-line entries of the
action table in :mod:`carapost.ui.actions`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from carapost.model.take import PointKind, Take

from .adapters import ops

if TYPE_CHECKING:  # pragma: no cover
    from .main_window import MainWindow

log = logging.getLogger("carapost")


def load_rom(w: "MainWindow") -> None:
    """Load ROM: read and check a solved ``.cara`` take (shown by the views' ROM option)."""
    path = w.prompts.open_file("Load ROM", "CaraPost projects (*.cara)", w.last_dir())
    if not path:
        return
    take = w.doc.take

    def job(progress, cancel):  # type: ignore[no-untyped-def]
        rom_ops = ops("rom")
        rom = rom_ops.read_rom(path, n_cameras=take.n_cameras)
        return rom, rom_ops.load_rom(take, path, rom=rom)

    def done(result, cancelled):  # type: ignore[no-untyped-def]
        rom, change = result
        w.doc.rom = rom
        w.apply(change, force=True)
        log.info("ROM %s: %d points, %d frames", path, rom.n_points, rom.n_frames)

    w.run_job("Load ROM", job, done)


def _initialize_from_rom(w: "MainWindow", brim_only: bool) -> None:
    """Initialize from ROM [Brim Only] in the current frame, in a worker; logs what was found."""
    doc = w.doc
    take, frame, session = doc.take, doc.frame, doc.session
    title = "Initialize from ROM [Brim Only]" if brim_only else "Initialize from ROM"
    if not take.rom_path:            # never loaded, or Load ROM undone
        raise ValueError(f"{title}: no ROM take has been loaded: use Process > Load ROM first")
    rom = doc.rom                    # None (e.g. a reopened project): read from take.rom_path
    image = session.image if session is not None and not session.missing else None

    def job(progress, cancel):  # type: ignore[no-untyped-def]
        return ops("rom").initialize_from_rom(take, image, frame, brim_only=brim_only, rom=rom)

    def done(change, cancelled):  # type: ignore[no-untyped-def]
        if w.apply(change, force=True):
            report = getattr(change, "report", {})
            log.info("%s", change.text)
            if report.get("not_found"):
                log.warning("%s: not found: %s", title, ", ".join(report["not_found"]))

    w.run_job(title, job, done)


def initialize_from_rom(w: "MainWindow") -> None:
    """Initialize from ROM: brim and face points of the ROM frame in the current frame."""
    _initialize_from_rom(w, False)


def initialize_from_rom_brim_only(w: "MainWindow") -> None:
    """Initialize from ROM [Brim Only]: the calibration and the brim."""
    _initialize_from_rom(w, True)


def _default_brim(w: "MainWindow", version: str) -> None:
    w.apply(ops("brim").initialize_default_brim(w.doc.take, version))


def brim_v20(w: "MainWindow") -> None:
    _default_brim(w, "v2.0")


def brim_v11(w: "MainWindow") -> None:
    _default_brim(w, "v1.1")


def brim_v10(w: "MainWindow") -> None:
    _default_brim(w, "v1.0")


def brim_correspondences(take: Take, frame: int) -> dict[int, dict[int, int]]:
    """The user's brim matches in ``frame``: ``{brim dot: {camera: detection}}`` from the
    detections attached (merged) to brim points."""
    cols = np.flatnonzero(take.points.kind == PointKind.BRIM)
    det = take.obs_det[frame][cols]                       # (B', C)
    out: dict[int, dict[int, int]] = {}
    for j, c in zip(*np.nonzero(det >= 0)):
        out.setdefault(int(take.points.brim_index[cols[j]]), {})[int(c)] = int(det[j, c])
    return out


def solve_brim(w: "MainWindow") -> None:
    """Solve Calibration Brim [Manual]: from the detections merged into brim points (>= 4 per
    camera) in the current frame."""
    take, frame = w.doc.take, w.doc.frame
    corr = brim_correspondences(take, frame)
    if not corr:
        raise ValueError("Solve Calibration Brim: merge detections into four or more brim points per camera "
                         "(select a brim point and its detections, then Merge) in the current frame")

    def job(progress, cancel):  # type: ignore[no-untyped-def]
        change, res = ops("brim").solve_brim_manual(take, frame, corr)
        return change

    w.run_job("Solve Calibration Brim [Manual]", job, lambda ch, cancelled: w.apply(ch, force=True))


def _reported(w: "MainWindow", title: str, build: Callable[[], Any]) -> None:
    """Run an operation that returns a change with a ``report`` in a worker; log the report."""
    def done(change: Any, cancelled: bool) -> None:
        if w.apply(change, force=True):
            for k, v in (getattr(change, "report", None) or {}).items():
                log.info("%s: %s = %s", title, k, v)

    w.run_job(title, lambda progress, cancel: build(), done)


def interpolate_gaps(w: "MainWindow") -> None:
    take, cols = w.doc.take, w.doc.selected_columns()
    rom = w.doc.rom                      # the loaded ROM: eyelid depths (blink), the face model (face_model)
    _reported(w, "Interpolate Gaps", lambda: ops("fill").interpolate_gaps(take, cols or None, rom=rom))


def stabilize_manual(w: "MainWindow") -> None:
    take, cols, f = w.doc.take, w.doc.selected_columns(), w.doc.frame
    _reported(w, "Stabilize Data [Manual]", lambda: ops("fill").stabilize_manual(take, cols, base_frame=f))


def stabilize_assisted(w: "MainWindow") -> None:
    take, cols, f = w.doc.take, w.doc.selected_columns(), w.doc.frame
    _reported(w, "Stabilize Data [Assisted]", lambda: ops("fill").stabilize_assisted(take, cols, base_frame=f))


def align_data(w: "MainWindow") -> None:
    take, cols, f = w.doc.take, w.doc.selected_columns(), w.doc.frame
    if len(cols) != 3:
        raise ValueError("Align Data: select exactly three face points")
    _reported(w, "Align Data", lambda: ops("fill").align_data(take, cols, frame=f))


def set_caddies(w: "MainWindow") -> None:
    """Caddies...: the camera pairs Initialize 3D grows two-view points in (two cameras on one
    side of a head rig), or none for cameras standing around a room."""
    from carapost.ops import settings as settings_ops

    take = w.doc.take
    text = w.prompts.get_text("Caddies", "Camera pairs on one side of the head rig (e.g. 0-1,2-3), or none "
                              "for cameras around a room:", settings_ops.format_caddies(take.caddies))
    if text is None:
        return
    pairs = settings_ops.parse_caddies(text)
    w.apply(settings_ops.set_caddies(take, pairs or []))
