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

With ``--static``, the calibration is checked against the static scene (``static_scene``):

* ``video_vs_extrinsics_image``: per camera, the background (median of frames 0, 10, ..., 90)
  registered on ``calibration/extrinsics/camNN_ext.png`` (SIFT, ratio 0.7, affine RANSAC at
  1.5 px): scale and shift (ext = scale * video + shift) and inliers. A camera moved between
  calibration and capture, or a resized video, shows here;
* ``bolts``: the hand-picked static landmarks :data:`pose2sim_case.STATIC_BOLTS` (bolt heads
  on the walkway, +-2 px): per pair their symmetric epipolar distances with the file's poses
  and, triangulated from all views, each camera's reprojection errors; in raw video pixels and
  with cam01/cam02's letterbox undone (:func:`pose2sim_case.video_to_calibration`);
* ``guided_sift``: SIFT features of the backgrounds matched per pair within 60 px of the
  file's epipolar lines (ratio 0.8, mutual): matches, their median epipolar distance and the
  fraction within 2 px (chance: 2/60 = 0.033), and the inliers of an essential matrix fitted
  to them (RANSAC at 1 px) with the file's median distance over those;
* ``auto_letterbox``: frame 0's automatic initialization (white blobs) with cam01/cam02's
  detections mapped by :func:`pose2sim_case.video_to_calibration`;
* ``sync_scan``: per camera pair, :func:`carapost.core.sync_offset.epipolar_offset_scores`
  of the white-blob detections near the person (frames 15, 17, ..., 43 of camera a against
  frames ``f + k`` of camera b, ``k = -10..10``, 2 px), with the file's poses: counts per
  offset, best offset (and sub-frame), contrast (peak over median). A pair whose poses are
  right and whose videos are in sync peaks at 0; a time offset moves the peak; wrong poses
  leave no peak;
* ``refined``: :func:`carapost.core.scene_refine.refine_poses` over the six static landmarks
  :data:`pose2sim_case.STATIC_LANDMARKS` (bolts and cone tops), cam02 fixed, and with cam01
  and cam02 both fixed: residuals before and after, each landmark left out in turn
  (``leave_one_out``: its median reprojection error with the file's poses and with poses
  refined without it), cameras turned / moved, the two spine markers' cam03-cam04 epipolar
  distances, the sync scan again and frame 0's automatic initialization with the refined
  poses.

With ``--tracks``, the poses are refined from the person's marker *tracks*, wand-style
(``tracks``, :mod:`carapost.core.track_calibration`; white blobs of all 100 frames linked into
2D tracks per camera, :data:`pose2sim_case.P2S_TRACKS`):

* ``moving_tracks``: tracks per camera that move (the others are clutter);
* ``track_pairs``: per camera pair, the track pairs whose epipolar distance under the file's
  poses is bounded and consistent over time (30 px, spread 3 px, sweep 3 x spread), and the
  same with camera b's tracks shifted by 20, -20, 30, -30 frames (null control: no true pair
  left);
* ``sync``: per accepted track pair, the time offset of camera b (-6..6 frames) that minimises
  the pair's spread: a time offset between the videos would move it away from 0;
* ``refined``: :func:`~carapost.core.track_calibration.refine_extrinsics` from the file's poses
  (cam01 fixed; cam01 and cam02 fixed), validated on what the fit did not use: the six static
  landmarks (median reprojection, file poses 9.5 px), the cameras turned / moved, and frame
  0's automatic initialization with the refined poses (points, on the person, median
  reprojection, its own null control); ``null_refined``: the same with one camera's tracks
  shifted by 20 frames;
* ``against_landmark_poses``: the accepted tracks' reprojection errors per camera with the
  file's poses and with the poses refined on the six landmarks alone (cam01, cam02 fixed;
  independent of the tracks), and a track bundle started from the landmark poses (the
  landmarks' error before and after: the tracks' conditioning).

CPU times are process times. Prints one JSON line.

    .venv/bin/python benchmarks/bench_pose2sim.py [--pooled] [--static] [--tracks] [--static-only]

(``--static-only``: only the ``static_scene`` / ``tracks`` sections, not the detector settings.)
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
from pose2sim_case import (CAM03_MARKERS_FRAME0, CAM04_SPINE_FRAME0, LETTERBOXED, P2S_INIT, P2S_TRACKS,  # noqa: E402
                           STATIC_BOLTS, STATIC_LANDMARKS, auto_kwargs, detect, file_calibration, near_person,
                           on_body, skeleton_points, video_to_calibration)

