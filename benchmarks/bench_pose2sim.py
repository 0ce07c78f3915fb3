"""Automatic initialization on real footage: the Pose2Sim demo, frame 0.

Four portrait videos (1080/1088 x 1920, 60 fps) of a person wearing retro-reflective body
markers, a Qualisys calibration, and Pose2Sim's markerless skeleton of the same frames (which
tells where the person is). For each detector setting (white blobs, ``detector="blobs"``, or
shaded marker spheres, ``detector="spheres"``: :mod:`carapost.core.sphere_markers`):

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
* ``null_points``: the same automatic initialization after shifting one camera's detections
  by 25 px (each camera in turn, right and down: 8 runs), which destroys every true
  correspondence of that camera; the median and largest number of points it still finds are
  the coincidences to expect. Points found beyond that are the evidence of real matches;
* ``pairs_2px``: per camera pair, the detection pairs within 2 px of each other's epipolar
  line (triangulating in front of both), near the person and elsewhere (``person``,
  ``room``), against the mean of the same count with the second camera's detections shifted by
  25 px in six directions (``*_shifted``): the excess is what the pair's geometry confirms;
* ``sync`` (the current setting only): the three-or-more-view points' RMS reprojection error
  for points that stand still between frames 0 and 1 (< 0.5 px/frame in every view) and for
  moving ones (nearest detection of frame 1 within 8 px; farther: not tracked). A time offset
  between the videos would show as larger errors on moving points.

With ``--pooled``, the sphere detections of frames 1..10 are also matched per frame (file
poses, three views, 3 px) and pooled into one bundle of the four static cameras (cam01 fixed,
robust loss), and frame 0, held out, is initialized again with the bundled poses
(``pooled``).

CPU times are process times. Prints one JSON line.

    .venv/bin/python benchmarks/bench_pose2sim.py [--pooled]
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
from pose2sim_case import (P2S_INIT, auto_kwargs, detect, near_person, on_body,  # noqa: E402
                           skeleton_points)

from carapost.core.auto_init import auto_initialize  # noqa: E402
from carapost.core.bundle import bundle_adjust  # noqa: E402
from carapost.core.camera import camera_centre  # noqa: E402
from carapost.core.epipolar_match import (detection_arrays, gather_xy, pair_candidates,  # noqa: E402
                                          triangulate_points)
from carapost.io.calibration import load_calibration  # noqa: E402
from carapost.io.sources import open_source  # noqa: E402

#: Settings compared, name -> (detector, overrides of the demo's settings): white blobs (the
#: earlier demo setting, the current one, a lower threshold) and marker spheres (the demo's,
#: a looser and a stricter score).
SETTINGS = {
    "r1-6_t0.10": ("blobs", {"white_max_radius": 6.0, "white_threshold": 0.1}),
    "current": ("blobs", {}),
    "r1-8_t0.02": ("blobs", {"white_threshold": 0.02}),
    "spheres": ("spheres", {}),
    "spheres_s0.4": ("spheres", {"threshold": 0.4}),
    "spheres_s0.6": ("spheres", {"threshold": 0.6}),
}
#: Shift of one camera's detections in the coincidence control, px.
NULL_SHIFT_PX = 25.0


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


def _null_points(dets: list, intr: list, R: np.ndarray, t: np.ndarray, min_views: int) -> dict:
    """Points found when one camera's detections are shifted by :data:`NULL_SHIFT_PX` (each
    camera, right and down): the coincidences, as median and maximum over the 8 runs."""
    counts = []
    for c in range(len(dets)):
        for dx, dy in ((NULL_SHIFT_PX, 0.0), (0.0, NULL_SHIFT_PX)):
            moved = [dict(d) for d in dets]
            moved[c]["x"] = moved[c]["x"] + np.float32(dx)
            moved[c]["y"] = moved[c]["y"] + np.float32(dy)
            res = auto_initialize(moved, intr, R, t, P2S_INIT, **auto_kwargs(bundle=False, min_views=min_views))
            counts.append(res.n_points)
    return {"median": float(np.median(counts)), "max": int(max(counts))}


#: Shifts of the second camera's detections in the pair control, px.
PAIR_SHIFTS = ((25, 0), (-25, 0), (0, 25), (0, -25), (18, 18), (-18, 18))


def _pairs(dets: list, near: list, intr: list, R: np.ndarray, t: np.ndarray, max_epipolar: float = 2.0) -> dict:
    """Per camera pair: detection pairs within ``max_epipolar`` near the person and elsewhere,
    real and with the second camera shifted (mean over :data:`PAIR_SHIFTS`)."""
    out = {}
    C = len(dets)
    for a in range(C):
        for b in range(a + 1, C):
            row = {}
            for region in ("person", "room"):
                def arr(c: int, shift=(0.0, 0.0)):
                    xy = np.c_[dets[c]["x"], dets[c]["y"]].astype(float)
                    keep = near[c] if region == "person" else ~near[c]
                    return detection_arrays(xy[keep] + np.asarray(shift, float), c)

                def count(shift=(0.0, 0.0)) -> int:
                    pc = pair_candidates(0, 1, [arr(a), arr(b, shift)], [intr[a], intr[b]], R[[a, b]], t[[a, b]],
                                         max_epipolar=max_epipolar)
                    return len(pc.ia)
                row[region] = count()
                row[region + "_shifted"] = round(float(np.mean([count(s) for s in PAIR_SHIFTS])), 1)
            out[f"{a + 1}-{b + 1}"] = row
    return out


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
            "pose_parameters": auto.get("pose_parameters"), "auto_init_cpu_s": round(t_auto, 3),
            "null_points": _null_points(dets, intr, R, t, min_views)}


def run(root: Path, pooled: bool = False) -> dict:
    cal = load_calibration(root / "calibration" / "Calib.qca.txt")
    R, t = cal.poses(1)
    R, t = R[0], t[0]
    intr = cal.intrinsics
    images = [open_source(root / "videos" / f"{n}.mp4").read(0) for n in cal.names]
    skel = skeleton_points(root, 0)
    out: dict = {"frame": 0, "cameras": cal.names}
    for name, (detector, overrides) in SETTINGS.items():
        t0 = time.process_time()
        dets = [detect(img, detector, **overrides) for img in images]
        t_det = time.process_time() - t0
        near = [near_person(np.c_[d["x"], d["y"]], skel, intr[c], R[c], t[c]) for c, d in enumerate(dets)]
        entry = {"detector": detector, "overrides": overrides,
                 "detections": [len(d["x"]) for d in dets],
                 "detections_near_person": [int(n.sum()) for n in near], "detect_cpu_s": round(t_det, 2)}
        if name in ("current", "spheres"):
            entry["pairs_2px"] = _pairs(dets, near, intr, R, t)
        entry.update(_auto_summary(dets, intr, R, t, skel, 3))
        if name == "current":
            entry["with_two_view_points"] = _auto_summary(dets, intr, R, t, skel, 2)
        out[name] = entry
        if name == "current":
            res, err = _auto(dets, intr, R, t, 3)
            nv = res.n_views
            dets1 = [detect(open_source(root / "videos" / f"{n}.mp4").read(1), detector, **overrides)
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
    if pooled:
        out["pooled"] = _pooled(root, cal, intr, R, t, skel)
    return out


#: Frames pooled into one bundle of the static cameras (frame 0 is held out).
POOLED_FRAMES = tuple(range(1, 11))


def _pooled(root: Path, cal, intr: list, R: np.ndarray, t: np.ndarray, skel: np.ndarray) -> dict:
    """Sphere detections of :data:`POOLED_FRAMES` matched per frame with the file's poses, one
    bundle of the four static cameras (cam01 fixed, Cauchy and soft-L1 losses at 1 px), and
    frame 0 initialized again with the bundled poses."""
    sources = [open_source(root / "videos" / f"{n}.mp4") for n in cal.names]
    obs = []
    for f in POOLED_FRAMES:
        dets = [detect(s.read(f), "spheres") for s in sources]
        res = auto_initialize(dets, intr, R, t, P2S_INIT, **auto_kwargs(bundle=False))
        obs.append(gather_xy(res.det_index, [detection_arrays(d, c) for c, d in enumerate(dets)]))
    P = max(len(o) for o in obs)
    O = np.full((len(obs), P, len(intr), 2), np.nan)
    for i, o in enumerate(obs):
        O[i, :len(o)] = o
    dets0 = [detect(s.read(0), "spheres") for s in sources]
    out: dict = {"frames": list(POOLED_FRAMES), "points_per_frame": [len(o) for o in obs]}
    for loss in ("cauchy", "soft_l1"):
        b = bundle_adjust(O, intr, np.repeat(R[None], len(obs), 0), np.repeat(t[None], len(obs), 0),
                          np.full((len(obs), P, 3), np.nan), shared_cameras=True,
                          fix_cameras=np.arange(len(intr)) == 0, loss=loss, f_scale=1.0, max_iterations=100)
        r = b.residuals[np.isfinite(b.residuals)]
        Rb, tb = b.R[0], b.t[0]
        moved = [np.linalg.norm(camera_centre(Rb[c], tb[c]) - camera_centre(R[c], t[c])) for c in range(len(intr))]
        turned = [np.degrees(np.arccos(np.clip((np.trace(Rb[c] @ R[c].T) - 1) / 2, -1, 1))) for c in range(len(intr))]
        held = _auto_summary(dets0, intr, Rb, tb, skel, 3)
        out[loss] = {"pooled_median_residual_px": round(float(np.median(r)), 3),
                     "pooled_within_2px": round(float(np.mean(r < 2.0)), 3),
                     "camera_moved_mm": [round(float(v), 1) for v in moved],
                     "camera_turned_deg": [round(float(v), 3) for v in turned],
                     "frame0_held_out": {k: held[k] for k in ("points", "on_person", "median_reprojection_px",
                                                              "null_points")}}
    return out


def main() -> None:
    base = real_data_dir()
    if base is None or not (base / "pose2sim-demo").is_dir():
        emit("pose2sim", skipped="real data not found (set CARAPOST_REAL_DATA)")
        return
    emit("pose2sim", **run(base / "pose2sim-demo", pooled="--pooled" in sys.argv[1:]))


if __name__ == "__main__":
    main()
