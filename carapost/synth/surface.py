"""The skin of one frame as a height-field grid (:class:`FaceSurface`), and ray casting against it.

The grid holds ``z = H(x, y)`` on a regular ``(x, y)`` grid of the head frame, with the
material coordinates ``U(x, y), V(x, y)`` of the skin seen at each node (for the skin texture);
:mod:`carapost.synth.builder` makes one for each expression state.

Ray casting marches along rays with steps bounded by a max-filtered copy of the height
field (big steps far from the skin, ~1 mm steps near it), then refines each crossing by
bisection, so the first hit is found even where the nose hides the cheek behind it.
Lookups use bilinear interpolation (``cv2.remap``) of the grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .face import FLOOR

__all__ = ["FaceSurface", "bilinear", "BACK", "LEVELS"]

_MAXR = 4  # radii (grid nodes) of the max filters used for safe ray steps
_MAXR2 = 16
#: Rays that reach this height (head frame, mm) without meeting the skin see the background.
BACK = -45.0
#: Heights (mm) whose horizontal distance fields bound the ray steps.
LEVELS = (BACK, -30.0, -15.0, 0.0)
_CHUNK = 240  # cv2.remap needs maps with fewer than 32767 rows: lookups are reshaped to (n, _CHUNK)


def bilinear(src: np.ndarray, col: np.ndarray, row: np.ndarray, border: float | tuple[float, ...], *,
           border_mode: int = cv2.BORDER_CONSTANT) -> np.ndarray:
    """Bilinear lookup of a (R, C[, K]) float32 grid at float coordinates ``(col, row)`` (N,)."""
    n = col.shape[0]
    if n == 0:
        return np.zeros((0,) + src.shape[2:], np.float32)
    if n < 32000:  # one row of maps, no copies
        out = cv2.remap(src, col.reshape(1, n), row.reshape(1, n), cv2.INTER_LINEAR,
                        borderMode=border_mode, borderValue=border)
        return out.reshape(n, src.shape[2]) if src.ndim == 3 else out.reshape(n)
    m = -(-n // _CHUNK) * _CHUNK
    mx = np.empty(m, np.float32)
    my = np.empty(m, np.float32)
    mx[:n] = col
    my[:n] = row
    mx[n:] = 0
    my[n:] = 0
    out = cv2.remap(src, mx.reshape(-1, _CHUNK), my.reshape(-1, _CHUNK), cv2.INTER_LINEAR,
                    borderMode=border_mode, borderValue=border)
    if src.ndim == 3:
        return out.reshape(m, src.shape[2])[:n]
    return out.reshape(m)[:n]


@dataclass(frozen=True)
class FaceSurface:
    """The skin of one frame as a height field on a regular grid (head frame, mm).

    Attributes
    ----------
    origin : (float, float)
        ``(x, y)`` of grid node ``[0, 0]``; rows go up in ``y``, columns up in ``x``.
    spacing : float
        Grid spacing, mm.
    geom : float32 array (R, C, 4)
        ``H, dH/dx, dH/dy`` and ``U`` (material u) per node.
    material : float32 array (R, C, 3)
        ``V`` (material v), and the mouth's inside (cavity weight, teeth weight) per node.
    stack : float32 array (R, C, 4)
        ``H``; ``H`` max-filtered over squares of half width ``_MAXR`` and ``_MAXR2`` nodes;
        and the horizontal distance (mm) to the nearest node where the skin is higher than
        :data:`BACK` (safe ray steps).
    levels : float32 array (R, C, 4)
        The horizontal distances to the skin higher than each of ``LEVELS[1:]``, and the
        largest slope ``|grad H|`` within ``_MAXR`` nodes.
    border_a, border_b : tuple of float
        Values of ``stack`` and ``levels`` just outside the grid (lower bounds).
    bounds : (x0, x1, y0, y1)
        Box around the skin higher than :data:`BACK`, mm.
    complete : bool
        False for a heights-only surface (see :class:`SurfaceBuilder`): :meth:`occluded`,
        :meth:`height_at` and :meth:`sample` work, ray casting does not.
    top : float
        Highest point of the skin, mm.
    """

    origin: tuple[float, float]
    spacing: float
    geom: np.ndarray
    material: np.ndarray
    stack: np.ndarray
    levels: np.ndarray
    top: float
    border_a: tuple[float, float, float, float]
    border_b: tuple[float, float, float, float]
    bounds: tuple[float, float, float, float]
    complete: bool = True

    @property
    def height(self) -> np.ndarray:
        return self.geom[..., 0]

    def _coords(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        inv = np.float32(1.0 / self.spacing)
        c = (np.asarray(x, np.float32) - np.float32(self.origin[0])) * inv
        r = (np.asarray(y, np.float32) - np.float32(self.origin[1])) * inv
        return c, r

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``H(x, y)`` (float32) for 1-D arrays of positions (mm); :data:`FLOOR` off the grid."""
        c, r = self._coords(x, y)
        return bilinear(self.geom[..., 0], c, r, FLOOR)

    def sample(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """``H, dH/dx, dH/dy, U, V`` at 1-D arrays of positions (float32 arrays)."""
        return self.sample_all(x, y)[:5]

    def sample_all(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """``H, dH/dx, dH/dy, U, V``, mouth cavity and teeth weights at 1-D arrays of positions."""
        c, r = self._coords(x, y)
        g = bilinear(self.geom, c, r, (FLOOR, 0.0, 0.0, 1e4))
        m = bilinear(self.material, c, r, (1e4, 0.0, 0.0))
        return g[:, 0], g[:, 1], g[:, 2], g[:, 3], m[:, 0], m[:, 1], m[:, 2]

    # ------------------------------------------------------------------ ray casting
    def cast(self, origin: np.ndarray, direction: np.ndarray, *, s_min: np.ndarray | float = 0.0,
             s_max: np.ndarray | float = np.inf, fine_step: float = 0.8, bisections: int = 6) -> np.ndarray:
        """Distance along each ray to its first crossing of the skin.

        Parameters
        ----------
        origin : array (3,) or (N, 3)
            Ray origin(s) (head frame, mm), above the skin (on the camera side).
        direction : array (N, 3)
            Unit directions.
        s_min, s_max : float or arrays (N,)
            Search interval along the rays, mm.
        fine_step : float
            Step (mm along the ray) when close to the skin; features thinner than this
            may be missed.
        bisections : int
            Bisection steps refining each crossing (then one secant step).

        Returns
        -------
        float64 array (N,)
            Distances, mm; ``inf`` where the ray does not meet the skin before ``s_max``
            or first reaches the height :data:`BACK` (behind the face).
        """
        d = np.asarray(direction, dtype=np.float32)
        o = np.asarray(origin, dtype=np.float64)
        if o.ndim == 1:
            ox, oy, oz = (np.float32(v) for v in o)
        else:
            ox, oy, oz = (np.ascontiguousarray(o[:, k], np.float32) for k in range(3))
        return self.cast_components(ox, oy, oz, np.ascontiguousarray(d[:, 0]), np.ascontiguousarray(d[:, 1]),
                                    np.ascontiguousarray(d[:, 2]), s_min=s_min, s_max=s_max,
                                    fine_step=fine_step, bisections=bisections)

    def cast_components(self, ox: np.ndarray | np.float32, oy: np.ndarray | np.float32, oz: np.ndarray | np.float32,
                        dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, *, s_min: np.ndarray | float = 0.0,
                        s_max: np.ndarray | float = np.inf, fine_step: float = 0.8,
                        bisections: int = 6, max_steps: int = 4000, on_cap: str = "nan",
                        march_steps: int = 4, dense_samples: int = 24) -> np.ndarray:
        """:meth:`cast` with origins and directions given as float32 components (each (N,) or scalar).

        The rays first march with safe steps (``march_steps`` of them, or until few rays are
        left); the rays still going then skim the skin, and are sampled every ``fine_step``
        along the rest of their path, up to ``dense_samples`` samples at a time, all in one
        lookup. After ``max_steps`` steps (marching or sampling) the rays still going get NaN
        (``on_cap="nan"``) or their current distance (``"hit"``).
        """
        if not self.complete:
            raise ValueError("ray casting needs a complete surface (this one holds heights only)")
        f32 = np.float32
        n = dx.shape[0]
        scalar_origin = np.ndim(ox) == 0
        inv_dxy = (1.0 / np.maximum(np.hypot(dx, dy), f32(1e-6))).astype(f32)
        inv_dz = (1.0 / np.maximum(-dz, f32(1e-6))).astype(f32)
        s = np.broadcast_to(np.asarray(s_min, f32), (n,)).astype(f32)
        smax = np.broadcast_to(np.asarray(s_max, np.float64), (n,)).astype(f32)
        # start where the ray comes down through the top of the skin; stop behind the face
        down = dz < 0
        s_top = np.where(down, (f32(self.top + 0.5) - oz) * inv_dz * f32(-1),
                         np.where(oz <= self.top, f32(0), f32(np.inf)))
        s_back = np.where(down, (f32(BACK) - oz) * inv_dz * f32(-1), f32(np.inf))
        np.maximum(s, s_top, out=s)
        np.minimum(smax, s_back, out=smax)
        # clip to the box (in x and y) around the skin higher than BACK
        x0, x1, y0, y1 = self.bounds
        with np.errstate(divide="ignore", invalid="ignore"):
            for o_, d_, lo_, hi_ in ((ox, dx, x0, x1), (oy, dy, y0, y1)):
                inv_d = f32(1) / d_
                ta = (f32(lo_) - o_) * inv_d
                tb = (f32(hi_) - o_) * inv_d
                within = (o_ >= lo_) & (o_ <= hi_)
                t_in = np.where(d_ != 0, np.minimum(ta, tb), np.where(within, f32(-np.inf), f32(np.inf)))
                t_out = np.where(d_ != 0, np.maximum(ta, tb), np.where(within, f32(np.inf), f32(-np.inf)))
                np.maximum(s, t_in, out=s)
                np.minimum(smax, t_out, out=smax)
        hit = np.full(n, np.inf, f32)
        prev = s.copy()
        lat1, lat2 = f32(_MAXR * self.spacing), f32(_MAXR2 * self.spacing)
        fine = f32(fine_step)
        inv = f32(1.0 / self.spacing)
        cx0, cy0 = f32(self.origin[0]), f32(self.origin[1])
        levels = np.asarray(LEVELS[1:], f32)
        # the working set: rays still marching (compacted when many have finished)
        ids = np.flatnonzero(s < smax)
        w_s, w_smax = s[ids], smax[ids]
        w_dx, w_dy, w_dz = dx[ids], dy[ids], dz[ids]
        w_idz, w_idxy = inv_dz[ids], inv_dxy[ids]
        w_dzabs, w_dxy = np.abs(w_dz), f32(1) / w_idxy
        if scalar_origin:
            w_ox, w_oy, w_oz = f32(ox - cx0), f32(oy - cy0), oz
        else:
            w_ox, w_oy, w_oz = ox[ids] - cx0, oy[ids] - cy0, oz[ids]
        w_prev = w_s.copy()
        w_live = np.ones(len(ids), bool)
        n0 = max(len(ids), 1)
        steps = 0
        for it in range(max_steps):
            if ids.size == 0 or (it >= march_steps and len(ids) < 0.25 * n0) or it >= 3 * march_steps:
                break
            steps += 1
            pz = w_oz + w_s * w_dz
            col = (w_ox + w_s * w_dx) * inv
            row = (w_oy + w_s * w_dy) * inv
            ha = bilinear(self.stack, col, row, self.border_a)
            hb = bilinear(self.levels, col, row, self.border_b)
            below = (pz < ha[:, 0]) & w_live
            # safe steps: the ray cannot meet skin lower than a local maximum height, nor skin
            # higher than a level further away (horizontally) than the level's free distance
            step = np.minimum(lat1 * w_idxy, (pz - ha[:, 1]) * w_idz)
            np.maximum(step, np.minimum(lat2 * w_idxy, (pz - ha[:, 2]) * w_idz), out=step)
            np.maximum(step, ha[:, 3] * w_idxy, out=step)
            for k in range(len(levels)):
                np.maximum(step, np.minimum(hb[:, k] * w_idxy, (pz - levels[k]) * w_idz), out=step)
            # Lipschitz bound from the largest nearby slope and the height above the skin
            np.maximum(step, np.minimum(lat1 * w_idxy, (pz - ha[:, 0]) / (w_dzabs + hb[:, 3] * w_dxy)), out=step)
            np.maximum(step, fine, out=step)
            w_live &= ~below
            if below.any():
                hit[ids[below]] = w_s[below]
            np.copyto(w_prev, w_s, where=w_live)
            w_s = np.where(w_live, w_s + step, w_s)
            w_live &= w_s < w_smax
            n_live = int(np.count_nonzero(w_live))
            if n_live < 0.8 * len(ids):
                prev[ids] = w_prev
                keep = np.flatnonzero(w_live)
                ids = ids[keep]
                w_s, w_smax, w_prev = w_s[keep], w_smax[keep], w_prev[keep]
                w_dx, w_dy, w_dz, w_idz, w_idxy = w_dx[keep], w_dy[keep], w_dz[keep], w_idz[keep], w_idxy[keep]
                w_dzabs, w_dxy = w_dzabs[keep], w_dxy[keep]
                if not scalar_origin:
                    w_ox, w_oy, w_oz = w_ox[keep], w_oy[keep], w_oz[keep]
                w_live = np.ones(len(ids), bool)
        prev[ids] = w_prev
        # the rest: sample each remaining path densely
        k_all = np.arange(dense_samples, dtype=f32) * fine
        while ids.size and steps < max_steps:
            keep = np.flatnonzero(w_live)
            ids, w_s, w_smax = ids[keep], w_s[keep], w_smax[keep]
            w_dx, w_dy, w_dz = w_dx[keep], w_dy[keep], w_dz[keep]
            if not scalar_origin:
                w_ox, w_oy, w_oz = w_ox[keep], w_oy[keep], w_oz[keep]
            if ids.size == 0:
                break
            K = int(min(dense_samples, max_steps - steps,
                        np.ceil(float((w_smax - w_s).max()) / fine_step) + 1))
            S = w_s[:, None] + k_all[None, :K]
            ox_, oy_, oz_ = (w_ox, w_oy, w_oz) if scalar_origin else (w_ox[:, None], w_oy[:, None], w_oz[:, None])
            pz = oz_ + S * w_dz[:, None]
            Hs = bilinear(self.stack[..., 0], ((ox_ + S * w_dx[:, None]) * inv).ravel(),
                        ((oy_ + S * w_dy[:, None]) * inv).ravel(), FLOOR).reshape(S.shape)
            below = (pz < Hs) & (S < w_smax[:, None])
            has = below.any(axis=1)
            first = np.argmax(below, axis=1)
            r_hit = np.flatnonzero(has)
            hit[ids[r_hit]] = S[r_hit, first[r_hit]]
            prev[ids[r_hit]] = np.where(first[r_hit] > 0, S[r_hit, np.maximum(first[r_hit] - 1, 0)],
                                        prev[ids[r_hit]])
            steps += K
            w_s = S[:, K - 1] + fine
            w_live = ~has & (w_s < w_smax)
        if ids.size and np.any(w_live):
            capped, s_capped = ids[w_live], w_s[w_live]
        else:
            capped, s_capped = ids[:0], w_s[:0]
        out = hit.astype(np.float64)
        # bisection between the last point above the skin and the first below
        idx = np.flatnonzero(np.isfinite(hit))
        if idx.size:
            lo = np.minimum(prev[idx], hit[idx])
            hi = hit[idx].copy()
            oxi, oyi, ozi = (ox, oy, oz) if scalar_origin else (ox[idx], oy[idx], oz[idx])
            dxi, dyi, dzi = dx[idx], dy[idx], dz[idx]
            for _ in range(bisections):
                mid = f32(0.5) * (lo + hi)
                below = ozi + mid * dzi < self.height_at(oxi + mid * dxi, oyi + mid * dyi)
                hi = np.where(below, mid, hi)
                lo = np.where(below, lo, mid)
            glo = ozi + lo * dzi - self.height_at(oxi + lo * dxi, oyi + lo * dyi)
            ghi = ozi + hi * dzi - self.height_at(oxi + hi * dxi, oyi + hi * dyi)
            den = glo - ghi
            frac = np.where(den > 0, glo / np.where(den > 0, den, f32(1)), f32(0.5))
            out[idx] = lo + np.clip(frac, 0.0, 1.0) * (hi - lo)
        if capped.size:
            out[capped] = np.nan if on_cap == "nan" else s_capped
        return out

    def occluded(self, origin: np.ndarray, target: np.ndarray, *, tolerance: float | np.ndarray = 0.4,
                 step: float = 0.5) -> np.ndarray:
        """Whether the skin hides each target point from the origin.

        The segment from each target towards its origin is sampled every ``step`` mm (all
        samples of all segments in one lookup) up to where it rises above the skin's highest
        point; the target is hidden if a sample lies below the skin. Occluders thinner than
        ``step`` along the segment may be missed.

        Parameters
        ----------
        origin : array (3,) or (N, 3)
            Eye point(s) (camera centres), head frame, mm.
        target : array (N, 3)
            Points to test (e.g. marker centres on the skin).
        tolerance : float or array (N,)
            Samples within this distance (mm) of the target are skipped (for points on a
            painted disc, about the disc's size: the skin curving next to a flat disc is not
            an occluder).
        step : float
            Sampling step, mm.

        Returns
        -------
        bool array (N,)
        """
        target = np.asarray(target, dtype=float)
        n = len(target)
        if n == 0:
            return np.zeros(0, bool)
        o = np.broadcast_to(np.asarray(origin, dtype=float), target.shape)
        vec = o - target
        dist = np.linalg.norm(vec, axis=1)
        d = vec / dist[:, None]
        # length of the segment that can meet the skin: until it rises above the top
        with np.errstate(divide="ignore", invalid="ignore"):
            up = np.where(d[:, 2] > 1e-9, (self.top + 0.5 - target[:, 2]) / d[:, 2], np.inf)
        length = np.minimum(dist, np.maximum(up, 0.0))
        tol = np.broadcast_to(np.asarray(tolerance, np.float32), (n,))
        k = int(np.ceil(max(float((length - tol).max()), 0.0) / step)) + 1
        s = tol[:, None] + step * np.arange(k, dtype=np.float32)[None, :]
        valid = s <= length[:, None].astype(np.float32)
        t32 = target.astype(np.float32)
        d32 = d.astype(np.float32)
        px = t32[:, 0:1] + s * d32[:, 0:1]
        py = t32[:, 1:2] + s * d32[:, 1:2]
        pz = t32[:, 2:3] + s * d32[:, 2:3]
        H = self.height_at(px.ravel(), py.ravel()).reshape(n, k)
        return np.any((pz < H) & valid, axis=1)
