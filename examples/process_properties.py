#!/usr/bin/env python3
"""List every property of every property group.

Shows all the blob detection, initialization, tracking, gap-filling, stabilization and export
parameters with their values: those of a take (``.cara`` project, or the ``.pico`` files of a
take, whose Blob Parameters are the ones recorded at capture), or the defaults when no take is
given. ``--verbose`` adds each property's unit, range and description; ``--json`` prints JSON.

Example::

    python process_properties.py
    python process_properties.py Example.cara --group "Tracking Parameters" --verbose
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("take", type=Path, nargs="?", help=".cara project or .pico file (default: the defaults)")
    p.add_argument("-g", "--group", help="only this property group (e.g. 'Blob Parameters')")
    p.add_argument("-v", "--verbose", action="store_true", help="add units, ranges and descriptions")
    p.add_argument("--json", action="store_true", help="print JSON")
    return p.parse_args(argv)


def describe(info: dict[str, Any]) -> str:
    parts = []
    if info["unit"]:
        parts.append(info["unit"])
    if info["choices"]:
        parts.append("one of " + ", ".join(info["choices"]))
    elif info["min"] is not None or info["max"] is not None:
        lo = "" if info["min"] is None else f"{info['min']:g}"
        hi = "" if info["max"] is None else f"{info['max']:g}"
        parts.append(f"range {lo}..{hi}")
    parts.append(f"default {info['default']}")
    text = "; ".join(parts)
    return f"[{text}]" + (f" {info['help']}" if info["help"] else "")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        if args.take is None:
            props = cp.default_properties(info=True)
            source = "defaults"
        else:
            with cp.CaraProcess(args.take) as take:
                props = take.properties(info=True)
            source = str(args.take)
        if args.group:
            key = "".join(ch for ch in args.group.lower() if ch.isalnum())
            props = {g: v for g, v in props.items() if "".join(ch for ch in g.lower() if ch.isalnum()) == key}
            if not props:
                raise ValueError(f"no property group named {args.group!r}")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        data = props if args.verbose else {g: {n: i["value"] for n, i in v.items()} for g, v in props.items()}
        print(json.dumps(data, indent=2))
        return 0
    print(f"Properties ({source})")
    for group, values in props.items():
        print(f"\n{group}")
        for name, info in values.items():
            line = f"    {name:<45s} {info['value']!s:>8}"
            print(line + (f"   {describe(info)}" if args.verbose else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
