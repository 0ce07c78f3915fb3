#!/usr/bin/env python3
"""Track the points of a take through its frames.

Either takes a ``.cara`` file and tracks from the first frame that has 3D points onwards, or
takes a ``.pico`` file, imports all the ``.pico`` files of that take, initializes it from the
supplied ROM take (``-rom ROM.cara``) and then tracks. With a ROM, the blobs are detected with the
ROM's Blob Parameters (same actor, marker set and cameras).

Example::

    python process_track.py Example.cara
    python process_track.py Example_0.pico -rom ROM.cara
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("input", type=Path, help="a .cara project, or any .pico file of a take (with -rom)")
    p.add_argument("-rom", "--rom", type=Path, help="solved ROM .cara of the same actor and marker set")
    p.add_argument("-o", "--output", type=Path,
                   help="output .cara (default: the input .cara itself, or NAME.cara next to the .pico files)")
    p.add_argument("--frame", type=int, help="frame to track from (default: the first frame with 3D points)")
    p.add_argument("--both-ways", action="store_true", help="also track backwards from the start frame")
    return p.parse_args(argv)


def first_frame_with_points(take: cp.CaraProcess) -> int:
    """The first frame of the active range in which some point has a 3D position."""
    a, b = take.active_range
    has = np.isfinite(take.data.xyz[a:b + 1]).all(-1).any(-1)
    if not has.any():
        raise ValueError(f"{take.path or take.name}: no frame has 3D points; initialize the take first")
    return a + int(np.argmax(has))


def open_take(args: argparse.Namespace) -> cp.CaraProcess:
    ext = args.input.suffix.lower()
    if ext == ".cara":
        if args.rom is not None:
            raise ValueError("-rom applies to a .pico input (a .cara is tracked from its own points)")
        return cp.CaraProcess.open(args.input)
    if ext != ".pico":
        raise ValueError(f"{args.input}: give a .cara or a .pico file")
    if args.rom is None:
        raise ValueError(f"{args.input}: a .pico take must be initialized from a ROM: give -rom ROM.cara")
    take = cp.CaraProcess.from_pico(args.input)
    try:
        print(take.load_rom(args.rom))
        # Same actor, markers and rig: detect the blobs as they were detected in the ROM.
        with cp.CaraProcess.open(args.rom) as rom:
            for name, value in rom.properties("Blob Parameters").items():
                take.set_property("Blob Parameters", name, value)
        print(take.initialize_from_rom(take.active_range[0]))
    except ValueError:
        take.close()
        raise
    return take


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    try:
        with open_take(args) as take:
            start = args.frame if args.frame is not None else first_frame_with_points(take)
            print(f"take {take.name}: {take.n_points} points, {take.n_frames} frames; tracking from frame {start}")
            show = (lambda i, n: print(f"\r  {i}/{n} frames", end="", flush=True)) if sys.stdout.isatty() else None
            if start < take.n_frames - 1:
                print(take.track(start, direction="forwards", progress=show))
            if args.both_ways and start > 0:
                print(take.track(start, direction="backwards", progress=show))
            out = args.output or (args.input if args.input.suffix.lower() == ".cara"
                                  else args.input.parent / f"{take.name}.cara")
            take.save(out)
            face = take.data.face_points
            tracked = np.isfinite(take.data.xyz[:, face]).all(-1).mean() if len(face) else 0.0
            print(f"{100 * tracked:.1f}% of face point-frames have 3D data; {time.perf_counter() - t0:.1f} s; wrote {out}")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
