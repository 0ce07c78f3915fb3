"""Fit the blob classifier's logistic coefficients on rendered frames with exact ground truth.

Renders frames of many kinds (black/white dots of 2-10 px, low light, JPEG, strong texture,
blur, occluding edges, merged pairs, saturated regions; ``tests/core/blob_images.py``) and
camera images of random synthetic takes (:mod:`carapost.synth`: faces with eyebrows, lips,
eyes, hair, a black background and the brim card), runs
the detector's candidate stage and fit (:func:`carapost.core.blobs.analyse_blobs`), labels every
fitted candidate and fits

* ``COEF`` (all features): positive = refined centre within ``POS_RADIUS`` px of the true
  centre of a dot of the same polarity (fully or partly visible); everything else negative
  (texture, occluder edges, biased centres of merged and partly occluded dots, poorly
  located fits);
* ``DENSE_COEF`` (``log_snr`` only, every candidate before fitting): positive = candidate pixel
  within ``max(1.5, r/2)`` of a visible dot centre.

by iteratively reweighted least squares with a small ridge. Prints the coefficients as Python
to paste into ``carapost/core/blob_score.py``, plus held-out log-loss and a reliability table
(predicted vs observed frequency), as one JSON line at the end.

Run: ``python benchmarks/fit_blob_score.py [--frames 80]``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "core"))
sys.path.insert(0, str(ROOT))

from blob_images import RenderConfig, render_frame  # noqa: E402

from carapost.core import blob_score  # noqa: E402
from carapost.core.blobs import analyse_blobs  # noqa: E402

POS_RADIUS = 0.5
MIN_RADIUS, MAX_RADIUS = 1.5, 20.0


def random_config(rng: np.random.Generator) -> RenderConfig:
    """A random rendering condition."""
    radius = [(2.0, 10.0), (2.0, 10.0), (2.0, 4.0), (4.0, 10.0)][rng.integers(4)]
    return RenderConfig(
        n_dots=int(rng.integers(60, 180)),
        radius=radius,
        polarity=["black", "white", "both"][rng.integers(3)],
        texture=float(rng.uniform(0.03, 0.16)),
        shading=float(rng.uniform(0.1, 0.9)),
        blur=(0.4, 0.8) if rng.random() < 0.6 else (0.8, 1.5),
        read_noise=float(rng.uniform(1.0, 3.0)),
        jpeg_quality=[None, None, 90, 75][rng.integers(4)],
        low_light=[1.0, 1.0, 0.5, 0.25, 0.12][rng.integers(5)],
        occluders=int(rng.integers(0, 5)),
        merged_pairs=int(rng.choice([0, 6, 12])),
        saturated_region=bool(rng.random() < 0.25),
        min_gap=float(rng.uniform(2.0, 8.0)),
    )


def synth_images(n_images: int, seed: int):
    """Yield ``(image, truth_xy (K, 2), polarity (K,), radius (K,))`` from random synthetic takes
    (:mod:`carapost.synth`): face markers and brim dots that are visible (centre unoccluded),
    with their area centroids as the true centres."""
    from carapost.synth import SynthConfig, generate_take

    rng = np.random.default_rng(seed)
    done = 0
    while done < n_images:
        cfg = SynthConfig(n_frames=2, n_markers=int(rng.choice([35, 80, 156])),
                          seed=int(rng.integers(1 << 30)),
                          marker_colour=str(rng.choice(["black", "white"])),
                          marker_radius_mm=float(rng.uniform(1.0, 2.5)),
                          blur_sigma=float(rng.uniform(0.4, 1.2)),
                          read_noise=float(rng.uniform(0.8, 3.0)),
                          vignetting=float(rng.uniform(0.0, 0.5)),
                          exposure=float(rng.uniform(120.0, 320.0)),
                          high_motion=bool(rng.random() < 0.3))
        take = generate_take(cfg)
        tr = take.truth
        mpol = -1 if cfg.marker_colour == "black" else 1
        for f in range(take.n_frames):
            for c in range(take.n_cameras):
                if done >= n_images:
                    return
                mk = tr.visible[f, :, c] & np.isfinite(tr.centroid_xy[f, :, c, 0])
                br = tr.brim_visible[f, :, c] & np.isfinite(tr.brim_centroid_xy[f, :, c, 0])
                xy = np.concatenate([tr.centroid_xy[f, mk, c], tr.brim_centroid_xy[f, br, c]])
                pol = np.concatenate([np.full(mk.sum(), mpol), np.full(br.sum(), -1)])
                rad = np.concatenate([tr.radius_px[f, mk, c], tr.brim_radius_px[f, br, c]])
                yield take.image(f, c), xy, pol.astype(np.int8), rad
                done += 1


def rendered_images(n_frames: int, seed: int):
    """Yield ``(image, xy, polarity, radius, seen, visible)`` from ``tests/core/blob_images.py``."""
    rng = np.random.default_rng(seed)
    for _ in range(n_frames):
        fr = render_frame(random_config(rng), seed=int(rng.integers(1 << 30)))
        yield (fr.image, fr.xy, fr.polarity, fr.axes[:, 0], fr.clean | fr.partial, fr.visible_frac > 0.5)


def collect(n_frames: int, seed: int, n_synth: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Features/labels of fitted candidates and (log_snr, label) of all candidates."""
    from scipy.spatial import cKDTree

    def sources():
        yield from rendered_images(n_frames, seed)
        for img, xy, pol, rad in synth_images(n_synth, seed + 7):
            ones = np.ones(len(xy), bool)
            yield img, xy, pol, rad, ones, ones

    X, y, Xd, yd = [], [], [], []
    for f, (image, xy_all, pol_all, rad_all, seen_all, vis_all) in enumerate(sources()):
        for pol in (-1, 1):
            if not (pol_all == pol).any():
                continue
            an = analyse_blobs(image, pol, min_radius=MIN_RADIUS, max_radius=MAX_RADIUS)
            same = pol_all == pol
            seen = seen_all & same
            visible = vis_all & same
            # Fitted candidates.
            sel = np.flatnonzero(an.ok)
            lab = np.zeros(len(sel), bool)
            if seen.any() and len(sel):
                d, _ = cKDTree(xy_all[seen]).query(np.stack([an.x[sel], an.y[sel]], 1))
                lab = d < POS_RADIUS
            X.append(an.features[sel])
            y.append(lab)
            # All candidates, dense model.
            labd = np.zeros(len(an.snr), bool)
            if visible.any() and len(an.snr):
                d, j = cKDTree(xy_all[visible]).query(np.stack([an.cand_x, an.cand_y], 1))
                labd = d < np.maximum(1.5, 0.5 * rad_all[visible][j])
            Xd.append(np.log(np.clip(an.snr, 1e-3, None)))
            yd.append(labd)
        print(f"image {f + 1}/{n_frames + n_synth}", file=sys.stderr, end="\r")
    print(file=sys.stderr)
    return np.concatenate(X), np.concatenate(y), np.concatenate(Xd), np.concatenate(yd)


