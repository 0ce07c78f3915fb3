"""The Pose2Sim demo as an automatic-initialization case (shared by the slow test and the benchmark).

Four portrait videos of a person wearing small white retro-reflective body markers, with a
Qualisys calibration. Frame 0 is read from each video, white blobs are detected with the
project's detector (a small radius range, a low threshold: the markers are 2-4 px across and
dim), and :func:`~carapost.core.auto_init.auto_initialize` runs without caddies (the four
cameras stand around the room).

Pose2Sim's own markerless reconstruction of the same frames (``pose-3d/*.trc``, metres, its
axes ``(x, y, z)`` being our ``(y, z, x)``) tells which points lie on the person: within
:data:`BODY_RADIUS_MM` of its skeleton.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carapost.model.params import Initialize3DParameters

#: Blob Parameters for the demo's markers.
P2S_BLOBS = dict(find_black_blobs=False, find_white_blobs=True, white_min_radius=1.0, white_max_radius=6.0,
                 white_threshold=0.1, adaptive_background=True)
#: Initialize 3D parameters (the defaults: no caddy growth happens here).
P2S_INIT = Initialize3DParameters()
#: Points closer than this to the markerless skeleton are on the person.
BODY_RADIUS_MM = 150.0


def auto_kwargs(bundle: bool = True) -> dict:
    """Keyword arguments of :func:`auto_initialize` for the demo."""
    return dict(min_views=3, max_reprojection_px=2.0, caddies=(), bundle=bundle)


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