from carapost.core.auto_init import auto_initialize  # noqa: E402
from carapost.core.bundle import bundle_adjust  # noqa: E402
from carapost.core.camera import camera_centre, project, symmetric_epipolar_distance  # noqa: E402
from carapost.core.scene_refine import pose_change, refine_poses  # noqa: E402
from carapost.core.sync_offset import epipolar_offset_scores  # noqa: E402
from carapost.core.track_calibration import (bundle_poses, link_tracks, match_tracks, moving_tracks,  # noqa: E402
                                             refine_extrinsics, track_pair_table, trajectory_observations)
from carapost.core.triangulate import triangulate  # noqa: E402
from carapost.core.epipolar_match import (detection_arrays, gather_xy, pair_candidates,  # noqa: E402
                                          triangulate_points)
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


def run(root: Path, pooled: bool = False, static: bool = False, settings: bool = True, tracks: bool = False) -> dict:
    cal, R, t = file_calibration(root)
    intr = cal.intrinsics
    images = [open_source(root / "videos" / f"{n}.mp4").read(0) for n in cal.names]
    skel = skeleton_points(root, 0)
    out: dict = {"frame": 0, "cameras": cal.names}
    for name, (detector, overrides) in (SETTINGS if settings else {}).items():
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
    if static:
        out["static_scene"] = _static_scene(root, cal, intr, R, t, skel)
    if tracks:
        out["tracks"] = _tracks(root, cal, intr, R, t, skel)
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


#: Frames whose median is a video's background (the person moves enough to vanish from it).
BACKGROUND_FRAMES = tuple(range(0, 100, 10))
#: Band of the guided static matching, px.
GUIDED_BAND_PX = 60.0


def _background(source) -> np.ndarray:
    """Temporal median of :data:`BACKGROUND_FRAMES`, (H, W) uint8."""
    frames = np.stack([np.asarray(source.read(f)) for f in BACKGROUND_FRAMES])
    if frames.ndim == 4:
        frames = frames.mean(axis=-1)
    return np.median(frames, axis=0).astype(np.uint8)


def _register(video_bg: np.ndarray, ext: np.ndarray) -> dict:
    """Affine map video -> extrinsics image from SIFT matches (RANSAC 1.5 px)."""
    import cv2
    sift = cv2.SIFT_create(nfeatures=8000)
    kb, db = sift.detectAndCompute(video_bg, None)
    ke, de = sift.detectAndCompute(ext, None)
    m = [x[0] for x in cv2.BFMatcher().knnMatch(db, de, k=2) if len(x) == 2 and x[0].distance < 0.7 * x[1].distance]
    pb = np.array([kb[x.queryIdx].pt for x in m])
    pe = np.array([ke[x.trainIdx].pt for x in m])
    A, inl = cv2.estimateAffine2D(pb, pe, ransacReprojThreshold=1.5)
    inl = inl.ravel().astype(bool)
    r = np.linalg.norm(pb[inl] @ A[:, :2].T + A[:, 2] - pe[inl], axis=1)
    return {"size": list(video_bg.shape[::-1]), "scale": [round(float(A[0, 0]), 5), round(float(A[1, 1]), 5)],
            "shift_px": [round(float(v), 2) for v in A[:, 2]], "matches": len(m), "inliers": int(inl.sum()),
            "median_residual_px": round(float(np.median(r)), 3)}


def _bolts(intr: list, R: np.ndarray, t: np.ndarray, letterbox: bool) -> dict:
    xy = STATIC_BOLTS.copy()
    if letterbox:
        for c in range(xy.shape[1]):
            xy[:, c] = video_to_calibration(xy[:, c], c)
    C = xy.shape[1]
    pairs = {}
    for a in range(C):
        for b in range(a + 1, C):
            d = symmetric_epipolar_distance(xy[:, a], xy[:, b], intr[a], R[a], t[a], intr[b], R[b], t[b])
            pairs[f"{a + 1}-{b + 1}"] = [None if not np.isfinite(v) else round(float(v), 1) for v in d]
    X = triangulate(xy, intr, R, t).xyz
    err = np.stack([np.linalg.norm(project(X, intr[c], R[c], t[c]) - xy[:, c], axis=1) for c in range(C)], 1)
    return {"epipolar_px": pairs, "xyz_mm": np.round(X).astype(int).tolist(),
            "reprojection_px_per_camera": [[None if not np.isfinite(v) else round(float(v), 1) for v in err[:, c]]
                                           for c in range(C)],
            "median_reprojection_px": _median(err.ravel())}


