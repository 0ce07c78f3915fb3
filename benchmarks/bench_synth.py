"""Synthetic take generation and rendering speed, on one core.

Target (synthetic take generator task): a 300-frame, 4-camera, 80-marker take at 1280 x 720
renders in well under a minute on one core (about 30 ms per image). Prints one JSON line with
wall and CPU times (the CPU time is what this process used, so a busy machine inflates the
wall time but not the CPU time much).

Usage: ``python benchmarks/bench_synth.py [--frames N] [--write DIR]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit  # noqa: E402

from carapost.synth import SynthConfig, generate_take, write_take  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--markers", type=int, default=80)
    ap.add_argument("--write", action="store_true", help="also write the take (pico, xcp, truth) to a temp folder")
    args = ap.parse_args()
    cv2.setNumThreads(1)  # one core
    cfg = SynthConfig(n_frames=args.frames, n_markers=args.markers)
    w0, c0 = time.perf_counter(), time.process_time()
    st = generate_take(cfg)
    w1, c1 = time.perf_counter(), time.process_time()
    st.images(0)  # first frame: builds the skin texture and the ray grids
    w2, c2 = time.perf_counter(), time.process_time()
    for f in range(1, cfg.n_frames):
        st.images(f)
    w3, c3 = time.perf_counter(), time.process_time()
    n_img = (cfg.n_frames - 1) * st.n_cameras
    fields = dict(
        frames=cfg.n_frames, cameras=st.n_cameras, markers=cfg.n_markers, size=f"{cfg.width}x{cfg.height}",
        truth_s=w1 - w0, truth_cpu_s=c1 - c0, first_frame_s=w2 - w1,
        render_s=w3 - w2, render_cpu_s=c3 - c2,
        ms_per_image=1e3 * (w3 - w2) / n_img, cpu_ms_per_image=1e3 * (c3 - c2) / n_img,
        total_cpu_s=c3 - c0,
    )
    if args.write:
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            st2 = generate_take(cfg)
            write_take(st2, tmp, name="Bench")
            fields["write_s"] = time.perf_counter() - t
    fields["target_met"] = bool(fields["total_cpu_s"] < 60.0)
    emit("synth", **fields)


if __name__ == "__main__":
    main()
