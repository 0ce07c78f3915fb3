"""Initialize from ROM on synthetic takes with ground truth: accuracy against the expression gap.

The ROM is seed 1's neutral frame 0 solved from the truth (80 markers, 1280 x 720); the new
takes are frames of seed 2 (other expressions, helmet slip and camera flex). For each new frame
the script reports how far the markers moved from the ROM frame (max / median px over the
cameras), the share of markers seen by >= 2 cameras that were initialized, wrong attached
detections, face points more than 2 mm from their labelled marker, brim points found, the 3D
error, and the CPU time of the match. With ``--images`` the new frame's blobs are detected by
the project's blob detector on the rendered images (the share the detector found in >= 2
cameras is ``attainable``); otherwise detections are the truth + 0.05 px noise + clutter.

    python benchmarks/bench_rom.py [--frames 0,45,60,70] [--images]

One JSON line per frame, then a summary line.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests" / "core"))
sys.path.insert(0, str(ROOT))

from _common import emit  # noqa: E402
from rom_cases import rom_take, score_init  # noqa: E402
from track_cases import label_detections, truth_detections  # noqa: E402

from carapost.core.blobs import detect_blobs  # noqa: E402
from carapost.core.rom_init import match_rom_frame  # noqa: E402
from carapost.model.detections import Detections  # noqa: E402
from carapost.model.params import BlobParameters  # noqa: E402
from carapost.synth import SynthConfig, generate_take  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", default="0,20,45,55,60,70", help="frames of the new take (seed 2)")
    p.add_argument("--images", action="store_true", help="detect blobs on rendered images")
    args = p.parse_args(argv)
    frames = [int(f) for f in args.frames.split(",")]
    rom = rom_take(SynthConfig(n_markers=80, n_frames=1, seed=1))
    synth = generate_take(SynthConfig(n_markers=80, n_frames=max(frames) + 1, seed=2))
    tr = synth.truth
    M = tr.visible.shape[1]
    rows = []
    for f in frames:
        if args.images:
            tables = [detect_blobs(synth.image(f, c), BlobParameters()) for c in range(4)]
            view = SimpleNamespace(visible=tr.visible[f:], brim_visible=tr.brim_visible[f:],
                                   centroid_xy=tr.centroid_xy[f:], brim_centroid_xy=tr.brim_centroid_xy[f:])
            dets = [Detections.from_frames(1, {0: tb}) for tb in tables]
            labels = label_detections(view, dets, [0])
        else:
            tb, lab = truth_detections(tr, [f], seed=3, brim_polarity=synth.brim.polarity)
            tables = [tb[c][f] for c in range(4)]
            labels = [{0: lab[c][f]} for c in range(4)]
        t0 = time.process_time()
        res = match_rom_frame(rom, 0, tables)
        cpu = time.process_time() - t0
        names = [rom.points.labels[i] for i in res.rom_points]
        case = SimpleNamespace(truth=tr, start=f, labels=labels)
        s = score_init(case, names, rom.points.kind[res.rom_points], res.xyz, res.recon, res.obs_det, 0)
        both = tr.visible[f] & np.isfinite(rom.obs_xy[0, :M])[..., 0]
        moved = np.linalg.norm(rom.obs_xy[0, :M] - tr.centroid_xy[f], axis=-1)[both]
        detected = np.zeros((M, 4), bool)
        for c in range(4):
            lab = labels[c][0]
            detected[lab[(lab >= 0) & (lab < M)], c] = True
        seen2 = tr.visible[f].sum(-1) >= 2
        row = {"frame": f, "moved_max_px": float(moved.max()), "moved_median_px": float(np.median(moved)),
               "attainable": float(((detected.sum(1) >= 2) & seen2).sum() / seen2.sum()), **s.as_dict(),
               "cpu_s": cpu}
        rows.append(row)
        emit("rom_init", mode="images" if args.images else "truth", **row)
    emit("rom_init_summary", mode="images" if args.images else "truth", frames=frames,
         coverage_min=min(r["coverage"] for r in rows), wrong_obs=sum(r["wrong_obs"] for r in rows),
         cpu_s_mean=float(np.mean([r["cpu_s"] for r in rows])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
