#!/usr/bin/env python3
"""Export a solved ``.cara`` take to FBX.

Produces the same output as the built-in FBX export (File > Export FBX): a marker node per point
(face and, optionally, brim) with its animated translation, and the cameras. Customise it, for
example, to export only some points (``--points``), another frame range, units or up axis. No
Autodesk FBX SDK is needed: CaraPost writes binary FBX 7.4 / 7.5 itself.

Example::

    python cara_fbx_export.py Example.cara -o c:/tmp/Example.fbx
    python cara_fbx_export.py Example.cara -o Example.fbx --units cm --up-axis Z --no-brim
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cara", type=Path, help="solved .cara project")
    p.add_argument("-o", "--output", type=Path, help="output .fbx (default NAME.fbx next to the .cara)")
    p.add_argument("--units", choices=("mm", "cm"), help="length unit (default: the take's Export property)")
    p.add_argument("--up-axis", choices=("Y", "Z"), help="up axis (default: the take's Export property)")
    p.add_argument("--stabilized", action="store_true", help="export the stabilized data")
    p.add_argument("--no-brim", action="store_true", help="leave the calibration brim points out")
    p.add_argument("--no-cameras", action="store_true", help="leave the camera nodes out")
    p.add_argument("--points", help="comma-separated point names to export (default all)")
    p.add_argument("--frames", help="inclusive frame range start:end (default all)")
    p.add_argument("--fbx-version", type=int, choices=(7400, 7500), default=7400, help="FBX file version")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        exp = cp.CaraExport(args.cara)
        props: dict[str, object] = {}
        if args.units:
            props["Units"] = args.units
        if args.up_axis:
            props["Up Axis"] = args.up_axis
        if args.stabilized:
            props["Export Stabilized Data"] = True
        if args.no_brim:
            props["Include Brim Points"] = False
        if args.no_cameras:
            props["Include Cameras"] = False
        kwargs: dict[str, object] = {"version": args.fbx_version}
        if args.points:
            try:
                kwargs["points"] = [exp.point_index(n.strip()) for n in args.points.split(",") if n.strip()]
            except KeyError as exc:
                raise ValueError(f"{args.cara}: {exc.args[0]}") from None
        if args.frames:
            a, _, b = args.frames.partition(":")
            try:
                kwargs["frames"] = (int(a), int(b if b else a))
            except ValueError:
                raise ValueError(f"--frames must be 'start:end', got {args.frames!r}") from None
        out = args.output or args.cara.with_suffix(".fbx")
        exp.export(out, properties=props, **kwargs)
        print(f"wrote {out} ({exp.n_frames} frames at {exp.frame_rate:g} Hz)")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
