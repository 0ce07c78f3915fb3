"""Facial expressions: where each material point of the skin is in a given expression state.

An expression state is a vector of channel amplitudes (:data:`CHANNELS`, each 0..1). The
deformation is a smooth function of the material coordinates ``(u, v)`` (mm, the rest
position in the head frame, see :mod:`carapost.synth.face`):

* ``smile_L/R`` pull the mouth corners up and out and raise the cheeks;
* ``pucker`` pushes the lips forward and draws the corners in;
* ``puff`` pushes the lower cheeks outwards;
* ``brow_L/R`` lift the brows and forehead;
* ``blink_L/R`` lower the upper lid over the eye (the eye opening is squeezed to a slit); the
  skin over the tarsal plate moves with the lid margin, the skin above it stretches;
* ``jaw`` rotates the lower face (below the lip line) about a jaw axis behind the cheeks, up
  to 15 degrees: the lips part and the dark mouth (upper teeth showing) opens between them.

Everything is vectorised over any array shape of points.
"""

from __future__ import annotations

import numpy as np

from .face import EYE, EYE_HALF_WIDTH, MOUTH_HALF_WIDTH, lip_line, rest_height

__all__ = [
    "CHANNELS",
    "JAW_MAX_DEG",
    "JAW_PIVOT",
    "PRESEPTAL_FADE_MM",
    "TARSAL_HEIGHT_MM",
    "Deformer",
    "blink_displacement",
    "deform",
    "eye_opening",
    "jaw_weight",
    "jaw_weights",
    "mouth_seam",
]

#: Expression channels, in the order of a state vector.
CHANNELS = ("jaw", "smile_L", "smile_R", "pucker", "puff", "brow_L", "brow_R", "blink_L", "blink_R")
#: Jaw rotation at ``jaw = 1``, degrees.
JAW_MAX_DEG = 15.0
#: A point on the jaw's rotation axis (the axis is parallel to the head ``x`` axis), mm.
JAW_PIVOT = (0.0, -30.0, -85.0)
_CH = {name: i for i, name in enumerate(CHANNELS)}
#: Upper and lower lid margins above / below the eye centre at the middle of the eye, mm.
LID_UP, LID_LO = 5.5, 4.0
#: Height of the upper tarsal plate above the lid margin at the middle of the eye, mm (in
#: ``v``, the frontal projection; 8.65 mm along the synthetic skin, which slopes back over the
#: eyeball): the skin over it follows the margin in a blink. The adult upper tarsus is
#: 9.3 +- 0.9 mm high centrally in Korean cadaver lids and 10-12 mm in Caucasians ("Shape and
#: height of tarsal plates", 54 lids; Gray's Anatomy, 41st ed., says about 10 mm) and tapers
#: towards the canthi (to about 70 % a quarter of the lid from either end): here it follows the
#: lid margin's profile (87 % there). The lower end of the range, because of the brow (below).
TARSAL_HEIGHT_MM = 8.0
#: Height above the tarsal plate over which the blink displacement fades out, mm (middle of the
#: eye): the preseptal skin, which in a real open eye is tucked into the lid fold and unfolds in
#: a blink, here stretches (up to 5x). The synthetic brow sits low (its markers 14.4 mm above
#: the margin, its hair from 11.8 mm; about 20 mm in real faces): the fade ends below both,
#: so brows and forehead do not move in a blink.
PRESEPTAL_FADE_MM = 3.5


