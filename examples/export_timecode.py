#!/usr/bin/env python3
"""Convert between the time representations CaraPost uses.

A take's frames are counted three ways: zero-based frame indices (what the data arrays use),
the frame numbers burnt into the video by the logger (``first frame number + index``), and
SMPTE timecode (the take's start timecode plus the index, drop-frame at 29.97 and 59.94 Hz).
Give values to convert with ``--frame``, ``--number`` or ``--timecode`` (repeatable); without
them, the first, middle and last frames of the take are shown. ``--rate`` and ``--start`` work
without a take.

Example::

    python export_timecode.py Example.cara
    python export_timecode.py Example.cara --frame 100 --timecode 10:00:01:00 --number 2000
    python export_timecode.py --rate 29.97 --start "00:59:59;28" --frame 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cara", type=Path, nargs="?", help=".cara project (or .c3d file)")
    p.add_argument("--frame", type=int, action="append", default=[], help="a frame index to convert")
    p.add_argument("--number", type=int, action="append", default=[], help="a burnt-in frame number to convert")
    p.add_argument("--timecode", action="append", default=[], help="a timecode HH:MM:SS:FF to convert")
    p.add_argument("--rate", type=float, help="frame rate in Hz (without a take, or to override it)")
    p.add_argument("--start", help="start timecode of frame 0 (without a take, or to override it)")
    p.add_argument("--first-number", type=int, help="burnt-in frame number of frame 0")
    p.add_argument("--drop-frame", action=argparse.BooleanOptionalAction, default=None,
                   help="force drop-frame timecode on or off (default: on at 29.97 / 59.94 Hz)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        n_frames = None
        if args.cara is not None:
            exp = cp.CaraExport(args.cara)
            rate, start, first, n_frames = exp.frame_rate, exp.start_timecode, exp.first_frame_number, exp.n_frames
        elif args.rate is None:
            raise ValueError("give a .cara file or --rate (and --start)")
        else:
            rate, start, first = args.rate, "00:00:00:00", 0
        rate = args.rate if args.rate is not None else rate
        start = args.start if args.start is not None else start
        first = args.first_number if args.first_number is not None else first
        tb = cp.TimeBase(rate, start, first, drop_frame=args.drop_frame)
        print(f"frame rate {tb.frame_rate:g} Hz, start timecode {tb.start_timecode}, first frame number "
              f"{tb.first_frame_number}, {'drop-frame' if tb.drop_frame else 'non-drop-frame'} timecode")
        frames = list(args.frame)
        frames += list(tb.number_to_frame(args.number)) if args.number else []
        frames += list(tb.timecode_to_frame(args.timecode)) if args.timecode else []
        if not frames:
            if n_frames is None:
                raise ValueError("give --frame, --number or --timecode values to convert")
            frames = sorted({0, (n_frames - 1) // 2, n_frames - 1})
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{'frame index':>12s} {'frame number':>13s} {'timecode':>12s} {'seconds':>10s}")
    numbers = tb.frame_to_number(frames)
    codes = tb.frame_to_timecode(frames)
    seconds = tb.frame_to_seconds(frames)
    for f, n, tc, s in zip(frames, numbers, codes, seconds):
        note = "" if n_frames is None or 0 <= f < n_frames else "   (outside the take)"
        print(f"{int(f):>12d} {int(n):>13d} {tc:>12s} {s:>10.4f}{note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
