"""The shading rays of one camera and where they meet the skin (coarse-to-fine ray casting).

The shading grid has one ray per ``scale`` x ``scale`` block of pixels. Rays on a grid
``coarse`` times sparser still are cast robustly against the skin; in between, the distance
along the ray is interpolated bilinearly wherever the four surrounding coarse hits lie on one
smooth patch of skin, and cast robustly in the cells that hold a silhouette or a fold. (A
silhouette that passes between coarse rays without touching any of them is missed: at the
default spacing of 8 pixels this shows only as a pixel or two at the tip of a silhouette.)
"""

from __future__ import annotations

import cv2
import numpy as np

from carapost.core.camera import Intrinsics, normalized_rays

from .surface import FaceSurface

__all__ = ["RayGrid", "hits_all", "rotate"]

#: Coarse cells whose hit points are further apart than this many pixel footprints are re-cast.
_FOLD = 5.0
#: Ray-march cap (marching steps plus dense samples): rays still skimming the skin after this are settled.
MAX_STEPS = 120


def rotate(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``M @ v`` for a (3, 3) matrix and component-major vectors ``v`` (3, N), float32."""
    m = np.asarray(M, np.float32)
    return np.stack([m[i, 0] * v[0] + m[i, 1] * v[1] + m[i, 2] * v[2] for i in range(3)])


def _unit_rays(xy: np.ndarray, intr: Intrinsics) -> np.ndarray:
    d = normalized_rays(xy, intr)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.ascontiguousarray(d.reshape(-1, 3).T, np.float32)


class RayGrid:
    """Shading rays of one camera.

    Parameters
    ----------
    intr : Intrinsics
    width, height : int
        Image size, pixels.
    scale : int
        Pixels per shading ray along each axis.
    coarse : int
        Shading rays per coarse ray along each axis.

    Attributes
    ----------
    shape : (int, int)
        Shading grid shape ``(h, w)``; ray ``i * w + j`` passes through the centre of the
        ``scale`` x ``scale`` block of pixels at block ``(i, j)``.
    rays : float32 array (3, h * w)
        Unit directions in the camera frame.
    """

    def __init__(self, intr: Intrinsics, width: int, height: int, scale: int, coarse: int = 4) -> None:
        s, k = int(scale), int(coarse)
        hl, wl = -(-height // s), -(-width // s)
        self.shape = (hl, wl)
        self.scale, self.coarse = s, k
        self.focal = float(intr.focal_length)
        off = 0.5 * (s - 1)
        gx, gy = np.meshgrid(s * np.arange(wl) + off, s * np.arange(hl) + off)
        self.rays = _unit_rays(np.stack([gx, gy], axis=-1), intr)
        # coarse rays every k shading rays, reaching (or passing) the last row and column
        nr, nc = -(-(hl - 1) // k) + 1, -(-(wl - 1) // k) + 1
        self.coarse_shape = (nr, nc)
        cx, cy = np.meshgrid(s * k * np.arange(nc) + off, s * k * np.arange(nr) + off)
        self.coarse_rays = _unit_rays(np.stack([cx, cy], axis=-1), intr)
        # the coarse coordinates of every shading ray (for bilinear interpolation)
        my, mx = np.mgrid[0:hl, 0:wl].astype(np.float32)
        self._mapx, self._mapy = mx / k, my / k

    def _cells(self, cell: np.ndarray) -> np.ndarray:
        """Per-shading-ray value of a per-cell array ``(nr - 1, nc - 1)``, flattened."""
        k = self.coarse
        hl, wl = self.shape
        full = np.repeat(np.repeat(cell, k, axis=0), k, axis=1)
        # the last shading row / column may sit exactly on the last coarse one
        full = np.pad(full, ((0, max(hl - full.shape[0], 0)), (0, max(wl - full.shape[1], 0))), mode="edge")
        return full[:hl, :wl].ravel()

    def hits(self, surface: FaceSurface, origin: np.ndarray, to_head: np.ndarray,
             s_max: np.ndarray) -> np.ndarray:
        """Distance (mm) along every shading ray to the skin; inf where it misses.

        Parameters
        ----------
        surface : FaceSurface
        origin : array (3,)
            Camera centre in the head frame.
        to_head : array (3, 3)
            Rotation from the camera frame to the head frame.
        s_max : float32 array (h * w,)
            Distance to something in front of the skin (the brim card), inf if none.

        Returns
        -------
        float32 array (h * w,)
        """
        return hits_all([self], surface, [origin], [to_head], [s_max])[0]

    def _coarse_dirs(self, to_head: np.ndarray) -> np.ndarray:
        return rotate(to_head, self.coarse_rays)

    def _plan(self, s_c: np.ndarray, origin: np.ndarray, dc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """From the coarse hits: interpolated distances (inf: no skin) and the rays to cast."""
        k = self.coarse
        nr, nc = self.coarse_shape
        s_c = s_c.reshape(nr, nc).astype(np.float32)
        unsure = np.isnan(s_c)
        fin = np.isfinite(s_c)
        sc = np.where(fin, s_c, np.float32(0.0))
        # hit points of the coarse rays, and their expected spacing on the skin
        P = np.asarray(origin, np.float32)[:, None, None] + sc[None] * dc.reshape(3, nr, nc)
        foot = sc * np.float32(k * self.scale / self.focal)
        f4 = fin[:-1, :-1] & fin[1:, :-1] & fin[:-1, 1:] & fin[1:, 1:]
        any4 = fin[:-1, :-1] | fin[1:, :-1] | fin[:-1, 1:] | fin[1:, 1:]
        un4 = unsure[:-1, :-1] | unsure[1:, :-1] | unsure[:-1, 1:] | unsure[1:, 1:]
        e1 = np.sqrt(((P[:, 1:, :] - P[:, :-1, :]) ** 2).sum(axis=0))
        e2 = np.sqrt(((P[:, :, 1:] - P[:, :, :-1]) ** 2).sum(axis=0))
        edge = np.maximum(np.maximum(e1[:, :-1], e1[:, 1:]), np.maximum(e2[:-1, :], e2[1:, :]))
        limit = _FOLD * np.maximum(foot[:-1, :-1], foot[1:, 1:]) + 0.5
        flag = (any4 & ~f4) | (f4 & (edge > limit)) | un4
        # 0: interpolate, 1: no skin, 2: cast
        status = np.where(flag, np.uint8(2), np.where(f4, np.uint8(0), np.uint8(1)))
        st = self._cells(status)
        s = cv2.remap(sc, self._mapx, self._mapy, cv2.INTER_LINEAR).ravel()
        s[st == 1] = np.inf
        return s, np.flatnonzero(st == 2)


def hits_all(grids: list[RayGrid], surface: FaceSurface, origins: list[np.ndarray], to_heads: list[np.ndarray],
             s_maxes: list[np.ndarray]) -> list[np.ndarray]:
    """:meth:`RayGrid.hits` for several cameras at once (one ray cast per stage for all)."""
    # stage 1: the coarse rays of every camera
    dcs = [g._coarse_dirs(M) for g, M in zip(grids, to_heads)]
    s_c = _cast_many(surface, origins, dcs, None, "nan")
    out, redo_dirs, redo_idx = [], [], []
    for g, o, M, dc, sc in zip(grids, origins, to_heads, dcs, s_c):
        s, redo = g._plan(sc, o, dc)
        out.append(s)
        redo_idx.append(redo)
        redo_dirs.append(rotate(M, g.rays[:, redo]))
    # stage 2: the rays of the cells holding a silhouette or a fold
    s_r = _cast_many(surface, origins, redo_dirs, [sm[r] for sm, r in zip(s_maxes, redo_idx)], "hit")
    for s, r, sr, sm in zip(out, redo_idx, s_r, s_maxes):
        s[r] = sr
        # skin behind the card is hidden by it
        s[s > sm] = np.inf
    return out


def _cast_many(surface: FaceSurface, origins: list[np.ndarray], dirs: list[np.ndarray],
               s_max: list[np.ndarray] | None, on_cap: str) -> list[np.ndarray]:
    """Cast rays of several origins in one call; returns the distances per origin."""
    sizes = [d.shape[1] for d in dirs]
    if sum(sizes) == 0:
        return [np.zeros(0) for _ in dirs]
    d = np.concatenate(dirs, axis=1)
    if len(dirs) == 1:
        ox, oy, oz = (np.float32(v) for v in origins[0])
    else:
        o = np.concatenate([np.broadcast_to(np.asarray(oo, np.float32)[:, None], (3, n))
                            for oo, n in zip(origins, sizes)], axis=1)
        ox, oy, oz = (np.ascontiguousarray(o[k]) for k in range(3))
    sm = np.inf if s_max is None else np.concatenate(s_max)
    res = surface.cast_components(ox, oy, oz, np.ascontiguousarray(d[0]), np.ascontiguousarray(d[1]),
                                  np.ascontiguousarray(d[2]), s_max=sm, max_steps=MAX_STEPS, on_cap=on_cap)
    return np.split(res, np.cumsum(sizes)[:-1])
