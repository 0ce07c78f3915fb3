"""The Pose2Sim demo as an automatic-initialization case (shared by the slow test and the benchmark).

Four portrait videos of a person wearing small retro-reflective body markers, with a
Qualisys calibration. Frame 0 is read from each video, markers are detected (:func:`detect`:
white blobs with the project's detector, a small radius range and a low threshold, the markers
being grey spheres 5-10 px across whose bright side is found; or, ``detector="spheres"``, the
shaded spheres themselves with :mod:`carapost.core.sphere_markers`), and
:func:`~carapost.core.auto_init.auto_initialize` runs
without caddies (the four cameras stand around the room), with a 3 px reprojection
tolerance: with the file's poses, points seen by three cameras (static ones included)
reproject 0.7-2.5 px off their detections (and about as many are found with one camera's
detections shifted by 25 px: most are coincidences, see ``docs/initialize-3d.md``). Two-view points are not accepted: on frame 0 the
five the matcher finds are coincidences (window blinds, edges) when the crops are inspected.

Pose2Sim's own markerless reconstruction of the same frames (``pose-3d/*.trc``, metres, its
axes ``(x, y, z)`` being our ``(y, z, x)``) tells which points lie on the person: within
:data:`BODY_RADIUS_MM` of its skeleton.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carapost.model.params import Initialize3DParameters

#: Blob Parameters for the demo's markers (``benchmarks/bench_pose2sim.py`` compares settings).
P2S_BLOBS = dict(find_black_blobs=False, find_white_blobs=True, white_min_radius=1.0, white_max_radius=8.0,
                 white_threshold=0.05, adaptive_background=True)
#: :class:`~carapost.core.sphere_markers.SphereParameters` for the demo's markers (the defaults).
P2S_SPHERES: dict = {}
#: 2D track settings for :mod:`carapost.core.track_calibration` on the demo (white blobs of all
#: 100 frames): :func:`link_tracks` gate, and :func:`moving_tracks` / ``min_common`` chosen so that
#: a camera whose tracks are shifted by 20-30 frames keeps 0-2 track pairs per camera pair (the
#: person balances: few markers move more than 8 px in the 1.7 s).
P2S_TRACKS = dict(gate_px=6.0, min_frames=10, min_motion_px=8.0, min_common=10)
#: The detectors :func:`detect` offers.
DETECTORS = ("blobs", "spheres")
#: Initialize 3D parameters (the defaults: no caddy growth happens here).
P2S_INIT = Initialize3DParameters()
#: Points closer than this to the markerless skeleton are on the person.
BODY_RADIUS_MM = 150.0
#: Markers on the person in cam03 (the back view), frame 0, picked by eye on 8x crops (raw px,
#: +-1.5 px): two spine markers, elbow, forearm, wrist, upper arm, hand.
CAM03_MARKERS_FRAME0 = np.array([(695.0, 692.5), (689.0, 737.5), (552.5, 800.0), (574.0, 863.5),
                                 (562.5, 884.0), (770.0, 763.5), (519.0, 946.5)])
#: The two spine markers of :data:`CAM03_MARKERS_FRAME0` (its first two rows) in cam04, frame 0,
#: picked the same way.
CAM04_SPINE_FRAME0 = np.array([(277.0, 788.0), (293.0, 832.0)])

#: Static scene landmarks picked by eye on 3x crops of each video's background (the median of
#: frames 0, 10, ..., 90, which removes the person): the bolt heads of four metal plates on the
#: walkway's edges, (landmark, camera, 2) raw video px (+-2 px), NaN where not picked. They
#: triangulate on the walkway top (z = -17..16 mm) 1.1-1.2 m apart. Identified across views by
#: their epipolar distances (each assignment unique; the others > 60 px).
STATIC_BOLTS = np.array([
    [(787.0, 1277.0), (802.0, 1267.0), (141.0, 1267.0), (487.0, 1133.0)],
    [(65.0, 1057.0), (414.0, 1029.0), (910.0, 1227.0), (885.0, 1432.0)],
    [(280.0, 1359.0), (283.0, 1207.0), (np.nan, np.nan), (932.0, 1055.0)],
    [(510.0, 1035.0), (np.nan, np.nan), (517.0, 1501.0), (324.0, 1464.0)],
])
#: The two cones' top rims at the walkway's end (the one with a cable first), (2, camera, 2)
#: raw video px: the centre of the rim's ellipse, picked by eye on 4x crops (+-3 px). They
#: triangulate 640 mm apart, 190 mm above the walkway.
STATIC_CONE_TOPS = np.array([
    [(661.0, 1522.0), (270.5, 1318.5), (262.0, 969.5), (830.5, 859.5)],
    [(942.0, 1427.0), (631.0, 1343.5), (60.0, 1060.0), (610.0, 919.5)],
])
#: All static landmarks, (6, camera, 2) raw video px.
STATIC_LANDMARKS = np.concatenate([STATIC_BOLTS, STATIC_CONE_TOPS])
#: The calibration's image is 1088 x 1920 (as are ``calibration/extrinsics/camNN_ext.png``);
#: cam01 and cam02's videos are 1080 x 1920: the 1088-wide frame scaled by 1080/1088 and
#: letterboxed (7 px top and bottom). Registering each video's background on its extrinsics
#: image (SIFT, homography) measures ext = 1.0074 * video - (0.0, 7.2) px for both, and the
#: identity (< 0.4 px) for cam03/cam04.
LETTERBOXED = (True, True, False, False)
CALIBRATION_SIZE = (1088, 1920)


def file_calibration(root: Path):
    """The demo's Qualisys calibration (``calibration/Calib.qca.txt`` under ``root``):
    ``(cal, R (C, 3, 3), t (C, 3))`` — the loaded calibration (``cal.names``,
    ``cal.intrinsics``) and its camera poses."""
    from carapost.io.calibration import load_calibration

    cal = load_calibration(root / "calibration" / "Calib.qca.txt")
    R, t = cal.poses(1)
    return cal, R[0], t[0]


def video_to_calibration(xy: np.ndarray, camera: int) -> np.ndarray:
    """Raw video px ``(n, 2)`` of ``camera`` (0-based) to the calibration's image px (the
    letterbox of :data:`LETTERBOXED` undone: scale 1088/1080, 7.1 px top margin removed)."""
    xy = np.asarray(xy, float)
    if not LETTERBOXED[camera]:
        return xy.copy()
    s = CALIBRATION_SIZE[0] / 1080.0
    top = (CALIBRATION_SIZE[1] - CALIBRATION_SIZE[1] / s) / 2.0
    return np.c_[xy[..., 0] * s, (xy[..., 1] - top) * s].reshape(xy.shape)


def detect(image: np.ndarray, detector: str = "blobs", **overrides) -> dict:
    """Detections of one frame: ``"blobs"`` (white blobs, :data:`P2S_BLOBS`) or ``"spheres"``
    (shaded marker spheres, :data:`P2S_SPHERES`); ``overrides`` replace settings."""
    if detector == "blobs":
        from carapost.core.blobs import detect_blobs
        from carapost.model.params import BlobParameters
        return detect_blobs(image, BlobParameters(**{**P2S_BLOBS, **overrides}))
    if detector == "spheres":
        from carapost.core.sphere_markers import SphereParameters, detect_spheres
        return detect_spheres(image, SphereParameters(**{**P2S_SPHERES, **overrides}))
    raise ValueError(f"detector must be one of {DETECTORS}, got {detector!r}")


def auto_kwargs(bundle: bool = True, min_views: int = 3) -> dict:
    """Keyword arguments of :func:`auto_initialize` for the demo."""
    return dict(min_views=min_views, max_reprojection_px=3.0, caddies=(), bundle=bundle)


def skeleton_points(root: Path, frame: int = 0) -> np.ndarray:
    """Points along the markerless skeleton of a frame, (N, 3) mm in the calibration's frame."""
    trc = next((root / "pose-3d").glob("*.trc"))
    lines = trc.read_text().splitlines()
    row = lines[5 + frame].split("\t")
    kp = np.array([float(v) for v in row[2:]]).reshape(-1, 3)[:, [2, 0, 1]] * 1000.0
    segs = [kp[i] + np.linspace(0, 1, 20)[:, None] * (kp[j] - kp[i])
            for i in range(len(kp)) for j in range(i + 1, len(kp)) if np.linalg.norm(kp[i] - kp[j]) < 600]
    return np.concatenate(segs)


def on_body(xyz: np.ndarray, skeleton: np.ndarray) -> np.ndarray:
    """bool (P,): points within :data:`BODY_RADIUS_MM` of the skeleton."""
    if len(xyz) == 0:
        return np.zeros(0, bool)
    d = np.min(np.linalg.norm(xyz[:, None, :] - skeleton[None], axis=-1), axis=1)
    return d < BODY_RADIUS_MM


def near_person(xy: np.ndarray, skeleton: np.ndarray, intrinsics, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """bool (n,): detections ``xy (n, 2)`` of one camera within :data:`BODY_RADIUS_MM` of the
    skeleton, measured in the image (the pixel distance to the nearest projected skeleton
    point, scaled to mm at that point's depth)."""
    from carapost.core.camera import project
    if len(xy) == 0:
        return np.zeros(0, bool)
    p = project(skeleton, intrinsics, R, t)
    depth = (skeleton @ R.T + t)[:, 2]
    d = np.linalg.norm(np.asarray(xy, float)[:, None, :] - p[None], axis=-1)
    k = np.argmin(d, axis=1)
    return d[np.arange(len(xy)), k] * depth[k] / intrinsics.focal_length < BODY_RADIUS_MM
