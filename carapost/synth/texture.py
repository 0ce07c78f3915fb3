"""Albedo of the synthetic face: skin texture in material coordinates, and the eyes.

The skin texture is a grid over the face's material coordinates (``(u, v)`` mm, see
:mod:`carapost.synth.face`): skin tone with blotches and pores, darker brows with hair
streaks, lips, nostrils, the dark line where the lips meet (it stretches into the dark mouth
when the jaw opens), lash lines, a few faint moles, and hair above the forehead. The eyes
(sclera, iris, pupil) are drawn in *current* head coordinates inside the material region of
the open eye, so a closing lid covers the iris rather than squashing it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .expressions import LID_LO, LID_UP, eye_opening, mouth_seam
from .face import DOMAIN, EYE, EYE_HALF_WIDTH, MOUTH_HALF_WIDTH, NOSE_TIP, lip_line
from .surface import bilinear

__all__ = ["SkinTexture", "make_skin_texture", "eye_albedo", "SKIN_ALBEDO"]

#: Mean albedo of the skin.
SKIN_ALBEDO = 0.52


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-variance Gaussian-filtered white noise."""
    n = rng.standard_normal(shape).astype(np.float32)
    n = cv2.GaussianBlur(n, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    return n / max(float(n.std()), 1e-6)


@dataclass(frozen=True)
class SkinTexture:
    """Skin albedo on a grid of material coordinates.

    Attributes
    ----------
    albedo : float32 array (R, C)
        Albedo (0..1); row ``i`` is ``v = origin[1] + i * spacing``, column ``j`` is
        ``u = origin[0] + j * spacing``.
    origin : (float, float)
    spacing : float
        mm per texel.
    """

    albedo: np.ndarray
    origin: tuple[float, float]
    spacing: float

    def lookup(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Albedo at material coordinates (1-D arrays), float32."""
        c = ((np.asarray(u) - self.origin[0]) / self.spacing).astype(np.float32)
        r = ((np.asarray(v) - self.origin[1]) / self.spacing).astype(np.float32)
        return bilinear(self.albedo, c, r, 0.15)


_TEXTURES: dict[tuple[int, float], SkinTexture] = {}


def make_skin_texture(seed: int, spacing: float = 0.35) -> SkinTexture:
    """The skin albedo texture (deterministic for a seed; the last few are cached)."""
    key = (int(seed), float(spacing))
    if key not in _TEXTURES:
        if len(_TEXTURES) >= 4:
            _TEXTURES.pop(next(iter(_TEXTURES)))
        _TEXTURES[key] = _make_skin_texture(*key)
    return _TEXTURES[key]


def _make_skin_texture(seed: int, spacing: float) -> SkinTexture:
    rng = np.random.default_rng([seed, 7331])
    u0, u1, v0, v1 = DOMAIN
    u = np.arange(u0, u1 + 1e-9, spacing)
    v = np.arange(v0, v1 + 1e-9, spacing)
    U, V = np.meshgrid(u, v)
    shape = U.shape
    px = 1.0 / spacing  # texels per mm

    tone = (1.0 + 0.06 * _smooth_noise(rng, shape, 15.0 * px) + 0.035 * _smooth_noise(rng, shape, 3.0 * px)
            + 0.045 * _smooth_noise(rng, shape, 0.6 * px))
    a = SKIN_ALBEDO * tone
    # slightly darker (redder) cheeks and a lighter nose bridge / forehead
    for s in (1, -1):
        a *= 1.0 - 0.05 * np.exp(-0.5 * (((U - s * 40) / 16) ** 2 + ((V + 40) / 14) ** 2))
    a *= 1.0 + 0.04 * np.exp(-0.5 * ((U / 20) ** 2 + ((V - 35) / 25) ** 2))

    # eyebrows: an arch of hair above each eye with streaks along the arch
    streak = _smooth_noise(rng, shape, 0.35 * px)
    streak = cv2.GaussianBlur(streak, (0, 0), sigmaX=2.5 * px, sigmaY=0.15 * px)
    streak /= max(float(streak.std()), 1e-6)
    for s in (1, -1):
        x = s * U
        centre = 15.5 + 5.0 * np.sin(np.pi * (x - 10.0) / 42.0)
        half = 3.2 * np.clip(1.0 - np.abs((x - 28.0) / 26.0) ** 3, 0.0, 1.0)
        inside = np.clip((half - np.abs(V - centre)) / 0.8, 0.0, 1.0) * ((x > 9) & (x < 56))
        hair = 0.18 * (1.0 + 0.35 * streak)
        a = a * (1 - inside) + hair * inside

    # hair above the forehead and at the temples / sideburns
    hairline = 84.0 + 10.0 * (U / 60.0) ** 2
    hw = np.clip((V - hairline) / 2.0, 0.0, 1.0)
    side = 64.0 + 0.08 * np.clip(-V - 20.0, 0.0, None)
    hw = np.maximum(hw, np.clip((np.abs(U) - side) / 3.0, 0.0, 1.0) * np.clip((V + 45.0) / 8.0, 0.0, 1.0))
    a = a * (1 - hw) + 0.12 * (1.0 + 0.4 * streak) * hw

    # lips
    ln = lip_line(U)
    lip_up = np.exp(-0.5 * (((V - ln - 3.0) / 2.6) ** 4 + (U / MOUTH_HALF_WIDTH) ** 6))
    lip_lo = np.exp(-0.5 * (((V - ln + 3.6) / 3.0) ** 4 + (U / (MOUTH_HALF_WIDTH - 2)) ** 6))
    lips = np.clip(lip_up + lip_lo, 0.0, 1.0)
    a *= 1.0 - 0.25 * lips
    # the line where the lips meet; it becomes the dark mouth when the jaw opens
    seam = mouth_seam(U, V)
    a = a * (1 - seam) + 0.05 * seam

    # nostrils, on the underside of the nose
    for s in (1, -1):
        d = ((U - s * 7.0) / 3.6) ** 2 + ((V - (NOSE_TIP[1] - 8.0)) / 2.0) ** 2
        w = np.clip((1.0 - d) / 0.3, 0.0, 1.0)
        a = a * (1 - w) + 0.04 * w

    # lash lines along the lid margins, and a darker lid crease
    for s in (1, -1):
        lo, up, _ = eye_opening(U, V, s)
        t = np.abs(U - s * EYE[0]) < EYE_HALF_WIDTH + 1.0
        lash_up = np.exp(-0.5 * ((V - up - 0.4) / 0.55) ** 2) * t
        lash_lo = np.exp(-0.5 * ((V - lo + 0.3) / 0.45) ** 2) * t
        crease = np.exp(-0.5 * ((V - up - 4.0) / 1.2) ** 2) * t
        a *= (1.0 - 0.75 * lash_up) * (1.0 - 0.35 * lash_lo) * (1.0 - 0.12 * crease)

    # a few faint moles
    for _ in range(6):
        mu, mv = rng.uniform(-50, 50), rng.uniform(-100, 60)
        r = rng.uniform(0.6, 1.3)
        d = np.hypot(U - mu, V - mv)
        a *= 1.0 - 0.25 * np.clip((r - d) / 0.4 + 0.5, 0.0, 1.0)

    a = np.clip(a, 0.02, 0.95).astype(np.float32)
    return SkinTexture(albedo=a, origin=(u0, v0), spacing=spacing)


def eye_albedo(mu: np.ndarray, mv: np.ndarray, x: np.ndarray, y: np.ndarray,
               base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Albedo with the eyes drawn in.

    Parameters
    ----------
    mu, mv : arrays (N,)
        Material coordinates of the skin points.
    x, y : arrays (N,)
        Their current head-frame positions, mm.
    base : array (N,)
        Skin albedo.

    Returns
    -------
    albedo : float32 array (N,)
        ``base`` with the sclera, iris and pupil where the points belong to an open eye.
    eye : bool array (N,)
        Points on an eye.
    """
    out = np.array(base, dtype=np.float32, copy=True)
    is_eye = np.zeros(len(out), bool)
    for s in (1, -1):
        ex, ey = s * EYE[0], EYE[1]
        near = np.flatnonzero((np.abs(mu - ex) < EYE_HALF_WIDTH) & (mv > ey - LID_LO - 0.5) & (mv < ey + LID_UP + 0.5))
        if near.size == 0:
            continue
        _, _, inside = eye_opening(mu[near], mv[near], s)
        idx = near[inside]
        if idx.size == 0:
            continue
        r = np.hypot(x[idx] - ex, y[idx] - (ey + 0.3))
        # sclera darkening towards the corners, iris with a dark limbal ring, pupil
        t = np.abs(x[idx] - ex) / EYE_HALF_WIDTH
        sclera = 0.72 - 0.18 * t * t
        iris = 0.16 + 0.05 * np.cos(r * 4.0) - 0.08 * np.clip((r - 4.6) / 1.0, 0.0, 1.0)
        pupil = 0.03
        w_iris = np.clip((5.6 - r) / 0.35, 0.0, 1.0)
        w_pupil = np.clip((2.1 - r) / 0.25, 0.0, 1.0)
        val = sclera * (1 - w_iris) + iris * w_iris
        val = val * (1 - w_pupil) + pupil * w_pupil
        out[idx] = val
        is_eye[idx] = True
    return out, is_eye
