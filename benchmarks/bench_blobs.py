"""Blob detection benchmark: our detector against OpenCV's SimpleBlobDetector.

Both run on the same 1280x720 frames with exact ground truth:

* camera images of synthetic takes (:mod:`carapost.synth`): black or white face markers (35,
  80 or 156) and the brim card's dots (black on white, or white on black with white markers),
  several seeds, the neutral frame and the frames where the jaw is most open and where another
  expression peaks, all four cameras, every other take JPEG-coded (quality 92); truth = area
  centroid of each dot's image;
* rendered frames (``tests/core/blob_images.py``): black and white dots of 2-10 px, skin
  texture, shading, blur, noise, JPEG, low light, occluding edges, merged pairs, saturated
  regions.

``cv2.SimpleBlobDetector`` is tuned fairly: area, circularity, convexity and inertia filters
are set for the radius range, each polarity is run separately, and its threshold ladder and
shape limits are chosen by a small grid search (best F1) on separate tuning frames.

A detection matches a truth dot of its polarity within 1.5 px (one-to-one). Dots that are
partly hidden (``truth.partly_hidden``: part of the rim behind the skin or the card), merged
with another dot, or within a pixel of the image border are excluded from the denominators;
detections near them (within their radius + 2 px) are neither right nor wrong, and are
reported separately (``partial``: how many such dots get a detection more than 1.5 px from
their true centre). ``faint_dots`` counts the dots to find that change the noise-free image by
less than ``FAINT_CONTRAST`` grey levels (a white dot on clipped skin, a black dot in a black
mouth); they count in ``recall``, and ``recall_not_faint`` is the recall without them.
Markers drawn in the image but seen beyond the generator's visibility angle (75-90 degrees
from the skin normal: thin ellipses, :func:`carapost.synth.evaluate.grazing_dots`) are not
required; a detection within 1.5 px of one is a real dot, neither right nor wrong
(``grazing_found``, as :func:`carapost.synth.evaluate.score_detections` counts them).
Time is CPU time of the calling thread per frame and polarity with OpenCV
limited to one thread and BLAS single-threaded (``per_core_ms``, median over frames;
``time_ratio``: our median over OpenCV's; ``time_ratio_per_image``: the median of the
per-image ratios). Both run in the same process on each image in turn (alternating which
goes first).

Prints one JSON line. ``python benchmarks/bench_blobs.py [--seeds 2] [--frames 10]``

``--compare TREE`` compares this checkout's detector with the one of another checkout
(``git worktree add /tmp/base HEAD``), imported in the same process as ``carapost_base``: both
run on each image in turn (alternating which goes first, the minimum CPU time of
``--repeat`` runs per image), and the JSON line gives the time ratio new / old per set, both
versions' missed and false detections, and how far the detection tables differ (images with
a different number of detections, the largest coordinate change of matched detections).
``--cache FILE`` keeps the generated images in a pickle (made on the first run).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time

# Single-threaded BLAS (set before numpy loads it): CPU time per image is then comparable.
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "core"))
sys.path.insert(0, str(ROOT))

from blob_images import RenderConfig, jpeg_roundtrip, render_frame, truth_dots  # noqa: E402

from carapost.core.blobs import detect_blobs  # noqa: E402
from carapost.model.params import BlobParameters  # noqa: E402

MATCH_RADIUS = 1.5
#: Dots that change the (noise-free, clipped) image by less than this many grey levels are
#: reported as ``faint`` (they stay in the recall; ``recall_not_faint`` leaves them out).
FAINT_CONTRAST = 8.0
R_MIN, R_MAX = 1.5, 14.0


class Case:
    """One image with its truth: centres ``xy (K, 2)``, polarity ``pol (K,)``, ``must (K,)``
    (must be found), ``partial (K,)`` (excluded), ``rad (K,)`` radii, ``brim (K,)``, a dict
    of condition labels ``tags``, ``faint (K,)`` and ``grazing (K,)`` (optional dots)."""

    def __init__(self, image, xy, pol, must, partial, rad, brim, tags, faint=None, grazing=None):
        self.image, self.xy, self.pol, self.must, self.partial = image, xy, pol, must, partial
        self.rad, self.brim, self.tags = rad, brim, tags
        self.faint = np.zeros(len(xy), bool) if faint is None else faint
        self.grazing = np.zeros(len(xy), bool) if grazing is None else grazing


def rendered_cases(n: int, seed: int) -> list[Case]:
    kinds = [("black", RenderConfig()), ("white", RenderConfig(polarity="white")),
             ("low_light", RenderConfig(low_light=0.25)),
             ("jpeg_texture", RenderConfig(jpeg_quality=75, texture=0.1)), ("blur", RenderConfig(blur=(1.0, 1.4))),
             ("occluded_merged", RenderConfig(occluders=3, merged_pairs=8)),
             ("both", RenderConfig(polarity="both", radius=(2.0, 5.0))),
             ("white_jpeg", RenderConfig(polarity="white", jpeg_quality=80)),
             ("saturated", RenderConfig(saturated_region=True, polarity="both"))]
    out = []
    for i in range(n):
        name, cfg = kinds[i % len(kinds)]
        fr = render_frame(cfg, seed=seed + i)
        out.append(Case(fr.image, fr.xy, fr.polarity.astype(int), fr.clean, fr.partial, fr.axes[:, 0],
                        np.zeros(len(fr.xy), bool), {"set": "rendered", "kind": name}))
    return out


def synth_cases(seeds: list[int], counts=(35, 80, 156), colours=("black", "white"), frames_per_take: int = 3,
                cameras=(0, 1, 2, 3)) -> list[Case]:
    """Camera images of synthetic takes (see the module docstring)."""
    from carapost.synth import SynthConfig, generate_take

    out = []
    for colour, n_markers, seed in itertools.product(colours, counts, seeds):
        cfg = SynthConfig(n_frames=120, n_markers=n_markers, seed=seed, marker_colour=colour,
                          brim_colour="white" if colour == "white" else "model")
        take = generate_take(cfg)
        tr = take.truth
        e = tr.expression
        jaw = int(np.argmax(e[:, 0]))
        other = int(np.argmax(e[:, 1:7].max(axis=1)))
        frames = sorted({0, jaw, other})[:frames_per_take]
        mpol = -1 if colour == "black" else 1
        bpol = 1 if cfg.brim_colour == "white" else -1
        jpeg = 92 if seed % 2 else 0
        for f in frames:
            imgs = take.images(f)
            contrast = image_contrast(take, f, cameras)
            for c in cameras:
                img = jpeg_roundtrip(imgs[c], jpeg)
                H, W = img.shape
                d = truth_dots(tr, f, c, mpol, bpol, (H, W))
                xy, vis, part, rad, pol, brim = d.xy, d.visible, d.partly_hidden, d.radius, d.polarity, d.brim
                cut = d.cut
                faint = np.array([contrast[c][min(max(int(round(y)), 0), H - 1), min(max(int(round(x)), 0), W - 1)]
                                  < FAINT_CONTRAST for x, y in xy], bool)
                out.append(Case(img, xy, pol, vis & ~part & ~cut, vis & (part | cut), rad, brim,
                                {"set": "synth", "colour": colour, "markers": n_markers,
                                 "jaw_open": bool(e[f, 0] > 0.3), "jpeg": bool(jpeg)}, faint, d.grazing))
    return out


def image_contrast(take, frame: int, cameras) -> dict:
    """``{camera: float32 (H, W)}``: how much the dots change the image — the largest absolute
    difference, over the 3x3 neighbourhood, between the noise-free frame with and without
    its dots, both clipped to 0..255 as the camera clips them. A white dot on skin that is
    already clipped, or a black dot inside a black mouth, changes nothing."""
    cams = list(cameras)
    a = np.clip(take.render(frame, cams, noise=False, dots=True, as_float=True), 0, 255)
    b = np.clip(take.render(frame, cams, noise=False, dots=False, as_float=True), 0, 255)
    return {c: cv2.dilate(np.abs(a[i] - b[i]).astype(np.float32), np.ones((3, 3), np.uint8))
            for i, c in enumerate(cams)}


def match_case(case: Case, xy: np.ndarray, pol: np.ndarray) -> dict:
    """Per-case counts: tp, fn, fp, excluded detections, errors, brim tp/fn, partial dots and
    those with a detection more than 1.5 px off."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    r = defaultdict(int)
    r["errs"] = []
    for p in sorted(set(case.pol.tolist())):
        D = xy[pol == p]
        want = np.flatnonzero((case.pol == p) & case.must)
        matched = np.zeros(len(D), bool)
        found = np.zeros(len(want), bool)
        if len(D) and len(want):
            dist = np.linalg.norm(D[:, None] - case.xy[want][None], axis=2)
            dist[dist > MATCH_RADIUS] = 1e6
            i, j = linear_sum_assignment(dist)
            ok = dist[i, j] <= MATCH_RADIUS
            matched[i[ok]] = True
            found[j[ok]] = True
            r["errs"].extend(dist[i[ok], j[ok]].tolist())
        r["tp"] += int(found.sum())
        r["fn"] += int((~found).sum())
        r["brim_tp"] += int(found[case.brim[want]].sum())
        r["brim_fn"] += int((~found[case.brim[want]]).sum())
        r["faint"] += int(case.faint[want].sum())
        r["faint_tp"] += int(found[case.faint[want]].sum())
        part = np.flatnonzero((case.pol == p) & case.partial)
        graze = np.flatnonzero((case.pol == p) & case.grazing)
        if len(graze) and (~matched).any():
            rest_i = np.flatnonzero(~matched)
            dd = cKDTree(case.xy[graze]).query(D[rest_i])[0]
            on = rest_i[dd <= MATCH_RADIUS]
            matched[on] = True
            r["grazing_found"] += len(on)
        r["grazing"] += len(graze)
        rest = D[~matched]
        near = np.zeros(len(rest), bool)
        if len(part):
            if len(rest):
                dd, jj = cKDTree(case.xy[part]).query(rest)
                near = dd < case.rad[part][jj] + 2.0
            if len(D):
                dd, jj = cKDTree(D).query(case.xy[part])
                close = dd < case.rad[part] + 2.0
                r["partial"] += len(part)
                r["partial_off"] += int((close & (dd > MATCH_RADIUS)).sum())
            else:
                r["partial"] += len(part)
        r["excluded"] += int(near.sum())
        r["fp"] += int((~near).sum())
    return r


