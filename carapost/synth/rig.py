"""The head-mounted rig: helmet, brim card, four cameras on two caddies, lights.

Frames
------
* **World = brim frame** (mm): ``X`` along the brim card, ``Y`` up the card, ``Z`` out of
  the card towards the cameras; origin at the card's centre.
* **Head frame** (see :mod:`carapost.synth.face`): ``x`` to the actor's left, ``y`` up,
  ``z`` out of the face. At rest the brim card sits about 25 mm in front of the upper forehead,
  its top tilted 20 degrees towards the cameras, so the head frame is the world frame
  rotated by 20 degrees about ``X`` and shifted.

Cameras look at the face from about 20 cm: channels 0 (upper) and 1 (lower) on the actor's
left arm, 2 (upper) and 3 (lower) on the right arm; each caddy is a vertical stereo pair
with a 50 mm baseline. All four see the brim in the upper part of the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carapost.core.camera import Intrinsics

__all__ = ["Rig", "nominal_rig", "look_at", "BRIM_CENTRE_HEAD", "BRIM_TILT_DEG"]

#: Centre of the brim card in the rest head frame, mm.
BRIM_CENTRE_HEAD = (0.0, 70.0, 22.0)
#: Tilt of the card's top towards the cameras, degrees.
BRIM_TILT_DEG = 20.0

# Camera centres and look-at targets in the rest head frame (mm): (0, 1) left arm, (2, 3) right.
_CAMERAS = [
    ((88.0, 22.0, 145.0), (0.0, 2.0, 0.0)),
    ((88.0, -28.0, 140.0), (0.0, -3.0, 0.0)),
    ((-88.0, 22.0, 145.0), (0.0, 2.0, 0.0)),
    ((-88.0, -28.0, 140.0), (0.0, -3.0, 0.0)),
]
# Per-camera deviations of the focal length (relative) and principal point (px at 1280 x 720).
_F_DEV = (0.004, -0.006, 0.007, -0.003)
_PP_DEV = ((3.5, -2.0), (-4.0, 3.0), (2.0, 4.5), (-3.0, -3.5))
# Radial terms at 1280 x 720 (about 2 px of correction at the corners), scaled with the size.
_RADIAL = ((4.0e-9, 1.5e-15), (3.6e-9, 1.8e-15), (4.4e-9, 1.2e-15), (3.8e-9, 1.6e-15))


def look_at(centre: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera rotation (3, 3) of a camera at ``centre`` looking at ``target``.

    The camera's ``+z`` points at the target, ``+y`` (image down) against ``up``.
    """
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


@dataclass(frozen=True)
class Rig:
    """Nominal geometry of the rig.

    Attributes
    ----------
    intrinsics : list of Intrinsics (C,)
    R : array (C, 3, 3)
        Nominal world-to-camera rotations.
    t : array (C, 3)
        Nominal translations, mm.
    head_R : array (3, 3)
        Rest head-to-world rotation: ``X_world = head_R @ X_head + head_t``.
    head_t : array (3,)
    lights : array (L, 3)
        Light positions in the world frame, mm (one per caddy, beside the cameras).
    caddies : tuple of (int, int)
    names : list of str
        Camera names.
    """

    intrinsics: list[Intrinsics]
    R: np.ndarray
    t: np.ndarray
    head_R: np.ndarray
    head_t: np.ndarray
    lights: np.ndarray
    caddies: tuple[tuple[int, int], ...]
    names: list[str]

    @property
    def n_cameras(self) -> int:
        return len(self.intrinsics)

    def centres(self) -> np.ndarray:
        """Camera centres (C, 3) in the world frame, mm."""
        return -np.einsum("cji,cj->ci", self.R, self.t)


def head_to_world() -> tuple[np.ndarray, np.ndarray]:
    """Rest head-to-world rotation (3, 3) and translation (3,)."""
    a = np.deg2rad(BRIM_TILT_DEG)
    # brim axes expressed in the head frame (rows): X along the card, Y up it, Z its normal
    axes = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), np.sin(a)], [0.0, -np.sin(a), np.cos(a)]])
    R = axes
    t = -axes @ np.asarray(BRIM_CENTRE_HEAD)
    return R, t


def nominal_rig(width: int = 1280, height: int = 720, *, focal_length: float = 515.0,
                distortion: bool = True) -> Rig:
    """The synthetic rig for an image size (intrinsics scale with the image height).

    Parameters
    ----------
    width, height : int
        Image size, pixels.
    focal_length : float
        Focal length at 720 rows, pixels.
    distortion : bool
        Include the radial terms.
    """
    hR, ht = head_to_world()
    scale = height / 720.0
    intr, Rs, ts = [], [], []
    up_w = hR @ np.array([0.0, 1.0, 0.0])
    for c, (centre_h, target_h) in enumerate(_CAMERAS):
        C = hR @ np.asarray(centre_h) + ht
        T = hR @ np.asarray(target_h) + ht
        R = look_at(C, T, up_w)
        Rs.append(R)
        ts.append(-R @ C)
        f = focal_length * scale * (1.0 + _F_DEV[c])
        pp = (0.5 * (width - 1) + _PP_DEV[c][0] * scale, 0.5 * (height - 1) + _PP_DEV[c][1] * scale)
        k1, k2 = _RADIAL[c]
        radial = (k1 / scale ** 2, k2 / scale ** 4, 0.0) if distortion else (0.0, 0.0, 0.0)
        intr.append(Intrinsics(focal_length=f, principal_point=pp, sensor_size=(width, height), radial=radial))
    lights_h = np.array([(95.0, -20.0, 150.0), (-95.0, -20.0, 150.0)])
    lights = lights_h @ hR.T + ht
    return Rig(intrinsics=intr, R=np.array(Rs), t=np.array(ts), head_R=hR, head_t=ht, lights=lights,
               caddies=((0, 1), (2, 3)), names=[f"Synth_Cam{c}" for c in range(4)])
