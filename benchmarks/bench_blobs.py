"""Blob detection benchmark: our detector against OpenCV's SimpleBlobDetector.

Both run on the same 1280x720 frames with exact ground truth:

* rendered frames (``tests/core/blob_images.py``): black and white dots of 2-10 px, skin
  texture, shading, blur, noise, JPEG, low light, occluding edges and merged pairs;
* camera images of synthetic takes (:mod:`carapost.synth`, when available): face markers and
  the brim card's dots, truth = area centroid of each visible dot.

``cv2.SimpleBlobDetector`` is tuned fairly: area, circularity, convexity and inertia filters
are set for 2-12 px dots, each polarity is run separately, and its threshold ladder and shape
limits are chosen by a small grid search (best F1) on separate tuning frames.

A detection matches a truth dot within 1.5 px (one-to-one). Detections near dots that are
partly occluded, merged, cut by the image border, or projected but hidden, are excluded from
both denominators and counted in ``excluded``. Time is CPU time of the calling thread per
frame and polarity with OpenCV limited to one thread (``per_core_ms``).

Prints one JSON line. ``python benchmarks/bench_blobs.py [--frames 12] [--synth 8]``
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "core"))
sys.path.insert(0, str(ROOT))

from blob_images import RenderConfig, render_frame  # noqa: E402

from carapost.core.blobs import detect_blobs  # noqa: E402
from carapost.model.params import BlobParameters  # noqa: E402

MATCH_RADIUS = 1.5
R_MIN, R_MAX = 1.5, 12.0


class Case:
    """One image with its truth: ``xy (K,2)``, ``pol (K,)``, ``count (K,)`` (must be found),
    and ``avoid (A,2)``/``avoid_r (A,)``: places where detections are neither right nor wrong."""

    def __init__(self, image, xy, pol, count, avoid, avoid_r, kind):
        self.image, self.xy, self.pol, self.count = image, xy, pol, count
        self.avoid, self.avoid_r, self.kind = avoid, avoid_r, kind


def rendered_cases(n: int, seed: int) -> list[Case]:
    kinds = [RenderConfig(), RenderConfig(polarity="white"), RenderConfig(low_light=0.25),
             RenderConfig(jpeg_quality=75, texture=0.1), RenderConfig(blur=(1.0, 1.4)),
             RenderConfig(occluders=3, merged_pairs=8), RenderConfig(polarity="both", radius=(2.0, 5.0))]
    out = []
    for i in range(n):
        fr = render_frame(kinds[i % len(kinds)], seed=seed + i)
        out.append(Case(fr.image, fr.xy, fr.polarity.astype(int), fr.clean, fr.xy[fr.partial],
                        fr.axes[fr.partial, 0] + 2.0, "rendered"))
    return out


def synth_cases(n: int, seed: int) -> list[Case]:
    try:
        from carapost.synth import SynthConfig, generate_take
    except ImportError:
        return []
    out = []
    rng = np.random.default_rng(seed)
    while len(out) < n:
        cfg = SynthConfig(n_frames=2, n_markers=int(rng.choice([80, 156])), seed=int(rng.integers(1 << 30)),
                          marker_colour=str(rng.choice(["black", "white"])))
        take = generate_take(cfg)
        tr = take.truth
        mpol = -1 if cfg.marker_colour == "black" else 1
        for f, c in itertools.product(range(take.n_frames), range(take.n_cameras)):
            if len(out) >= n:
                break
            mk = np.isfinite(tr.centroid_xy[f, :, c, 0])
            br = np.isfinite(tr.brim_centroid_xy[f, :, c, 0])
            xy = np.concatenate([tr.centroid_xy[f, mk, c], tr.brim_centroid_xy[f, br, c]])
            vis = np.concatenate([tr.visible[f, mk, c], tr.brim_visible[f, br, c]])
            rad = np.concatenate([tr.radius_px[f, mk, c], tr.brim_radius_px[f, br, c]])
            pol = np.concatenate([np.full(mk.sum(), mpol), np.full(br.sum(), -1)])
            out.append(Case(take.image(f, c), xy, pol, vis, xy[~vis], rad[~vis] + 2.0, "synth"))
    return out


def score(cases: list[Case], dets: list[np.ndarray]) -> dict:
    """Recall, precision, centre errors over cases; ``dets`` are (n, 2) arrays of centres."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    tp = fn = fp = excl = 0
    errs = []
    for case, d in zip(cases, dets):
        want = case.xy[case.count]
        matched = np.zeros(len(d), bool)
        if len(d) and len(want):
            dist = np.linalg.norm(d[:, None] - want[None], axis=2)
            dist[dist > MATCH_RADIUS] = 1e6
            r, c = linear_sum_assignment(dist)
            ok = dist[r, c] <= MATCH_RADIUS
            matched[r[ok]] = True
            tp += int(ok.sum())
            errs.extend(dist[r[ok], c[ok]].tolist())
            fn += len(want) - int(ok.sum())
        else:
            fn += len(want)
        rest = d[~matched]
        if len(rest) and len(case.avoid):
            dd, j = cKDTree(case.avoid).query(rest)
            near = dd < case.avoid_r[j]
        else:
            near = np.zeros(len(rest), bool)
        # Unmatched detections of a dot that must be found (duplicates, > 1.5 px) are errors.
        excl += int(near.sum())
        fp += int((~near).sum())
    e = np.asarray(errs)
    return {"recall": round(tp / max(tp + fn, 1), 5), "precision": round(tp / max(tp + fp, 1), 5),
            "tp": tp, "fn": fn, "fp": fp, "excluded": excl,
            "median_err_px": round(float(np.median(e)), 4) if len(e) else None,
            "p95_err_px": round(float(np.percentile(e, 95)), 4) if len(e) else None}