def _guided_sift(bgs: list, cal, intr: list, R: np.ndarray, t: np.ndarray) -> dict:
    """Background SIFT matches per pair within :data:`GUIDED_BAND_PX` of the file's epipolar lines."""
    import cv2
    sift = cv2.SIFT_create(nfeatures=6000, contrastThreshold=0.01)
    kd = [sift.detectAndCompute(b, None) for b in bgs]
    pts = [np.array([k.pt for k in kk[0]]) for kk in kd]
    des = [kk[1].astype(np.float32) for kk in kd]

    def normalised(xy: np.ndarray, c: int) -> np.ndarray:
        dist = cal.cameras[c].extra["opencv_distortion"]["coefficients"]
        i = intr[c]
        K = np.array([[i.focal_length, 0, i.principal_point[0]], [0, i.focal_length / i.aspect, i.principal_point[1]],
                      [0, 0, 1]])
        return cv2.undistortPoints(xy.reshape(-1, 1, 2), K, np.asarray(dist, float)).reshape(-1, 2)
    out = {}
    for a in range(len(bgs)):
        for b in range(a + 1, len(bgs)):
            D = symmetric_epipolar_distance(pts[a][:, None], pts[b][None], intr[a], R[a], t[a], intr[b], R[b], t[b])
            sq = (des[a] ** 2).sum(1)[:, None] + (des[b] ** 2).sum(1)[None] - 2 * des[a] @ des[b].T
            dd = np.sqrt(np.maximum(0, sq))
            dd[D > GUIDED_BAND_PX] = np.inf
            j = np.argmin(dd, 1)
            s2 = np.sort(dd, 1)[:, :2]
            mutual = np.argmin(dd, 0)[j] == np.arange(len(j))
            ia = np.flatnonzero(np.isfinite(s2[:, 0]) & (s2[:, 0] < 0.8 * s2[:, 1]) & mutual)
            ib = j[ia]
            d = D[ia, ib]
            row = {"matches": len(ia), "median_epipolar_px": _median(d), "within_2px": round(float(np.mean(d < 2)), 3)}
            if len(ia) >= 8:
                E, inl = cv2.findEssentialMat(normalised(pts[a][ia], a), normalised(pts[b][ib], b), np.eye(3),
                                              cv2.RANSAC, 0.999, 1.0 / intr[a].focal_length)
                inl = inl.ravel().astype(bool) if inl is not None else np.zeros(len(ia), bool)
                row.update(essential_inliers=int(inl.sum()), file_median_px_on_inliers=_median(d[inl]))
            out[f"{a + 1}-{b + 1}"] = row
    return out


def _static_scene(root: Path, cal, intr: list, R: np.ndarray, t: np.ndarray, skel: np.ndarray) -> dict:
    """The file's poses against the static scene (see the module docstring, ``--static``)."""
    import cv2
    sources = [open_source(root / "videos" / f"{n}.mp4") for n in cal.names]
    bgs = [_background(s) for s in sources]
    reg = {}
    for c, n in enumerate(cal.names):
        ext = cv2.imread(str(root / "calibration" / "extrinsics" / f"{n}_ext.png"), cv2.IMREAD_GRAYSCALE)
        reg[n] = _register(bgs[c], ext) | {"extrinsics_image_size": list(ext.shape[::-1])}
    out: dict = {"video_vs_extrinsics_image": reg,
                 "bolts": {"raw": _bolts(intr, R, t, False), "letterbox_undone": _bolts(intr, R, t, True)}}
    t0 = time.process_time()
    out["guided_sift"] = _guided_sift(bgs, cal, intr, R, t)
    out["guided_sift_cpu_s"] = round(time.process_time() - t0, 1)
    dets = [detect(s.read(0), "blobs") for s in sources]
    for c in range(len(dets)):
        if LETTERBOXED[c]:
            xy = video_to_calibration(np.c_[dets[c]["x"], dets[c]["y"]], c)
            dets[c] = dict(dets[c])
            dets[c]["x"], dets[c]["y"] = xy[:, 0].astype(dets[c]["x"].dtype), xy[:, 1].astype(dets[c]["y"].dtype)
    res, err = _auto(dets, intr, R, t, 3)
    out["auto_letterbox"] = {"points": res.n_points, "on_person": int(on_body(res.xyz, skel).sum()),
                             "median_reprojection_px": _median(err.ravel())}
    t0 = time.process_time()
    near = _near_person_tracks(root, sources, intr, R, t)
    out["sync_scan_detect_cpu_s"] = round(time.process_time() - t0, 1)
    out["sync_scan"] = _sync_scan(near, intr, R, t)
    dets0 = [detect(s.read(0), "blobs") for s in sources]
    out["refined"] = {}
    for name, fixed in (("cam02_fixed", 1), ("cam01_cam02_fixed", (0, 1))):
        out["refined"][name] = _refined(near, dets0, intr, R, t, skel, fixed)
    return out


