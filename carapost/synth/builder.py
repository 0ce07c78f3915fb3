"""Build the skin of a frame: the expression deformation resampled as a height-field grid.

:class:`SurfaceBuilder` evaluates the expression deformation (:mod:`.expressions`) on a
regular grid of material points and inverts it (Newton iterations) so that the current skin is
again a height field on a regular ``(x, y)`` grid (:class:`~carapost.synth.surface.FaceSurface`).
When the jaw parts the lips, the maps seen from each lip are inverted separately and the gap
between them is filled with the inside of the mouth.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from .expressions import CHANNELS, Deformer
from .face import DOMAIN, FLOOR, MOUTH_HALF_WIDTH, lip_line, rest_height
from .surface import _MAXR, _MAXR2, BACK, LEVELS, FaceSurface, bilinear

__all__ = ["SurfaceBuilder", "build_surface", "rest_surface"]

_CAVITY = 6.0  # depth of the open mouth behind the lips, mm
_TEETH = 2.0  # the upper teeth show this far (mm) below the upper lip
_UNCONVERGED_MM = 0.5  # inversion residual (mm, before the last step) that earns more Newton steps
_EXTRA_ITERATIONS = 6


def _grid(spacing: float) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    u0, u1, v0, v1 = DOMAIN
    u = np.arange(u0, u1 + 0.5 * spacing, spacing)
    v = np.arange(v0, v1 + 0.5 * spacing, spacing)
    U, V = np.meshgrid(u, v)
    return U, V, (u0, v0)


def _distances(H: np.ndarray, spacing: float) -> tuple[np.ndarray, tuple[float, ...]]:
    """Horizontal distance (mm) to the skin higher than each of :data:`LEVELS`, and the
    largest slope within ``_MAXR`` nodes: array (R, C, len(LEVELS) + 1).

    Distances are conservative (one node less than exact); also returns the smallest value on
    the grid's border of each channel (a lower bound just outside the grid).
    """
    out = np.empty(H.shape + (len(LEVELS) + 1,), np.float32)
    gy, gx = np.gradient(H, spacing)
    k1 = 2 * _MAXR + 1
    out[..., -1] = cv2.dilate(np.hypot(gx, gy).astype(np.float32), np.ones((k1, k1), np.uint8),
                              borderType=cv2.BORDER_REPLICATE)
    for k, z in enumerate(LEVELS):
        mask = (H <= z).astype(np.uint8)
        if mask.all():
            out[..., k] = 1e4
            continue
        d = cv2.distanceTransform(mask, cv2.DIST_L2, 5)
        out[..., k] = np.maximum(d * spacing - spacing, 0.0)
    border = tuple(float(min(out[0, :, k].min(), out[-1, :, k].min(), out[:, 0, k].min(), out[:, -1, k].min()))
                   for k in range(len(LEVELS)))
    return out, border + (1e4,)


def _bounds(H: np.ndarray, origin: tuple[float, float], spacing: float) -> tuple[float, float, float, float]:
    rows = np.flatnonzero((H > BACK).any(axis=1))
    cols = np.flatnonzero((H > BACK).any(axis=0))
    return (origin[0] + (cols[0] - 1) * spacing, origin[0] + (cols[-1] + 1) * spacing,
            origin[1] + (rows[0] - 1) * spacing, origin[1] + (rows[-1] + 1) * spacing)


def _finish(H: np.ndarray, U: np.ndarray, V: np.ndarray, origin: tuple[float, float], spacing: float) -> FaceSurface:
    H = np.maximum(H, FLOOR).astype(np.float32)
    gy, gx = np.gradient(H, spacing)
    geom = np.stack([H, gx.astype(np.float32), gy.astype(np.float32), U.astype(np.float32)], axis=-1)
    k1, k2 = 2 * _MAXR + 1, 2 * _MAXR2 + 1
    h1 = cv2.dilate(H, np.ones((k1, k1), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=FLOOR)
    h2 = cv2.dilate(h1, np.ones((k2 - k1 + 1, k2 - k1 + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                    borderValue=FLOOR)
    dist, border = _distances(H, spacing)
    material = np.zeros(H.shape + (3,), np.float32)
    material[..., 0] = V
    return FaceSurface(origin=origin, spacing=spacing, geom=geom, material=material,
                       stack=np.stack([H, h1, h2, dist[..., 0]], axis=-1), levels=np.ascontiguousarray(dist[..., 1:]),
                       top=float(H.max()), border_a=(FLOOR, FLOOR, FLOOR, border[0]), border_b=border[1:],
                       bounds=_bounds(H, origin, spacing))


def _update(rest: FaceSurface, H: np.ndarray, U: np.ndarray, V: np.ndarray, win: tuple[slice, slice],
            mouth: np.ndarray | None = None, heights_only: bool = False) -> FaceSurface:
    """The rest surface with the window ``win`` of the grid replaced by ``H``, ``U``, ``V``.

    ``H``, ``U``, ``V`` (shaped like the window) hold the new heights and material coordinates,
    ``mouth`` (window + (2,)) the cavity and teeth weights.
    Gradients and max filters are recomputed around the window, the distance fields everywhere
    (unless ``heights_only``: then only ``H`` changes and the result cannot cast rays).
    """
    sp = rest.spacing
    if heights_only:
        geom = rest.geom.copy()
        geom[win + (0,)] = np.maximum(H, FLOOR)
        return replace(rest, geom=geom, top=float(max(rest.top, float(H.max()))), complete=False)
    nr, nc = rest.geom.shape[:2]
    Hf = rest.geom[..., 0].copy()
    Hf[win] = np.maximum(H, FLOOR)
    geom = rest.geom.copy()
    geom[..., 0] = Hf
    # gradients on the window grown by one node
    r0, r1 = max(win[0].start - 1, 0), min(win[0].stop + 1, nr)
    c0, c1 = max(win[1].start - 1, 0), min(win[1].stop + 1, nc)
    e0, e1 = max(r0 - 1, 0), min(r1 + 1, nr)
    f0, f1 = max(c0 - 1, 0), min(c1 + 1, nc)
    gy, gx = np.gradient(Hf[e0:e1, f0:f1], sp)
    geom[r0:r1, c0:c1, 1] = gx[r0 - e0:r1 - e0, c0 - f0:c1 - f0]
    geom[r0:r1, c0:c1, 2] = gy[r0 - e0:r1 - e0, c0 - f0:c1 - f0]
    geom[win + (3,)] = U
    mv = rest.material.copy()
    mv[win + (0,)] = V
    if mouth is not None:
        mv[win + (slice(1, 3),)] = mouth
    # max filters on the window grown by their reach
    stack = rest.stack.copy()
    g = _MAXR2 + 1
    r0, r1 = max(win[0].start - g, 0), min(win[0].stop + g, nr)
    c0, c1 = max(win[1].start - g, 0), min(win[1].stop + g, nc)
    e0, e1 = max(r0 - g, 0), min(r1 + g, nr)
    f0, f1 = max(c0 - g, 0), min(c1 + g, nc)
    sub = Hf[e0:e1, f0:f1]
    k1, k2 = 2 * _MAXR + 1, 2 * _MAXR2 + 1
    h1 = cv2.dilate(sub, np.ones((k1, k1), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=FLOOR)
    h2 = cv2.dilate(h1, np.ones((k2 - k1 + 1, k2 - k1 + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                    borderValue=FLOOR)
    stack[..., 0] = Hf
    stack[r0:r1, c0:c1, 1] = h1[r0 - e0:r1 - e0, c0 - f0:c1 - f0]
    stack[r0:r1, c0:c1, 2] = h2[r0 - e0:r1 - e0, c0 - f0:c1 - f0]
    dist, border = _distances(Hf, sp)
    stack[..., 3] = dist[..., 0]
    return FaceSurface(origin=rest.origin, spacing=sp, geom=geom, material=mv, stack=stack,
                       levels=np.ascontiguousarray(dist[..., 1:]), top=float(max(rest.top, float(H.max()))),
                       border_a=(FLOOR, FLOOR, FLOOR, border[0]), border_b=border[1:],
                       bounds=_bounds(Hf, rest.origin, sp))


class SurfaceBuilder:
    """Builds :class:`FaceSurface` grids for many expression states (caches the rest grid).

    Parameters
    ----------
    spacing : float
        Grid spacing, mm.
    """

    def __init__(self, spacing: float = 1.0) -> None:
        self.spacing = float(spacing)
        U, V, self.origin = _grid(self.spacing)
        self.U, self.V = U, V
        H0 = rest_height(U, V)
        self.rest = _finish(H0, U, V, self.origin, self.spacing)
        self.deformer = Deformer(U, V, H0)
        # per channel: the box of grid nodes it moves, grown by how far they move
        basis = self.deformer.basis
        self.boxes = []
        for k in range(basis.shape[0]):
            mag = np.abs(basis[k]).max(axis=-1)
            if CHANNELS[k] == "jaw":
                mag = np.maximum(mag, self.deformer.jaw_w * 30.0)
            moved = (mag > 0.01) & (H0 > BACK - 20.0)
            rows = np.flatnonzero(moved.any(axis=1))
            cols = np.flatnonzero(moved.any(axis=0))
            m = int(np.ceil((mag[moved].max() + 3.0) / self.spacing))
            self.boxes.append((max(rows[0] - m, 0), min(rows[-1] + m + 1, U.shape[0]),
                               max(cols[0] - m, 0), min(cols[-1] + m + 1, U.shape[1])))

    def window(self, state: np.ndarray) -> tuple[slice, slice]:
        """Grid window holding every node that ``state`` moves (and its image)."""
        act = [self.boxes[k] for k in np.flatnonzero(np.asarray(state) > 0)]
        return (slice(min(b[0] for b in act), max(b[1] for b in act)),
                slice(min(b[2] for b in act), max(b[3] for b in act)))

    def __call__(self, state: np.ndarray, *, iterations: int = 3, heights_only: bool = False) -> FaceSurface:
        """The skin in an expression ``state`` (array (len(CHANNELS),)).

        ``heights_only`` skips what only ray casting needs (enough for :meth:`FaceSurface.occluded`).
        """
        state = np.asarray(state, dtype=float)
        if not np.any(state > 0):
            return self.rest
        win = self.window(state)
        shape = self.U[win].shape
        if state[CHANNELS.index("jaw")] <= 0:
            H, U, V = self._invert(state, win, None, iterations)
            return _update(self.rest, H.reshape(shape), U.reshape(shape), V.reshape(shape), win,
                           heights_only=heights_only)
        # the jaw parts the lips. Both lips' maps are smooth: invert the lower lip's map over
        # the window; inside the mouth also the upper lip's, keep each lip's own side, and fill
        # the gap between them with the inside of the mouth
        H, U, V = (a.reshape(shape) for a in self._invert(state, win, "lower", iterations))
        mw = self._mouth_window(win)
        sub = (slice(mw[0].start - win[0].start, mw[0].stop - win[0].start),
               slice(mw[1].start - win[1].start, mw[1].stop - win[1].start))
        Hb, Ub, Vb = H[sub].ravel(), U[sub].ravel(), V[sub].ravel()
        Ha, Ua, Va = self._invert(state, mw, "upper", iterations)
        ok_a = Va >= lip_line(Ua) - 0.05
        ok_b = Vb <= lip_line(Ub) + 0.05
        gap = ~ok_a & ~ok_b
        Hm = np.where(ok_a, Ha, np.where(ok_b, Hb, np.minimum(Ha, Hb) - _CAVITY))
        Um = np.where(ok_a, Ua, Ub)
        Vm = np.where(ok_a, Va, np.where(ok_b, Vb, lip_line(Ua)))
        msub = np.zeros(Hm.shape + (2,), np.float32)
        below_upper = lip_line(Ua) - Va  # about the distance (mm) below the upper lip's edge
        above_lower = Vb - lip_line(Ub)
        msub[:, 0] = gap * np.clip(np.minimum(below_upper, above_lower) / 0.7, 0.0, 1.0)
        # the upper teeth show just below the upper lip
        msub[:, 1] = msub[:, 0] * np.clip((_TEETH - below_upper) / 0.6, 0.0, 1.0) * \
            np.clip((MOUTH_HALF_WIDTH - 7.0 - np.abs(Ua)) / 2.0, 0.0, 1.0)
        ms = H[sub].shape
        H[sub], U[sub], V[sub] = Hm.reshape(ms), Um.reshape(ms), Vm.reshape(ms)
        mouth = np.zeros(shape + (2,), np.float32)
        mouth[sub] = msub.reshape(ms + (2,))
        return _update(self.rest, H, U, V, win, mouth, heights_only=heights_only)

    def _mouth_window(self, win: tuple[slice, slice]) -> tuple[slice, slice]:
        """Grid nodes (within ``win``) where the lips may part: around the mouth, down the jaw's reach."""
        sp = self.spacing
        u0, v0 = self.origin
        c0 = int(np.floor((-MOUTH_HALF_WIDTH - 8.0 - u0) / sp))
        c1 = int(np.ceil((MOUTH_HALF_WIDTH + 8.0 - u0) / sp)) + 1
        r0 = int(np.floor((lip_line(0.0) - 35.0 - v0) / sp))
        r1 = int(np.ceil((lip_line(MOUTH_HALF_WIDTH) + 12.0 - v0) / sp)) + 1
        return (slice(max(r0, win[0].start), min(r1, win[0].stop)), slice(max(c0, win[1].start), min(c1, win[1].stop)))

    def _over_a_blink(self, state: np.ndarray, win: tuple[slice, slice]) -> np.ndarray:
        """Flat bool mask of the nodes of ``win`` in the box of an active blink channel."""
        rows = np.arange(win[0].start, win[0].stop)[:, None]
        cols = np.arange(win[1].start, win[1].stop)[None, :]
        near = np.zeros((rows.shape[0], cols.shape[1]), bool)
        for name in ("blink_L", "blink_R"):
            k = CHANNELS.index(name)
            if state[k] > 0:
                r0, r1, c0, c1 = self.boxes[k]
                near |= (rows >= r0) & (rows < r1) & (cols >= c0) & (cols < c1)
        return near.ravel()

    def _invert(self, state: np.ndarray, win: tuple[slice, slice], lip: str | None,
                iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height and material coordinates at the current-space grid nodes of ``win`` (flat)."""
        spacing = self.spacing
        # the forward map is evaluated a few nodes beyond the solved window
        g = 6
        nr, nc = self.U.shape
        fwin = (slice(max(win[0].start - g, 0), min(win[0].stop + g, nr)),
                slice(max(win[1].start - g, 0), min(win[1].stop + g, nc)))
        u0 = self.origin[0] + fwin[1].start * spacing
        v0 = self.origin[1] + fwin[0].start * spacing
        cmax = np.float32(fwin[1].stop - fwin[1].start - 1)
        rmax = np.float32(fwin[0].stop - fwin[0].start - 1)
        P = self.deformer(state, fwin, lip=lip)
        Px, Py, Pz = (P[..., k].astype(np.float32) for k in range(3))
        dPx_dv, dPx_du = np.gradient(Px, spacing)
        dPy_dv, dPy_du = np.gradient(Py, spacing)
        fwd = np.stack([Px, Py, dPx_du, dPx_dv], axis=-1)
        fwd2 = np.stack([dPy_du, dPy_dv, Pz], axis=-1)
        inv = np.float32(1.0 / spacing)

        def lookup(uu: np.ndarray, vv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            c = np.clip((uu - np.float32(u0)) * inv, 0, cmax)
            r = np.clip((vv - np.float32(v0)) * inv, 0, rmax)
            return (bilinear(fwd, c, r, (0.0, 0.0, 1.0, 0.0)), bilinear(fwd2, c, r, (0.0, 1.0, FLOOR)))

        x = self.U[win].ravel().astype(np.float32)
        y = self.V[win].ravel().astype(np.float32)
        # initial guess: subtract the displacement found at the current position
        a, _ = lookup(x, y)
        uu = 2.0 * x - a[:, 0]
        vv = 2.0 * y - a[:, 1]

        def newton(idx: np.ndarray | slice) -> np.ndarray:
            """One damped Newton step for the nodes ``idx``; returns their residual before it (mm)."""
            a, b = lookup(uu[idx], vv[idx])
            rx = a[:, 0] - x[idx]
            ry = a[:, 1] - y[idx]
            j11, j12, j21, j22 = a[:, 2], a[:, 3], b[:, 0], b[:, 1]
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-3, np.float32(1e-3), det)
            du = (j22 * rx - j12 * ry) / det
            dv = (j11 * ry - j21 * rx) / det
            # damp wild steps (where the map is nearly singular, e.g. a closed eye)
            f = np.minimum(np.float32(1.0), np.float32(4.0) / np.maximum(np.hypot(du, dv), np.float32(1e-12)))
            uu[idx] -= f * du
            vv[idx] -= f * dv
            return np.hypot(rx, ry)

        res = np.zeros_like(x)
        for _ in range(iterations):
            res = newton(slice(None))
        # over a closing eye the skin moves ~9 mm and nodes whose first guess was far off (just
        # above the lid) need more damped steps: a few more for them only (elsewhere, e.g. in
        # the parted lips, nodes without a preimage are left as they were)
        idx = np.flatnonzero((res > _UNCONVERGED_MM) & self._over_a_blink(state, win))
        for _ in range(_EXTRA_ITERATIONS):
            if idx.size == 0:
                break
            idx = idx[newton(idx) > _UNCONVERGED_MM]
        _, b = lookup(uu, vv)
        return b[:, 2], uu, vv


_BUILDERS: dict[float, SurfaceBuilder] = {}


def _builder(spacing: float) -> SurfaceBuilder:
    if spacing not in _BUILDERS:
        _BUILDERS[spacing] = SurfaceBuilder(spacing)
    return _BUILDERS[spacing]


def rest_surface(spacing: float = 1.0) -> FaceSurface:
    """The undeformed face (cached)."""
    return _builder(spacing).rest


def build_surface(state: np.ndarray, spacing: float = 1.0, *, iterations: int = 3) -> FaceSurface:
    """The skin in an expression state as a height-field grid (see :class:`SurfaceBuilder`)."""
    return _builder(spacing)(state, iterations=iterations)
