"""Accuracy of a processed take against a synthetic take's ground truth.

Used by ``carapost demo``, the accuracy tests and the benchmarks. Every truth dot (face marker
or brim dot) seen by a camera is a target; a detection within ``match_px`` of its image centre
is that dot's. A point of the take is identified with the marker most of its attached
detections belong to; any other attached detection is a *mismatch*.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from carapost.model.detections import Detections
from carapost.model.take import PointKind, Take

from .take import GroundTruth

__all__ = ["DetectionScore", "score_detections", "detection_identities", "grazing_dots", "PointScore", "score_points"]


@dataclass(frozen=True)
class DetectionScore:
    recall: float               #: visible dots found / visible dots
    precision: float            #: detections on a dot / detections
    median_error_px: float
    p95_error_px: float
    n_truth: int
    n_detections: int
    n_matched: int

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def grazing_dots(truth: GroundTruth, f: int, c: int) -> np.ndarray:
    """bool (M,): markers drawn in camera ``c`` at frame ``f`` that ``visible`` leaves out
    because they are seen beyond :data:`~carapost.synth.take.MAX_VIEW_ANGLE_DEG` (but within
    90 degrees, not behind a blink). Their image is a thin ellipse a detector may
    legitimately find; occlusion is not tested for them (the generator does not)."""
    out = (~truth.visible[f, :, c] & ~truth.occluded[f, :, c] & np.isfinite(truth.centroid_xy[f, :, c]).all(-1)
           & (truth.view_angle_deg[f, :, c] < 90))
    if len(truth.blink_frames) and truth.blink_frames[f]:
        out[truth.eyelid_indices] = False
    return out


def _truth_dots(truth: GroundTruth, f: int, c: int, *, include_partly_hidden: bool,
                imaged: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Image centroids (n, 2) and ids (n,) of the dots visible in camera c, frame f.

    Face markers have ids 0..M-1, brim dots M..M+B-1. With ``imaged``, also dots whose image
    exists but that ``visible`` leaves out (seen at a grazing angle beyond the generator's
    visibility limit): a detector may legitimately find them.
    """
    vis = truth.visible[f, :, c].copy()
    if imaged:
        vis |= grazing_dots(truth, f, c)
    if not include_partly_hidden:
        vis &= ~truth.partly_hidden[f, :, c]
    bvis = truth.brim_visible[f, :, c]
    xy = np.concatenate([truth.centroid_xy[f, vis, c], truth.brim_centroid_xy[f, bvis, c]])
    ids = np.concatenate([np.flatnonzero(vis), len(truth.names) + np.flatnonzero(bvis)])
    return xy, ids


def detection_identities(dets: Sequence[Detections], truth: GroundTruth, frames: Sequence[int], *,
                         match_px: float = 3.0) -> dict[tuple[int, int], np.ndarray]:
    """``{(frame, camera): ids}``: the nearest imaged truth dot of every detection (-1 = none
    within ``match_px``; such a detection is spurious: a pupil, a lash line, noise)."""
    out = {}
    for c, det in enumerate(dets):
        for f in frames:
            xy = det.xy(f)
            txy, tid = _truth_dots(truth, f, c, include_partly_hidden=True, imaged=True)
            ids = np.full(len(xy), -1, np.int64)
            if len(xy) and len(txy):
                d, j = cKDTree(txy).query(xy)
                ids = np.where(d <= match_px, tid[j], -1)
            out[(f, c)] = ids
    return out