def summarise(rows: list[dict]) -> dict:
    tp = sum(r["tp"] for r in rows)
    fn = sum(r["fn"] for r in rows)
    fp = sum(r["fp"] for r in rows)
    e = np.asarray([x for r in rows for x in r["errs"]])
    out = {"frames": len(rows), "recall": round(tp / max(tp + fn, 1), 5), "precision": round(tp / max(tp + fp, 1), 5),
           "tp": tp, "fn": fn, "fp": fp, "excluded": sum(r["excluded"] for r in rows),
           "median_err_px": round(float(np.median(e)), 4) if len(e) else None,
           "p95_err_px": round(float(np.percentile(e, 95)), 4) if len(e) else None}
    btp = sum(r["brim_tp"] for r in rows)
    bfn = sum(r["brim_fn"] for r in rows)
    if btp + bfn:
        out["brim_recall"] = round(btp / (btp + bfn), 5)
    nf = sum(r["faint"] for r in rows)
    if nf:
        ftp = sum(r["faint_tp"] for r in rows)
        out["faint_dots"] = nf
        out["faint_found"] = ftp
        out["recall_not_faint"] = round((tp - ftp) / max(tp + fn - nf, 1), 5)
    if sum(r["grazing"] for r in rows):
        out["grazing_dots"] = sum(r["grazing"] for r in rows)
        out["grazing_found"] = sum(r["grazing_found"] for r in rows)
    npart = sum(r["partial"] for r in rows)
    if npart:
        out["partial_dots"] = npart
        out["partial_off_1.5px"] = round(sum(r["partial_off"] for r in rows) / npart, 4)
    return out


