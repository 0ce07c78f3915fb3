"""``carapost export SRC DST``: write a .cara or .c3d take as .c3d/.fbx/.xcp/.csv/.trc/.bvh/.bva."""

from __future__ import annotations

import argparse
import dataclasses
import time
from typing import Any

from .common import parse_frames

__all__ = ["cmd_export", "add_parsers"]


def cmd_export(args: argparse.Namespace) -> dict[str, Any]:
    from carapost.io.export import export_take, load_for_export

    take = load_for_export(args.source)
    changes: dict[str, Any] = {}
    if args.units:
        changes["units"] = args.units
    if args.up_axis:
        changes["up_axis"] = args.up_axis
    if args.stabilized:
        changes["use_stabilized"] = True
    if args.no_brim:
        changes["include_brim"] = False
    if args.no_cameras:
        changes["include_cameras"] = False
    options = dataclasses.replace(take.params.export, **changes)
    fmt: dict[str, Any] = {}
    if args.fbx_version:
        fmt["version"] = args.fbx_version
    if args.frame is not None:
        fmt["frame"] = args.frame
    if args.all_frames:
        fmt["all_frames"] = True
    if args.csv:
        fmt["kind"] = args.csv
    if args.camera is not None:
        fmt["camera"] = args.camera
    if args.length_units:
        fmt["units"] = args.length_units
    frames = None
    if args.frames:
        sel = parse_frames(args.frames, take.n_frames)
        frames = (sel[0], sel[-1])
    t0 = time.perf_counter()
    export_take(take, args.destination, options=options, frames=frames, **fmt)
    dt = time.perf_counter() - t0
    print(f"carapost export: wrote {args.destination} ({take.n_points} points, {take.n_frames} frames) in {dt:.2f} s")
    return {"source": args.source, "destination": args.destination, "points": take.n_points,
            "frames": take.n_frames, "seconds": dt}


def add_parsers(sub: Any) -> dict[str, Any]:
    p = sub.add_parser("export", help="export a .cara or .c3d take (format from the extension)",
                       description="Formats: .c3d .fbx .xcp .csv .trc .bvh .bva")
    p.add_argument("source", help="TAKE.cara or DATA.c3d")
    p.add_argument("destination", help="OUT.c3d | OUT.fbx | OUT.xcp | OUT.csv | OUT.trc | OUT.bvh | OUT.bva")
    p.add_argument("--units", choices=("mm", "cm"), help="FBX/CSV/BVH length unit (Export section)")
    p.add_argument("--up-axis", choices=("Y", "Z"), help="up axis of the exported data")
    p.add_argument("--stabilized", action="store_true", help="export stabilized rather than raw data")
    p.add_argument("--no-brim", action="store_true", help="leave the calibration brim points out")
    p.add_argument("--no-cameras", action="store_true", help="no camera nodes (FBX)")
    p.add_argument("--frames", help="frame range a:b (inclusive)")
    p.add_argument("--fbx-version", type=int, choices=(7400, 7500))
    p.add_argument("--frame", type=int, help="XCP: the frame whose camera poses are written")
    p.add_argument("--all-frames", action="store_true", help="XCP: one KeyFrame per frame for moving cameras")
    p.add_argument("--csv", choices=("3d", "2d"), help="CSV: 3D trajectories (default) or 2D tracks")
    p.add_argument("--camera", type=int, help="BVA: write this camera's 2D tracks")
    p.add_argument("--length-units", choices=("mm", "cm", "m", "in"), help="TRC/BVA length unit")
    return {"export": cmd_export}