def score_detections(dets: Sequence[Detections], truth: GroundTruth, frames: Sequence[int], *,
                     match_px: float = 1.5) -> DetectionScore:
    """Recall, precision and centre error of detections against the visible dots.

    Dots partly hidden by an occluding edge are left out of the recall denominator (their
    image is cut, so any centre is biased), and detections on them are neither true nor false.
    """
    errs, n_truth, n_det, n_match, n_neutral = [], 0, 0, 0, 0
    for c, det in enumerate(dets):
        for f in frames:
            xy = det.xy(f)
            full_xy, _ = _truth_dots(truth, f, c, include_partly_hidden=False)
            all_xy, _ = _truth_dots(truth, f, c, include_partly_hidden=True)
            n_truth += len(full_xy)
            n_det += len(xy)
            if not len(xy):
                continue
            if len(full_xy):
                d, j = cKDTree(xy).query(full_xy)
                ok = d <= match_px
                # one detection per dot: count unique detections
                n_match += len(np.unique(j[ok]))
                errs.append(d[ok])
            if len(all_xy) > len(full_xy):
                d_all, _ = cKDTree(all_xy).query(xy)
                d_full = cKDTree(full_xy).query(xy)[0] if len(full_xy) else np.full(len(xy), np.inf)
                n_neutral += int(np.sum((d_all <= match_px) & (d_full > match_px)))
    e = np.concatenate(errs) if errs else np.zeros(0)
    denom = max(n_det - n_neutral, 1)
    return DetectionScore(recall=n_match / max(n_truth, 1), precision=min(1.0, n_match / denom),
                          median_error_px=float(np.median(e)) if len(e) else float("nan"),
                          p95_error_px=float(np.percentile(e, 95)) if len(e) else float("nan"),
                          n_truth=n_truth, n_detections=n_det, n_matched=n_match)


@dataclass(frozen=True)
class PointScore:
    marker: np.ndarray          #: (P,) truth id of each take point (-1 unidentified); brim ids offset by M
    n_points: int
    mismatched_observations: int
    coverage: float             #: marker-frames with >= 2 visible cameras that the take has in 3D
    median_error_mm: float
    p95_error_mm: float
    swaps: int                  #: points whose identity changes over the take

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items() if k != "marker"}


def score_points(take: Take, truth: GroundTruth, frames: Sequence[int] | None = None, *,
                 match_px: float = 3.0) -> PointScore:
    """Identify the take's face points with truth markers and measure coverage and 3D error.

    An attached detection is *mismatched* when it is the image of another marker than the
    point's; a detection on no marker (spurious) on a point that has a marker counts too.
    """
    frames = list(range(take.n_frames)) if frames is None else list(frames)
    M = len(truth.names)
    ids = detection_identities(take.detections, truth, frames, match_px=match_px)
    P = take.n_points
    votes: list[dict[int, int]] = [dict() for _ in range(P)]
    per_frame_id = np.full((len(frames), P), -1, np.int64)
    for k, f in enumerate(frames):
        for c in range(take.n_cameras):
            od = take.obs_det[f, :, c]
            for p in np.flatnonzero(od >= 0):
                tid = int(ids[(f, c)][od[p]])
                votes[p][tid] = votes[p].get(tid, 0) + 1
        # identity per frame = majority over this frame's cameras
        for p in range(P):
            fr = [int(ids[(f, c)][take.obs_det[f, p, c]]) for c in range(take.n_cameras) if take.obs_det[f, p, c] >= 0]
            fr = [i for i in fr if i >= 0]
            if fr:
                per_frame_id[k, p] = max(set(fr), key=fr.count)
    marker = np.array([max(v, key=v.get) if v and max(v, key=v.get) >= 0 else -1 for v in votes], np.int64)
    mismatched = sum(n for p in range(P) for tid, n in votes[p].items() if tid != marker[p])
    face = (take.points.kind == PointKind.FACE) & (marker >= 0) & (marker < M)
    errs = []
    covered = np.zeros((len(frames), M), bool)
    for p in np.flatnonzero(face):
        m = marker[p]
        X = take.xyz[frames, p]
        ok = np.isfinite(X).all(-1)
        errs.append(np.linalg.norm(X[ok] - truth.xyz[np.asarray(frames)[ok], m], axis=-1))
        covered[ok, m] = True
    seen2 = truth.visible[frames].sum(-1) >= 2
    coverage = float((covered & seen2).sum() / max(seen2.sum(), 1))
    e = np.concatenate(errs) if errs else np.zeros(0)
    swaps = int(sum(len({i for i in per_frame_id[:, p] if i >= 0}) > 1 for p in range(P)))
    return PointScore(marker=marker, n_points=P, mismatched_observations=int(mismatched), coverage=coverage,
                      median_error_mm=float(np.median(e)) if len(e) else float("nan"),
                      p95_error_mm=float(np.percentile(e, 95)) if len(e) else float("nan"), swaps=swaps)