def run_ours(cases: list[Case]) -> tuple[list[np.ndarray], float]:
    times, out = [], []
    for case in cases:
        pols = sorted(set(case.pol.tolist()))
        p = BlobParameters(black_min_radius=R_MIN, black_max_radius=R_MAX, white_min_radius=R_MIN,
                           white_max_radius=R_MAX, find_black_blobs=-1 in pols, find_white_blobs=1 in pols)
        t = time.thread_time()
        d = detect_blobs(case.image, p)
        times.append((time.thread_time() - t) / len(pols))
        out.append(np.stack([d["x"], d["y"]], 1).astype(float))
    return out, float(np.median(times)) * 1e3


def sbd_params(min_thr: float, step: float, circ: float, inertia: float, colour: int) -> cv2.SimpleBlobDetector:
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor, p.blobColor = True, colour
    p.minThreshold, p.maxThreshold, p.thresholdStep = min_thr, 245, step
    p.minRepeatability = 2
    p.minDistBetweenBlobs = 2.0
    p.filterByArea, p.minArea, p.maxArea = True, 0.5 * np.pi * R_MIN ** 2, np.pi * R_MAX ** 2
    p.filterByCircularity, p.minCircularity = True, circ
    p.filterByConvexity, p.minConvexity = True, 0.85
    p.filterByInertia, p.minInertiaRatio = True, inertia
    return cv2.SimpleBlobDetector_create(p)


def run_sbd(cases: list[Case], setting: tuple) -> tuple[list[np.ndarray], float]:
    times, out = [], []
    for case in cases:
        pols = sorted(set(case.pol.tolist()))
        pts = []
        t = time.thread_time()
        for pol in pols:
            det = sbd_params(*setting, colour=0 if pol < 0 else 255)
            pts.extend(k.pt for k in det.detect(case.image))
        times.append((time.thread_time() - t) / len(pols))
        out.append(np.asarray(pts, float).reshape(-1, 2))
    return out, float(np.median(times)) * 1e3


def tune_sbd(cases: list[Case]) -> tuple:
    best, best_f1 = None, -1.0
    for setting in itertools.product((10, 30), (10, 20), (0.5, 0.7), (0.1, 0.3)):
        dets, _ = run_sbd(cases, setting)
        r = score(cases, dets)
        f1 = 2 * r["recall"] * r["precision"] / max(r["recall"] + r["precision"], 1e-9)
        if f1 > best_f1:
            best, best_f1 = setting, f1
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=14, help="rendered test frames")
    ap.add_argument("--synth", type=int, default=8, help="synthetic-take camera images")
    ap.add_argument("--seed", type=int, default=500)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    tuning = rendered_cases(3, args.seed + 1000) + synth_cases(min(args.synth, 2), args.seed + 1000)
    rendered = rendered_cases(args.frames, args.seed)
    synth = synth_cases(args.synth, args.seed)
    setting = tune_sbd(tuning)
    result = {"benchmark": "blobs", "image": "1280x720", "match_radius_px": MATCH_RADIUS,
              "sbd_setting": dict(zip(("minThreshold", "thresholdStep", "minCircularity", "minInertiaRatio"),
                                      setting))}
    for name, cases in (("rendered", rendered), ("synth", synth), ("all", rendered + synth)):
        if not cases:
            continue
        ours, t_ours = run_ours(cases)
        sbd, t_sbd = run_sbd(cases, setting)
        result[name] = {"frames": len(cases),
                        "ours": {**score(cases, ours), "per_core_ms": round(t_ours, 2)},
                        "opencv_sbd": {**score(cases, sbd), "per_core_ms": round(t_sbd, 2)}}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
