"""Image formation: the face, the brim card and the painted dots as a camera sees them.

Per camera and frame:

1. Rays through a grid of pixels (``shading_scale`` times coarser than the image) are cast
   against the brim card (analytic) and the skin height field (:mod:`.surface`).
2. Each hit is shaded: Lambertian light from the two lamps beside the caddies with inverse
   square fall-off, a little ambient light and a weak specular sheen (strong on the eyes);
   the albedo comes from the skin texture (:mod:`.texture`), the eyes, or the card. Rays that
   miss are the dark inside of the helmet.
3. The shaded image is interpolated to full resolution; the dots (face markers and brim dots)
   are composited at full resolution from their exact coverage (:mod:`.dots`), cut by the
   nose or the card where those hide part of a dot.
4. Vignetting, optical blur, shot and read noise, 8-bit quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from carapost.core.camera import Intrinsics

from .card import BrimCard
from .dots import dot_patches
from .rays import RayGrid, hits_all, rotate
from .surface import FaceSurface, bilinear
from .texture import SkinTexture, eye_albedo

__all__ = ["FrameScene", "Renderer", "INK_ALBEDO"]

#: Albedo of black and white paint.
INK_ALBEDO = {"black": 0.035, "white": 0.92}
_AMBIENT = 0.10
_LAMP = 0.62  # irradiance of a lamp at _LAMP_DIST, head-on
_LAMP_DIST = 200.0
_BACKGROUND = 0.05  # radiance of the helmet's inside (times exposure)
_MOUTH = 0.03  # albedo inside the mouth
_CARD_MARGIN = 24  # shading pixels around the card's image searched for it
_TEETH = 0.42  # albedo of the teeth


@dataclass
class FrameScene:
    """Everything the renderer needs for one frame.

    Attributes
    ----------
    surface : FaceSurface
        The skin (head frame).
    head_R, head_t : arrays (3, 3), (3,)
        Head-to-world pose.
    R, t : arrays (C, 3, 3), (C, 3)
        World-to-camera poses.
    dots_xyz, dots_normal : arrays (D, 3)
        Dot centres and unit normals (world frame): face markers then brim dots.
    dots_radius, dots_ink : arrays (D,)
        Radii (mm) and albedo of the paint.
    dots_face : bool array (D,)
        Dots on the skin (the nose or the card may hide part of them).
    dots_draw : bool array (D, C)
        Which dots to draw in each camera (facing it, not hidden by a blink, not fully
        occluded).
    dots_cut : bool array (D, C)
        Dots partly hidden in a camera: their pixels are tested against the occluders.
    """

    surface: FaceSurface
    head_R: np.ndarray
    head_t: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dots_xyz: np.ndarray
    dots_normal: np.ndarray
    dots_radius: np.ndarray
    dots_ink: np.ndarray
    dots_face: np.ndarray
    dots_draw: np.ndarray
    dots_cut: np.ndarray


def _normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors of component-major ``v`` (3, N) (in place)."""
    inv = 1.0 / np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    v *= inv
    return v


