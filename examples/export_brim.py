#!/usr/bin/env python3
"""Print the calibration brim of a ``.cara`` file to the console.

First the brim model (each dot's centre in the brim frame, radius and colour), then the 3D
data of the brim points in every frame (x y z in millimetres, ``nan`` where a dot has no
position) with the number of cameras that observed the dot.

Example::

    python export_brim.py Example.cara
    python export_brim.py Example.cara --frames 0:0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cara", type=Path, help=".cara project")
    p.add_argument("--frames", help="inclusive frame range start:end (default all)")
    p.add_argument("--model-only", action="store_true", help="print the brim model only")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        exp = cp.CaraExport(args.cara)
        if exp.brim is None:
            raise ValueError(f"{args.cara}: the take has no calibration brim")
        start, end = 0, exp.n_frames - 1
        if args.frames:
            a, _, b = args.frames.partition(":")
            try:
                start, end = int(a), int(b if b else a)
            except ValueError:
                raise ValueError(f"--frames must be 'start:end', got {args.frames!r}") from None
            if not 0 <= start <= end < exp.n_frames:
                raise ValueError(f"frames {start}:{end} outside the take (0..{exp.n_frames - 1})")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    brim = exp.brim
    print(f"# brim {brim.name}: {len(brim)} dots (brim frame, mm)")
    print("# dot x y z radius colour")
    for i in range(len(brim)):
        x, y, z = brim.xyz[i]
        colour = "white" if brim.polarity[i] > 0 else "black"
        print(f"{i} {x:.3f} {y:.3f} {z:.3f} {brim.radius[i]:.3f} {colour}")
    if args.model_only:
        return 0
    cols = exp.brim_points
    cols = cols[np.argsort(exp.brim_indices[cols], kind="stable")]   # in dot order
    dots = exp.brim_indices[cols]
    names = exp.point_names
    views = np.isfinite(exp.observations[..., 0]).sum(-1)                      # (F, P) cameras
    print(f"# brim points, frames {start}-{end}")
    print("# frame dot point x y z cameras")
    for f in range(start, end + 1):
        for d, p in zip(dots, cols):
            x, y, z = exp.xyz[f, p]
            print(f"{f} {d} {names[p]} {x:.3f} {y:.3f} {z:.3f} {views[f, p]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
