#!/usr/bin/env python3
"""Make a small synthetic take to try the example scripts on.

Writes, in OUT_DIR, a capture as the logger would (``Example_0.pico`` .. ``Example_3.pico``, the
calibration ``Example.xcp``, the brim ``Example_brim.json`` and a seeds file
``Example_seeds.json``), then processes it with the scripting API:

* ``Example_b.cara``: the take with its blob detections (what ``process_detect_blobs.py`` makes);
* ``Example.cara``: the solved take: brim solved from the seeds, Initialize 3D, tracked through
  the take (what ``export_*.py`` and ``cara_fbx_export.py`` read).

Example::

    python make_demo_take.py demo --frames 30
    python export_3d_simple.py demo/Example.cara
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import carapost.api as cp
from carapost.synth import SynthConfig, generate_take, write_take


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="The images are rendered, so every marker's true position is known "
                                       "(Example_truth.npz).")
    p.add_argument("out_dir", type=Path, help="folder to write the take to (created if missing)")
    p.add_argument("--name", default="Example", help="take name (default Example)")
    p.add_argument("--frames", type=int, default=4, help="number of frames (default 4)")
    p.add_argument("--markers", type=int, default=35, choices=(35, 80, 156), help="face markers (default 35)")
    p.add_argument("--size", default="640x360", help="image size WIDTHxHEIGHT (default 640x360)")
    p.add_argument("--seed", type=int, default=3, help="random seed (default 3)")
    p.add_argument("--no-track", action="store_true", help="stop after Initialize 3D (no tracking)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"error: --size must be WIDTHxHEIGHT, got {args.size!r}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        synth = generate_take(SynthConfig(n_markers=args.markers, n_frames=args.frames, width=width, height=height,
                                          seed=args.seed))
        files = write_take(synth, args.out_dir, args.name)
        print(f"wrote {args.frames} frames x {synth.n_cameras} cameras to {args.out_dir}")

        with cp.CaraProcess.from_pico(files["pico_0"]) as take:   # finds Example.xcp next to the files
            # Dots are small in small images: accept blobs down to 2 px radius.
            take.set_property("Blob Parameters", "Black Min Radius", 2)
            take.set_property("Blob Parameters", "White Min Radius", 2)
            take.detect_blobs()
            print(f"detected {take.n_detections()} blobs; saved {take.save(args.out_dir / f'{args.name}_b.cara')}")

            summary = take.run_pipeline(seeds=files["seeds"], brim=str(files["brim_json"]), detect="none")
            print(f"initialized {summary['points']} face points")
            if not args.no_track and take.n_frames > 1:
                print(take.track(take.current_frame))
                if take.current_frame > 0:
                    print(take.track(take.current_frame, direction="backwards"))
            print(f"saved {take.save(args.out_dir / f'{args.name}.cara')}")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
