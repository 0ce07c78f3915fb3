"""Synthetic 3D-initialization cases with ground truth, and scoring (shared by tests and benchmark).

A *case* is one frame of a synthetic take as Initialize 3D sees it: per-camera detections
(either the truth projections with noise, dropped detections and clutter, or the project's
blob detector run on the rendered images), the label of every detection (marker index, brim
dot or clutter), the nominal calibration (the ``.xcp`` poses, without the per-frame flex), the
seeds of ``carapost.synth.seeds_for`` snapped to the detections, and the brim model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from carapost.core.camera import Intrinsics
from carapost.io.seeds import snap_seeds
from carapost.model.params import Initialize3DParameters, Parameters, dense_156_preset, sparse_35_preset
from carapost.synth import SynthConfig, generate_take
from carapost.synth.seeds import seeds_for

CLUTTER = -1
#: Brim dot ``b`` is labelled ``BRIM - b``.
BRIM = -1000


def preset_for(n_markers: int) -> Initialize3DParameters:
    """The guide's Initialize 3D settings for a marker set (sparse 35, default 80, dense 156)."""
    p = {35: sparse_35_preset, 156: dense_156_preset}.get(n_markers, lambda: Parameters())()
    return p.init3d


@dataclass
class Case:
    synth: object
    frame: int
    dets: list[np.ndarray]
    labels: list[np.ndarray]
    intrinsics: list[Intrinsics]
    R: np.ndarray
    t: np.ndarray
    seeds: list[dict[int, int]]
    seed_names: list[str | None]
    brim_xyz: np.ndarray
    params: Initialize3DParameters
    info: dict = field(default_factory=dict)

    @property
    def truth(self):
        return self.synth.truth


def _take(n_markers: int, seed: int = 0, n_frames: int = 1, **kw):
    return generate_take(SynthConfig(n_markers=n_markers, n_frames=n_frames, seed=seed, **kw))


def _finish(synth, frame, dets, labels, seeds_dict, info) -> Case:
    tr = synth.truth
    snapped = snap_seeds(seeds_dict, dets, radius_px=3.0)
    info = dict(info, seed_messages=snapped.messages)
    return Case(synth=synth, frame=frame, dets=dets, labels=labels, intrinsics=list(tr.intrinsics),
                R=tr.nominal_R.copy(), t=tr.nominal_t.copy(), seeds=snapped.face_seeds,
                seed_names=snapped.face_names, brim_xyz=tr.brim_xyz.copy(),
                params=preset_for(synth.config.n_markers), info=info)


def truth_case(n_markers: int, *, noise_px: float = 0.15, drop: float = 0.1, clutter: int = 4,
               seed: int = 0, synth=None, frame: int = 0) -> Case:
    """Detections = visible truth projections (markers and brim) + Gaussian noise, with a
    fraction ``drop`` missing and ``clutter`` false detections per camera on the face (10-40 px
    from a marker, at least 8 px from every dot: skin features the detector mistakes for dots).

    The defaults mimic the project's blob detector on rendered frames (about 0.1 px error,
    10-25 % of the visible markers missed, a few false detections per camera)."""
    synth = _take(n_markers, seed) if synth is None else synth
    tr = synth.truth
    rng = np.random.default_rng(1000 + 7919 * seed + frame)
    W, H = tr.image_size
    dets, labels = [], []
    for c in range(tr.n_cameras):
        m = np.flatnonzero(tr.visible[frame, :, c])
        b = np.flatnonzero(tr.brim_visible[frame, :, c])
        xy = np.concatenate([tr.xy[frame, m, c], tr.brim_xy[frame, b, c]])
        lab = np.concatenate([m, BRIM - b])
        keep = rng.random(len(xy)) >= drop
        xy, lab = xy[keep], lab[keep]
        xy = xy + rng.normal(0.0, noise_px, xy.shape)
        # clutter at least 8 px from every real dot
        real = np.concatenate([tr.xy[frame, :, c], tr.brim_xy[frame, :, c]])
        real = real[np.isfinite(real).all(1)]
        base = tr.xy[frame, m, c]
        k = rng.integers(0, max(len(base), 1), clutter * 4)
        ang = rng.uniform(0, 2 * np.pi, len(k))
        rad = rng.uniform(10, 40, len(k))
        cl = base[k] + np.stack([np.cos(ang), np.sin(ang)], 1) * rad[:, None] if len(base) else np.zeros((0, 2))
        inside = (cl[:, 0] >= 0) & (cl[:, 0] <= W - 1) & (cl[:, 1] >= 0) & (cl[:, 1] <= H - 1)
        cl = cl[inside]
        d, _ = cKDTree(real).query(cl)
        cl = cl[d > 8][:clutter]
        xy = np.concatenate([xy, cl])
        lab = np.concatenate([lab, np.full(len(cl), CLUTTER)])
        order = rng.permutation(len(xy))
        dets.append(xy[order])
        labels.append(lab[order])
    seeds_dict = seeds_for(synth, frame)
    return _finish(synth, frame, dets, labels, seeds_dict,
                   {"kind": "truth", "noise_px": noise_px, "drop": drop, "clutter": clutter})


