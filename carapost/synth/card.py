"""The brim card: a planar or cylindrical card in the world (brim) frame, for ray casting."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carapost.io.brim import flatten_brim
from carapost.model.take import BrimModel

__all__ = ["BrimCard", "card_for"]


@dataclass(frozen=True)
class BrimCard:
    """The card carrying the brim dots.

    Attributes
    ----------
    extent : (x0, x1, y0, y1)
        Card outline in flattened card coordinates (arc length along the card, ``Y``), mm.
    curvature : float or None
        Cylinder radius (axis along ``Y`` through ``(0, ., -curvature)``), ``None`` if planar.
    albedo : float
        Albedo of the card.
    """

    extent: tuple[float, float, float, float]
    curvature: float | None
    albedo: float

    def normals(self, xyz: np.ndarray) -> np.ndarray:
        """Unit normals (N, 3) of the card at points on it (towards the cameras)."""
        xyz = np.asarray(xyz, float)
        if self.curvature is None:
            return np.broadcast_to(np.array([0.0, 0.0, 1.0]), xyz.shape).copy()
        r = self.curvature
        n = np.c_[xyz[:, 0], np.zeros(len(xyz)), xyz[:, 2] + r]
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def intersect(self, origin: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays with the card.

        Parameters
        ----------
        origin : array (3,)
            Ray origin (camera centre), world frame, mm.
        d : array (N, 3)
            Unit ray directions.

        Returns
        -------
        s : array (N,)
            Distance to the card, ``inf`` where the ray misses it.
        normal : array (N, 3)
            Card normal at the hit (towards the cameras; undefined where ``s`` is inf).
        """
        o = np.asarray(origin, float)
        d = np.asarray(d, float)
        x0, x1, y0, y1 = self.extent
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.curvature is None:
                s = -o[2] / d[:, 2]
                p = o + s[:, None] * d
                fx = p[:, 0]
            else:
                r = self.curvature
                oz = o[2] + r
                a = d[:, 0] ** 2 + d[:, 2] ** 2
                b = 2 * (o[0] * d[:, 0] + oz * d[:, 2])
                c = o[0] ** 2 + oz ** 2 - r * r
                disc = b * b - 4 * a * c
                s = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
                s = np.where(disc >= 0, s, np.nan)
                p = o + s[:, None] * d
                fx = r * np.arctan2(p[:, 0], p[:, 2] + r)
        inside = (s > 0) & (fx >= x0) & (fx <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
        s = np.where(inside, s, np.inf)
        nrm = self.normals(np.where(inside[:, None], p, 0.0))
        return s, nrm

    def intersect_components(self, origin: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`intersect` for component-major float32 rays ``d`` (3, N).

        Returns ``s`` float32 (N,) and normals float32 (3, N).
        """
        f32 = np.float32
        ox, oy, oz = (f32(v) for v in np.asarray(origin, float))
        dx, dy, dz = d[0], d[1], d[2]
        x0, x1, y0, y1 = (f32(v) for v in self.extent)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if self.curvature is None:
                s = -oz / dz
                px, py = ox + s * dx, oy + s * dy
                fx = px
                nrm = np.zeros((3, len(dx)), f32)
                nrm[2] = 1
            else:
                r = f32(self.curvature)
                ozr = oz + r
                a = dx * dx + dz * dz
                b = f32(2) * (ox * dx + ozr * dz)
                cc = ox * ox + ozr * ozr - r * r
                disc = b * b - f32(4) * a * cc
                s = (-b - np.sqrt(np.maximum(disc, f32(0)))) / (f32(2) * a)
                s[disc < 0] = np.nan
                px, py, pz = ox + s * dx, oy + s * dy, oz + s * dz
                fx = r * np.arctan2(px, pz + r)
                nrm = np.stack([px, np.zeros_like(px), pz + r]) / r
        inside = (s > 0) & (fx >= x0) & (fx <= x1) & (py >= y0) & (py <= y1)
        s = np.where(inside, s, f32(np.inf)).astype(f32)
        return s, nrm


def card_for(brim: BrimModel, *, margin: float = 7.0) -> BrimCard:
    """The card for a brim model: its dots' flattened bounding box plus a margin."""
    flat, r = flatten_brim(brim.xyz)
    rad = np.asarray(brim.radius, float)
    x0 = float(np.min(flat[:, 0] - rad)) - margin
    x1 = float(np.max(flat[:, 0] + rad)) + margin
    y0 = float(np.min(flat[:, 1] - rad)) - margin
    y1 = float(np.max(flat[:, 1] + rad)) + margin
    black_dots = np.sum(np.asarray(brim.polarity) < 0) >= np.sum(np.asarray(brim.polarity) > 0)
    return BrimCard(extent=(x0, x1, y0, y1), curvature=r, albedo=0.80 if black_dots else 0.06)
