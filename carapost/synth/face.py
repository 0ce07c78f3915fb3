"""The synthetic face at rest: an analytic height field in the head frame.

Head frame (mm): ``x`` towards the actor's **left**, ``y`` up, ``z`` out of the face (towards
the cameras); the origin is between the eyes, roughly on the skin. The rest surface is
``z = rest_height(u, v)``; a material point of the skin is named by its rest coordinates
``(u, v)`` (the expressions in :mod:`carapost.synth.expressions` move it).

The height field is a head-sized ellipsoid plus Gaussian features: brow ridge, eye sockets
with eyeballs, a nose whose tip stands about 28 mm proud of the cheeks (it hides markers on
the far side of the face from a side camera), alae, cheekbones, lips, chin. Outside the head
the surface falls steeply to :data:`FLOOR` (the dark background).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "FLOOR",
    "DOMAIN",
    "EYE",
    "EYE_HALF_WIDTH",
    "MOUTH_Y",
    "MOUTH_HALF_WIDTH",
    "NOSE_TIP",
    "rest_height",
    "lip_line",
]

#: Height of the background "floor" far behind the face, mm.
FLOOR = -150.0
#: Extent of the face grid: (u_min, u_max, v_min, v_max), mm.
DOMAIN = (-110.0, 110.0, -155.0, 130.0)
#: Centre of the left eye (the right eye is mirrored), mm.
EYE = (32.0, 0.0)
EYE_HALF_WIDTH = 13.0
#: Height of the mouth line at the centre and half width of the mouth, mm.
MOUTH_Y = -67.0
MOUTH_HALF_WIDTH = 24.0
NOSE_TIP = (0.0, -36.0)

# Head ellipsoid: centre (0, _YC, _ZC), semi-axes _A (x), _B (y), _C (z).
_A, _B, _C, _YC, _ZC = 80.0, 128.0, 95.0, -12.0, -75.0


def _g(x: np.ndarray, y: np.ndarray, sx: float, sy: float) -> np.ndarray:
    return np.exp(-0.5 * ((x / sx) ** 2 + (y / sy) ** 2))


def _pair(u: np.ndarray, y: np.ndarray, cx: float | np.ndarray, sx: float, sy: float) -> np.ndarray:
    """A mirrored pair of Gaussians at ``u = +-cx`` (smooth across the midline)."""
    return _g(u - cx, y, sx, sy) + _g(u + cx, y, sx, sy)


def lip_line(u: np.ndarray) -> np.ndarray:
    """Rest height ``v`` of the line where the lips meet, mm, as a function of ``u``.

    A gentle "cupid's bow": slightly higher at the corners.
    """
    u = np.asarray(u, dtype=float)
    t = np.clip(np.abs(u) / MOUTH_HALF_WIDTH, 0.0, 1.5)
    return MOUTH_Y + 2.0 * t * t


def rest_height(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rest skin height ``z`` (mm) at material coordinates ``(u, v)`` (mm), any shape."""
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    # Head: an ellipsoid continued smoothly past its rim so the sides fall away steeply.
    q = 1.0 - (u / _A) ** 2 - ((v - _YC) / _B) ** 2
    base = _ZC + _C * np.sign(q) * np.sqrt(np.abs(q))
    # Flatten the front a little (faces are flatter than ellipsoids across the cheeks).
    base = base - 6.0 * _g(u, v + 20.0, 26.0, 60.0)

    ex, ey = EYE
    feat = (
        # brow ridge and glabella
        4.5 * _pair(u, v - 15.0, 30.0, 16.0, 5.5)
        + 2.5 * _g(u, v - 12.0, 9.0, 7.0)
        # eye sockets and eyeballs
        - 10.0 * _pair(u, v - ey + 1.0, ex, 13.0, 9.5)
        + 6.5 * _pair(u, v - ey, ex, 9.0, 6.5)
        # cheekbones and lower cheeks
        + 7.0 * _pair(u, v + 28.0, 42.0, 17.0, 13.0)
        + 3.0 * _pair(u, v + 62.0, 36.0, 14.0, 14.0)
        # lips, mentolabial sulcus, chin
        + 6.0 * _g(u, v - MOUTH_Y - 6.5, 21.0, 4.8)
        + 5.0 * _g(u, v - MOUTH_Y + 6.5, 18.0, 4.2)
        - 2.5 * _g(u, v + 84.0, 15.0, 3.5)
        + 8.0 * _g(u, v + 101.0, 16.0, 9.0)
        # nasolabial fold (a shallow groove from the ala to beside the mouth corner)
        - 2.0 * _pair(u, v + 58.0, 18.0 + 0.45 * (-45.0 - v), 3.5, 14.0)
    )
    return base + feat + _nose(u, v)


def _nose(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Nose height above the face: ridge from the bridge to the tip, alae, a steep underside."""
    tip_v = NOSE_TIP[1]
    # fraction along the ridge from the bridge (v = 10) to the tip
    t = np.clip((10.0 - v) / (10.0 - tip_v), 0.0, 1.0)
    ridge = 26.0 * t ** 1.25
    # the underside: a steep but smooth drop below the tip to the upper lip
    under = 1.0 / (1.0 + np.exp((v - (tip_v - 6.0)) / -2.2))
    width = 5.5 + 6.0 * t
    nose = ridge * under * np.exp(-0.5 * (u / width) ** 2)
    # rounded tip and alae (wings of the nostrils)
    nose = nose + 4.0 * _g(u, v - tip_v, 6.5, 5.5)
    nose = nose + 8.0 * _pair(u, v - tip_v + 6.0, 13.0, 5.5, 5.0)
    return nose
