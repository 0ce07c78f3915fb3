"""Automatic initialization on real footage: the Pose2Sim demo, frame 0.

Four portrait videos (1080/1088 x 1920, 60 fps) of a person wearing retro-reflective body
markers, a Qualisys calibration, and Pose2Sim's markerless skeleton of the same frames (which
tells where the person is). For each blob-detection setting:

* ``detections``: per camera, all and those within 150 mm of the skeleton (measured in the
  image at the skeleton's depth: markers on the person, plus whatever blob touches them);
* ``auto``: :func:`~carapost.core.auto_init.auto_initialize` with the demo's settings
  (``tests/core/pose2sim_case.py``): points, points per number of views, points on the person
  (within 150 mm of the skeleton), the median reprojection error with the file's poses over all
  the views and over the points seen by three or more cameras (two-view points reproject at
  about half their epipolar distance whatever their quality), and whether the poses were
  bundled (refused when the points leave too few degrees of freedom; see
  ``carapost.core.auto_init.pose_redundancy``); for the current setting also with two-view
  points accepted (``with_two_view_points``);
* ``sync`` (the current setting only): the three-or-more-view points' RMS reprojection error
  for points that stand still between frames 0 and 1 (< 0.5 px/frame in every view) and for
  moving ones (nearest detection of frame 1 within 8 px; farther: not tracked). A time offset
  between the videos would show as larger errors on moving points.

CPU times are process times. Prints one JSON line.

    .venv/bin/python benchmarks/bench_pose2sim.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "core"))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from _common import emit  # noqa: E402
from conftest import real_data_dir  # noqa: E402
from pose2sim_case import (P2S_BLOBS, P2S_INIT, auto_kwargs, near_person, on_body,  # noqa: E402
                           skeleton_points)

from carapost.core.auto_init import auto_initialize  # noqa: E402
from carapost.core.blobs import detect_blobs  # noqa: E402
from carapost.core.epipolar_match import detection_arrays, triangulate_points  # noqa: E402
from carapost.io.calibration import load_calibration  # noqa: E402
from carapost.io.sources import open_source  # noqa: E402
from carapost.model.params import BlobParameters  # noqa: E402

#: Blob settings compared: the earlier demo setting, the current one, a lower threshold.
SETTINGS = {
    "r1-6_t0.10": {**P2S_BLOBS, "white_max_radius": 6.0, "white_threshold": 0.1},
    "current": P2S_BLOBS,
    "r1-8_t0.02": {**P2S_BLOBS, "white_threshold": 0.02},
}


#: A point whose detections have no detection within this distance in frame 1 is not tracked.
MAX_TRACK_PX = 8.0


def _median(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return round(float(np.median(v)), 3) if len(v) else None


def _speeds(det_index: np.ndarray, dets0: list, dets1: list) -> np.ndarray:
    """Largest image motion of each point's detections from frame 0 to 1, px/frame (P,)."""
    out = np.zeros(len(det_index))
    for c in range(det_index.shape[1]):
        sel = np.flatnonzero(det_index[:, c] >= 0)
        if len(sel) == 0:
            continue
        xy0 = np.c_[dets0[c]["x"], dets0[c]["y"]][det_index[sel, c]]
        xy1 = np.c_[dets1[c]["x"], dets1[c]["y"]]
        d = np.linalg.norm(xy0[:, None] - xy1[None], axis=-1).min(axis=1) if len(xy1) else np.full(len(sel), np.inf)
        out[sel] = np.maximum(out[sel], d)
    return out


def _auto(dets: list, intr: list, R: np.ndarray, t: np.ndarray, min_views: int):
    """The demo's automatic initialization and its errors with the file's poses (P, C) px."""
    res = auto_initialize(dets, intr, R, t, P2S_INIT, **auto_kwargs(min_views=min_views))
    da = [detection_arrays(d, c) for c, d in enumerate(dets)]
    _, err = triangulate_points(res.det_index, da, intr, R, t)
    return res, err


def _auto_summary(dets: list, intr: list, R: np.ndarray, t: np.ndarray, skel: np.ndarray, min_views: int) -> dict:
    t0 = time.process_time()
    res, err = _auto(dets, intr, R, t, min_views)
    t_auto = time.process_time() - t0
    nv = res.n_views
    body = on_body(res.xyz, skel)
    auto = res.report["auto"]
    return {"min_views": min_views, "points": res.n_points,
            "points_by_views": {str(k): int((nv == k).sum()) for k in range(2, len(dets) + 1)},
            "on_person": int(body.sum()), "on_person_3plus_views": int((body & (nv >= 3)).sum()),
            "median_reprojection_px": _median(err.ravel()),
            "median_reprojection_3plus_views_px": _median(err[nv >= 3].ravel()),
            "median_reprojection_on_person_px": _median(err[body].ravel()),
            "poses_bundled": auto["poses_bundled"], "bundle_dof": auto.get("bundle_dof"),
            "pose_parameters": auto.get("pose_parameters"), "auto_init_cpu_s": round(t_auto, 3)}


def run(root: Path) -> dict:
    cal = load_calibration(root / "calibration" / "Calib.qca.txt")
    R, t = cal.poses(1)
    R, t = R[0], t[0]
    intr = cal.intrinsics
    images = [open_source(root / "videos" / f"{n}.mp4").read(0) for n in cal.names]
    skel = skeleton_points(root, 0)
    out: dict = {"frame": 0, "cameras": cal.names}
    for name, blob in SETTINGS.items():
        t0 = time.process_time()
        dets = [detect_blobs(img, BlobParameters(**blob)) for img in images]
        t_det = time.process_time() - t0
        near = [near_person(np.c_[d["x"], d["y"]], skel, intr[c], R[c], t[c]) for c, d in enumerate(dets)]
        entry = {"blob_parameters": {k: blob[k] for k in ("white_min_radius", "white_max_radius", "white_threshold")},
                 "detections": [len(d["x"]) for d in dets],
                 "detections_near_person": [int(n.sum()) for n in near], "detect_cpu_s": round(t_det, 2)}
        entry.update(_auto_summary(dets, intr, R, t, skel, 3))
        if name == "current":
            entry["with_two_view_points"] = _auto_summary(dets, intr, R, t, skel, 2)
        out[name] = entry
        if name == "current":
            res, err = _auto(dets, intr, R, t, 3)
            nv = res.n_views
            dets1 = [detect_blobs(open_source(root / "videos" / f"{n}.mp4").read(1), BlobParameters(**blob))
                     for n in cal.names]
            sp = _speeds(res.det_index, dets, dets1)
            rms = np.sqrt(np.nanmean(err ** 2, axis=1))
            multi = nv >= 3
            tracked = sp <= MAX_TRACK_PX
            still, moving = multi & (sp < 0.5), multi & (sp >= 0.5) & tracked
            out["sync"] = {"static_points": int(still.sum()), "static_median_rms_px": _median(rms[still]),
                           "moving_points": int(moving.sum()), "moving_median_rms_px": _median(rms[moving]),
                           "moving_median_speed_px_per_frame": _median(sp[moving]),
                           "untracked_points": int((multi & ~tracked).sum())}
    return out


def main() -> None:
    base = real_data_dir()
    if base is None or not (base / "pose2sim-demo").is_dir():
        emit("pose2sim", skipped="real data not found (set CARAPOST_REAL_DATA)")
        return
    emit("pose2sim", **run(base / "pose2sim-demo"))


if __name__ == "__main__":
    main()
