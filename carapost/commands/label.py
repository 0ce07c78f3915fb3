"""``carapost label IN OUT``: label (and repair swaps in) marker trajectories from C3D or CSV."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from .progress import progress_bar

__all__ = ["cmd_label", "add_parsers"]


def cmd_label(args: argparse.Namespace) -> dict[str, Any]:
    from carapost.ops.label_file import label_file

    t0 = time.perf_counter()
    with progress_bar("label", unit="frame") as prog:
        report = label_file(args.input, args.output, method=args.method, template=args.template, progress=prog,
                            reference_frame=args.reference_frame, ignore_markers=args.ignore or (),
                            hand_heuristics=args.hand_heuristics, plot_every=args.plot_every,
                            plot_dir=args.plot_dir, units=args.units,
                            options=_checks_off(args))
    dt = time.perf_counter() - t0
    report = dict(report)
    report["seconds"] = dt
    print(f"carapost label: wrote {args.output} ({args.method}) in {dt:.1f} s")
    for key in ("markers", "frames", "labelled_samples", "unlabelled_points", "relabelled_samples"):
        if key in report:
            print(f"  {key}: {report[key]}")
    named = report.get("labeller", {}).get("unseen_named", 0)
    renamed = sum(report.get("labeller", {}).get(k, 0) for k in ("take_renamed", "range_named", "range_unnamed"))
    if renamed:
        print(f"  note: the take check renamed or unnamed {renamed} piece(s) by the marker set learnt over the take "
              "(run with --no-take-check to compare)")
    if named:
        print(f"  note: {named} isolated tracklet(s) took the name of the one marker never seen in the reference "
              "frame (check them, or run with --no-isolated-check)")
    return report


def _checks_off(args: argparse.Namespace) -> dict[str, bool] | None:
    """The default method's checks the command line turned off (None: all on)."""
    if args.method != "assignment":
        return None
    off = {name: False for name in ("isolated_check", "take_check") if not getattr(args, name)}
    return off or None


def add_parsers(sub: Any) -> dict[str, Any]:
    p = sub.add_parser("label", help="label marker trajectories (C3D or CSV) and repair swapped labels")
    p.add_argument("input", help="IN.c3d or IN.csv")
    p.add_argument("output", help="OUT.c3d or OUT.csv")
    p.add_argument("--method", choices=("assignment", "nearest"), default="assignment",
                   help="global per-frame assignment (default) or seed 002's nearest-neighbour method")
    p.add_argument("--template", type=Path, help="marker-set template (.json) naming the markers")
    p.add_argument("--reference-frame", type=int, help="frame whose input labels are right (default: automatic)")
    p.add_argument("--ignore", nargs="+", metavar="NAME", help="markers to leave as they are")
    p.add_argument("--hand-heuristics", action="store_true", help="crossing-bone and fingertip rules (hand names)")
    p.add_argument("--plot-every", type=int, default=0, help="save an inspection plot every N frames")
    p.add_argument("--plot-dir", type=Path, help="folder for the inspection plots")
    p.add_argument("--no-isolated-check", dest="isolated_check", action="store_false",
                   help="(assignment) do not unname pieces their neighbours rule out, nor give the one marker never "
                        "seen in the reference frame to isolated unlabelled tracklets")
    p.add_argument("--no-take-check", dest="take_check", action="store_false",
                   help="(assignment) do not name pieces by the marker set learnt over the whole take (the last "
                        "check, run only where a marker is long absent or an earlier check repaired something)")
    p.add_argument("--units", choices=("mm", "cm", "m"), help="CSV input units (default mm)")
    return {"label": cmd_label}