def run_ours(cases: list[Case]) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[float]]:
    times, out = [], []
    for case in cases:
        pols = sorted(set(case.pol.tolist()))
        p = BlobParameters(black_min_radius=R_MIN, black_max_radius=R_MAX, white_min_radius=R_MIN,
                           white_max_radius=R_MAX, find_black_blobs=-1 in pols, find_white_blobs=1 in pols)
        t = time.thread_time()
        d = detect_blobs(case.image, p)
        times.append((time.thread_time() - t) / len(pols))
        out.append((np.stack([d["x"], d["y"]], 1).astype(float), d["polarity"].astype(int)))
    return out, times


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


def run_sbd(cases: list[Case], setting: tuple) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[float]]:
    times, out = [], []
    for case in cases:
        pols = sorted(set(case.pol.tolist()))
        pts, pp = [], []
        t = time.thread_time()
        for pol in pols:
            det = sbd_params(*setting, colour=0 if pol < 0 else 255)
            k = det.detect(case.image)
            pts.extend(kp.pt for kp in k)
            pp.extend([pol] * len(k))
        times.append((time.thread_time() - t) / len(pols))
        out.append((np.asarray(pts, float).reshape(-1, 2), np.asarray(pp, int)))
    return out, times


def tune_sbd(cases: list[Case]) -> tuple:
    best, best_f1 = None, -1.0
    for setting in itertools.product((10, 30), (10, 20), (0.5, 0.7), (0.1, 0.3)):
        dets, _ = run_sbd(cases, setting)
        r = summarise([match_case(c, *d) for c, d in zip(cases, dets)])
        f1 = 2 * r["recall"] * r["precision"] / max(r["recall"] + r["precision"], 1e-9)
        if f1 > best_f1:
            best, best_f1 = setting, f1
    return best


