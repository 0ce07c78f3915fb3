#!/usr/bin/env python3
"""Generate a ``.cara`` file for a Cara ROM take, ready to be processed in CaraPost.

Imports all the ``.pico`` files of the ROM take (with the calibration ``NAME.xcp`` next to them
if there is one), applies the parameter preset of the marker set, initializes the calibration
brim, detects blobs, and saves ``NAME.cara``. Open it in CaraPost to solve the brim, add seeds,
Initialize 3D, track and label it; it then initializes other takes of the same actor
(``process_track.py TAKE_0.pico -rom ROM.cara``).

With ``--seeds`` (a seeds file of brim dots and face markers matched across the cameras) the
brim is solved and the take initialized here too.

Example::

    python process_setup_ROM.py ROM_0.pico
    python process_setup_ROM.py ROM_0.pico --preset dense --brim v2.0 --frames 0:0 -o ROM.cara
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pico", type=Path, help="any .pico file of the ROM take")
    p.add_argument("-o", "--output", type=Path, help="output .cara (default NAME.cara next to the .pico files)")
    p.add_argument("--calibration", type=Path, help=".xcp/.toml/.qca calibration (default NAME.xcp if present)")
    p.add_argument("--preset", choices=("default", "dense", "sparse"),
                   help="parameter set for the marker set: dense (156 markers), sparse (35), or default (every "
                        "property back to its default); without it the take keeps the capture's Blob Parameters")
    p.add_argument("--brim", default="v2.0",
                   help="default brim v1.0 / v1.1 / v2.0, a brim .svg or .json file, or 'none' (default v2.0)")
    p.add_argument("--frames", help="inclusive frame range start:end to detect blobs in (default all; "
                                    "tracking detects the others later)")
    p.add_argument("--seeds", type=Path, help="seeds file: also solve the brim and Initialize 3D")
    p.add_argument("-p", "--property", nargs=3, action="append", default=[], metavar=("GROUP", "NAME", "VALUE"),
                   help="set a property after the preset (repeatable)")
    return p.parse_args(argv)


def setup_brim(take: cp.CaraProcess, brim: str) -> None:
    if brim.lower() == "none":
        return
    if brim.lower().endswith((".svg", ".json")):
        print(take.import_brim(brim))
    else:
        print(take.initialize_default_brim(brim))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        with cp.CaraProcess.from_pico(args.pico, args.calibration) as take:
            print(f"ROM take {take.name}: {take.n_cameras} sensors, {take.n_frames} frames")
            if args.preset:
                print(take.apply_preset(args.preset))
            for group, name, value in args.property:
                print(take.set_property(group, name, value))
            setup_brim(take, args.brim)
            start = end = None
            if args.frames:
                a, _, b = args.frames.partition(":")
                try:
                    start, end = int(a), int(b if b else a)
                except ValueError:
                    raise ValueError(f"--frames must be 'start:end', got {args.frames!r}") from None
            take.detect_blobs(None, start, end)
            print(f"{take.n_detections()} blob detections")
            if args.seeds is not None:
                summary = take.run_pipeline(seeds=args.seeds, detect="frame")
                print(f"initialized {summary['points']} face points in frame {take.current_frame}")
            out = args.output or args.pico.parent / f"{take.name}.cara"
            take.save(out)
            print(f"wrote {out}")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