def label_detections(synth, frame: int, dets: list[np.ndarray], *, radius: float = 3.0) -> list[np.ndarray]:
    """Label detector output by the nearest true dot centroid (marker or brim) within ``radius`` px.

    3 px: the detector's centre of a dot cut by the eyelid or the brow can be 2 px off, and
    dots are more than 8 px apart in the images."""
    tr = synth.truth
    out = []
    for c, xy in enumerate(dets):
        ref = np.concatenate([tr.centroid_xy[frame, :, c], tr.brim_centroid_xy[frame, :, c]])
        lab = np.concatenate([np.arange(len(tr.names)), BRIM - np.arange(len(tr.brim_xyz))])
        ok = np.isfinite(ref).all(1)  # a dot seen more obliquely than "visible" may still be detected
        ref, lab = ref[ok], lab[ok]
        labels = np.full(len(xy), CLUTTER, np.int64)
        if len(xy) and len(ref):
            d, j = cKDTree(ref).query(xy)
            labels[d <= radius] = lab[j[d <= radius]]
        out.append(labels)
    return out


def detector_case(n_markers: int, *, seed: int = 0, synth=None, frame: int = 0, blob_params=None) -> Case:
    """Detections from the project's blob detector on the rendered images of the frame."""
    from carapost.core.blobs import detect_blobs
    from carapost.model.params import BlobParameters

    synth = _take(n_markers, seed) if synth is None else synth
    bp = BlobParameters() if blob_params is None else blob_params
    imgs = synth.images(frame)
    dets = []
    for c in range(synth.n_cameras):
        d = detect_blobs(imgs[c], bp)
        dets.append(np.stack([np.asarray(d["x"], float), np.asarray(d["y"], float)], axis=1))
    labels = label_detections(synth, frame, dets)
    seeds_dict = seeds_for(synth, frame)
    return _finish(synth, frame, dets, labels, seeds_dict, {"kind": "detector"})


def score(case: Case, res) -> dict:
    """Coverage, mismatches and 3D error of an :class:`~carapost.core.init3d.Init3DResult`.

    * ``target``: markers visible in at least two cameras (truth); ``detectable``: markers
      with a (correctly labelled) detection in at least two cameras.
    * A point's marker is the most common marker label among its attached detections; every
      attached detection with another label (another marker, a brim dot, clutter) is a
      *mismatch*. A point with no marker detection at all is *spurious* (counted apart: with
      the real detector these are consistent non-marker features such as a pupil).
    * ``duplicates``: extra points of a marker that already has one.
    """
    tr = case.truth
    f = case.frame
    M = len(tr.names)
    target = tr.visible[f].sum(axis=1) >= 2
    has = np.zeros((M, len(case.labels)), bool)
    for c, lab in enumerate(case.labels):
        has[np.unique(lab[lab >= 0]), c] = True
    detectable = has.sum(axis=1) >= 2
    caddy_detectable = (has[:, 0] & has[:, 1]) | (has[:, 2] & has[:, 3]) if has.shape[1] >= 4 else detectable
    P, C = res.det_index.shape
    point_label = np.full(P, CLUTTER, np.int64)
    mismatched = 0
    bad_points = 0
    spurious = 0
    for p in range(P):
        labs = np.array([case.labels[c][res.det_index[p, c]] for c in range(C) if res.det_index[p, c] >= 0])
        marker = labs[labs >= 0]
        if len(marker) == 0:  # no marker at all: a consistent non-marker feature (or clutter)
            spurious += 1
            continue
        vals, counts = np.unique(marker, return_counts=True)
        best = int(vals[np.argmax(counts)])
        point_label[p] = best
        wrong = int((labs != best).sum())
        mismatched += wrong
        bad_points += wrong > 0
    good = point_label >= 0
    found = np.zeros(M, bool)
    found[point_label[good]] = True
    n_pts_per = np.bincount(point_label[good], minlength=M)
    err = np.linalg.norm(res.xyz[good] - tr.xyz[f, point_label[good]], axis=1) if good.any() else np.zeros(0)
    aligned = _rigid_residuals(res.xyz[good], tr.xyz[f, point_label[good]]) if good.sum() >= 3 else err
    return {
        "markers": M,
        "target": int(target.sum()),
        "detectable": int(detectable.sum()),
        "initialized": int((found & target).sum()),
        "coverage": float((found & target).sum() / max(target.sum(), 1)),
        "coverage_detectable": float((found & detectable).sum() / max(detectable.sum(), 1)),
        "caddy_detectable": int(caddy_detectable.sum()),
        "coverage_caddy": float((found & caddy_detectable).sum() / max(caddy_detectable.sum(), 1)),
        "points": int(P),
        "views": int((res.det_index >= 0).sum()),
        "mismatched_detections": int(mismatched),
        "mismatched_points": int(bad_points),
        "spurious_points": int(spurious),
        "duplicates": int(np.maximum(n_pts_per - 1, 0).sum()),
        "median_err_mm": float(np.median(err)) if len(err) else float("nan"),
        "p95_err_mm": float(np.percentile(err, 95)) if len(err) else float("nan"),
        "max_err_mm": float(err.max()) if len(err) else float("nan"),
        # after the best rigid motion: the shape error, without the uncertainty of the brim's frame
        "median_err_aligned_mm": float(np.median(aligned)) if len(aligned) else float("nan"),
    }


def _rigid_residuals(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances between ``b`` and ``a`` moved onto it by the best rigid motion (Kabsch)."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    Rm = Vt.T @ D @ U.T
    return np.linalg.norm((a - ca) @ Rm.T + cb - b, axis=1)