#: Frames of camera a in the sync scan, and the offsets tried.
SYNC_FRAMES = tuple(range(15, 45, 2))
SYNC_OFFSETS = tuple(range(-10, 11))


def _near_person_tracks(root: Path, sources: list, intr: list, R: np.ndarray, t: np.ndarray) -> list:
    """White-blob detections near the person (file poses), per camera and frame 0..54 (n, 2)."""
    last = max(SYNC_FRAMES) + max(SYNC_OFFSETS) + 1
    out = []
    for c, s in enumerate(sources):
        frames = []
        for f in range(last):
            d = detect(s.read(f), "blobs")
            xy = np.c_[d["x"], d["y"]].astype(float)
            frames.append(xy[near_person(xy, skeleton_points(root, f), intr[c], R[c], t[c])])
        out.append(frames)
    return out


def _sync_scan(near: list, intr: list, R: np.ndarray, t: np.ndarray) -> dict:
    out = {}
    for a in range(len(near)):
        for b in range(a + 1, len(near)):
            s = epipolar_offset_scores(near[a], near[b], intr[a], R[a], t[a], intr[b], R[b], t[b],
                                       offsets=SYNC_OFFSETS, frames=SYNC_FRAMES)
            out[f"{a + 1}-{b + 1}"] = {"counts": s.counts.tolist(), "best": s.best,
                                       "subframe": round(s.subframe, 2), "contrast": round(s.contrast, 2)}
    return out


def _refined(near: list, dets0: list, intr: list, R: np.ndarray, t: np.ndarray, skel: np.ndarray, fixed) -> dict:
    xy = STATIC_LANDMARKS
    r = refine_poses(xy, intr, R, t, fixed=fixed)
    loo = []
    for k in range(len(xy)):
        keep = np.arange(len(xy)) != k
        rk = refine_poses(xy[keep], intr, R, t, fixed=fixed)
        row = []
        for Rk, tk in ((R, t), (rk.R, rk.t)):
            X = triangulate(xy[k:k + 1], intr, Rk, tk).xyz
            row.append(_median(np.array([np.linalg.norm(project(X, intr[c], Rk[c], tk[c]) - xy[k:k + 1, c])
                                         for c in range(len(intr))])))
        loo.append(row)
    spine = symmetric_epipolar_distance(CAM03_MARKERS_FRAME0[:2], CAM04_SPINE_FRAME0, intr[2], r.R[2], r.t[2],
                                        intr[3], r.R[3], r.t[3])
    auto = _auto_summary(dets0, intr, r.R, r.t, skel, 3)
    return {"median_residual_px_before": _median(r.initial_residuals.ravel()),
            "median_residual_px_after": _median(r.residuals.ravel()),
            "max_residual_px_after": round(float(np.nanmax(r.residuals)), 2),
            "leave_one_out_file_vs_refined_px": loo,
            "camera_turned_deg": [round(float(v), 2) for v in r.turned_deg],
            "camera_moved_mm": [round(float(v), 1) for v in r.moved_mm],
            "spine_cam03_cam04_epipolar_px": [round(float(v), 1) for v in spine],
            "sync_scan": _sync_scan(near, intr, r.R, r.t),
            "frame0_auto": {k: auto[k] for k in ("points", "points_by_views", "on_person", "median_reprojection_px",
                                                  "null_points")}}


