"""``carapost process``: import, detect, solve the brim, initialize 3D (or from a ROM), track, fill,
stabilize and write the results."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from carapost.model.params import FILL_METHODS

from .common import add_settings_arguments, check_outputs, interrupt_cancels, parse_caddies, parse_settings
from .progress import progress_bar

__all__ = ["cmd_process", "add_parsers"]


def cmd_process(args: argparse.Namespace) -> dict[str, Any]:
    from carapost.ops.pipeline import PipelineOptions, run_pipeline
    from carapost.ops.session import Session
    from carapost.ops.settings import apply_settings

    if not args.seeds and not args.auto_init and not args.rom:
        raise ValueError("give --seeds SEEDS.json, --auto-init or --rom ROM.cara")
    check_outputs(args.out, args.c3d, args.fbx)
    settings, caddies = parse_settings(args.set), parse_caddies(args.caddies)
    t0 = time.perf_counter()
    try:
        session = Session.from_sources(args.cameras, args.calibration, name=Path(args.out).stem)
    except (ValueError, OSError) as exc:
        raise ValueError(f"import: {exc}") from None

    def report(stage: str, seconds: float, **numbers: Any) -> None:
        extra = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in numbers.items())
        print(f"  {stage:<26s} {seconds:7.2f} s   {extra}")

    with session:
        for m in session.messages:
            print(f"  warning: {m}")
        apply_settings(session, preset=args.preset, settings=settings, caddies=caddies)
        detect = args.detect or ("range" if args.track else "frame")
        opts = PipelineOptions(frame=args.frame, detect=detect, brim=args.brim, seeds=args.seeds,
                               auto_init=args.auto_init, rom=args.rom, track=args.track,
                               fill=args.fill_method if args.fill else None, stabilize=args.stabilize,
                               c3d=args.c3d, fbx=args.fbx)
        with interrupt_cancels("carapost process") as cancel:
            summary = run_pipeline(session, opts, report=report, progress=progress_bar, cancel=cancel)
            summary["cancelled"] = cancel()
        for m in summary.get("seed_messages", []) + summary.get("brim_messages", []):
            print(f"  note: {m}")
        try:
            session.save(args.out)
        except (ValueError, OSError) as exc:
            raise ValueError(f"save: {exc}") from None
    summary["files"].append(str(args.out))
    summary["seconds"] = time.perf_counter() - t0
    tracked = next((st for st in summary["stages"] if st["stage"] == "track"), None)
    what = f"{summary['points']} points initialized"
    if tracked is not None:
        what += f", {100 * tracked['coverage']:.1f}% of face point-frames tracked"
    if summary["cancelled"]:
        what += " (cancelled: the frames finished before Ctrl+C are saved)"
    print(f"carapost process: {what}; wrote {', '.join(summary['files'])} "
          f"in {summary['seconds']:.1f} s")
    return summary


def add_parsers(sub: Any) -> dict[str, Any]:
    p = sub.add_parser("process", help="import a take and run detection, brim solve, Initialize 3D, tracking, "
                                       "gap filling and stabilization",
                       description="Sources may be .pico files, video files or image folders (one per camera).")
    p.add_argument("--cameras", nargs="+", required=True, metavar="SRC", help="one source per camera, channel order")
    p.add_argument("--calibration", required=True, help=".xcp, .qca or .toml camera calibration")
    p.add_argument("--brim", help="v1.0 | v1.1 | v2.0 | FILE.svg | FILE.json (calibration brim)")
    init = p.add_mutually_exclusive_group()
    init.add_argument("--seeds", help="seeds JSON: brim dots and face markers matched across cameras")
    init.add_argument("--auto-init", action="store_true", help="initialize without seeds")
    init.add_argument("--rom", type=Path, help="solved ROM .cara of the same actor and marker set: Initialize from ROM")
    p.add_argument("--frame", type=int, help="frame to initialize (default: the seeds' frame, else 0)")
    p.add_argument("--detect", choices=("frame", "range", "none"),
                   help="detect blobs in the initialization frame only (the default without --track; the tracker "
                        "detects the rest as it goes) or in the whole active range first, on all cores (the "
                        "default with --track)")
    p.add_argument("--track", action="store_true",
                   help="track forwards from the initialized frame to the end, then backwards to the start")
    p.add_argument("--fill", action="store_true", help="Interpolate Gaps after tracking")
    p.add_argument("--fill-method", choices=FILL_METHODS, default="neighbours",
                   help="gap-filling method (default: the guide's neighbour interpolation)")
    p.add_argument("--stabilize", action="store_true",
                   help="Stabilize Data [Assisted] over the gap-free face points (exports use the stabilized data "
                        "when the Export section says so)")
    add_settings_arguments(p)
    p.add_argument("--out", required=True, type=Path, help="the .cara project to write")
    p.add_argument("--c3d", type=Path, help="also export a C3D")
    p.add_argument("--fbx", type=Path, help="also export an FBX")
    return {"process": cmd_process}