def _g(x: np.ndarray, y: np.ndarray, sx: float, sy: float) -> np.ndarray:
    return np.exp(-0.5 * ((x / sx) ** 2 + (y / sy) ** 2))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def eye_opening(u: np.ndarray, v: np.ndarray, side: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest lid margins of one eye at material ``u``.

    Parameters
    ----------
    u, v : arrays
        Material coordinates, mm.
    side : +1 (left eye) or -1 (right eye)

    Returns
    -------
    lo, up : arrays
        ``v`` of the lower and upper lid margins (equal outside the eye).
    inside : bool array
        Material points of the open eye (between the margins).
    """
    ex, ey = side * EYE[0], EYE[1]
    t = (np.asarray(u, float) - ex) / EYE_HALF_WIDTH
    s = np.sqrt(np.clip(1.0 - t * t, 0.0, None))
    lo = ey - LID_LO * s
    up = ey + LID_UP * s
    inside = (np.asarray(v) > lo) & (np.asarray(v) < up)
    return lo, up, inside


def blink_displacement(u: np.ndarray, v: np.ndarray, side: int) -> np.ndarray:
    """Displacement ``(dy, dz)`` (mm, array ``shape + (2,)``) of a full blink of one eye.

    The upper lid margin comes down 0.97 of the way to the lower margin (a slit stays, so the
    rest -> current map remains one-to-one); the open eye between the margins is squeezed
    into that slit. The pretarsal skin -- from the margin up to the upper border of the
    tarsal plate, :data:`TARSAL_HEIGHT_MM` above it at the middle of the eye -- follows the
    margin fully (the tarsus is rigid); above it the displacement fades to nothing over
    :data:`PRESEPTAL_FADE_MM` (the preseptal skin unfolding from the lid fold), below the brow.
    Both heights follow the margin's profile (tallest at the middle of the eye, nothing at the
    corners). Where the lid covers the eye it is lifted a little (it slides over the eyeball).
    The lower lid does not move.
    """
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    lo, up, _ = eye_opening(u, v, side)
    gap = up - lo
    profile = gap / (LID_UP + LID_LO)                 # 1 at the middle of the eye, 0 at the corners
    top = up + TARSAL_HEIGHT_MM * profile             # upper border of the tarsal plate
    fade = np.maximum(PRESEPTAL_FADE_MM * profile, 1e-9)
    in_eye = np.clip(v - lo, 0.0, None)
    dy = 0.97 * np.where(v < up, -np.minimum(in_eye, gap), -gap * (1.0 - _smoothstep((v - top) / fade)))
    dz = 1.2 * np.clip(-dy / 9.5, 0.0, 1.0) * (v >= up)
    return np.stack([dy, dz], axis=-1)


def jaw_weights(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How much of the jaw rotation material points follow, as seen from each lip.

    Returns two smooth weights: ``upper`` (about 0 along the lip line inside the mouth) and
    ``lower`` (about 1 there). They agree beyond the mouth corners, where the skin stretches
    over the jaw. A point follows ``upper`` above the lip line and ``lower`` below it (see
    :func:`jaw_weight`): inside the mouth the lips part and the mouth opens.
    """
    u = np.asarray(u, float)
    v = np.asarray(v, float)
    au = np.abs(u)
    out = np.clip(au - MOUTH_HALF_WIDTH, 0.0, None)
    soft = 0.8 + 0.7 * out
    # the lips' offset from the line, fading to nothing just beyond the corners
    delta = 2.5 * (1.0 - _smoothstep(out / 3.0))
    lip = lip_line(u)
    # far out on the cheeks the weight fades upwards and is gone at the cheekbones
    fade = _smoothstep((-12.0 - v) / 20.0)
    return _sigmoid((lip - delta - v) / soft) * fade, _sigmoid((lip + delta - v) / soft) * fade


