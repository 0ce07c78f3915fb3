#!/usr/bin/env python3
"""Detect blobs in a take and save it as ``<take_name>_b.cara``.

Takes one ``.pico`` file, loads all the ``.pico`` files of that take (``NAME_0.pico``,
``NAME_1.pico``, ...; with the calibration ``NAME.xcp`` next to them if there is one), performs
blob detection on them with the take's Blob Parameters, and writes ``NAME_b.cara`` next to the
files.

Example::

    python process_detect_blobs.py Example_0.pico
    python process_detect_blobs.py Example_0.pico --sensors 0,2 --frames 10:50 \\
        -p "Blob Parameters" "Black Threshold" 0.3
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import carapost.api as cp


def frame_range(spec: str) -> tuple[int, int]:
    """``"a:b"`` (inclusive) or ``"a"``."""
    a, _, b = spec.partition(":")
    try:
        return int(a), int(b if b else a)
    except ValueError:
        raise argparse.ArgumentTypeError(f"frames must be 'start:end', got {spec!r}") from None


def sensor_list(spec: str) -> list[int]:
    try:
        return [int(s) for s in spec.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"sensors must be a comma-separated list, got {spec!r}") from None


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pico", type=Path, help="any .pico file of the take, e.g. Example_0.pico")
    p.add_argument("-o", "--output", type=Path, help="output .cara (default NAME_b.cara next to the .pico files)")
    p.add_argument("--calibration", type=Path, help=".xcp/.toml/.qca calibration (default NAME.xcp if present)")
    p.add_argument("--sensors", type=sensor_list, help="comma-separated sensors (default all)")
    p.add_argument("--frames", type=frame_range, help="inclusive frame range start:end (default all)")
    p.add_argument("-p", "--property", nargs=3, action="append", default=[], metavar=("GROUP", "NAME", "VALUE"),
                   help='set a property first, e.g. -p "Blob Parameters" "Black Threshold" 0.3 (repeatable)')
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    try:
        with cp.CaraProcess.from_pico(args.pico, args.calibration) as take:
            print(f"take {take.name}: {take.n_cameras} sensors, {take.n_frames} frames")
            for group, name, value in args.property:
                print(take.set_property(group, name, value))
            start, end = args.frames if args.frames else (None, None)
            show = (lambda i, n: print(f"\r  {i}/{n} images", end="", flush=True)) if sys.stdout.isatty() else None
            done = take.detect_blobs(args.sensors, start, end, progress=show)
            if show:
                print()
            if not done:
                print("warning: blob detection did not complete", file=sys.stderr)
            out = args.output or args.pico.parent / f"{take.name}_b.cara"
            take.save(out)
            print(f"{take.n_detections()} detections in {time.perf_counter() - t0:.1f} s; wrote {out}")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
