"""``carapost demo``: generate a synthetic take and run every pipeline stage on it: detect blobs,
solve the brim, Initialize 3D from the seeds, track the whole take both ways, fill the gaps,
stabilize, and export C3D, FBX and the ``.cara``.

Ends with a report: what was done, how long each stage took, accuracy against the ground
truth, and the files written.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from .progress import progress_bar

__all__ = ["cmd_demo", "add_parsers"]


class _Report:
    def __init__(self) -> None:
        self.stages: list[dict[str, Any]] = []
        self.files: list[str] = []

    def stage(self, name: str, seconds: float, **numbers: Any) -> None:
        self.stages.append({"stage": name, "seconds": round(seconds, 3), **numbers})
        extra = ", ".join(f"{k} {_fmt(v)}" for k, v in numbers.items())
        print(f"  {name:<28s} {seconds:7.2f} s   {extra}")


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def cmd_demo(args: argparse.Namespace) -> dict[str, Any]:
    from carapost.ops.session import Session
    from carapost.synth import SynthConfig, generate_take, write_take

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rep = _Report()
    total0 = time.perf_counter()
    print(f"carapost demo: a synthetic {args.markers}-marker take, {args.frames} frames, 4 cameras -> {out}")

    t0 = time.perf_counter()
    synth = generate_take(SynthConfig(n_markers=args.markers, n_frames=args.frames, seed=args.seed))
    with progress_bar("render take") as prog:
        files = write_take(synth, out, "Demo", progress=prog)
    rep.stage("generate + write .pico", time.perf_counter() - t0, images=4 * args.frames)
    rep.files += [str(files[f"pico_{c}"]) for c in range(4)] + [str(files["xcp"]), str(files["seeds"])]

    t0 = time.perf_counter()
    session = Session.from_sources([files[f"pico_{c}"] for c in range(4)], files["xcp"], name="Demo")
    with session:
        rep.stage("import", time.perf_counter() - t0, cameras=session.take.n_cameras, frames=session.take.n_frames)
        return _run(session, synth, files, rep, out, total0)


def _run(session: Any, synth: Any, files: dict, rep: _Report, out: Path, total0: float) -> dict[str, Any]:
    from carapost.ops.detect import detect_blobs
    from carapost.io.export import export_take
    from carapost.ops.fill import interpolate_gaps
    from carapost.ops.pipeline import PipelineOptions, run_pipeline, stabilize_all, track_both_ways
    from carapost.synth.evaluate import score_detections

    take = session.take

    t0 = time.perf_counter()
    with progress_bar("detect blobs") as prog:
        session.apply(detect_blobs(take, session.image, range(take.n_frames), progress=prog,
                                   sources=session.sources))
    sc = score_detections(take.detections, synth.truth, range(take.n_frames))
    rep.stage("detect blobs [active range]", time.perf_counter() - t0, recall=sc.recall, precision=sc.precision,
              median_err_px=sc.median_error_px)

    run_pipeline(session, PipelineOptions(seeds=files["seeds"], brim=str(files["brim_json"])),
                 report=rep.stage, progress=progress_bar)
    frame = take.current_frame
    if take.n_points:
        _score(rep, take, synth, [frame], "accuracy at the seeds' frame")

    t0 = time.perf_counter()
    numbers = track_both_ways(session, frame, progress=progress_bar)
    rep.stage("track forwards + backwards", time.perf_counter() - t0, **numbers)
    _score(rep, take, synth, None, "accuracy after tracking")

    t0 = time.perf_counter()
    change = interpolate_gaps(take)
    session.apply(change)
    rep.stage("interpolate gaps", time.perf_counter() - t0,
              **{k: v for k, v in change.report.items() if k in ("filled", "unfilled")})

    t0 = time.perf_counter()
    try:
        rep.stage("stabilize data [assisted]", time.perf_counter() - t0, **stabilize_all(session))
    except ValueError as exc:  # too few gap-free points: report it, export the raw data
        print(f"  stabilize skipped: {exc}")

    for path in (out / "Demo.c3d", out / "Demo.fbx"):
        t0 = time.perf_counter()
        export_take(take, path)
        rep.files.append(str(path))
        rep.stage(f"export {path.suffix[1:].upper()}", time.perf_counter() - t0)
    cara = session.save(out / "Demo.cara")
    rep.files.append(str(cara))
    total = time.perf_counter() - total0
    print(f"carapost demo: done in {total:.1f} s. Files:")
    for f in rep.files:
        print(f"  {f}")
    return {"stages": rep.stages, "files": rep.files, "seconds": total}


def _score(rep: _Report, take: Any, synth: Any, frames: list[int] | None, what: str) -> None:
    from carapost.synth.evaluate import score_points

    ps = score_points(take, synth.truth, frames)
    face = (ps.marker >= 0) & (ps.marker < len(synth.truth.names))
    rep.stage(what, 0.0, markers=int(face.sum()), coverage=ps.coverage, median_3d_err_mm=ps.median_error_mm,
              p95_3d_err_mm=ps.p95_error_mm, mismatches=ps.mismatched_observations, swaps=ps.swaps)


def add_parsers(sub: argparse._SubParsersAction) -> dict[str, Any]:
    p = sub.add_parser("demo", help="generate a demo take and run every stage on it")
    p.add_argument("--out", default="demo_out", help="output folder (default: ./demo_out)")
    p.add_argument("--markers", type=int, default=80, choices=(35, 80, 156), help="face markers (default 80)")
    p.add_argument("--frames", type=int, default=60, help="frames (default 60)")
    p.add_argument("--seed", type=int, default=0)
    return {"demo": cmd_demo}
