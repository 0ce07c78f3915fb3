#!/usr/bin/env python3
"""Print the 3D face data of a ``.cara`` file to the console.

One line per frame and face point: frame index, point name, x y z in millimetres (``nan`` in
gaps) and how the position was obtained (multi-view, single-sensor, interpolated, none).

Example::

    python export_3d_simple.py Example.cara
    python export_3d_simple.py Example.cara --frames 0:9 --stabilized > face.txt
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cara", type=Path, help=".cara project (or .c3d file)")
    p.add_argument("--frames", help="inclusive frame range start:end (default all)")
    p.add_argument("--stabilized", action="store_true", help="print the stabilized data")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        exp = cp.CaraExport(args.cara)
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
    xyz = exp.xyz_stabilized if args.stabilized else exp.xyz      # (F, P, 3) mm
    recon = exp.reconstruction                                     # (F, P)
    names = exp.point_names
    face = exp.face_points
    print(f"# {exp.name or args.cara.name}: {len(face)} face points, frames {start}-{end} of {exp.n_frames}, "
          f"{exp.frame_rate:g} Hz, mm{' (stabilized)' if args.stabilized else ''}")
    print("# frame point x y z reconstruction")
    for f in range(start, end + 1):
        for p in face:
            x, y, z = xyz[f, p]
            print(f"{f} {names[p]} {x:.3f} {y:.3f} {z:.3f} {cp.Recon(recon[f, p]).name.lower()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
