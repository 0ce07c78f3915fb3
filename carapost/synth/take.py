"""A synthetic take: ground truth computed up front, images rendered lazily per frame."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field, fields

import numpy as np

from carapost.core.camera import Intrinsics, project
from carapost.io.brim import bend_brim, load_default_brim
from carapost.model.take import BrimModel

from .card import BrimCard, card_for
from .config import SynthConfig
from .dots import rim_points
from .expressions import CHANNELS, Deformer
from .markers import MarkerSet, marker_set
from .motion import BLINK_HIDDEN_LEVEL, Motion, make_motion
from .render import INK_ALBEDO, FrameScene, Renderer
from .rig import Rig, nominal_rig
from .builder import SurfaceBuilder
from .surface import FaceSurface
from .texture import make_skin_texture

__all__ = ["GroundTruth", "SynthTake", "generate_take", "MAX_VIEW_ANGLE_DEG"]

#: Markers seen more obliquely than this (angle between the skin normal and the line of
#: sight) are not visible.
MAX_VIEW_ANGLE_DEG = 75.0
_COS_MAX = float(np.cos(np.deg2rad(MAX_VIEW_ANGLE_DEG)))
#: Lines of sight from a dot's rim ignore the skin within this many dot radii (the skin curves
#: away from or over the flat disc there; real paint follows it).
_RIM_TOLERANCE = 1.5


@dataclass
class GroundTruth:
    """Exact ground truth of a synthetic take (``F`` frames, ``M`` markers, ``C`` cameras,
    ``B`` brim dots). World frame = brim frame, mm; image coordinates are raw pixels.

    Attributes
    ----------
    names : list of str (M,)
        Marker labels.
    xyz : array (F, M, 3)
        Marker centres, mm.
    normals : array (F, M, 3)
        Unit skin normals at the markers.
    xy : array (F, M, C, 2)
        Projection of each marker centre, raw px (NaN if behind the camera).
    centroid_xy : array (F, M, C, 2)
        Area centroid of each dot's image (the projected disc), raw px: what an ideal blob
        detector measures. It differs from ``xy`` by the perspective offset (up to a few
        hundredths of a pixel for these dots).
    visible : bool array (F, M, C)
        Centre unoccluded, inside the image, facing the camera within
        :data:`MAX_VIEW_ANGLE_DEG`, not hidden by a blink.
    occluded : bool array (F, M, C)
        Centre hidden by the skin (e.g. the nose) or the brim card (tested for markers inside
        the image and facing the camera within :data:`MAX_VIEW_ANGLE_DEG`; False for others).
    partly_hidden : bool array (F, M, C)
        Visible markers whose dot is partly hidden (part of its rim is behind the skin or the
        card): their image is cut, so its centroid is not the marker's.
    view_angle_deg : array (F, M, C)
        Angle between the skin normal and the line of sight, degrees.
    radius_px : array (F, M, C)
        Approximate image radius of each dot (half its longest axis), px.
    brim_xyz : array (B, 3)
        Brim dot centres, mm (the brim model).
    brim_xy : array (F, B, C, 2)
    brim_centroid_xy : array (F, B, C, 2)
    brim_visible : bool array (F, B, C)
    brim_radius_px : array (F, B, C)
    R, t : arrays (F, C, 3, 3), (F, C, 3)
        True per-frame world-to-camera poses (with flex).
    nominal_R, nominal_t : arrays (C, 3, 3), (C, 3)
        Rig poses without flex (what the written ``.xcp`` holds).
    intrinsics : list of Intrinsics (C,)
    head_R, head_t : arrays (F, 3, 3), (F, 3)
        Head-to-world pose per frame (rest pose plus helmet slip).
    expression : array (F, K)
        Expression amplitudes; channel names in ``channels``.
    channels : tuple of str (K,)
    blink : array (F, 2)
        Blink amplitude of the (left, right) eye.
    blink_frames : bool array (F,)
        Frames where an eye is closed enough to hide its upper-lid markers.
    eyelid : dict
        ``{"L": indices, "R": indices}`` of the upper-lid markers.
    eyelid_indices : int array
        All upper-lid marker indices.
    marker_uv : array (M, 2)
        Material coordinates of the markers on the face, mm.
    marker_radius_mm : float
    events : list of (str, int, int)
        Expression and blink events: ``(channel, first frame, last frame)``.
    image_size : (int, int)
        (width, height).
    frame_rate : float
    """

    names: list[str]
    xyz: np.ndarray
    normals: np.ndarray
    xy: np.ndarray
    centroid_xy: np.ndarray
    visible: np.ndarray
    occluded: np.ndarray
    partly_hidden: np.ndarray
    view_angle_deg: np.ndarray
    radius_px: np.ndarray
    brim_xyz: np.ndarray
    brim_xy: np.ndarray
    brim_centroid_xy: np.ndarray
    brim_visible: np.ndarray
    brim_radius_px: np.ndarray
    R: np.ndarray
    t: np.ndarray
    nominal_R: np.ndarray
    nominal_t: np.ndarray
    intrinsics: list[Intrinsics]
    head_R: np.ndarray
    head_t: np.ndarray
    expression: np.ndarray
    channels: tuple[str, ...]
    blink: np.ndarray
    blink_frames: np.ndarray
    eyelid: dict[str, np.ndarray]
    eyelid_indices: np.ndarray
    marker_uv: np.ndarray
    marker_radius_mm: float
    events: list[tuple[str, int, int]] = field(default_factory=list)
    image_size: tuple[int, int] = (0, 0)
    frame_rate: float = 60.0

    @property
    def n_frames(self) -> int:
        return self.xyz.shape[0]

    @property
    def n_cameras(self) -> int:
        return len(self.intrinsics)

    def arrays(self) -> dict[str, np.ndarray]:
        """Every array of the truth (for ``np.savez``), intrinsics flattened."""
        out: dict[str, np.ndarray] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                out[f.name] = v
        out["names"] = np.array(self.names)
        out["channels"] = np.array(self.channels)
        out["eyelid_L"] = self.eyelid["L"]
        out["eyelid_R"] = self.eyelid["R"]
        out["marker_radius_mm"] = np.array(self.marker_radius_mm)
        out["image_size"] = np.array(self.image_size)
        out["frame_rate"] = np.array(self.frame_rate)
        out["focal_length"] = np.array([i.focal_length for i in self.intrinsics])
        out["principal_point"] = np.array([i.principal_point for i in self.intrinsics])
        out["radial"] = np.array([i.radial for i in self.intrinsics])
        out["events_channel"] = np.array([e[0] for e in self.events], dtype=str)
        out["events_frames"] = np.array([e[1:] for e in self.events], dtype=np.int64).reshape(-1, 2)
        return out


class _Model:
    """What is fixed for a take: the rig, face, markers, brim and the per-frame motion."""

    def __init__(self, config: SynthConfig) -> None:
        self.config = config
        self.rig: Rig = nominal_rig(config.width, config.height, focal_length=config.focal_length,
                                    distortion=config.distortion)
        brim = load_default_brim(config.brim)
        if config.curved_brim:
            brim = bend_brim(brim, config.brim_curvature_mm)
        if config.brim_colour != "model":
            brim.polarity = np.full(len(brim), 1 if config.brim_colour == "white" else -1, np.int8)
        self.brim: BrimModel = brim
        self.card: BrimCard = card_for(brim)
        self.markers: MarkerSet = marker_set(config.n_markers)
        self.motion: Motion = make_motion(
            config.n_frames, config.frame_rate, self.rig.R, self.rig.t, self.rig.head_R, self.rig.head_t,
            config.seed, expressions=config.expressions, blinks=config.blinks, high_motion=config.high_motion,
            slip_mm=config.slip_mm, flex=config.flex, caddies=config.caddies)
        uv = self.markers.uv
        eps = 0.05
        self._deformers = [Deformer(uv[:, 0] + du, uv[:, 1] + dv) for du, dv in ((0, 0), (eps, 0), (0, eps))]
        self._eps = eps
        self.surfaces = SurfaceBuilder(1.0)

    def markers_head(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Marker centres and unit normals in the head frame, (M, 3) each."""
        st = self.motion.expression[frame]
        P, Pu, Pv = (d(st) for d in self._deformers)
        n = np.cross(Pu - P, Pv - P)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return P, n

    def hidden_by_blink(self, frame: int) -> np.ndarray:
        """Markers hidden by a closed eye, bool (M,)."""
        hid = np.zeros(len(self.markers), bool)
        blink = self.motion.blink[frame]
        for side, amount in zip(("L", "R"), blink):
            if amount >= BLINK_HIDDEN_LEVEL:
                hid[self.markers.eyelid[side]] = True
        return hid


