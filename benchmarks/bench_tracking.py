"""The automatic tracker on synthetic takes with ground truth: accuracy and speed.

Two modes, each printing one JSON line per take:

* ``truth`` — detections are the truth (every visible dot's image centroid + 0.05 px noise,
  plus 15 clutter detections per camera over the face), so the tracker is measured alone.
  300 frames at 60 fps, 1280 x 720, high motion, blinks; 35 (sparse preset), 80 (default)
  and 156 (dense preset) markers. Targets: >= 99.5 % of the marker-frames seen by two
  cameras tracked, no swaps, 80 markers: median 3D error <= 0.15 mm, 95th percentile
  <= 0.5 mm; >= 100 frames/s for 80 markers x 4 cameras on one core.
* ``images`` — the take is written as ``.pico`` files (JPEG), decoded, and the project's blob
  detector runs on every frame; the tracker then uses the decoded images (appearance checks,
  patch tracking). Reports the tracking rate and its ratio to the rate of just decoding
  the frames (``decode_over_track``: > 1 means tracking is faster than decoding).

Frame 0 is initialised from the truth (a perfect Initialize 3D). Rates are frames per second
of CPU time (one dedicated core's rate, robust to a busy machine) and of wall time.

    python benchmarks/bench_tracking.py [--mode truth|images|both] [--markers 35,80,156]
                                        [--frames 300] [--image-frames 100]
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests" / "core"))
sys.path.insert(0, str(ROOT))

from _common import emit  # noqa: E402
from track_cases import apply_result, build_take, evaluate, label_detections, truth_case  # noqa: E402

from carapost.core.tracking import track  # noqa: E402
from carapost.model.params import Parameters, dense_156_preset, sparse_35_preset  # noqa: E402
from carapost.synth import SynthConfig, generate_take  # noqa: E402
from carapost.synth.evaluate import score_points  # noqa: E402


def preset(n_markers: int):
    return {35: sparse_35_preset, 156: dense_156_preset}.get(n_markers, lambda: Parameters())().tracking


def timed_track(take, **kw):
    w0, c0 = time.perf_counter(), time.process_time()
    res = track(take, 0, **kw)
    return res, time.perf_counter() - w0, time.process_time() - c0


def summary(take, truth, labels, res, wall, cpu) -> dict:
    out = copy.deepcopy(take)
    apply_result(out, res)
    s = evaluate(out, truth, labels, res.frames)
    ps = score_points(out, truth, res.frames)
    n = len(res.frames)
    tot = res.report["totals"]
    return {"frames": n, "coverage": s.coverage, "swapped_points": s.swapped_points, "wrong_frames": s.wrong_frames,
            "mismatched_obs": s.mismatched_obs, "median_mm": s.median_mm, "p95_mm": s.p95_mm, "max_mm": s.max_mm,
            "score_points_swaps": ps.swaps, "score_points_coverage": ps.coverage,
            "patch_obs": tot.get("patch_obs", 0), "single_sensor": tot.get("single_sensor", 0),
            "fps_cpu": n / cpu, "fps_wall": n / wall}


def run_truth(markers: list[int], frames: int) -> None:
    for m in markers:
        cfg = SynthConfig(n_markers=m, n_frames=frames, frame_rate=60, high_motion=True, blinks=True)
        case = truth_case(cfg)
        res, wall, cpu = timed_track(case.take, params=preset(m))
        emit("tracking_truth_detections", markers=m, cameras=4,
             **summary(case.take, case.truth, case.labels, res, wall, cpu))


def run_images(frames: int) -> None:
    from carapost.core.blobs import detect_blobs
    from carapost.io.pico import PicoReader
    from carapost.model.params import BlobParameters
    from carapost.synth import write_take

    synth = generate_take(SynthConfig(n_markers=80, n_frames=frames, frame_rate=60, high_motion=True, blinks=True))
    tr = synth.truth
    C = tr.n_cameras
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_take(synth, tmp, "Bench")
        readers = [PicoReader(paths[f"pico_{c}"]) for c in range(C)]
        w0, c0 = time.perf_counter(), time.process_time()
        images = np.stack([np.stack([readers[c].read(f) for c in range(C)]) for f in range(frames)])
        dec_wall, dec_cpu = time.perf_counter() - w0, time.process_time() - c0
        for r in readers:
            r.close()
    params = BlobParameters()
    t0 = time.process_time()
    tables = [{f: detect_blobs(images[f, c], params) for f in range(frames)} for c in range(C)]
    det_cpu = time.process_time() - t0
    # identities of the detections (for scoring and for the frame-0 initialisation)
    from carapost.model.detections import Detections

    dets = [Detections.from_frames(frames, tables[c]) for c in range(C)]
    labels = label_detections(tr, dets, range(frames), match_px=1.5)
    take = build_take(synth, tables, labels, start=0)
    image = lambda cam, f: images[f, cam]  # noqa: E731
    for use_images in (True, False):
        res, wall, cpu = timed_track(take, image=image if use_images else None)
        s = summary(take, tr, labels, res, wall, cpu)
        emit("tracking_detector_images", markers=80, cameras=4, images=use_images,
             decode_fps_cpu=frames / dec_cpu, decode_fps_wall=frames / dec_wall,
             decode_over_track=dec_cpu / frames * s["fps_cpu"],
             detect_fps_cpu=frames / det_cpu, **s)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mode", choices=("truth", "images", "both"), default="both")
    ap.add_argument("--markers", default="35,80,156")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--image-frames", type=int, default=100)
    a = ap.parse_args(argv)
    if a.mode in ("truth", "both"):
        run_truth([int(m) for m in a.markers.split(",")], a.frames)
    if a.mode in ("images", "both"):
        run_images(a.image_frames)


if __name__ == "__main__":
    main()
