"""The headless pipeline: what ``carapost process``, ``carapost demo``, batch jobs and the API run.

Stages, each an undoable change on the session's stack (so a script can undo any of them):
detect blobs -> calibration brim -> seeds / brim solve -> bundle -> Initialize 3D -> (later stages
register here as they land) -> exports. A failure raises :class:`PipelineError` naming the
stage and the cause; the stages already done stay applied.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .session import Session

__all__ = ["PipelineError", "PipelineOptions", "run_pipeline"]

Report = Callable[..., None]  # report(stage, seconds, **numbers)


class PipelineError(ValueError):
    """A stage failed; ``stage`` names it and the message gives the cause."""

    def __init__(self, stage: str, cause: str) -> None:
        super().__init__(f"{stage}: {cause}")
        self.stage = stage


@contextlib.contextmanager
def _no_progress(description: str, unit: str = "frame") -> Iterator[Callable[[int, int], None]]:
    yield lambda done, total: None


class PipelineOptions:
    """What to run. Paths may be strings or ``Path``s; ``None`` skips a stage.

    Attributes
    ----------
    frame : int or None
        The frame to initialize (default: the seeds file's frame, else 0).
    detect : {"frame", "range", "none"}
        Detect blobs in the initialization frame only (tracking detects the rest as it goes) or
        in the whole active range first.
    brim : str or None
        ``"v1.0"``, ``"v1.1"``, ``"v2.0"`` or a brim ``.svg`` / ``.json`` file.
    seeds : path or None
        Seeds file (brim dots and face markers matched across cameras, raw px).
    auto_init : bool
        Initialize 3D without seeds.
    c3d, fbx : path or None
        Export files written at the end.
    """

    def __init__(self, *, frame: int | None = None, detect: str = "frame", brim: str | None = None,
                 seeds: str | os.PathLike | None = None, auto_init: bool = False,
                 c3d: str | os.PathLike | None = None, fbx: str | os.PathLike | None = None) -> None:
        if detect not in ("frame", "range", "none"):
            raise ValueError(f"detect must be 'frame', 'range' or 'none', got {detect!r}")
        if seeds is None and not auto_init:
            raise ValueError("give a seeds file or ask for automatic initialization")
        self.frame, self.detect, self.brim, self.seeds, self.auto_init = frame, detect, brim, seeds, auto_init
        self.c3d, self.fbx = c3d, fbx


def run_pipeline(session: Session, options: PipelineOptions, *, report: Report | None = None,
                 progress: Callable[..., Any] = _no_progress, cancel: Callable[[], bool] | None = None) -> dict[str, Any]:
    """Run the stages on ``session``; returns a JSON-able summary (counts, timings, files).

    Raises
    ------
    PipelineError
        Naming the stage that failed and why.
    """
    from carapost.io.seeds import read_seeds, snap_seeds
    from carapost.ops.brim import initialize_default_brim, set_brim, solve_brim_manual
    from carapost.ops.detect import detect_blobs
    from carapost.ops.init3d import add_seed_points, bundle_current_frame, initialize_3d_op

    take = session.take
    summary: dict[str, Any] = {"stages": [], "files": []}

    def done(stage: str, t0: float, **numbers: Any) -> None:
        dt = time.perf_counter() - t0
        summary["stages"].append({"stage": stage, "seconds": round(dt, 3), **numbers})
        if report is not None:
            report(stage, dt, **numbers)

    @contextlib.contextmanager
    def stage(name: str) -> Iterator[None]:
        try:
            yield
        except PipelineError:
            raise
        except (ValueError, OSError, KeyError, IndexError) as exc:
            raise PipelineError(name, str(exc)) from exc

    seeds = None
    if options.seeds is not None:
        with stage("seeds"):
            seeds = read_seeds(options.seeds)
    frame = options.frame if options.frame is not None else (seeds.frame if seeds is not None else 0)
    if not 0 <= frame < take.n_frames:
        raise PipelineError("seeds", f"frame {frame} is outside the take (0..{take.n_frames - 1})")
    take.current_frame = frame

    # 1. Blob detection.
    frames = [frame] if options.detect == "frame" else list(range(take.active_range[0], take.active_range[1] + 1))
    todo = [f for f in frames if not all(d.detected[f] for d in take.detections)]
    if options.detect != "none" and todo:
        t0 = time.perf_counter()
        with stage("detect blobs"), progress("detect blobs") as prog:
            session.apply(detect_blobs(take, session.image, todo, progress=prog, cancel=cancel))
        done("detect blobs", t0, frames=len(todo), detections=int(sum(len(d) for d in take.detections)))

    # 2. Calibration brim.
    if options.brim is not None:
        t0 = time.perf_counter()
        with stage("calibration brim"):
            b = str(options.brim)
            if b.lower().endswith(".svg"):
                from carapost.ops.brim import import_brim_svg

                session.apply(import_brim_svg(take, b))
            elif b.lower().endswith(".json"):
                from carapost.io.brim import load_brim_json

                session.apply(set_brim(take, load_brim_json(b), f"Load brim {Path(b).name}"))
            else:
                session.apply(initialize_default_brim(take, b))
        done("calibration brim", t0, dots=len(take.brim) if take.brim is not None else 0)

    # 3. Seeds and brim solve.
    if seeds is not None:
        t0 = time.perf_counter()
        with stage("seeds"):
            snapped = snap_seeds(seeds, [take.detections[c].xy(frame) for c in range(take.n_cameras)])
        summary["seed_messages"] = snapped.messages
        done("snap seeds", t0, brim_seeds=len(snapped.brim), face_seeds=len(snapped.face), misses=len(snapped.misses))
        if snapped.brim and take.brim is not None:
            t0 = time.perf_counter()
            with stage("solve calibration brim"):
                change, res = solve_brim_manual(take, frame, snapped.brim)
                session.apply(change)
            summary["brim_messages"] = res.messages
            done("solve calibration brim", t0, cameras=int(res.solved.sum()),
                 rms_px=float(np.nanmax(res.rms_px)) if res.solved.any() else float("nan"))
        with stage("seeds"):
            session.apply(add_seed_points(take, frame, snapped))
        t0 = time.perf_counter()
        with stage("bundle current frame"):
            session.apply(bundle_current_frame(take, frame))
        done("bundle seeds", t0)

    # 4. Initialize 3D.
    t0 = time.perf_counter()
    with stage("initialize 3D"):
        session.apply(initialize_3d_op(take, frame, auto=options.auto_init))
    face = take.face_points()
    n3d = int(np.isfinite(take.xyz[frame, face]).all(-1).sum())
    done("initialize 3D", t0, points=n3d)

    # 5. Exports.
    for path, what in ((options.c3d, "C3D"), (options.fbx, "FBX")):
        if path is None:
            continue
        t0 = time.perf_counter()
        with stage(f"export {what}"):
            from carapost.io.export import export_take

            export_take(take, path)
        summary["files"].append(str(path))
        done(f"export {what}", t0)
    summary["points"] = n3d
    return summary