def _polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroids ``(..., 2)`` of closed polygons ``(..., n, 2)`` (NaN if degenerate)."""
    x, y = poly[..., 0], poly[..., 1]
    x1, y1 = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cr = x * y1 - x1 * y
    a = cr.sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cx = ((x + x1) * cr).sum(axis=-1) / (3 * a)
        cy = ((y + y1) * cr).sum(axis=-1) / (3 * a)
    out = np.stack([cx, cy], axis=-1)
    out[np.abs(a) < 1e-9] = np.nan
    return out


def _in_image(p: np.ndarray, W: int, H: int) -> np.ndarray:
    """Points ``(N, 2)`` (raw px) inside the image (pixel centres 0..W-1, 0..H-1)."""
    with np.errstate(invalid="ignore"):
        return (p[:, 0] >= 0) & (p[:, 0] <= W - 1) & (p[:, 1] >= 0) & (p[:, 1] <= H - 1)


def _radius_px(rim_xy: np.ndarray) -> np.ndarray:
    """Half the longest extent of projected rims, ``rim_xy (..., n, 2)`` -> ``(...)``."""
    n = rim_xy.shape[-2]
    opp = rim_xy[..., : n // 2, :] - rim_xy[..., n // 2:, :]
    return 0.5 * np.max(np.linalg.norm(opp, axis=-1), axis=-1)


def _compute_truth(m: _Model) -> GroundTruth:
    cfg, rig, mo = m.config, m.rig, m.motion
    F, M, C, B = cfg.n_frames, len(m.markers), rig.n_cameras, len(m.brim)
    W, H = cfg.width, cfg.height
    xyz = np.empty((F, M, 3))
    normals = np.empty((F, M, 3))
    xy = np.empty((F, M, C, 2))
    cxy = np.empty((F, M, C, 2))
    brim_cxy = np.empty((F, B, C, 2))
    visible = np.zeros((F, M, C), bool)
    occluded = np.zeros((F, M, C), bool)
    rim_hidden = np.zeros((F, M, C), bool)
    angle = np.empty((F, M, C))
    radius = np.empty((F, M, C))
    brim_xy = np.empty((F, B, C, 2))
    brim_vis = np.zeros((F, B, C), bool)
    brim_rad = np.empty((F, B, C))
    r_mm = np.full(M, cfg.marker_radius_mm)
    brim_n = m.card.normals(m.brim.xyz)
    brim_rim = rim_points(m.brim.xyz, brim_n, m.brim.radius, 32)
    for f in range(F):
        Ph, nh = m.markers_head(f)
        hR, ht = mo.head_R[f], mo.head_t[f]
        Pw = Ph @ hR.T + ht
        nw = nh @ hR.T
        xyz[f], normals[f] = Pw, nw
        rim = rim_points(Pw, nw, r_mm, 32)
        surf = m.surfaces(mo.expression[f], heights_only=True)
        hidden = m.hidden_by_blink(f)
        occ_o, occ_p, occ_who = [], [], []
        for c in range(C):
            R, t = mo.R[f, c], mo.t[f, c]
            intr = rig.intrinsics[c]
            Cc = -R.T @ t
            p = project(Pw, intr, R, t)
            xy[f, :, c] = p
            v = Cc - Pw
            dist = np.linalg.norm(v, axis=1)
            cosang = np.einsum("ij,ij->i", nw, v) / dist
            angle[f, :, c] = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
            rim_xy = project(rim, intr, R, t)
            radius[f, :, c] = _radius_px(rim_xy)
            cxy[f, :, c] = _polygon_centroid(rim_xy)
            inside = _in_image(p, W, H)
            cand = np.flatnonzero(inside & (cosang > _COS_MAX))
            if cand.size:
                # the centre and 8 points of the rim of each candidate, against the card ...
                pts_w = np.concatenate([Pw[cand, None], rim[cand, ::4]], axis=1)  # (n, 9, 3)
                vec = pts_w.reshape(-1, 3) - Cc
                dd = np.linalg.norm(vec, axis=1)
                s_card, _ = m.card.intersect(Cc, vec / dd[:, None])
                card_occ = (s_card < dd - 0.3).reshape(-1, 9)
                occluded[f, cand, c] = card_occ[:, 0]
                rim_hidden[f, cand, c] = card_occ[:, 1:].any(axis=1)
                # ... and (below, for all cameras at once) against the skin
                occ_o.append(np.broadcast_to(hR.T @ (Cc - ht), (cand.size * 9, 3)))
                occ_p.append((pts_w.reshape(-1, 3) - ht) @ hR)
                occ_who.append((c, cand))
            visible[f, :, c] = inside & (cosang > _COS_MAX) & ~hidden
            # brim
            bp = project(m.brim.xyz, intr, R, t)
            brim_xy[f, :, c] = bp
            bv = Cc - m.brim.xyz
            bcos = np.einsum("ij,ij->i", brim_n, bv) / np.linalg.norm(bv, axis=1)
            b_in = _in_image(bp, W, H)
            brim_vis[f, :, c] = b_in & (bcos > _COS_MAX)
            brim_rim_xy = project(brim_rim, intr, R, t)
            brim_rad[f, :, c] = _radius_px(brim_rim_xy)
            brim_cxy[f, :, c] = _polygon_centroid(brim_rim_xy)
        # one test of the lines of sight of all cameras
        if occ_o:
            eyes = np.concatenate(occ_o).reshape(-1, 9, 3)
            targets = np.concatenate(occ_p).reshape(-1, 9, 3)
            # centres every 0.5 mm; rims (which only mark partly hidden dots) every 1 mm
            occ_c = surf.occluded(eyes[:, 0], targets[:, 0])
            occ_r = surf.occluded(eyes[:, 1:].reshape(-1, 3), targets[:, 1:].reshape(-1, 3), step=1.0,
                                  tolerance=_RIM_TOLERANCE * cfg.marker_radius_mm).reshape(-1, 8)
            k = 0
            for c, cand in occ_who:
                occluded[f, cand, c] |= occ_c[k:k + cand.size]
                rim_hidden[f, cand, c] |= occ_r[k:k + cand.size].any(axis=1)
                k += cand.size
        visible[f] &= ~occluded[f]
        rim_hidden[f] &= visible[f]
    blink = mo.blink
    return GroundTruth(
        names=list(m.markers.names), xyz=xyz, normals=normals, xy=xy, centroid_xy=cxy, visible=visible,
        occluded=occluded, partly_hidden=rim_hidden, view_angle_deg=angle, radius_px=radius,
        brim_xyz=np.array(m.brim.xyz, float), brim_xy=brim_xy, brim_centroid_xy=brim_cxy, brim_visible=brim_vis,
        brim_radius_px=brim_rad, R=mo.R.copy(), t=mo.t.copy(), nominal_R=rig.R.copy(),
        nominal_t=rig.t.copy(), intrinsics=list(rig.intrinsics), head_R=mo.head_R.copy(), head_t=mo.head_t.copy(),
        expression=mo.expression.copy(), channels=CHANNELS, blink=blink.copy(),
        blink_frames=np.any(blink >= BLINK_HIDDEN_LEVEL, axis=1),
        eyelid={k: v.copy() for k, v in m.markers.eyelid.items()},
        eyelid_indices=np.sort(np.concatenate(list(m.markers.eyelid.values()))),
        marker_uv=m.markers.uv.copy(), marker_radius_mm=float(cfg.marker_radius_mm), events=list(mo.events),
        image_size=(W, H), frame_rate=float(cfg.frame_rate))


class SynthTake:
    """A generated take: its config, exact ground truth, brim, and lazily rendered images.

    Build one with :func:`generate_take`.
    """

    def __init__(self, config: SynthConfig, model: _Model, truth: GroundTruth) -> None:
        self.config = config
        self._m = model
        self.truth = truth
        self.brim: BrimModel = model.brim
        self._renderer_obj: Renderer | None = None
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._surf_cache: OrderedDict[int, FaceSurface] = OrderedDict()

    # --------------------------------------------------------------- properties
    @property
    def n_frames(self) -> int:
        return self.config.n_frames

    @property
    def n_cameras(self) -> int:
        return self._m.rig.n_cameras

    @property
    def rig(self) -> Rig:
        return self._m.rig

    @property
    def camera_names(self) -> list[str]:
        return list(self._m.rig.names)

    @property
    def caddies(self) -> list[tuple[int, int]]:
        return [tuple(c) for c in self.config.caddies]

    # -------------------------------------------------------------- rendering
    @property
    def _renderer(self) -> Renderer:
        """The renderer, built on first use (the skin texture takes a moment)."""
        if self._renderer_obj is None:
            cfg, m = self.config, self._m
            self._renderer_obj = Renderer(
                m.rig.intrinsics, cfg.width, cfg.height, lights=m.rig.lights, card=m.card,
                texture=make_skin_texture(cfg.seed), shading_scale=cfg.shading_scale, exposure=cfg.exposure,
                blur_sigma=cfg.blur_sigma, noise=cfg.noise, read_noise=cfg.read_noise,
                shot_noise=cfg.shot_noise, vignetting=cfg.vignetting, seed=cfg.seed)
        return self._renderer_obj

    def surface(self, frame: int) -> FaceSurface:
        """The skin height field of a frame (head frame; cached for a few frames)."""
        self._check_frame(frame)
        if frame in self._surf_cache:
            self._surf_cache.move_to_end(frame)
            return self._surf_cache[frame]
        s = self._m.surfaces(self._m.motion.expression[frame])
        self._surf_cache[frame] = s
        while len(self._surf_cache) > 3:
            self._surf_cache.popitem(last=False)
        return s

    def scene(self, frame: int) -> FrameScene:
        """What the renderer needs for a frame (dots, poses, skin)."""
        self._check_frame(frame)
        m, tr = self._m, self.truth
        cfg = self.config
        M, C = len(m.markers), self.n_cameras
        surf = self.surface(frame)
        hR, ht = m.motion.head_R[frame], m.motion.head_t[frame]
        R, t = tr.R[frame], tr.t[frame]
        brim_n = m.card.normals(m.brim.xyz)
        xyz = np.concatenate([tr.xyz[frame], m.brim.xyz])
        nrm = np.concatenate([tr.normals[frame], brim_n])
        rad = np.concatenate([np.full(M, cfg.marker_radius_mm), m.brim.radius])
        ink_face = INK_ALBEDO[cfg.marker_colour]
        ink = np.concatenate([np.full(M, ink_face),
                              np.where(np.asarray(m.brim.polarity) > 0, INK_ALBEDO["white"], INK_ALBEDO["black"])])
        D = len(xyz)
        face = np.zeros(D, bool)
        face[:M] = True
        draw = np.zeros((D, C), bool)
        cut = np.zeros((D, C), bool)
        hidden = m.hidden_by_blink(frame)
        Ph_face = (tr.xyz[frame] - ht) @ hR
        rim = rim_points(tr.xyz[frame], tr.normals[frame], np.full(M, cfg.marker_radius_mm), 8)
        rim_h = (rim - ht) @ hR  # (M, 8, 3) head frame
        W, H = cfg.width, cfg.height
        tests = []  # (camera, face dots tested, eye points (n, 3), test points (n, 3)) in the head frame
        for c in range(C):
            Cc = -R[c].T @ t[c]
            v = Cc - xyz
            facing = np.einsum("ij,ij->i", nrm, v) > 0.0
            p = np.concatenate([tr.xy[frame, :, c], tr.brim_xy[frame, :, c]])
            near = np.all(np.isfinite(p), axis=1)
            margin = 30.0
            near &= (p[:, 0] > -margin) & (p[:, 0] < W + margin) & (p[:, 1] > -margin) & (p[:, 1] < H + margin)
            ok = facing & near
            ok[:M] &= ~hidden
            draw[:, c] = ok
            # face dots: test the centre and 8 rim points against the skin and the card
            fc = np.flatnonzero(ok[:M])
            if fc.size:
                pts = np.concatenate([Ph_face[fc, None, :], rim_h[fc]], axis=1).reshape(-1, 3)
                tests.append((c, fc, np.broadcast_to(hR.T @ (Cc - ht), pts.shape), pts))
        if tests:
            targets = np.concatenate([p for _, _, _, p in tests])
            tol = np.tile(np.r_[0.4, np.full(8, _RIM_TOLERANCE * cfg.marker_radius_mm)], len(targets) // 9)
            occ_all = surf.occluded(np.concatenate([e for _, _, e, _ in tests]), targets, step=1.0, tolerance=tol)
            k = 0
            for c, fc, _, pts in tests:
                occ = occ_all[k:k + len(pts)].reshape(len(fc), 9)
                k += len(pts)
                Cc = -R[c].T @ t[c]
                vec = (pts @ hR.T + ht) - Cc
                dist = np.linalg.norm(vec, axis=1)
                s_card, _ = m.card.intersect(Cc, vec / dist[:, None])
                occ |= (s_card < dist - 0.3).reshape(len(fc), 9)
                n_occ = occ.sum(axis=1)
                draw[fc[n_occ == 9], c] = False
                cut[fc[(n_occ > 0) & (n_occ < 9)], c] = True
        return FrameScene(surface=surf, head_R=hR, head_t=ht, R=R, t=t, dots_xyz=xyz, dots_normal=nrm,
                          dots_radius=rad, dots_ink=ink, dots_face=face, dots_draw=draw, dots_cut=cut)

    def images(self, frame: int) -> np.ndarray:
        """All cameras' images of a frame, uint8 array (C, H, W) (before any JPEG coding)."""
        self._check_frame(frame)
        if frame in self._cache:
            self._cache.move_to_end(frame)
            return self._cache[frame].copy()
        imgs = self._renderer.render(frame, self.scene(frame))
        self._cache[frame] = imgs
        while len(self._cache) > 2:
            self._cache.popitem(last=False)
        return imgs.copy()

    def image(self, frame: int, camera: int) -> np.ndarray:
        """One camera's image of a frame, uint8 array (H, W)."""
        if not 0 <= camera < self.n_cameras:
            raise ValueError(f"camera must be within 0..{self.n_cameras - 1}, got {camera}")
        if frame in self._cache:
            return self._cache[frame][camera].copy()
        return self._renderer.render(frame, self.scene(frame), [camera])[0]

    def render(self, frame: int, cameras: list[int] | None = None, *, noise: bool | None = None,
               blur_sigma: float | None = None, dots: bool = True, as_float: bool = False) -> np.ndarray:
        """Images of a frame with options overridden (not cached).

        Parameters
        ----------
        frame : int
        cameras : list of int, optional
            Default all.
        noise : bool, optional
            Add sensor noise (default: the config's ``noise``).
        blur_sigma : float, optional
            Optical blur (default: the config's).
        dots : bool
            Draw the dots (``False``: the bare face and card, e.g. as a background estimate).
        as_float : bool
            Return float32 grey levels before noise and quantisation.

        Returns
        -------
        array (C', H, W)
            uint8 (or float32 with ``as_float``).
        """
        self._check_frame(frame)
        if cameras is not None:
            for c in cameras:
                if not 0 <= c < self.n_cameras:
                    raise ValueError(f"camera must be within 0..{self.n_cameras - 1}, got {c}")
        r = self._renderer
        old = r.blur_sigma
        try:
            if blur_sigma is not None:
                if blur_sigma < 0:
                    raise ValueError(f"blur_sigma must not be negative, got {blur_sigma}")
                r.blur_sigma = float(blur_sigma)
            return r.render(frame, self.scene(frame), cameras, noise=noise, dots=dots, as_float=as_float)
        finally:
            r.blur_sigma = old

    def _check_frame(self, frame: int) -> None:
        if not 0 <= frame < self.n_frames:
            raise ValueError(f"frame must be within 0..{self.n_frames - 1}, got {frame}")


def generate_take(config: SynthConfig | None = None, **overrides: object) -> SynthTake:
    """Generate a synthetic take.

    Parameters
    ----------
    config : SynthConfig, optional
        Defaults to ``SynthConfig()``.
    **overrides
        Fields replacing those of ``config`` (e.g. ``n_frames=5``).

    Returns
    -------
    SynthTake
        Ground truth is computed now; images are rendered when asked for.
    """
    if config is None:
        config = SynthConfig(**overrides)  # type: ignore[arg-type]
    elif overrides:
        from dataclasses import replace
        config = replace(config, **overrides)  # type: ignore[arg-type]
    model = _Model(config)
    truth = _compute_truth(model)
    return SynthTake(config, model, truth)
