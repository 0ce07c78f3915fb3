"""``carapost batch PATTERN...``: process many takes, in parallel, on this machine or a Dask cluster."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from carapost.model.params import FILL_METHODS

from .common import add_settings_arguments, parse_caddies, parse_settings
from .progress import progress_bar

__all__ = ["cmd_batch", "add_parsers"]

_MARK = {"done": "done", "skipped": "skipped", "error": "FAILED"}


def _line(res: dict[str, Any]) -> str:
    head = f"  {_MARK.get(res['status'], res['status']):<8s} {res['take']:<24s}"
    if res["status"] == "done":
        steps = ", ".join(f"{s['step']} {s['seconds']:.1f} s" for s in res["steps"])
        return f"{head} {res['seconds']:7.1f} s   {steps}"
    if res["status"] == "skipped":
        return f"{head} {'':9s} {res['reason']}"
    return f"{head} {res['seconds']:7.1f} s   {res['error']}"


def cmd_batch(args: argparse.Namespace) -> dict[str, Any]:
    from carapost.cli import CliError
    from carapost.ops.batch import BatchOptions, find_takes, job_plan, run_batch
    from carapost.ops.batch_pool import cpu_count, open_pool
    from carapost.ops.batch_steps import resolve_steps

    if args.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {args.workers}")
    threads = args.threads or (1 if args.scheduler else max(1, cpu_count() // args.workers))
    options = BatchOptions(steps=tuple(args.steps.split(",")), out_dir=args.out, calibration=args.calibration,
                           brim=args.brim, auto_init=args.auto_init, frame=args.frame,
                           formats=tuple(args.formats.split(",")), fill_method=args.fill_method, force=args.force,
                           threads=threads, split_detect=args.split_detect, preset=args.preset,
                           settings=tuple(parse_settings(args.set)), caddies=_caddies(args.caddies))
    steps, unavailable = resolve_steps(options.steps)
    for name, why in unavailable.items():
        print(f"carapost batch: step {name} skipped: {why}", file=sys.stderr)
    jobs = find_takes(args.patterns, options)
    summary: dict[str, Any] = {"steps": list(steps), "skipped_steps": unavailable, "takes": []}
    if args.dry_run:
        for job in jobs:
            action, reason = job_plan(job, options)
            print(f"  {action:<8s} {job.name:<24s} {reason}")
            summary["takes"].append({"take": job.name, "kind": job.kind, "inputs": list(job.inputs),
                                     "output": job.output, "action": action, "reason": reason})
        return summary
    t0 = time.perf_counter()
    with open_pool(args.workers, args.scheduler) as pool:
        print(f"carapost batch: {len(jobs)} take(s), steps {','.join(steps) or '-'}, "
              f"{pool.workers} worker(s) ({pool.where})")
        finished = 0
        with progress_bar("batch", unit="take") as prog:
            def on_result(res: dict[str, Any]) -> None:
                nonlocal finished
                finished += 1
                print(_line(res), flush=True)
                prog(finished, len(jobs))

            results = run_batch(jobs, options, pool=pool, on_result=on_result)
        summary.update(workers=pool.workers, where=pool.where)
    counts = {s: sum(r["status"] == s for r in results) for s in ("done", "skipped", "error")}
    summary.update(takes=results, done=counts["done"], skipped=counts["skipped"], failed=counts["error"],
                   seconds=round(time.perf_counter() - t0, 3))
    print(f"carapost batch: {len(results)} take(s): {counts['done']} done, {counts['skipped']} skipped, "
          f"{counts['error']} failed in {summary['seconds']:.1f} s")
    if counts["error"]:
        if args.json:  # the summary still goes out; the exit status says something failed
            print(json.dumps(summary, default=str))
        failed = [r["take"] for r in results if r["status"] == "error"]
        raise CliError(f"{len(failed)} of {len(results)} take(s) failed: {', '.join(failed)}")
    return summary


def add_parsers(sub: Any) -> dict[str, Any]:
    p = sub.add_parser(
        "batch", help="process many takes (detect, init, track, fill, export) in parallel",
        description="Takes are found from folders (searched recursively), wildcards, .pico files (grouped by "
                    "take name) and .cara projects. Each take is saved as <take>.cara next to its files (or in "
                    "--out) with a <take>.carapost.json manifest; a rerun skips takes that are up to date.")
    p.add_argument("patterns", nargs="+", metavar="PATTERN", help="folder, wildcard, .pico file or .cara project")
    p.add_argument("--steps", default="detect",
                   help="comma-separated steps among detect,init,track,fill,export (default: detect)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1: this process)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="run on a Dask cluster, e.g. tcp://host:8786")
    p.add_argument("--threads", type=int, help="detection threads per take (default: cores / workers)")
    p.add_argument("--split-detect", choices=("auto", "on", "off"), default="auto",
                   help="split each take's blob detection by frame range across workers (auto: when there are "
                        "fewer takes than workers)")
    p.add_argument("--out", metavar="DIR", help="write the .cara files, exports and manifests here")
    p.add_argument("--calibration", help="calibration for every .pico take (default: <take>.xcp next to it)")
    p.add_argument("--brim", help="v1.0 | v1.1 | v2.0 | FILE.svg | FILE.json (default: <take>_brim.json next "
                                  "to it)")
    p.add_argument("--auto-init", action="store_true", help="init: initialize 3D without a seeds file")
    p.add_argument("--frame", type=int, help="init/track: the frame to initialize and track from")
    p.add_argument("--formats", default="c3d", help="export: comma-separated formats among c3d,fbx (default c3d)")
    p.add_argument("--fill-method", choices=FILL_METHODS, default="neighbours",
                   help="fill: gap-filling method")
    p.add_argument("--force", action="store_true",
                   help="redo up-to-date takes and overwrite .cara files that batch did not write")
    add_settings_arguments(p)
    p.add_argument("--dry-run", action="store_true", help="list the takes and what would be done; change nothing")
    return {"batch": cmd_batch}


def _caddies(spec: str | None) -> tuple[tuple[int, int], ...] | None:
    pairs = parse_caddies(spec)
    return None if pairs is None else tuple(pairs)