def jaw_weight(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """How much of the jaw rotation a material point follows (0 above the lips, 1 below)."""
    upper, lower = jaw_weights(u, v)
    return np.where(np.asarray(v, float) >= lip_line(u), upper, lower)


def mouth_seam(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """0..1 profile of the line where the lips meet (material coordinates)."""
    au = np.abs(np.asarray(u, float))
    across = np.exp(-0.5 * ((np.asarray(v, float) - lip_line(u)) / 0.6) ** 2)
    return across * _sigmoid((MOUTH_HALF_WIDTH - 1.0 - au) / 1.2)


class Deformer:
    """The deformation of a fixed set of material points, fast for many expression states.

    Every channel but ``jaw`` moves the skin linearly in its amplitude, so its displacement
    field is evaluated once here; the jaw is a rotation applied last.

    Parameters
    ----------
    u, v : arrays, same shape S
        Material (rest) coordinates, mm.
    height : array S, optional
        ``rest_height(u, v)`` if already known.
    """

    def __init__(self, u: np.ndarray, v: np.ndarray, height: np.ndarray | None = None) -> None:
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        if u.shape != v.shape:
            raise ValueError(f"u and v must have the same shape, got {u.shape} and {v.shape}")
        z = rest_height(u, v) if height is None else np.asarray(height, dtype=float)
        self.shape = u.shape
        self.rest = np.stack([u, v, z], axis=-1)
        basis = np.zeros((len(CHANNELS),) + u.shape + (3,))
        for side, smile, brow, blink in ((1, "smile_L", "brow_L", "blink_L"), (-1, "smile_R", "brow_R", "blink_R")):
            b = basis[_CH[smile]]
            w = _g(u - side * 25.0, v + 65.0, 13.0, 11.0)
            b[..., 0] += side * 5.0 * w
            b[..., 1] += 5.0 * w
            b[..., 2] -= 2.5 * w
            w = _g(u - side * 38.0, v + 40.0, 16.0, 13.0)
            b[..., 0] += side * 1.0 * w
            b[..., 1] += 3.5 * w
            b[..., 2] += 2.0 * w
            b = basis[_CH[brow]]
            w = _g(u - side * 30.0, v - 22.0, 24.0, 16.0) * _sigmoid((v - 7.0) / 1.5)
            b[..., 1] += 6.0 * w
            b[..., 2] += 0.5 * w
            b = basis[_CH[blink]]
            b[..., 1:] += blink_displacement(u, v, side)
        b = basis[_CH["pucker"]]
        w = _g(u, v + 67.0, 20.0, 10.0)
        b[..., 0] -= 0.25 * u * w
        b[..., 2] += 6.0 * w
        b = basis[_CH["puff"]]
        for side in (1, -1):
            w = _g(u - side * 40.0, v + 62.0, 15.0, 16.0)
            b[..., 0] += side * 3.5 * w
            b[..., 2] += 4.5 * w
        self.basis = basis
        self.jaw_upper, self.jaw_lower = jaw_weights(u, v)
        self.jaw_w = np.where(v >= lip_line(u), self.jaw_upper, self.jaw_lower)

    def __call__(self, state: np.ndarray, window: tuple[slice, ...] | None = None, *,
                 lip: str | None = None) -> np.ndarray:
        """Current head-frame positions, array ``S + (3,)`` mm, in expression ``state``.

        ``window`` (slices of the point array's axes) evaluates only part of the points.
        ``lip="upper"`` / ``"lower"`` deforms every point as if it were on that side of the
        lip line (a smooth map, for inverting it); by default each point follows its side.
        """
        a = np.clip(np.asarray(state, dtype=float), 0.0, 1.0)
        if a.shape != (len(CHANNELS),):
            raise ValueError(f"expression state must have {len(CHANNELS)} channels, got shape {a.shape}")
        win = (...,) if window is None else tuple(window)
        P = self.rest[win].copy()
        for k in np.flatnonzero(a > 0):
            P += a[k] * self.basis[k][win]
        kj = a[_CH["jaw"]]
        if kj > 0:
            w = {None: self.jaw_w, "upper": self.jaw_upper, "lower": self.jaw_lower}[lip][win]
            theta = np.deg2rad(JAW_MAX_DEG) * kj * w
            py, pz = JAW_PIVOT[1], JAW_PIVOT[2]
            dy0 = P[..., 1] - py
            dz0 = P[..., 2] - pz
            c, s = np.cos(theta), np.sin(theta)
            P[..., 1] = py + c * dy0 - s * dz0
            # the condyle slides forwards as the jaw opens
            P[..., 2] = pz + s * dy0 + c * dz0 + 9.0 * kj * w
        return P


def deform(u: np.ndarray, v: np.ndarray, state: np.ndarray) -> np.ndarray:
    """Current head-frame positions ``S + (3,)`` (mm) of material points ``(u, v)`` (shape S).

    A one-off :class:`Deformer`; build a :class:`Deformer` to evaluate many states.
    """
    return Deformer(u, v)(state)
