"""The headless pipeline: what ``carapost process``, ``carapost demo``, batch jobs and the API run.

Stages, each an undoable change on the session's stack (so a script can undo any of them):
detect blobs -> calibration brim -> seeds / brim solve -> bundle -> Initialize 3D (from the seeds,
automatically, or Initialize from ROM) -> Track Forwards then Backwards [Sequence] -> Interpolate
Gaps -> Stabilize Data [Assisted] -> exports. A failure raises :class:`PipelineError` naming the
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

from carapost.model.take import Take

from .session import Session

__all__ = ["PipelineError", "PipelineOptions", "run_pipeline", "track_both_ways", "stabilize_all"]

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
    rom : path or None
        A solved ROM ``.cara`` of the same actor and marker set: Load ROM, then Initialize from
        ROM (cameras, brim, points, labels and sticks) instead of seeds / automatic init.
    track : bool
        Track Forwards [Sequence] then Track Backwards [Sequence] from the initialized frame.
    fill : str or None
        Interpolate Gaps with this method (``"neighbours"``, ``"face_model"`` or ``"blink"``;
        with a ROM take, the blink method takes the eyelids' closing depth from it).
    stabilize : bool
        Stabilize Data [Assisted] over the face points that are gap-free in the active range.
    c3d, fbx : path or None
        Export files written at the end.
    """

    def __init__(self, *, frame: int | None = None, detect: str = "frame", brim: str | None = None,
                 seeds: str | os.PathLike | None = None, auto_init: bool = False,
                 rom: str | os.PathLike | None = None, track: bool = False, fill: str | None = None,
                 stabilize: bool = False,
                 c3d: str | os.PathLike | None = None, fbx: str | os.PathLike | None = None) -> None:
        if detect not in ("frame", "range", "none"):
            raise ValueError(f"detect must be 'frame', 'range' or 'none', got {detect!r}")
        if sum((seeds is not None, bool(auto_init), rom is not None)) != 1:
            raise ValueError("give exactly one of a seeds file, automatic initialization or a ROM take")
        from carapost.model.params import FILL_METHODS

        if fill is not None and fill not in FILL_METHODS:
            raise ValueError(f"fill must be one of {', '.join(FILL_METHODS)}, got {fill!r}")
        self.frame, self.detect, self.brim, self.seeds, self.auto_init = frame, detect, brim, seeds, auto_init
        self.rom, self.track, self.fill, self.stabilize = rom, track, fill, stabilize
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
            session.apply(detect_blobs(take, session.image, todo, progress=prog, cancel=cancel,
                                       sources=session.sources))
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

    # 4. Initialize 3D (or from the ROM).
    t0 = time.perf_counter()
    rom = None
    if options.rom is not None:
        from carapost.ops.rom import initialize_from_rom, load_rom, read_rom

        with stage("initialize from ROM"):
            rom = read_rom(options.rom, n_cameras=take.n_cameras)     # read once: also used by the fill
            session.apply(load_rom(take, options.rom, rom=rom))
            session.apply(initialize_from_rom(take, session.image, frame, rom=rom))
        face = take.face_points()
        n3d = int(np.isfinite(take.xyz[frame, face]).all(-1).sum())
        done("initialize from ROM", t0, points=n3d)
    else:
        with stage("initialize 3D"):
            session.apply(initialize_3d_op(take, frame, auto=options.auto_init))
        face = take.face_points()
        n3d = int(np.isfinite(take.xyz[frame, face]).all(-1).sum())
        done("initialize 3D", t0, points=n3d, median_reprojection_px=_median_reprojection(take, frame, face))

    # 5. Tracking, gap filling, stabilization.
    if options.track:
        t0 = time.perf_counter()
        with stage("track"):
            numbers = track_both_ways(session, frame, progress=progress, cancel=cancel)
        done("track", t0, **numbers)
    if options.fill is not None and not _cancelled(cancel):
        from carapost.ops.fill import interpolate_gaps

        t0 = time.perf_counter()
        with stage("interpolate gaps"):
            change = interpolate_gaps(take, method=options.fill, rom=rom)   # the ROM: eyelid depths, face model
            session.apply(change)
        done("interpolate gaps", t0, **{k: v for k, v in change.report.items()
                                        if k in ("filled", "single_sensor", "unfilled")})
    if options.stabilize and not _cancelled(cancel):
        t0 = time.perf_counter()
        with stage("stabilize"):
            numbers = stabilize_all(session)
        done("stabilize", t0, **numbers)

    # 6. Exports.
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


def _cancelled(cancel: Callable[[], bool] | None) -> bool:
    return cancel is not None and bool(cancel())


def track_both_ways(session: Session, frame: int, *, progress: Callable[..., Any] = _no_progress,
                    cancel: Callable[[], bool] | None = None) -> dict[str, Any]:
    """Track Forwards [Sequence] then Track Backwards [Sequence] from ``frame`` (two undoable
    entries). Returns ``frames`` tracked and ``coverage``: the fraction of face point-frames of
    the active range with a 3D position afterwards."""
    from carapost.ops.track import track_backwards_sequence, track_forwards_sequence

    take = session.take
    if not 0 <= frame < take.n_frames:
        raise ValueError(f"frame {frame} is outside the take (0..{take.n_frames - 1})")
    take.current_frame = frame
    a, b = take.active_range
    frames = 0
    if frame < b and not _cancelled(cancel):
        with progress("track forwards") as prog:
            session.apply(track_forwards_sequence(take, session.image, frame, n_frames=b - frame,
                                                  progress=prog, cancel=cancel))
        frames += b - frame
    if frame > a and not _cancelled(cancel):
        with progress("track backwards") as prog:
            session.apply(track_backwards_sequence(take, session.image, frame, n_frames=frame - a,
                                                   progress=prog, cancel=cancel))
        frames += frame - a
    face = take.face_points()
    cover = np.isfinite(take.xyz[a:b + 1, face]).all(-1).mean() if len(face) else 0.0
    return {"frames": frames, "coverage": float(cover)}


def stabilize_all(session: Session) -> dict[str, Any]:
    """Stabilize Data [Assisted] with every face point that is gap-free in the active range as
    a candidate (the assisted method keeps the Stable Points Percent most rigid of them)."""
    from carapost.ops.fill import stabilize_assisted

    take = session.take
    a, b = take.active_range
    face = take.face_points()
    full = face[np.isfinite(take.xyz[a:b + 1, face]).all(-1).all(0)]
    if len(full) < 3:
        raise ValueError(f"only {len(full)} face points are gap-free in frames {a}..{b}; stabilization needs 3 "
                         f"(fill the gaps first)")
    change = stabilize_assisted(take, full)
    session.apply(change)
    return {"points": int(len(full)), **{k: v for k, v in change.report.items() if isinstance(v, (int, float))}}


def _median_reprojection(take: Take, frame: int, points: np.ndarray) -> float:
    """Median reprojection error (raw px) of the observations of ``points`` in ``frame``
    (NaN without any)."""
    from carapost.core.bundle import reprojection_errors

    sel = np.asarray(points)
    if not len(sel):
        return float("nan")
    err = reprojection_errors(take.obs_xy[frame:frame + 1, sel].astype(float), take.intrinsics(),
                              take.R[frame:frame + 1], take.t[frame:frame + 1], take.xyz[frame:frame + 1, sel])
    err = err[np.isfinite(err)]
    return round(float(np.median(err)), 3) if len(err) else float("nan")
