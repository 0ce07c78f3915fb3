#!/usr/bin/env python3
"""Detect blobs in every take found under folders or matching file patterns.

Each argument is a folder (searched recursively) or a file name that may include wildcards
(``C:/Data/ROM*.pico``). Every take found (the ``NAME_<n>.pico`` files of one folder sharing a
``NAME``) that does not already have a ``NAME_b.cara`` with blob detections gets one, as
``process_detect_blobs.py`` makes it. A take that fails is reported and the others go on.

Example::

    python process_batch_detect_blobs.py C:/Data/Jobs
    python process_batch_detect_blobs.py "C:/Data/ROM*.pico"
"""

from __future__ import annotations

import argparse
import glob
import re
import sys
import time
from pathlib import Path

import carapost.api as cp

PICO_NAME = re.compile(r"^(?P<take>.+)_(?P<channel>\d+)\.pico$", re.IGNORECASE)


def find_takes(patterns: list[str]) -> list[Path]:
    """One ``.pico`` file per take (the lowest channel), sorted by folder and take name."""
    files: list[Path] = []
    for pattern in patterns:
        p = Path(pattern)
        if p.is_dir():
            files += p.rglob("*.pico")
        else:
            files += [Path(f) for f in glob.glob(pattern, recursive=True)]
    takes: dict[tuple[Path, str], tuple[int, Path]] = {}
    for f in files:
        m = PICO_NAME.match(f.name)
        if m is None or not f.is_file():
            continue
        key = (f.parent.resolve(), m["take"])
        ch = int(m["channel"])
        if key not in takes or ch < takes[key][0]:
            takes[key] = (ch, f)
    return [takes[k][1] for k in sorted(takes)]


def output_for(pico: Path) -> Path:
    return pico.parent / f"{PICO_NAME.match(pico.name)['take']}_b.cara"   # type: ignore[index]


def has_detections(cara: Path) -> bool:
    """True if ``cara`` exists, opens, and holds blob detections."""
    if not cara.is_file():
        return False
    try:
        return cp.CaraExport(cara).n_detections() > 0
    except ValueError as exc:
        print(f"  {cara}: unreadable ({exc}); detecting again")
        return False


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("inputs", nargs="+", help="folders and/or .pico file names (wildcards allowed)")
    p.add_argument("--frames", help="inclusive frame range start:end to detect (default all)")
    p.add_argument("-p", "--property", nargs=3, action="append", default=[], metavar=("GROUP", "NAME", "VALUE"),
                   help='set a property first, e.g. -p "Blob Parameters" "Black Threshold" 0.3 (repeatable)')
    p.add_argument("-n", "--dry-run", action="store_true", help="only list what would be done")
    return p.parse_args(argv)


def detect_take(pico: Path, out: Path, args: argparse.Namespace) -> None:
    start = end = None
    if args.frames:
        a, _, b = args.frames.partition(":")
        try:
            start, end = int(a), int(b if b else a)
        except ValueError:
            raise ValueError(f"--frames must be 'start:end', got {args.frames!r}") from None
    with cp.CaraProcess.from_pico(pico) as take:
        for group, name, value in args.property:
            take.set_property(group, name, value)
        take.detect_blobs(None, start, end)
        take.save(out)
        print(f"  {take.n_detections()} detections -> {out}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    takes = find_takes(args.inputs)
    if not takes:
        print(f"error: no takes (NAME_<n>.pico files) found in {', '.join(args.inputs)}", file=sys.stderr)
        return 1
    done = skipped = failed = 0
    t0 = time.perf_counter()
    for pico in takes:
        out = output_for(pico)
        print(f"{pico.parent / PICO_NAME.match(pico.name)['take']}:")  # type: ignore[index]
        if has_detections(out):
            print(f"  skipped: {out.name} already has blob detections")
            skipped += 1
            continue
        if args.dry_run:
            print(f"  would detect blobs -> {out}")
            continue
        try:
            detect_take(pico, out, args)
            done += 1
        except ValueError as exc:
            print(f"  failed: {exc}", file=sys.stderr)
            failed += 1
    print(f"{len(takes)} take(s): {done} detected, {skipped} skipped, {failed} failed "
          f"({time.perf_counter() - t0:.1f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
