"""What a camera view draws over the image, computed with numpy from the take (no Qt).

All coordinates are raw image pixels of the camera (the views map them to the screen).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from carapost.core.camera import project
from carapost.model.take import Take

__all__ = ["Overlay", "compute_overlay", "project_points", "image_size"]


@dataclass
class Overlay:
    """Overlay geometry of one camera in one frame.

    Attributes
    ----------
    det : dict of arrays (n,)
        This frame's detections (``x y major minor angle polarity score``).
    det_owner : int array (n,)
        Point column each detection is attached to (-1 = unused).
    obs_cols : int array (k,)
        Point columns observed in this camera.
    obs_xy : float array (k, 2)
    obs_src : uint8 array (k,)
    obs_axes : float array (k, 3)
        Ring semi-axes and angle (the attached detection's, else a default circle).
    proj_cols : int array (m,)
        Point columns whose 3D position projects into the image.
    proj_xy : float array (m, 2)
    proj_connected : bool array (m,)
        The point has an observation in this camera (connected projection).
    """

    det: dict[str, np.ndarray] = field(default_factory=dict)
    det_owner: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    obs_cols: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    obs_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    obs_src: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    obs_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    proj_cols: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    proj_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    proj_connected: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def point_xy(self, P: int) -> np.ndarray:
        """Best 2D position of every point column (observation, else projection), (P, 2)."""
        out = np.full((P, 2), np.nan)
        out[self.proj_cols] = self.proj_xy
        out[self.obs_cols] = self.obs_xy
        return out


def image_size(take: Take, camera: int) -> tuple[int, int]:
    """(width, height) of a camera's images (from the source, else the calibration's sensor)."""
    cam = take.cameras[camera]
    w, h = cam.image_size
    if w <= 0 or h <= 0:
        w, h = cam.intrinsics.sensor_size
    return (int(w), int(h)) if w > 0 and h > 0 else (1280, 720)


def project_points(take: Take, camera: int, frame: int, xyz: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Project 3D points into a camera: (columns, xy) of those landing inside the image."""
    X = take.xyz[frame] if xyz is None else xyz
    R, t = take.R[frame, camera], take.t[frame, camera]
    if len(X) == 0 or not (np.isfinite(R).all() and np.isfinite(t).all()):
        return np.zeros(0, np.int64), np.zeros((0, 2))
    xy = project(np.asarray(X, float), take.cameras[camera].intrinsics, R, t)
    w, h = image_size(take, camera)
    ok = np.isfinite(xy).all(1) & (xy[:, 0] > -0.5) & (xy[:, 1] > -0.5) & (xy[:, 0] < w - 0.5) & (xy[:, 1] < h - 0.5)
    cols = np.flatnonzero(ok)
    return cols, xy[cols]


def compute_overlay(take: Take, camera: int, frame: int) -> Overlay:
    """Detections, observations and projections of one camera in one frame."""
    ov = Overlay()
    dets = take.detections[camera]
    ov.det = {k: np.asarray(v, float) for k, v in dets.frame(frame).items()}
    n = len(ov.det["x"])
    ov.det_owner = np.full(n, -1, np.int64)
    if take.n_points == 0:
        return ov
    od = take.obs_det[frame, :, camera]
    att = np.flatnonzero((od >= 0) & (od < n))
    ov.det_owner[od[att]] = att
    xy = take.obs_xy[frame, :, camera].astype(float)
    cols = np.flatnonzero(np.isfinite(xy).all(1))
    ov.obs_cols, ov.obs_xy = cols, xy[cols]
    ov.obs_src = take.obs_src[frame, cols, camera]
    axes = np.tile([4.0, 4.0, 0.0], (len(cols), 1))
    d = od[cols]
    has = (d >= 0) & (d < n)
    if has.any():
        axes[has, 0] = ov.det["major"][d[has]]
        axes[has, 1] = ov.det["minor"][d[has]]
        axes[has, 2] = ov.det["angle"][d[has]]
    ov.obs_axes = axes
    ov.proj_cols, ov.proj_xy = project_points(take, camera, frame)
    ov.proj_connected = np.isin(ov.proj_cols, cols)
    return ov
