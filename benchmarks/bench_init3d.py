"""Initialize 3D (seeded and automatic): accuracy and speed on synthetic takes and real footage.

For each synthetic marker set (35 sparse / 80 default / 156 dense, with the guide's parameter
presets) and several frames of a 100-frame take (expressions change the face):

* ``truth``: detections = the true projections + 0.15 px noise, 10 % missed, 4 false
  detections per camera on the face (the shared test cases, ``tests/core/init3d_cases.py``);
* ``detector``: the project's blob detector on the rendered images;

each initialized from the seeds of ``seeds_for`` (snapped to the detections) and without
seeds (``auto_initialize``), starting from the nominal calibration. Printed per set: coverage
of the markers visible in two or more cameras (``coverage``), of those detected in two or more
cameras (``coverage_detected``) and of those detected by both cameras of a caddy
(``coverage_caddy``: what caddy growth can reach), mismatched detections, spurious points (no
marker detection at all: with the detector, a pupil seen by three cameras), duplicates, median
3D error in the brim frame and after a rigid alignment (shape), and time per frame.

The real footage (the Pose2Sim demo's frame 0, auto-initialized) has its own benchmark,
``bench_pose2sim.py``.

Prints one JSON line.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "core"))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from _common import emit  # noqa: E402
from init3d_cases import _take, detector_case, score, truth_case  # noqa: E402

from carapost.core.auto_init import auto_initialize  # noqa: E402
from carapost.core.init3d import initialize_3d  # noqa: E402

KEYS = ("coverage", "coverage_detectable", "coverage_caddy")


def _summary(rows: list[tuple[dict, float]]) -> dict:
    s = [r for r, _ in rows]
    return {
        "frames": len(s),
        "coverage": round(float(np.mean([r["coverage"] for r in s])), 4),
        "coverage_min": round(float(np.min([r["coverage"] for r in s])), 4),
        "coverage_detected": round(float(np.mean([r["coverage_detectable"] for r in s])), 4),
        "coverage_caddy": round(float(np.mean([r["coverage_caddy"] for r in s])), 4),
        "coverage_caddy_min": round(float(np.min([r["coverage_caddy"] for r in s])), 4),
        "mismatched_detections": int(sum(r["mismatched_detections"] for r in s)),
        "spurious_points": int(sum(r["spurious_points"] for r in s)),
        "duplicates": int(sum(r["duplicates"] for r in s)),
        "median_err_mm": round(float(np.median([r["median_err_mm"] for r in s])), 4),
        "median_err_aligned_mm": round(float(np.median([r["median_err_aligned_mm"] for r in s])), 4),
        "ms_per_frame": round(1000 * float(np.mean([dt for _, dt in rows])), 1),
    }


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def synthetic(n: int, frames: list[int], seeds: list[int], detector: bool) -> dict:
    synth = _take(n, 0, n_frames=100)
    out = {}
    rows: dict[str, list] = {"seeded_truth": [], "auto_truth": [], "seeded_detector": [], "auto_detector": []}
    for f in frames:
        cases = [("truth", truth_case(n, seed=s, synth=synth, frame=f)) for s in seeds]
        if detector:
            cases.append(("detector", detector_case(n, synth=synth, frame=f)))
        for kind, case in cases:
            res, dt = _timed(lambda: initialize_3d(case.dets, case.intrinsics, case.R, case.t, case.seeds,
                                                   case.params, brim_xyz=case.brim_xyz))
            rows[f"seeded_{kind}"].append((score(case, res), dt))
            res, dt = _timed(lambda: auto_initialize(case.dets, case.intrinsics, case.R, case.t, case.params,
                                                     brim_xyz=case.brim_xyz))
            rows[f"auto_{kind}"].append((score(case, res), dt))
    for k, v in rows.items():
        if v:
            out[k] = _summary(v)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 50, 99])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--no-detector", action="store_true", help="skip the rendered-image cases")
    args = ap.parse_args()
    result = {str(n): synthetic(n, args.frames, args.seeds, not args.no_detector) for n in (35, 80, 156)}
    emit("init3d", **result)


if __name__ == "__main__":
    main()
