"""``carapost convert`` and ``carapost detect``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from .common import add_settings_arguments, check_outputs, open_session, parse_cameras, parse_frames, parse_settings
from .progress import progress_bar

__all__ = ["cmd_convert", "cmd_detect"]


def cmd_convert(args: argparse.Namespace) -> dict[str, Any]:
    """Convert video files / image folders (or .pico) to a take's .pico files."""
    from carapost.io.convert import convert_to_pico

    offsets = [int(x) for x in args.offsets.split(",")] if args.offsets else None
    t0 = time.perf_counter()
    with progress_bar("convert") as prog:
        out = convert_to_pico(args.sources, args.out, args.name, codec="lossless" if args.lossless else "jpeg",
                              quality=args.quality, frame_offsets=offsets, max_frames=args.max_frames, progress=prog)
    dt = time.perf_counter() - t0
    for p in out:
        print(f"wrote {p}")
    print(f"carapost convert: {len(out)} camera file(s) in {dt:.1f} s")
    return {"files": [str(p) for p in out], "seconds": dt}


def cmd_detect(args: argparse.Namespace) -> dict[str, Any]:
    """Detect blobs in a take's frames; write a CSV and/or save the take."""
    if not args.csv and not args.save:
        raise ValueError("nothing to write: give --csv OUT.csv and/or --save TAKE.cara")
    check_outputs(args.csv, args.save)
    settings = parse_settings(args.set)
    session = open_session(args.inputs, args.calibration)
    try:
        return _detect(session, args, settings)
    finally:
        session.close()


def _detect(session: Any, args: argparse.Namespace, settings: list[tuple[str, str, str]]) -> dict[str, Any]:
    from carapost.io.detections_csv import tables_from_detections, write_detections_csv
    from carapost.ops.detect import detect_blobs
    from carapost.ops.settings import apply_settings, set_property

    take = session.take
    apply_settings(session, preset=args.preset, settings=settings)     # then the flags below
    for name in ("black_threshold", "white_threshold", "black_min_radius", "black_max_radius",
                 "white_min_radius", "white_max_radius"):
        value = getattr(args, name)
        if value is not None:
            session.apply(set_property(take, "blobs", name, value))
    if args.white is not None:
        session.apply(set_property(take, "blobs", "find_white_blobs", args.white))
    if args.black is not None:
        session.apply(set_property(take, "blobs", "find_black_blobs", args.black))
    frames = parse_frames(args.frames, take.n_frames)
    cams = parse_cameras(args.cameras, take.n_cameras)
    t0 = time.perf_counter()
    with progress_bar("detect blobs") as prog:
        session.apply(detect_blobs(take, session.image, frames, cameras=cams, workers=args.workers, progress=prog,
                                       sources=session.sources))
    dt = time.perf_counter() - t0
    n = sum(len(d) for d in take.detections)
    used = cams if cams is not None else list(range(take.n_cameras))
    tables = {k: v for k, v in tables_from_detections(take.detections).items() if k[1] in used and k[0] in set(frames)}
    if args.csv:
        write_detections_csv(args.csv, tables)
        print(f"wrote {args.csv}")
    if args.save:
        session.save(args.save)
        print(f"wrote {args.save}")
    rate = len(frames) * len(used) / dt if dt > 0 else float("inf")
    print(f"carapost detect: {n} detections in {len(frames)} frame(s) x {len(used)} camera(s), "
          f"{dt:.1f} s ({rate:.0f} images/s)")
    return {"detections": n, "frames": len(frames), "cameras": used, "seconds": dt,
            "csv": args.csv, "cara": str(args.save) if args.save else None}


def add_parsers(sub: argparse._SubParsersAction) -> dict[str, Any]:
    p = sub.add_parser("convert", help="convert video files or image folders to .pico files")
    p.add_argument("sources", nargs="+", help="one source per camera, in channel order")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--name", required=True, help="take name: files are NAME_0.pico, NAME_1.pico, ...")
    p.add_argument("--lossless", action="store_true", help="lossless frames instead of JPEG")
    p.add_argument("--quality", type=int, default=92, help="JPEG quality (default 92)")
    p.add_argument("--offsets", help="per-camera frame offsets, e.g. 0,0,1,0")
    p.add_argument("--max-frames", type=int, help="convert at most this many frames")

    p = sub.add_parser("detect", help="detect blobs; write a CSV of detections and/or a .cara")
    p.add_argument("inputs", nargs="+", help="a .cara, one .pico of a take, or one source per camera")
    p.add_argument("--calibration", help=".xcp, .qca or .toml calibration for sources")
    p.add_argument("--csv", help="write frame,camera,x,y,major,minor,angle,polarity,score rows here")
    p.add_argument("--save", type=Path, help="save the take with its detections as this .cara")
    p.add_argument("--frames", help="frame range a:b (inclusive); default all")
    p.add_argument("--cameras", help="comma-separated channels; default all")
    p.add_argument("--workers", type=int, default=2, help="worker processes (threads for short ranges; default 2)")
    p.add_argument("--white", action=argparse.BooleanOptionalAction, default=None, help="find white blobs")
    p.add_argument("--black", action=argparse.BooleanOptionalAction, default=None, help="find black blobs")
    for colour in ("black", "white"):
        p.add_argument(f"--{colour}-threshold", dest=f"{colour}_threshold", type=float)
        p.add_argument(f"--{colour}-min-radius", dest=f"{colour}_min_radius", type=float)
        p.add_argument(f"--{colour}-max-radius", dest=f"{colour}_max_radius", type=float)
    add_settings_arguments(p, caddies=False)
    return {"convert": cmd_convert, "detect": cmd_detect}
