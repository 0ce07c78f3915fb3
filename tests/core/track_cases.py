"""Synthetic tracking cases with ground truth (shared by the tracking tests and the benchmark).

A case is a :class:`~carapost.model.take.Take` built from a synthetic take:

* detections either from the truth (every visible dot's image centroid plus Gaussian noise,
  with clutter detections scattered over the face) — to measure the tracker alone — or from
  the project's blob detector run on the rendered images;
* the start frame initialised from the truth (what a perfect Initialize 3D gives): one point
  per face marker at its true position with the detections of the cameras that see it
  attached, and one brim point per brim dot attached to its detections;
* the start frame's camera poses solved (the true poses), every other frame holding the
  nominal calibration (the tracker must re-estimate the flex from the brim).

:func:`evaluate` scores a tracked take against the truth using the identity of every
detection (marker, brim dot or clutter), so a swap or a mismatch is counted exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from carapost.model.detections import Detections
from carapost.model.take import CameraInfo, ObsSource, PointKind, Recon, Take

CLUTTER = -1


@dataclass
class TrackCase:
    synth: object
    take: Take
    labels: list[dict[int, np.ndarray]]  #: per camera: {frame: label of each detection}
    start: int

    @property
    def truth(self):
        return self.synth.truth


def truth_detections(truth, frames, *, noise_px: float = 0.05, clutter: int = 15, seed: int = 0,
                     brim_polarity: np.ndarray | None = None, marker_polarity: int = -1
                     ) -> tuple[list[dict[int, dict]], list[dict[int, np.ndarray]]]:
    """Detection tables from the truth: ``([{frame: table}] per camera, [{frame: labels}])``.

    Labels: marker ``m`` -> ``m``, brim dot ``b`` -> ``M + b``, clutter -> -1.
    """
    rng = np.random.default_rng(seed)
    F, M, C = truth.visible.shape
    B = len(truth.brim_xyz)
    bpol = np.full(B, -1, np.int8) if brim_polarity is None else np.asarray(brim_polarity, np.int8)
    W, H = truth.image_size
    tables: list[dict[int, dict]] = [dict() for _ in range(C)]
    labels: list[dict[int, np.ndarray]] = [dict() for _ in range(C)]
    for f in frames:
        for c in range(C):
            vis = np.flatnonzero(truth.visible[f, :, c])
            bvis = np.flatnonzero(truth.brim_visible[f, :, c])
            xy = np.concatenate([truth.centroid_xy[f, vis, c], truth.brim_centroid_xy[f, bvis, c]])
            rad = np.concatenate([truth.radius_px[f, vis, c], truth.brim_radius_px[f, bvis, c]])
            ang = np.concatenate([truth.view_angle_deg[f, vis, c], np.full(len(bvis), 30.0)])
            pol = np.concatenate([np.full(len(vis), marker_polarity, np.int8), bpol[bvis]])
            lab = np.concatenate([vis, M + bvis])
            xy = xy + rng.normal(0.0, noise_px, xy.shape)
            if clutter and len(vis):
                lo = truth.centroid_xy[f, vis, c].min(0) - 20
                hi = truth.centroid_xy[f, vis, c].max(0) + 20
                cxy = rng.uniform(lo, hi, (clutter, 2))
                # keep clutter off the dots themselves (a detector reports one blob per dot)
                d, _ = cKDTree(xy).query(cxy)
                cxy = cxy[d > 6.0]
                xy = np.concatenate([xy, cxy])
                rad = np.concatenate([rad, rng.uniform(2.0, 8.0, len(cxy))])
                ang = np.concatenate([ang, rng.uniform(0, 60, len(cxy))])
                pol = np.concatenate([pol, np.full(len(cxy), marker_polarity, np.int8)])
                lab = np.concatenate([lab, np.full(len(cxy), CLUTTER)])
            inside = (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] <= W - 1) & (xy[:, 1] <= H - 1)
            order = rng.permutation(np.flatnonzero(inside))
            minor = rad * np.clip(np.cos(np.radians(ang)), 0.3, 1.0)
            tables[c][f] = {"x": xy[order, 0], "y": xy[order, 1], "major": rad[order], "minor": minor[order],
                            "angle": np.zeros(len(order)), "polarity": pol[order], "score": np.ones(len(order))}
            labels[c][f] = lab[order]
    return tables, labels


def label_detections(truth, dets: list[Detections], frames, *, match_px: float = 1.5) -> list[dict[int, np.ndarray]]:
    """Labels of real detections: the truth dot within ``match_px`` of each (-1 = clutter)."""
    F, M, C = truth.visible.shape
    out: list[dict[int, np.ndarray]] = [dict() for _ in range(C)]
    for c in range(C):
        for f in frames:
            xy = dets[c].xy(f)
            txy = np.concatenate([truth.centroid_xy[f, :, c], truth.brim_centroid_xy[f, :, c]])
            seen = np.concatenate([truth.visible[f, :, c], truth.brim_visible[f, :, c]])
            lab = np.full(len(xy), CLUTTER, np.int64)
            ids = np.flatnonzero(seen)
            if len(xy) and len(ids):
                d, j = cKDTree(txy[ids]).query(xy)
                lab = np.where(d <= match_px, ids[j], CLUTTER)
            out[c][f] = lab
    return out


def build_take(synth, tables: list[dict[int, dict]], labels: list[dict[int, np.ndarray]], *, start: int = 0,
               nominal_poses: bool = True) -> Take:
    """A take with the given detections, initialised from the truth at ``start``."""
    tr = synth.truth
    F, M, C = tr.visible.shape
    B = len(tr.brim_xyz)
    W, H = tr.image_size
    cams = [CameraInfo(f"cam{c}", c, tr.intrinsics[c], (W, H)) for c in range(C)]
    if nominal_poses:
        take = Take.new(cams, F, tr.frame_rate, R=tr.nominal_R, t=tr.nominal_t)
        take.R[start], take.t[start] = tr.R[start], tr.t[start]
    else:
        take = Take.new(cams, F, tr.frame_rate, R=tr.R, t=tr.t)
    for c in range(C):
        take.detections[c] = take.detections[c].with_frames(tables[c])
    take.brim = synth.brim
    face = take.add_points(M, labels=list(tr.names))
    brim = take.add_points(B, kind=PointKind.BRIM, brim_index=np.arange(B))
    take.xyz[start, face] = tr.xyz[start]
    take.xyz[start, brim] = tr.brim_xyz
    for c in range(C):
        lab = labels[c][start]
        xy = take.detections[c].xy(start)
        for i, m in enumerate(lab):
            if m < 0:
                continue
            col = face[m] if m < M else brim[m - M]
            take.obs_det[start, col, c] = i
            take.obs_xy[start, col, c] = xy[i]
            take.obs_src[start, col, c] = ObsSource.BLOB
    nv = take.n_views()[start]
    take.recon[start] = np.where(nv >= 2, Recon.MULTI_VIEW, np.where(nv == 1, Recon.SINGLE_SENSOR,
                                                                     Recon.INTERPOLATED))
    return take


def truth_case(config, *, start: int = 0, noise_px: float = 0.05, clutter: int = 15, seed: int = 0) -> TrackCase:
    from carapost.synth import generate_take

    synth = generate_take(config)
    tr = synth.truth
    tables, labels = truth_detections(tr, range(tr.n_frames), noise_px=noise_px, clutter=clutter, seed=seed,
                                      brim_polarity=synth.brim.polarity,
                                      marker_polarity=-1 if config.marker_colour == "black" else 1)
    return TrackCase(synth, build_take(synth, tables, labels, start=start), labels, start)


@dataclass
class Score:
    coverage: float          #: marker-frames seen by >= 2 cameras that have a 3D position
    swapped_points: int      #: points holding another marker's detections in some frame
    wrong_frames: int        #: point-frames whose observations mostly belong to another dot
    mismatched_obs: int      #: observations on another dot or on clutter
    median_mm: float
    p95_mm: float
    max_mm: float
    n_frames: int
    brim_obs: int
    patch_obs: int

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else int(v)) for k, v in self.__dict__.items()}


def evaluate(take: Take, truth, labels: list[dict[int, np.ndarray]], frames) -> Score:
    """Score the tracked ``frames`` of a take built by :func:`build_take` (point ``i < M`` is
    marker ``i``; brim point ``M + b`` is brim dot ``b``)."""
    frames = np.asarray(list(frames))
    F, M, C = truth.visible.shape
    P = take.n_points
    own = np.arange(P)                                   # label each point should carry
    wrong = np.zeros((len(frames), P), np.int64)
    right = np.zeros((len(frames), P), np.int64)
    for k, f in enumerate(frames):
        for c in range(C):
            od = take.obs_det[f, :, c]
            has = od >= 0
            lab = labels[c][f]
            got = np.full(P, -2)
            got[has] = lab[od[has]]
            blob = has
            right[k] += blob & (got == own)
            wrong[k] += blob & (got != own)
    face = own < M
    xyz = take.xyz[frames][:, face]
    known = np.isfinite(xyz).all(-1)
    seen2 = truth.visible[frames].sum(-1) >= 2
    coverage = float((known & seen2).sum() / max(seen2.sum(), 1))
    err = np.linalg.norm(xyz - truth.xyz[frames], axis=-1)[known]
    wrong_frames = int((wrong > right).sum())
    swapped = int(((wrong > right).any(0)).sum())
    src = take.obs_src[frames]
    return Score(coverage=coverage, swapped_points=swapped, wrong_frames=wrong_frames,
                 mismatched_obs=int(wrong.sum()),
                 median_mm=float(np.median(err)) if len(err) else float("nan"),
                 p95_mm=float(np.percentile(err, 95)) if len(err) else float("nan"),
                 max_mm=float(err.max()) if len(err) else float("nan"), n_frames=len(frames),
                 brim_obs=int((take.obs_det[frames][:, M:] >= 0).sum()),
                 patch_obs=int((src == ObsSource.PATCH).sum()))


def apply_result(take: Take, res) -> None:
    """Write a :class:`~carapost.core.tracking.TrackResult` into a take (for scoring)."""
    fr = np.asarray(res.frames, np.int64)
    if len(fr) == 0:
        return
    idx = (fr[:, None], res.points[None, :])
    take.xyz[idx] = res.xyz
    take.recon[idx] = res.recon
    take.obs_xy[idx] = res.obs_xy
    take.obs_det[idx] = res.obs_det
    take.obs_src[idx] = res.obs_src
    take.obs_q[idx] = res.obs_q
    take.R[fr], take.t[fr] = res.R, res.t