#: Time shifts of camera b's tracks in the track-pair null control, frames.
TRACK_SHIFTS = (20, -20, 30, -30)
#: Offsets scanned per accepted track pair (``sync``), frames.
TRACK_SYNC_OFFSETS = tuple(range(-6, 7))
#: Prior of the track bundle: a camera turned by this much, or moved by this much, costs as
#: much as a 1 px residual.
TRACK_PRIOR = dict(rotation_sigma_deg=0.5, centre_sigma_mm=30.0)


def _shift_tracks(T: np.ndarray, k: int) -> np.ndarray:
    """Tracks ``(n, F, 2)`` moved ``k`` frames later (earlier for k < 0), NaN-filled."""
    out = np.full_like(T, np.nan)
    if k > 0:
        out[:, k:] = T[:, :-k]
    elif k < 0:
        out[:, :k] = T[:, -k:]
    else:
        out = T.copy()
    return out


def _landmark_error(R: np.ndarray, t: np.ndarray, intr: list) -> float | None:
    """Median reprojection error of :data:`pose2sim_case.STATIC_LANDMARKS` triangulated with the poses."""
    X = triangulate(STATIC_LANDMARKS, intr, R, t).xyz
    return _median(np.stack([np.linalg.norm(project(X, intr[c], R[c], t[c]) - STATIC_LANDMARKS[:, c], axis=1)
                             for c in range(len(intr))]).ravel())


def _track_residuals(tracks: list, label: list, intr: list, R: np.ndarray, t: np.ndarray) -> list:
    """Median reprojection error per camera of the matched trajectories' points (triangulated
    with the poses), px."""
    O = trajectory_observations(tracks, label)
    xy = O.reshape(-1, len(intr), 2)
    xy = xy[np.isfinite(xy[..., 0]).sum(1) >= 2]
    X = triangulate(xy, intr, R, t).xyz
    return [_median(np.linalg.norm(project(X, intr[c], R[c], t[c]) - xy[:, c], axis=1)) for c in range(len(intr))]