class Renderer:
    """Renders frames of a synthetic take.

    Parameters
    ----------
    intrinsics : list of Intrinsics (C,)
    width, height : int
    lights : array (L, 3)
        Lamp positions, world frame, mm.
    card : BrimCard
    texture : SkinTexture
    shading_scale : int
    exposure : float
        Grey level of albedo 1 lit by one lamp head-on at 200 mm.
    blur_sigma : float
    noise : bool
    read_noise, shot_noise : float
    vignetting : float
    seed : int
    """

    def __init__(self, intrinsics: list[Intrinsics], width: int, height: int, *, lights: np.ndarray,
                 card: BrimCard, texture: SkinTexture, shading_scale: int = 2, exposure: float = 255.0,
                 blur_sigma: float = 0.7, noise: bool = True, read_noise: float = 1.2,
                 shot_noise: float = 0.035, vignetting: float = 0.25, seed: int = 0) -> None:
        self.intrinsics = list(intrinsics)
        self.width, self.height = int(width), int(height)
        self.lights = np.asarray(lights, float)
        self.card = card
        self.texture = texture
        self.scale = int(shading_scale)
        self.exposure = float(exposure)
        self.blur_sigma = float(blur_sigma)
        self.noise = bool(noise)
        self.read_noise = float(read_noise)
        self.shot_noise = float(shot_noise)
        self.seed = int(seed)
        self._grids = [RayGrid(intr, self.width, self.height, self.scale) for intr in self.intrinsics]
        self.low_shape = self._grids[0].shape if self._grids else (0, 0)
        yy, xx = np.mgrid[0:self.height, 0:self.width].astype(np.float32)
        r2 = ((xx - 0.5 * (self.width - 1)) ** 2 + (yy - 0.5 * (self.height - 1)) ** 2)
        r2 /= r2.max()
        self._vignette = (1.0 - float(vignetting) * r2).astype(np.float32)
        self._gain = self._vignette * np.float32(self.exposure)
        self._noise_bank: np.ndarray | None = None
        self._card_cache: list[np.ndarray | None] = [None] * len(self.intrinsics)

    # ---------------------------------------------------------------- shading
    def _irradiance(self, P: np.ndarray, n: np.ndarray, view: np.ndarray, gloss: np.ndarray | float,
                    sheen: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Diffuse irradiance and specular radiance, float32 (N,) each.

        ``P`` points, ``n`` unit normals, ``view`` unit vectors towards the camera: (3, N).
        """
        E = np.full(P.shape[1], _AMBIENT, np.float32)
        spec = np.zeros(P.shape[1], np.float32)
        for L in self.lights.astype(np.float32):
            l = L[:, None] - P
            d2 = l[0] * l[0] + l[1] * l[1] + l[2] * l[2]
            inv = 1.0 / np.sqrt(d2)
            l *= inv
            fall = np.float32(_LAMP_DIST ** 2) / d2
            ndl = n[0] * l[0] + n[1] * l[1] + n[2] * l[2]
            E += np.float32(_LAMP) * fall * np.maximum(ndl, 0)
            h = _normalize(l + view)
            nh = np.maximum(n[0] * h[0] + n[1] * h[1] + n[2] * h[2], 0)
            spec += sheen * fall * np.power(nh, gloss)
        return E, spec

    def _card_rays(self, c: int, C: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Indices of the shading rays of camera ``c`` that may meet the card.

        Found once, from the first pose seen, as the rays meeting the card grown by a wide
        margin (the card is fixed to the helmet and the cameras flex by well under a pixel).
        """
        if self._card_cache[c] is None:
            grid = self._grids[c]
            s, _ = self.card.intersect_components(C, rotate(R.T, grid.rays))
            m = np.isfinite(s).reshape(grid.shape).astype(np.uint8)
            k = 2 * _CARD_MARGIN + 1
            m = cv2.dilate(m, np.ones((k, k), np.uint8))
            self._card_cache[c] = np.flatnonzero(m.ravel())
        return self._card_cache[c]

    def _geometry(self, cams: list[int], scene: FrameScene) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """For each camera: distances to the skin and to the card, and the card normals."""
        cards, origins, to_heads = [], [], []
        hR, ht = scene.head_R, scene.head_t
        for c in cams:
            R, t = scene.R[c], scene.t[c]
            C = -R.T @ t
            rays = self._grids[c].rays
            n_rays = rays.shape[1]
            # the card: only rays near where it was seen before can meet it (the rig barely flexes)
            near = self._card_rays(c, C, R)
            s_card = np.full(n_rays, np.inf, np.float32)
            n_card = np.zeros((3, n_rays), np.float32)
            if near.size:
                s_near, n_near = self.card.intersect_components(C, rotate(R.T, rays[:, near]))
                s_card[near] = s_near
                n_card[:, near] = n_near
            cards.append((s_card, n_card))
            origins.append(hR.T @ (C - ht))
            to_heads.append(hR.T @ R.T)
        s_face = hits_all([self._grids[c] for c in cams], scene.surface, origins, to_heads, [sc for sc, _ in cards])
        return [(sf, sc, nc) for sf, (sc, nc) in zip(s_face, cards)]

    def _shade(self, c: int, scene: FrameScene, geometry: tuple[np.ndarray, np.ndarray, np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray]:
        """Low-resolution radiance and diffuse irradiance of camera ``c``, float32 arrays (h, w)."""
        R, t = scene.R[c], scene.t[c]
        C = -R.T @ t
        rays = self._grids[c].rays
        n_rays = rays.shape[1]
        hR, ht = scene.head_R, scene.head_t
        o_h = hR.T @ (C - ht)
        to_head = hR.T @ R.T
        s_face, s_card, n_card = geometry
        face = np.isfinite(s_face)
        card = ~face & np.isfinite(s_card)
        radiance = np.full(n_rays, _BACKGROUND, np.float32)
        E_all = np.zeros(n_rays, np.float32)
        # skin
        fi = np.flatnonzero(face)
        if fi.size:
            sf = s_face[fi].astype(np.float32)
            Ph = o_h.astype(np.float32)[:, None] + sf * rotate(to_head, rays[:, fi])
            H, hx, hy, U, V, cavity, teeth = scene.surface.sample_all(Ph[0], Ph[1])
            nh = _normalize(np.stack([-hx, -hy, np.ones_like(hx)]))
            n_w = rotate(hR, nh)
            d_wf = rotate(R.T, rays[:, fi])
            P_w = C.astype(np.float32)[:, None] + sf * d_wf
            alb = self.texture.lookup(U, V)
            alb, eye = eye_albedo(U, V, Ph[0], Ph[1], alb)
            if np.any(cavity > 0):
                # inside the open mouth: dark, with the upper teeth just below the upper lip
                inner = _MOUTH + (_TEETH - _MOUTH) * np.clip(teeth / np.maximum(cavity, 1e-6), 0, 1)
                alb = alb * (1 - cavity) + cavity * inner
            gloss = np.where(eye, np.float32(2500.0), np.float32(18.0))
            sheen = np.where(eye, np.float32(0.9), np.float32(0.05))
            E, spec = self._irradiance(P_w, n_w, -d_wf, gloss, sheen)
            radiance[fi] = E * alb + spec
            E_all[fi] = E
        ci = np.flatnonzero(card)
        if ci.size:
            sc = s_card[ci].astype(np.float32)
            d_wc = rotate(R.T, rays[:, ci])
            P_w = C.astype(np.float32)[:, None] + sc * d_wc
            E, spec = self._irradiance(P_w, n_card[:, ci], -d_wc, np.float32(12.0), np.float32(0.02))
            radiance[ci] = E * np.float32(self.card.albedo) + spec
            E_all[ci] = E
        hl, wl = self.low_shape
        return radiance.reshape(hl, wl), E_all.reshape(hl, wl)

    # ------------------------------------------------------------------- dots
    def _composite_dots(self, c: int, scene: FrameScene, img: np.ndarray, E_low: np.ndarray) -> None:
        """Paint the dots visible in camera ``c`` into ``img`` (H, W) radiance, in place."""
        sel = np.flatnonzero(scene.dots_draw[:, c])
        if sel.size == 0:
            return
        R, t = scene.R[c], scene.t[c]
        H, W = img.shape
        flat_img = img.reshape(-1)
        s = self.scale
        # face dots and brim dots are rasterised separately: their patches differ in size
        for group in (sel[scene.dots_face[sel]], sel[~scene.dots_face[sel]]):
            if group.size == 0:
                continue
            patches = dot_patches(scene.dots_xyz[group], scene.dots_normal[group], scene.dots_radius[group],
                                  self.intrinsics[c], R, t)
            alpha = patches.alpha
            cut = scene.dots_cut[group, c]
            if np.any(cut):
                alpha = alpha.copy()
                self._cut(c, scene, patches, np.flatnonzero(cut), alpha, scene.dots_radius[group])
            kk, ii, jj = np.nonzero(alpha > 0)
            x = patches.x0[kk] + jj
            y = patches.y0[kk] + ii
            keep = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            kk, ii, jj, x, y = kk[keep], ii[keep], jj[keep], x[keep], y[keep]
            a = alpha[kk, ii, jj]
            # irradiance at the dot pixels, interpolated from the shading grid
            off = np.float32(0.5 * (s - 1))
            Ep = bilinear(E_low, (x.astype(np.float32) - off) / s, (y.astype(np.float32) - off) / s, 0.0,
                        border_mode=cv2.BORDER_REPLICATE)
            ink = scene.dots_ink[group][kk].astype(np.float32)
            idx = y * W + x
            flat_img[idx] = flat_img[idx] * (1.0 - a) + a * Ep * ink

    def _cut(self, c: int, scene: FrameScene, patches, which: np.ndarray, alpha: np.ndarray,
             radii: np.ndarray) -> None:
        """Zero the coverage of dot pixels hidden behind the skin or the card.

        ``which`` indexes the patches to test, ``radii`` (one per patch) are the dots' radii.
        """
        R, t = scene.R[c], scene.t[c]
        C = -R.T @ t
        hR, ht = scene.head_R, scene.head_t
        o_h = hR.T @ (C - ht)
        a = alpha[which]
        idx = np.nonzero(a > 0)
        if idx[0].size == 0:
            return
        k = which[idx[0]]
        d_cam = patches.rays[k, idx[1], idx[2]].astype(float)
        depth = patches.depth[k, idx[1], idx[2]].astype(float)
        d_w = d_cam @ R
        s_card, _ = self.card.intersect(C, d_w)
        hidden = s_card < depth - 0.3
        d_h = d_w @ hR
        tol = np.maximum(0.4, 1.5 * np.asarray(radii, float)[k])
        hidden |= scene.surface.occluded(o_h, o_h + depth[:, None] * d_h, tolerance=tol)
        a[idx[0][hidden], idx[1][hidden], idx[2][hidden]] = 0.0
        alpha[which] = a

    # ------------------------------------------------------------------ frame
    def _noise(self, frame: int, c: int, img: np.ndarray) -> np.ndarray:
        n = img.size
        if self._noise_bank is None:
            rng = np.random.default_rng([self.seed, 555])
            self._noise_bank = rng.standard_normal(3 * n + 4096).astype(np.float32)
        off = int(np.random.default_rng([self.seed, frame, c, 777]).integers(0, 2 * n))
        z = self._noise_bank[off:off + n].reshape(img.shape)
        sigma = np.sqrt(self.read_noise ** 2 + self.shot_noise * np.maximum(img, 0.0))
        return img + sigma * z

    def render(self, frame: int, scene: FrameScene, cameras: list[int] | None = None, *,
               noise: bool | None = None, dots: bool = True, as_float: bool = False) -> np.ndarray:
        """Images of one frame, uint8 array (C', H, W) for ``cameras`` (default all).

        ``noise`` overrides the renderer's setting; ``dots=False`` leaves the dots out;
        ``as_float`` returns the float32 grey levels before noise and quantisation.
        """
        cams = list(range(len(self.intrinsics))) if cameras is None else list(cameras)
        out = np.empty((len(cams), self.height, self.width), np.float32 if as_float else np.uint8)
        use_noise = self.noise if noise is None else noise
        geometry = self._geometry(cams, scene)
        for i, c in enumerate(cams):
            rad_low, E_low = self._shade(c, scene, geometry[i])
            if self.scale > 1:
                img = cv2.resize(rad_low, (self.width, self.height), interpolation=cv2.INTER_LINEAR)
            else:
                img = rad_low.copy()
            if dots:
                self._composite_dots(c, scene, img, E_low)
            img *= self._gain
            if self.blur_sigma > 0:
                img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma, borderType=cv2.BORDER_REFLECT)
            if as_float:
                out[i] = img
                continue
            if use_noise:
                img = self._noise(frame, c, img)
            np.clip(img + 0.5, 0, 255, out=img)
            out[i] = img.astype(np.uint8)
        return out
