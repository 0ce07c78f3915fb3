"""Appearance for the frame-to-frame tracker: patch comparison and grey-level patch tracking.

* :class:`Appearance` — the *Patch Match Threshold* test of a match: the normalised
  cross-correlation of the *Patch Match Size* patch around the candidate detection with the
  point's patch in the previous frame (each detection's patch is sampled once per frame).
* :func:`patch_track` — where no blob matched a point in a camera, its previous-frame patch
  is searched for near the prediction (source PATCH), and accepted at the Patch Match
  Threshold unless it lands on another point's detection.
* :func:`update_templates` — the new frame's patches become the next step's templates.

Shapes: ``C`` cameras, ``T`` points, ``S`` patch size.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from carapost.model.take import ObsSource

from .track_match import FrameDetections, PatchSampler, search_patch

if TYPE_CHECKING:  # pragma: no cover
    from .track_step import StepContext

__all__ = ["Appearance", "patch_track", "update_templates", "PATCH_WEIGHT"]

#: Weight of a patch-tracked observation relative to a blob in triangulation.
PATCH_WEIGHT = 0.5


class Appearance:
    """Normalised patches of this frame's detections (computed once each, on demand)."""

    def __init__(self, ctx: "StepContext", dets: FrameDetections, images: Sequence[np.ndarray | None]) -> None:
        self.ctx = ctx
        self.dets = dets
        self.images = images
        G = len(dets)
        self.patch = np.zeros((G, ctx.tmpl.shape[2]), np.float32)
        self.good = np.zeros(G, bool)
        self.done = np.zeros(G, bool)

    def det_patches(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised patches ``(n, S*S)`` and validity ``(n,)`` of detections ``g``.

        The first request of a camera samples all its detections at once (one ``cv2.remap``
        per camera and frame is cheaper than many small ones)."""
        need = g[~self.done[g]]
        if len(need):
            cams = np.unique(self.dets.cam[need])
            need = np.concatenate([np.arange(self.dets.start[c], self.dets.start[c + 1]) for c in cams])
            cam = self.dets.cam[need]
            for c in np.unique(cam):
                sel = need[cam == c]
                img = self.images[c]
                if img is None:
                    self.done[sel] = True
                    continue
                p, inside = self.ctx.sampler.sample(img, self.dets.raw[sel])
                a, ok = PatchSampler.normalise(p, inside)
                self.patch[sel] = a
                self.good[sel] = ok
                self.done[sel] = True
        return self.patch[g], self.good[g]

    def check(self, c: np.ndarray, t: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Patch Match Threshold test of detections ``g`` for points ``t`` in cameras ``c``."""
        a, good = self.det_patches(g)
        has = self.ctx.tmpl_ok[c, t] & good
        ncc = np.einsum("ij,ij->i", a, self.ctx.tmpl[c, t])
        return ~has | (ncc >= self.ctx.params.patch_match_threshold)


def patch_track(ctx: "StepContext", dets: FrameDetections, images: Sequence[np.ndarray | None], want: np.ndarray,
                 pred: np.ndarray, anchors: np.ndarray, sup: np.ndarray, R: np.ndarray, t: np.ndarray,
                 claimed: np.ndarray, obs_raw: np.ndarray, obs_uv: np.ndarray, obs_src: np.ndarray,
                 obs_q: np.ndarray, weight: np.ndarray) -> None:
    """Grey-level patch tracking where no blob matched (fills the observation arrays in place)."""
    p = ctx.params
    cams = ctx.cams
    S = ctx.sampler.size
    uvp = cams.project_uv(pred, R, t)
    elastic = p.face_point_max_elastic_prediction_distance
    radius = np.where(anchors, min(p.max_allowed_2d_projection_error, elastic),
                      np.where(sup, elastic, p.face_point_tracking_distance))
    cc, tt = np.nonzero(want)
    found_xy = np.full((len(cc), 2), np.nan)
    score = np.full(len(cc), -1.0)
    for c in np.unique(cc):
        img = images[c]
        if img is None:
            continue
        sel = np.flatnonzero(cc == c)
        raw = cams.to_raw(int(c), uvp[c, tt[sel]])
        for k, i in enumerate(sel):
            if not np.isfinite(raw[k]).all():
                continue
            found_xy[i], score[i] = search_patch(img, ctx.tmpl[c, tt[i]].reshape(S, S), raw[k], float(radius[tt[i]]))
    ok = score >= p.patch_match_threshold
    if not np.any(ok):
        return
    # a patch on a detection that another point owns is that point's marker, not ours
    if len(dets):
        key = found_xy.copy()
        key[:, 0] += cc * 1.0e6
        d, j = dets.tree.query(np.where(np.isfinite(key), key, -1e12), k=1)
        j = np.minimum(j, len(dets) - 1)
        near_owned = (d <= np.maximum(dets.minor[j], 1.5)) & claimed[j]
        ok &= ~near_owned
    for c in np.unique(cc[ok]):
        sel = np.flatnonzero(ok & (cc == c))
        uv = cams.normalise(int(c), found_xy[sel])
        obs_raw[c, tt[sel]] = found_xy[sel]
        obs_uv[c, tt[sel]] = uv
        obs_src[c, tt[sel]] = ObsSource.PATCH
        obs_q[c, tt[sel]] = score[sel]
        weight[c, tt[sel]] = PATCH_WEIGHT


def update_templates(ctx: "StepContext", dets: FrameDetections, images: Sequence[np.ndarray | None] | None,
                      app: Appearance | None, keep: np.ndarray, obs_g: np.ndarray, obs_raw: np.ndarray) -> None:
    """The new frame's patches become the templates of the next step."""
    if images is None or app is None:
        ctx.fresh[:] = False
        return
    fresh = np.zeros_like(ctx.fresh)
    blob = keep & (obs_g >= 0)
    if np.any(blob):
        a, good = app.det_patches(obs_g[blob])
        cb, tb = np.nonzero(blob)
        ctx.tmpl[cb[good], tb[good]] = a[good]
        fresh[cb[good], tb[good]] = True
    patch = keep & (obs_g < 0)
    for c in np.unique(np.nonzero(patch)[0]):
        img = images[c]
        if img is None:
            continue
        tp = np.flatnonzero(patch[c])
        pt, inside = ctx.sampler.sample(img, obs_raw[c, tp])
        a, good = PatchSampler.normalise(pt, inside)
        ctx.tmpl[c, tp[good]] = a[good]
        fresh[c, tp[good]] = True
    ctx.fresh = fresh
    ctx.tmpl_ok |= fresh
