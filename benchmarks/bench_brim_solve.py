"""Solve Calibration Brim [Manual]: speed and accuracy on synthetic frames.

Per frame of a synthetic take: true brim projections + 0.1 px noise, 10% of the dots missing,
40 random detections, a decoy 8-20 px from every dot and one 2-5 px from every missing dot;
four user clicks per camera (the brim's corners). Also the hard case: 35% missing, 0.3 px.
Reports the time per solve (4 cameras), wrong attachments, detected dots left unattached,
camera-centre errors against the truth, and the per-camera RMS. Prints one JSON line.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "core"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit  # noqa: E402
from test_brim_solve import SPREAD, clicks, make_detections  # noqa: E402

from carapost.core.brim_solve import solve_brim  # noqa: E402
from carapost.core.camera import camera_centre  # noqa: E402
from carapost.synth import SynthConfig, generate_take  # noqa: E402


def run(take, noise: float, missing: float, n_clutter: int, seed: int) -> dict:
    tr = take.truth
    times, errs, rms = [], [], []
    wrong = unattached = 0
    for f in range(tr.n_frames):
        rng = np.random.default_rng(seed + f)
        dets, labels = make_detections(tr, f, rng, noise=noise, missing=missing, n_clutter=n_clutter, keep=SPREAD)
        t0 = time.perf_counter()
        res = solve_brim(take.brim, tr.intrinsics, dets, clicks(labels, SPREAD))
        times.append(time.perf_counter() - t0)
        for c in range(len(dets)):
            att = res.det_index[:, c]
            m = att >= 0
            wrong += int(np.sum(labels[c][att[m]] != np.flatnonzero(m)))
            unattached += len(set(labels[c][labels[c] >= 0].tolist()) - set(np.flatnonzero(m).tolist()))
        errs.append(np.linalg.norm(camera_centre(res.R, res.t) - camera_centre(tr.R[f], tr.t[f]), axis=1))
        rms.append(res.rms_px)
    e = np.concatenate(errs)
    return {"solve_ms_median": 1e3 * float(np.median(times)), "solve_ms_max": 1e3 * float(np.max(times)),
            "wrong_attachments": wrong, "unattached_detected_dots": unattached,
            "centre_err_mm_rms": float(np.sqrt(np.mean(e * e))), "centre_err_mm_max": float(e.max()),
            "centre_within_0.5mm": float(np.mean(e <= 0.5)),
            "rms_px_median": float(np.median(rms))}


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 30
    take = generate_take(SynthConfig(n_frames=n, seed=0))
    curved = generate_take(SynthConfig(n_frames=n, seed=1, curved_brim=True))
    emit("brim_solve", frames=n,
         nominal=run(take, 0.1, 0.1, 40, 0),
         curved=run(curved, 0.1, 0.1, 40, 1000),
         hard=run(take, 0.3, 0.35, 120, 2000))


if __name__ == "__main__":
    main()