def groups(cases: list[Case]) -> dict[str, list[int]]:
    """Indices of the cases in each reported condition."""
    g: dict[str, list[int]] = defaultdict(list)
    for i, c in enumerate(cases):
        t = c.tags
        if t["set"] == "synth":
            g["synth"].append(i)
            g[f"synth_{t['colour']}"].append(i)
            g[f"synth_{t['markers']}_markers"].append(i)
            if t["jaw_open"]:
                g["synth_jaw_open"].append(i)
            if t["jpeg"]:
                g["synth_jpeg"].append(i)
        else:
            g["rendered"].append(i)
            g[f"rendered_{t['kind']}"].append(i)
        g["all"].append(i)
    return g


def load_base(tree: str):
    """``detect_blobs`` of the checkout at ``tree``, imported as the package ``carapost_base``
    (its modules import each other relatively, so both versions live in one process)."""
    import importlib
    import importlib.util
    import tempfile

    from numba.core import config as numba_config

    pkg = Path(tree).resolve() / "carapost"
    spec = importlib.util.spec_from_file_location("carapost_base", pkg / "__init__.py",
                                                  submodule_search_locations=[str(pkg)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["carapost_base"] = mod
    # The base's kernels are cached apart: in the tree's own __pycache__ (numba's default)
    # they would be recorded under the module name carapost_base, and every later import of
    # that tree as carapost would fail loading them.
    saved = numba_config.CACHE_DIR
    numba_config.CACHE_DIR = str(Path(tempfile.gettempdir()) / "carapost_base_numba")
    try:
        spec.loader.exec_module(mod)
        return importlib.import_module("carapost_base.core.blobs").detect_blobs
    finally:
        numba_config.CACHE_DIR = saved


def table_difference(a: dict, b: dict) -> tuple[int, float, float]:
    """``(count difference, largest centre change (px), largest score change)`` between two
    detection tables, detections matched by polarity and nearest centre (within 1 px)."""
    from scipy.spatial import cKDTree

    dn, dxy, ds = abs(len(a["x"]) - len(b["x"])), 0.0, 0.0
    for p in (-1, 1):
        ia, ib = np.flatnonzero(a["polarity"] == p), np.flatnonzero(b["polarity"] == p)
        if not len(ia) or not len(ib):
            continue
        pa = np.stack([a["x"][ia], a["y"][ia]], 1).astype(float)
        pb = np.stack([b["x"][ib], b["y"][ib]], 1).astype(float)
        dd, jj = cKDTree(pb).query(pa)
        m = dd < 1.0
        if m.any():
            dxy = max(dxy, float(dd[m].max()))
            ds = max(ds, float(np.abs(a["score"][ia[m]].astype(float) - b["score"][ib[jj[m]]]).max()))
    return dn, dxy, ds


def compare(cases: list[Case], tree: str, repeat: int) -> dict:
    """This checkout's detector against the one at ``tree`` on the same images (one process)."""
    base = load_base(tree)
    runs = {"new": detect_blobs, "old": base}
    times = {k: [] for k in runs}
    found = {k: [] for k in runs}
    diffs = []
    for k in runs:                     # first calls: imports, compiled kernels' cache
        runs[k](cases[0].image, BlobParameters())
    for i, case in enumerate(cases):
        pols = sorted(set(case.pol.tolist()))
        p = BlobParameters(black_min_radius=R_MIN, black_max_radius=R_MAX, white_min_radius=R_MIN,
                           white_max_radius=R_MAX, find_black_blobs=-1 in pols, find_white_blobs=1 in pols)
        best = {k: np.inf for k in runs}
        tab = {}
        for _ in range(repeat):
            for k in (("new", "old") if i % 2 == 0 else ("old", "new")):
                t = time.thread_time()
                tab[k] = runs[k](case.image, p)
                best[k] = min(best[k], time.thread_time() - t)
        for k in runs:
            times[k].append(best[k])
            d = tab[k]
            found[k].append(match_case(case, np.stack([d["x"], d["y"]], 1).astype(float), d["polarity"].astype(int)))
        diffs.append(table_difference(tab["new"], tab["old"]))
    out = {"benchmark": "blobs_compare", "base": str(tree), "repeat": repeat}
    for name, idx in groups(cases).items():
        if "_" in name and name not in ("synth_black", "synth_white"):
            continue
        tn, to = np.asarray(times["new"])[idx], np.asarray(times["old"])[idx]
        sn, so = summarise([found["new"][i] for i in idx]), summarise([found["old"][i] for i in idx])
        out[name] = {"time_ratio_new_old": round(float(tn.sum() / to.sum()), 3),
                     "time_ratio_per_image": round(float(np.median(tn / to)), 3),
                     "new_ms": round(1e3 * float(np.median(tn)), 1), "old_ms": round(1e3 * float(np.median(to)), 1),
                     "new_missed_false": [sn["fn"], sn["fp"]], "old_missed_false": [so["fn"], so["fp"]],
                     "images_count_differs": int(sum(diffs[i][0] > 0 for i in idx)),
                     "max_centre_change_px": float(max(diffs[i][1] for i in idx)),
                     "max_score_change": float(max(diffs[i][2] for i in idx))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2, help="synthetic takes per (colour, marker count)")
    ap.add_argument("--frames", type=int, default=9, help="rendered frames")
    ap.add_argument("--seed", type=int, default=500)
    ap.add_argument("--cameras", type=int, default=4, help="cameras per synthetic frame")
    ap.add_argument("--compare", metavar="TREE", help="compare with the detector of another checkout")
    ap.add_argument("--repeat", type=int, default=1, help="runs per image with --compare (minimum CPU time)")
    ap.add_argument("--cache", metavar="FILE", help="pickle of the generated images (made if missing)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    import pickle

    if args.cache and Path(args.cache).exists():
        with open(args.cache, "rb") as fh:
            tuning, cases = pickle.load(fh)
    else:
        tuning = rendered_cases(3, args.seed + 1000) + synth_cases([args.seed + 1000], counts=(80,),
                                                                   frames_per_take=1, cameras=(0,))
        cases = synth_cases([args.seed + k for k in range(args.seeds)], cameras=tuple(range(args.cameras)))
        cases += rendered_cases(args.frames, args.seed)
        if args.cache:
            with open(args.cache, "wb") as fh:
                pickle.dump((tuning, cases), fh)
    if args.compare:
        print(json.dumps(compare(cases, args.compare, args.repeat)))
        return
    setting = tune_sbd(tuning)
    # Interleaved per image (alternating which goes first), so that the load of a shared
    # machine and warm caches fall on both detectors alike.
    ours, t_ours, sbd, t_sbd = [], [], [], []
    for i, case in enumerate(cases):
        for which in ((0, 1) if i % 2 == 0 else (1, 0)):
            if which == 0:
                d, t = run_ours([case])
                ours += d
                t_ours += t
            else:
                d, t = run_sbd([case], setting)
                sbd += d
                t_sbd += t
    m_ours = [match_case(c, *d) for c, d in zip(cases, ours)]
    m_sbd = [match_case(c, *d) for c, d in zip(cases, sbd)]
    result = {"benchmark": "blobs", "image": "1280x720", "match_radius_px": MATCH_RADIUS,
              "radius_range_px": [R_MIN, R_MAX],
              "sbd_setting": dict(zip(("minThreshold", "thresholdStep", "minCircularity", "minInertiaRatio"), setting))}
    for name, idx in groups(cases).items():
        mo, ms = float(np.median([t_ours[i] for i in idx])), float(np.median([t_sbd[i] for i in idx]))
        result[name] = {
            "ours": {**summarise([m_ours[i] for i in idx]), "per_core_ms": round(1e3 * mo, 1)},
            "opencv_sbd": {**summarise([m_sbd[i] for i in idx]), "per_core_ms": round(1e3 * ms, 1)},
            "time_ratio": round(mo / max(ms, 1e-9), 2),
            "time_ratio_per_image": round(float(np.median([t_ours[i] / max(t_sbd[i], 1e-9) for i in idx])), 2),
        }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
