"""``carapost demo``: generate a synthetic take and run every pipeline stage on it.

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
    from carapost.ops.pipeline import PipelineOptions, run_pipeline
    from carapost.synth.evaluate import score_detections, score_points

    take = session.take

    t0 = time.perf_counter()
    with progress_bar("detect blobs") as prog:
        session.apply(detect_blobs(take, session.image, range(take.n_frames), progress=prog))
    sc = score_detections(take.detections, synth.truth, range(take.n_frames))
    rep.stage("detect blobs [active range]", time.perf_counter() - t0, recall=sc.recall, precision=sc.precision,
              median_err_px=sc.median_error_px)

    c3d, fbx = out / "Demo.c3d", out / "Demo.fbx"
    result = run_pipeline(session, PipelineOptions(seeds=files["seeds"], brim=str(files["brim_json"]), c3d=c3d,
                                                   fbx=fbx),
                          report=rep.stage, progress=progress_bar)
    rep.files += result["files"]
    if take.n_points:
        ps = score_points(take, synth.truth, [take.current_frame])
        face = (ps.marker >= 0) & (ps.marker < len(synth.truth.names))
        rep.stage("accuracy vs ground truth", 0.0, markers=int(face.sum()), coverage=ps.coverage,
                  median_3d_err_mm=ps.median_error_mm, p95_3d_err_mm=ps.p95_error_mm,
                  mismatches=ps.mismatched_observations)
    cara = session.save(out / "Demo.cara")
    rep.files.append(str(cara))
    total = time.perf_counter() - total0
    print(f"carapost demo: done in {total:.1f} s. Files:")
    for f in rep.files:
        print(f"  {f}")
    return {"stages": rep.stages, "files": rep.files, "seconds": total}


def add_parsers(sub: argparse._SubParsersAction) -> dict[str, Any]:
    p = sub.add_parser("demo", help="generate a demo take and run every stage on it")
    p.add_argument("--out", default="demo_out", help="output folder (default: ./demo_out)")
    p.add_argument("--markers", type=int, default=80, choices=(35, 80, 156), help="face markers (default 80)")
    p.add_argument("--frames", type=int, default=60, help="frames (default 60)")
    p.add_argument("--seed", type=int, default=0)
    return {"demo": cmd_demo}