def _tracks(root: Path, cal, intr: list, R: np.ndarray, t: np.ndarray, skel: np.ndarray) -> dict:
    """Extrinsics from marker tracks (see the module docstring, ``--tracks``)."""
    sources = [open_source(root / "videos" / f"{n}.mp4") for n in cal.names]
    t0 = time.process_time()
    frames = []
    for s in sources:
        frames.append([])
        for f in range(s.n_frames):
            d = detect(s.read(f), "blobs")
            frames[-1].append(np.c_[d["x"], d["y"]].astype(float))
    out: dict = {"frames": len(frames[0]), "detect_cpu_s": round(time.process_time() - t0, 1)}
    t0 = time.process_time()
    linked = [link_tracks(fr, gate_px=P2S_TRACKS["gate_px"]) for fr in frames]
    tracks = [T[moving_tracks(T, min_frames=P2S_TRACKS["min_frames"], min_motion_px=P2S_TRACKS["min_motion_px"])]
              for T in linked]
    out["link_cpu_s"] = round(time.process_time() - t0, 2)
    out["tracks"] = [len(T) for T in linked]
    out["moving_tracks"] = [len(T) for T in tracks]
    C = len(intr)
    crit = dict(min_common=P2S_TRACKS["min_common"])
    pairs = {}
    for a in range(C):
        for b in range(a + 1, C):
            row = []
            for k in (0,) + TRACK_SHIFTS:
                sh = [T if c != b else _shift_tracks(T, k) for c, T in enumerate(tracks)]
                _, edges = match_tracks([sh[a], sh[b]], [intr[a], intr[b]], R[[a, b]], t[[a, b]], **crit)
                row.append(len(edges))
            pairs[f"{a + 1}-{b + 1}"] = {"real": row[0], "shifted": row[1:]}
    out["track_pairs"] = pairs
    label, edges = match_tracks(tracks, intr, R, t, **crit)
    sync: dict = {}
    for a, i, b, j, _ in edges:
        spreads = [track_pair_table(tracks[a][i:i + 1], _shift_tracks(tracks[b][j:j + 1], k), intr[a], R[a], t[a],
                                    intr[b], R[b], t[b]).spread[0, 0] for k in TRACK_SYNC_OFFSETS]
        sync.setdefault(f"{a + 1}-{b + 1}", []).append(TRACK_SYNC_OFFSETS[int(np.nanargmin(spreads))])
    out["sync_best_offsets"] = sync
    dets0 = [detect(s.read(0), "blobs") for s in sources]
    out["file_poses"] = {"static_landmarks_median_px": _landmark_error(R, t, intr),
                         "frame0_auto": {k: v for k, v in _auto_summary(dets0, intr, R, t, skel, 3).items()
                                         if k in ("points", "on_person", "median_reprojection_px", "null_points")}}
    out["refined"] = {}
    for name, fixed in (("cam01_fixed", 0), ("cam01_cam02_fixed", (0, 1))):
        t0 = time.process_time()
        r = refine_extrinsics(tracks, intr, R, t, fixed=fixed, **crit, **TRACK_PRIOR)
        cpu = time.process_time() - t0
        spine = symmetric_epipolar_distance(CAM03_MARKERS_FRAME0[:2], CAM04_SPINE_FRAME0, intr[2], r.R[2], r.t[2],
                                            intr[3], r.R[3], r.t[3])
        auto = _auto_summary(dets0, intr, r.R, r.t, skel, 3)
        last = r.rounds[-1]
        entry = {"cpu_s": round(cpu, 2), "track_pairs": last["pairs_per_camera_pair"],
                 "trajectories": last["trajectories"], "observations": last["observations"],
                 "median_residual_px": round(last["median_residual_px"], 2),
                 "camera_turned_deg": [round(float(v), 2) for v in r.turned_deg],
                 "camera_moved_mm": [round(float(v), 1) for v in r.moved_mm],
                 "static_landmarks_median_px": _landmark_error(r.R, r.t, intr),
                 "spine_cam03_cam04_epipolar_px": [round(float(v), 1) for v in spine],
                 "frame0_auto": {k: auto[k] for k in ("points", "points_by_views", "on_person",
                                                      "median_reprojection_px", "null_points")}}
        nulls = {}
        for c in range(1, C):
            sh = [T if k != c else _shift_tracks(T, 20) for k, T in enumerate(tracks)]
            try:
                rn = refine_extrinsics(sh, intr, R, t, fixed=fixed, **crit, **TRACK_PRIOR)
            except ValueError as e:
                nulls[cal.names[c]] = str(e)
                continue
            own = sum(v for k, v in rn.rounds[-1]["pairs_per_camera_pair"].items() if str(c + 1) in k.split("-"))
            nulls[cal.names[c]] = {"its_track_pairs": own,
                                   "static_landmarks_median_px": _landmark_error(rn.R, rn.t, intr)}
        entry["null_refined_shift_20"] = nulls
        out["refined"][name] = entry
    # the tracks against poses refined on the six landmarks alone (independent of the tracks)
    rl = refine_poses(STATIC_LANDMARKS, intr, R, t, fixed=(0, 1))
    label_l, edges_l = match_tracks(tracks, intr, rl.R, rl.t, max_bias_px=8.0, max_spread_px=2.0, **crit)
    O = trajectory_observations(tracks, label_l)
    xy = O.reshape(-1, C, 2)
    xy = xy[np.isfinite(xy[..., 0]).sum(1) >= 2]
    Rb, tb, _ = bundle_poses(xy, intr, rl.R, rl.t, fixed=(0, 1), **TRACK_PRIOR)
    out["against_landmark_poses"] = {
        "file_poses_track_median_px_per_camera": _track_residuals(tracks, label, intr, R, t),
        "landmark_poses_track_median_px_per_camera": _track_residuals(tracks, label_l, intr, rl.R, rl.t),
        "landmark_poses_static_median_px": _landmark_error(rl.R, rl.t, intr),
        "bundled_from_landmark_poses": {
            "track_median_px_per_camera": _track_residuals(tracks, label_l, intr, Rb, tb),
            "static_landmarks_median_px": _landmark_error(Rb, tb, intr),
            "camera_turned_deg": [round(float(v), 2) for v in pose_change(rl.R, rl.t, Rb, tb)[0]],
            "camera_moved_mm": [round(float(v), 1) for v in pose_change(rl.R, rl.t, Rb, tb)[1]]}}
    return out


def main() -> None:
    base = real_data_dir()
    if base is None or not (base / "pose2sim-demo").is_dir():
        emit("pose2sim", skipped="real data not found (set CARAPOST_REAL_DATA)")
        return
    args = sys.argv[1:]
    emit("pose2sim", **run(base / "pose2sim-demo", pooled="--pooled" in args, static="--static" in args,
                           settings="--static-only" not in args, tracks="--tracks" in args))


if __name__ == "__main__":
    main()
