"""The steps a batch job can run on a take, in their fixed order.

``detect`` (Detect Blobs [Active Range], frames not detected yet), ``init`` (calibration brim,
seeds, Initialize 3D through :func:`carapost.ops.pipeline.run_pipeline`), ``track`` (Track
Forwards and Backwards [Sequence] from the initialized frame), ``fill`` (Interpolate Gaps) and
``export`` (``.c3d`` and/or ``.fbx`` next to the ``.cara``).

A new step plugs in with :func:`register_step`; a step whose operation is not available
(``available()`` returns why) is skipped with that message. A step function gets the job's
:class:`JobContext`, applies its changes to ``ctx.session`` and returns a small JSON-able dict
of numbers for the summary; it raises ``ValueError`` (or ``OSError``) to fail the take.

Steps run inside worker processes: register them at import time of this module (or of a
module imported by it), not from a script, or the workers will not know them.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from .batch_jobs import BatchOptions, TakeJob
    from .session import Session

__all__ = ["JobContext", "Step", "STEPS", "register_step", "resolve_steps", "EXPORT_FORMATS"]

#: Export formats of the ``export`` step.
EXPORT_FORMATS = ("c3d", "fbx")


@dataclass
class JobContext:
    """What a step works on.

    Attributes
    ----------
    session : Session
        The open take; apply changes through ``session.apply``.
    job : TakeJob
    options : BatchOptions
    detections : dict or None
        Blob detections computed beforehand by split detection: ``{"tables": {camera: {frame:
        table}}, "seconds": float, "chunks": int}``.
    files : list of str
        Files written by the steps besides the ``.cara`` (recorded in the manifest).
    messages : list of str
        Notes for the summary.
    """

    session: "Session"
    job: "TakeJob"
    options: "BatchOptions"
    detections: dict[str, Any] | None = None
    files: list[str] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)


StepFn = Callable[[JobContext], dict[str, Any]]


def _always() -> str | None:
    return None


@dataclass(frozen=True)
class Step:
    """A batch step: ``run(ctx) -> numbers``; ``available() -> None`` or why it cannot run."""

    name: str
    run: StepFn
    help: str = ""
    available: Callable[[], str | None] = _always


#: The steps, in the order they run.
STEPS: dict[str, Step] = {}


def register_step(step: Step, *, before: str | None = None) -> None:
    """Add (or replace) a step; new steps go last, or just before the step ``before``."""
    if before is not None and before not in STEPS:
        raise ValueError(f"no step {before!r} to insert {step.name!r} before")
    items = [(k, v) for k, v in STEPS.items() if k != step.name]
    at = len(items) if before is None else [k for k, _ in items].index(before)
    items.insert(at, (step.name, step))
    STEPS.clear()
    STEPS.update(items)


def resolve_steps(names: Sequence[str]) -> tuple[tuple[str, ...], dict[str, str]]:
    """The requested steps in run order, and the unavailable ones with the reason.

    Raises
    ------
    ValueError
        Unknown step names (the message lists them and the known steps) or no step at all.
    """
    wanted = [n.strip().lower() for n in names if n.strip()]
    if not wanted:
        raise ValueError(f"no steps given (known steps: {', '.join(STEPS)})")
    unknown = [n for n in wanted if n not in STEPS]
    if unknown:
        raise ValueError(f"unknown step(s): {', '.join(unknown)} (known steps: {', '.join(STEPS)})")
    skipped = {n: why for n in STEPS if n in wanted and (why := STEPS[n].available()) is not None}
    return tuple(n for n in STEPS if n in wanted and n not in skipped), skipped


def _op_available(module: str, *names: str) -> Callable[[], str | None]:
    """``available()`` for a step needing ``carapost.ops.<module>`` with functions ``names``."""

    def check() -> str | None:
        try:
            mod = importlib.import_module(f"carapost.ops.{module}")
        except ImportError as exc:
            return f"carapost.ops.{module} is not available ({exc})"
        missing = [n for n in names if not hasattr(mod, n)]
        return f"carapost.ops.{module} has no {', '.join(missing)}" if missing else None

    return check


# -------------------------------------------------------------------------------------------
# the steps
# -------------------------------------------------------------------------------------------
def _undetected(take: Any) -> list[int]:
    a, b = take.active_range
    det = np.ones(take.n_frames, bool)
    for d in take.detections:
        det &= np.asarray(d.detected, bool)
    return [f for f in range(a, b + 1) if not det[f]]


def _detect(ctx: JobContext) -> dict[str, Any]:
    from .detect import detect_blobs
    from .split_detect import detections_change

    take = ctx.session.take
    frames = _undetected(take)
    numbers: dict[str, Any] = {"frames": len(frames)}
    if ctx.detections is not None:
        tables = ctx.detections["tables"]
        change = detections_change(take, tables)
        numbers.update(split_chunks=ctx.detections.get("chunks", 0),
                       split_seconds=round(float(ctx.detections.get("seconds", 0.0)), 3),
                       frames=len({f for t in tables.values() for f in t}))
    elif frames:
        change = detect_blobs(take, ctx.session.image, frames, workers=max(1, ctx.options.threads))
    else:
        change = None
    ctx.session.apply(change)
    numbers["detections"] = int(sum(len(d) for d in take.detections))
    return numbers


def _init(ctx: JobContext) -> dict[str, Any]:
    from .pipeline import PipelineOptions, run_pipeline

    job, opt = ctx.job, ctx.options
    if job.seeds is None and not opt.auto_init:
        raise ValueError(f"no seeds file ({job.name}_seeds.json next to the take) and no --auto-init")
    if job.kind == "pico" and job.calibration is None:
        raise ValueError(f"no calibration: put {job.name}.xcp (or .toml, .qca) next to the .pico files "
                         f"or give --calibration")
    summary = run_pipeline(ctx.session, PipelineOptions(frame=opt.frame, detect="frame", brim=job.brim,
                                                        seeds=job.seeds, auto_init=opt.auto_init))
    ctx.messages += summary.get("seed_messages", []) + summary.get("brim_messages", [])
    return {"frame": int(ctx.session.take.current_frame), "points": int(summary.get("points", 0))}


def _point_frames(take: Any) -> int:
    return int(np.isfinite(take.xyz[:, take.face_points()]).all(-1).sum())


def _track(ctx: JobContext) -> dict[str, Any]:
    from .pipeline import track_both_ways

    take = ctx.session.take
    frame = ctx.options.frame if ctx.options.frame is not None else int(take.current_frame)
    numbers = track_both_ways(ctx.session, frame)
    return {"frame": frame, "point_frames": _point_frames(take), "coverage": numbers["coverage"]}


def _fill(ctx: JobContext) -> dict[str, Any]:
    from .fill import interpolate_gaps

    change = interpolate_gaps(ctx.session.take, method=ctx.options.fill_method)
    ctx.session.apply(change)
    return {k: v for k, v in change.report.items() if k in ("filled", "single_sensor", "unfilled")}


def _export(ctx: JobContext) -> dict[str, Any]:
    from carapost.io.export import export_take

    out = Path(ctx.job.output)
    written = []
    for fmt in ctx.options.formats:
        path = out.with_name(f"{out.stem}.{fmt}")
        export_take(ctx.session.take, path)
        written.append(str(path))
    ctx.files += written
    return {"files": written}


for _s in (
    Step("detect", _detect, "Detect Blobs [Active Range]: frames not detected yet"),
    Step("init", _init, "brim, seeds (<take>_seeds.json) or --auto-init, Initialize 3D"),
    Step("track", _track, "Track Forwards and Backwards [Sequence] from the initialized frame",
         _op_available("track", "track_forwards_sequence", "track_backwards_sequence")),
    Step("fill", _fill, "Interpolate Gaps", _op_available("fill", "interpolate_gaps")),
    Step("export", _export, "export .c3d (and/or .fbx: --formats) next to the .cara"),
):
    register_step(_s)