def fit_logistic(X: np.ndarray, y: np.ndarray, ridge: float = 1e-3, iters: int = 50) -> np.ndarray:
    """IRLS logistic regression (first column is the bias, not penalised)."""
    w = np.zeros(X.shape[1])
    pen = np.full(X.shape[1], ridge * len(y))
    pen[0] = 0.0
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-(X @ w)))
        g = X.T @ (p - y) + pen * w
        H = (X * (p * (1 - p))[:, None]).T @ X + np.diag(pen) + 1e-9 * np.eye(X.shape[1])
        step = np.linalg.solve(H, g)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return w


def log_loss(p: np.ndarray, y: np.ndarray) -> float:
    p = np.clip(p, 1e-9, 1 - 1e-9)
    return float(-np.mean(y * np.log(p) + (1 - y) * np.log(1 - p)))


def reliability(p: np.ndarray, y: np.ndarray) -> list[tuple[float, float, int]]:
    """(mean predicted, observed frequency, count) per probability decile."""
    edges = np.linspace(0, 1, 11)
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (p >= a) & (p < b) if b < 1 else (p >= a)
        if m.any():
            out.append((round(float(p[m].mean()), 3), round(float(y[m].mean()), 3), int(m.sum())))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--synth", type=int, default=80, help="camera images from carapost.synth takes")
    ap.add_argument("--seed", type=int, default=1234)
    args = ap.parse_args()
    X, y, Xd, yd = collect(args.frames, args.seed, args.synth)
    Xv, yv, Xdv, ydv = collect(max(args.frames // 4, 5), args.seed + 1, max(args.synth // 4, 4))
    coef = fit_logistic(X, y.astype(float))
    Dd = np.stack([np.ones_like(Xd), Xd], 1)
    dcoef = fit_logistic(Dd, yd.astype(float))
    pv = blob_score.probability(Xv, coef)
    pdv = blob_score.dense_probability(np.exp(Xdv), dcoef)
    print("COEF: np.ndarray = np.array([" + ", ".join(f"{c:.4f}" for c in coef) + "])")
    print("DENSE_COEF: np.ndarray = np.array([" + ", ".join(f"{c:.4f}" for c in dcoef) + "])")
    print(json.dumps({
        "features": list(blob_score.FEATURES), "coef": [round(float(c), 4) for c in coef],
        "dense_coef": [round(float(c), 4) for c in dcoef],
        "train": {"n": int(len(y)), "positives": int(y.sum())},
        "validation": {"n": int(len(yv)), "positives": int(yv.sum()), "log_loss": log_loss(pv, yv),
                       "log_loss_current": log_loss(blob_score.probability(Xv), yv),
                       "reliability": reliability(pv, yv),
                       "dense_log_loss": log_loss(pdv.astype(float), ydv),
                       "dense_reliability": reliability(pdv.astype(float), ydv)},
    }))


if __name__ == "__main__":
    main()
