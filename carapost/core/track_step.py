"""One frame step of the automatic tracker (see :mod:`.tracking` for the algorithm).

:func:`track_frame` advances a :class:`StepContext` (the tracker's state: motion model,
templates, blob sizes, camera poses) by one frame and returns that frame's point arrays.
Everything is vectorised over points and cameras; the only loop over individual points is
the grey-level patch tracking of the few observations no blob matched.

Shapes: ``C`` cameras, ``T`` tracked points, ``G`` detections of the frame. Observation
arrays are camera-first ``(C, T, ...)`` inside the step and point-first in the output (the
take's layout).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from carapost.model.params import TrackingParameters
from carapost.model.take import ObsSource, Recon

from .track_cameras import CameraSet, bundle_frame, reprojection_fixed
from .track_assign import complete_anchors, elastic_radius, inside, match_points, occluded, reclaim
from .track_match import FrameDetections, PatchSampler
from .track_patches import Appearance, patch_track, update_templates
from .track_predict import MotionModel, NeighbourGraph, transfer
from .track_reject import GATE, consistent_views, elastic_prediction, prune_views, single_sensor

__all__ = ["StepContext", "FrameOutput", "track_frame"]

#: Rounds of matching (the first un-refined, then elastic) per frame.
MAX_ROUNDS = 4
#: Reprojection error below which a point matched in two cameras anchors its neighbours, px.
ANCHOR_PX = 2.0
#: Largest leave-one-out reprojection error of a kept observation, px (see prune_views).
LOO_PX = 3.0
#: Cost added to points that were lost in the previous frame, so tracked points win conflicts.
LOST_PENALTY = 1.0e3
#: Uncertainty added to a lost point's elastic prediction per frame lost, and its largest
#: value, mm.
LOST_SIGMA_MM = 0.25
LOST_SIGMA_CAP_MM = 1.5
#: A point lost for more frames than this is re-acquired only when seen in two frames in a
#: row (or CONFIRM_WITHIN frames apart) within CONFIRM_MM of the same place relative to its
#: neighbours.
CONFIRM_AFTER = 1
CONFIRM_MM = 2.0
CONFIRM_WITHIN = 3
#: ... or when the previous sighting (however long ago), carried by how its neighbours moved
#: since (:func:`~.track_predict.transfer`), is within CARRY_CONFIRM_MM of this one, mm ...
CARRY_CONFIRM_MM = 1.0
#: ... or at once when seen by this many cameras.
CONFIRM_VIEWS = 3
#: Single-sensor tracking takes up a point lost for at most this many frames (0: it only
#: continues a track; restarting lost points from one view let stray detections in).
SS_RESTART_WITHIN = 0
#: A point lost for a while is not re-acquired where another lost point's prediction is
#: nearly as close (less than REACQUIRE_RATIO times farther) ...
REACQUIRE_RATIO = 1.5
#: ... unless it is this close to its own prediction, mm.
REACQUIRE_FREE_MM = 3.0


@dataclass
class StepContext:
    """The tracker's state between frames (``T`` points, ``C`` cameras, ``S`` patch size)."""

    params: TrackingParameters
    cams: CameraSet
    cam_ok: np.ndarray          #: (C,) cameras with a pose
    image_size: np.ndarray      #: (C, 2) width, height (0 = unknown)
    R: np.ndarray               #: (C, 3, 3) current poses
    t: np.ndarray               #: (C, 3)
    is_brim: np.ndarray         #: (T,) brim points
    brim_X: np.ndarray          #: (T, 3) fixed brim positions (NaN for face points)
    polarity: np.ndarray        #: (T,) -1 / 1 / 0 unknown
    size: np.ndarray            #: (C, T, 2) last blob (major, minor) per camera
    motion: MotionModel
    graph: NeighbourGraph
    sampler: PatchSampler
    tmpl: np.ndarray            #: (C, T, S*S) last normalised patch per camera
    fresh: np.ndarray           #: (C, T) the template is from the previous frame
    lost: np.ndarray            #: (T,) frames since the point was last measured
    has_brim: bool              #: re-estimate camera poses from brim points
    context: np.ndarray | None = None  #: (T,) known points not being tracked (default none)

    def __post_init__(self) -> None:
        if self.context is None:
            self.context = np.zeros(len(self.lost), bool)
        self.tmpl_ok = self.fresh.copy()   #: (C, T) a template exists
        #: (T, 3) offset from its neighbours' prediction at which a long-lost point was seen
        #: in the previous frame (NaN = not seen)
        self.pending = np.full((len(self.lost), 3), np.nan)
        self.pending_age = np.zeros(len(self.lost), np.int64)
        #: (T, 3), (T, k, 3): where that was, and its neighbours then
        self.pending_X = np.full((len(self.lost), 3), np.nan)
        self.pending_nb = np.full((len(self.lost), self.graph.index.shape[1], 3), np.nan)
        self.pending_cams = np.zeros((len(self.lost), len(self.R)), bool)   #: (T, C) its cameras
        #: (T, 3), (T, k, 3): each point's position when last measured in several views and
        #: its neighbours' positions then (see :func:`~.track_predict.transfer`)
        self.last_X = self.motion.x.copy()
        self.last_nb = self.last_X[self.graph.index]
        self.nbw = self.graph.weight       #: (T, k) this frame's neighbour weights


@dataclass
class FrameOutput:
    """One frame's results, in the take's layout (``T`` points, ``C`` cameras)."""

    xyz: np.ndarray       #: (T, 3)
    recon: np.ndarray     #: (T,) uint8
    obs_xy: np.ndarray    #: (T, C, 2) float32 raw px
    obs_det: np.ndarray   #: (T, C) int32
    obs_src: np.ndarray   #: (T, C) uint8
    obs_q: np.ndarray     #: (T, C) float32
    counts: dict


def track_frame(ctx: StepContext, dets: FrameDetections, claimed: np.ndarray,
                images: Sequence[np.ndarray | None] | None,
                fixed_pose: tuple[np.ndarray, np.ndarray] | None,
                context_X: np.ndarray | None = None) -> FrameOutput:
    """Track every point of ``ctx`` into the next frame.

    Parameters
    ----------
    ctx : StepContext
        Updated in place (the tracker's state moves to the new frame).
    dets : FrameDetections
        The new frame's detections.
    claimed : bool array (G + 1,)
        Detections attached to points that are not being tracked.
    images : sequence of uint8 (H, W) or None, optional
        The new frame's images (None: no appearance checks, no patch tracking).
    fixed_pose : (R, t) or None
        The new frame's poses when they are not re-estimated from the brim.
    context_X : array (T, 3), optional
        Positions in the new frame of the context points (known, not tracked; NaN elsewhere).

    Returns
    -------
    FrameOutput
    """
    p = ctx.params
    cams = ctx.cams
    sc = cams.scale
    C, T = ctx.tmpl.shape[:2]
    claimed = claimed.copy()
    app = Appearance(ctx, dets, images) if images is not None else None
    all_cols = np.arange(T)
    counts = {"points": 0, "multi_view": 0, "single_sensor": 0, "lost": 0, "blob_obs": 0, "patch_obs": 0,
              "rejected_2d": 0, "rejected_3d": 0, "brim_obs": 0, "rounds": 0}
    max2d = p.max_allowed_2d_projection_error if p.remove_bad_2d_projections else np.inf
    obs_g = np.full((C, T), -1, np.int64)

    # ------------------------------------------------------------------ 1. brim
    # matched with the previous frame's poses (the cameras move well under a pixel a frame);
    # the poses are re-estimated below, once the face is matched too
    R, t = (ctx.R, ctx.t) if fixed_pose is None else fixed_pose
    brim = np.flatnonzero(ctx.is_brim)
    adjust = ctx.has_brim and len(brim) > 0 and fixed_pose is None
    gb = np.full((C, len(brim)), -1, np.int64)
    if len(brim):
        Xb = ctx.brim_X[brim]
        pc = cams.to_pixels(cams.project_uv(Xb, R, t))
        active = inside(pc, ctx.image_size) & ctx.cam_ok[:, None]
        gb = match_points(ctx, dets, pc, active, np.full(len(brim), p.brim_point_tracking_distance), claimed, brim, app,
                    ratio=None, penalty=None)
        claimed[gb[gb >= 0]] = True
        obs_g[:, brim] = gb
        Xbc = np.broadcast_to(Xb, (C,) + Xb.shape)

    # ------------------------------------------------------------------ 2. face: rounds of matching
    motion = ctx.motion
    face = ~ctx.is_brim & ~ctx.context & motion.known
    Xcv = motion.predict()
    nbw = ctx.graph.motion_weights(motion.v)
    ctx.nbw = nbw
    lost = ctx.lost > 0
    penalty = np.where(lost, LOST_PENALTY, 0.0)
    # points not being tracked but known in this frame (re-tracking a selection) are
    # anchors from the start: they carry their neighbours' elastic predictions
    known = ctx.context.copy()
    if context_X is not None:
        known &= np.isfinite(context_X).all(1)
        Xk = np.where(known[:, None], context_X, np.nan)
    else:
        known[:] = False
        Xk = np.full((T, 3), np.nan)
    anchors = known.copy()
    Xa = Xk.copy()
    tent = np.full((C, T), -1, np.int64)
    face_r = p.face_point_tracking_distance
    elastic_r = p.face_point_max_elastic_prediction_distance
    anchor_px = min(ANCHOR_PX, max2d)
    max3d = p.max_allowed_3d_point_error if p.remove_bad_3d_points else np.inf
    # a lost point's prediction drifts with its neighbours: it is allowed farther from it
    drift = np.minimum(LOST_SIGMA_MM * ctx.lost, LOST_SIGMA_CAP_MM)
    reach = max3d + GATE * drift
    # round 0: the un-refined (motion model) prediction, unambiguous matches only, then
    # verified against the neighbours matched in the same way (leave-one-out elastic prediction)
    part = face & ~lost
    uvp = cams.project_uv(Xcv, R, t)
    pc = cams.to_pixels(uvp)
    hidden = occluded(np.where(known[:, None], Xk, Xcv), face, (face & ~lost) | known, pc, R, t)
    active = part[None, :] & inside(pc, ctx.image_size) & ctx.cam_ok[:, None] & ~hidden
    g = match_points(ctx, dets, pc, active, np.full(T, face_r), claimed, all_cols, app, ratio=np.ones(T, bool),
                     penalty=penalty, vote=np.ones(T, bool), owners=np.where(part[None, :, None], pc, np.nan))
    uvg = dets.uv[g]
    sel = np.flatnonzero(part & ((g >= 0).sum(0) >= 2))
    # (the cameras still have the previous frame's poses, up to half a pixel off: a looser
    # leave-one-out test until they are re-estimated)
    r0_loo = min(LOO_PX, 1.5 * max2d)
    w, X = _prune(uvg, (g >= 0).astype(float), sel, R, t, sc, anchor_px, r0_loo, uvp)
    counts["rounds"] = 1
    cand = part & ((w > 0).sum(0) >= 2) & np.isfinite(X).all(1)
    Xel, sigma, sup = elastic_prediction(ctx.graph, np.where(known[:, None], Xk, X), Xcv, (cand & ~lost) | known,
                                         weight=nbw)
    # again where a view was dropped, now that the neighbours' prediction can tell which one
    redo = sel[((g[:, sel] >= 0) & (w[:, sel] == 0)).any(0) & sup[sel]]
    if len(redo):
        w[:, redo], X[redo] = _prune(uvg[:, redo], (g[:, redo] >= 0).astype(float), np.arange(len(redo)), R, t, sc,
                                     anchor_px, r0_loo, uvp[:, redo], Xel[redo], sigma[redo])
    cand = part & ((w > 0).sum(0) >= 2) & np.isfinite(X).all(1)
    w, X, ok = consistent_views(uvg, w, X, Xel, sigma, cand & sup, R, t, sc, max_mm=max3d)
    ok &= _plausible(ctx, X, Xcv, cand & ~sup, max3d)
    new = cand & ok
    _anchor(new, X, w, g, anchors, Xa, tent, claimed, not p.remove_bad_2d_projections)
    tent[:, part & ~new] = g[:, part & ~new]
    # the cameras of this frame: brim dots fixed, the confidently matched face points free
    if adjust:
        R, t, gb, Xa = _adjust_cameras(ctx, dets, Xbc, gb, tent, anchors, Xa, R, t, max2d, counts)
        obs_g[:, brim] = gb
    # the anchors claim their detections in the cameras they were not matched in, before the
    # others go looking
    done = face & anchors & ~known
    # (first, detections taken by points placed from two views that a point placed from more
    # views projects onto are released to it)
    done &= ~_reclaim(ctx, dets, done, face & ~known, anchors, Xa, tent, claimed, R, t)[0]
    complete_anchors(ctx, dets, done, Xa, tent, claimed, R, t, app, anchor_px, not p.remove_bad_2d_projections,
                     np.where(known[:, None], Xk, Xcv), (face & ~lost) | known, hidden)
    # elastic rounds: the others, predicted from their matched neighbours
    occ = None
    for _ in range(1, MAX_ROUNDS):
        Xel, sigma, sup = elastic_prediction(ctx.graph, Xa, Xcv, anchors & ~lost, weight=nbw)
        part = face & ~anchors
        if not np.any(part):
            break
        counts["rounds"] += 1
        uvp = cams.project_uv(Xel, R, t)
        pc = cams.to_pixels(uvp)
        # search radius: what the prediction's uncertainty allows, within the parameter; lost
        # points (being re-acquired: their prediction may have drifted) search the whole Face
        # Point Tracking Distance but take only unambiguous matches
        radius = elastic_radius(Xel, sigma, R, t, cams, elastic_r)
        radius = np.where(sup & ~lost, radius, face_r)
        ratio = ~sup | lost
        if occ is None:
            Xo = np.where(anchors[:, None], Xa, Xel)
            occ = occluded(Xo, face, (face & (anchors | ~lost)) | known, cams.to_pixels(cams.project_uv(Xo, R, t)),
                            R, t)
        active = part[None, :] & inside(pc, ctx.image_size) & ctx.cam_ok[:, None] & ~occ
        Xw = np.where(anchors[:, None], Xa, np.where((face & ~lost)[:, None], Xel, np.nan))
        g = match_points(ctx, dets, pc, active, radius, claimed, all_cols, app, ratio=ratio, penalty=penalty,
                         vote=~sup & ~lost, owners=cams.to_pixels(cams.project_uv(Xw, R, t)),
                         hidden_by_claimed=lost)
        # (a lost point's prediction has drifted with its neighbours for a while: less certain)
        sigma = sigma + drift
        uvg = dets.uv[g]
        sel = np.flatnonzero(part & ((g >= 0).sum(0) >= 2))
        w, X = _prune(uvg, (g >= 0).astype(float), sel, R, t, sc, anchor_px, anchor_px, uvp, Xel, sigma, sup)
        cand = part & ((w > 0).sum(0) >= 2) & np.isfinite(X).all(1)
        w, X, ok = consistent_views(uvg, w, X, Xel, sigma, cand & sup, R, t, sc, max_mm=reach, loo_checked=True)
        ok &= _plausible(ctx, X, Xcv, cand & ~sup, max3d)
        new = cand & ok
        _anchor(new, X, w, g, anchors, Xa, tent, claimed, not p.remove_bad_2d_projections)
        tent[:, part & ~new] = g[:, part & ~new]
        if not np.any(new):
            break
    # (the same for the later anchors)
    _, claimants = _reclaim(ctx, dets, face & anchors & ~known, face & ~known, anchors, Xa, tent, claimed, R, t)
    Xel, sigma, sup = elastic_prediction(ctx.graph, Xa, Xcv, anchors & ~lost, weight=nbw)
    complete_anchors(ctx, dets, face & anchors & ~known & (~done | claimants), Xa, tent, claimed, R, t, app, anchor_px,
                     not p.remove_bad_2d_projections, Xel, (face & ~lost) | known, occ)
    Xel, sigma, sup = elastic_prediction(ctx.graph, Xa, Xcv, anchors & ~lost, weight=nbw)
    pred = np.where(anchors[:, None], Xa, Xel)
    obs_g[:, face] = tent[:, face]

    # ------------------------------------------------------------------ 3. patch tracking fallback
    obs_raw = dets.raw[obs_g]            # the padding row (index -1) is NaN
    obs_uv = dets.uv[obs_g]
    obs_src = np.where(obs_g >= 0, np.uint8(ObsSource.BLOB), np.uint8(ObsSource.NONE)).astype(np.uint8)
    obs_q = np.full((C, T), np.nan, np.float32)
    weight = (obs_g >= 0).astype(float)
    if images is not None:
        alive = face & (anchors | (tent >= 0).any(0) | sup)
        want = (obs_g < 0) & ctx.fresh & alive[None, :] & ctx.cam_ok[:, None]
        if np.any(want):
            patch_track(ctx, dets, images, want, pred, anchors, sup, R, t, claimed, obs_raw, obs_uv, obs_src,
                        obs_q, weight)

    # ------------------------------------------------------------------ 4. reconstruct and reject
    uvp = cams.project_uv(pred, R, t)
    fw = np.where(face[None, :], weight, 0.0)
    # anchors' views were checked (more strictly) when they were matched; the others, and any
    # patch-tracked views, are checked now (and, with Remove Bad 2D Projections off, every
    # point is reconstructed from all the detections it matched)
    fw2 = fw.copy()
    X = np.where(anchors[:, None] & face[:, None], Xa, np.nan)
    recheck = ~anchors | (obs_src == ObsSource.PATCH).any(0) | (not p.remove_bad_2d_projections)
    check = np.flatnonzero(face & recheck & ((fw > 0).sum(0) >= 2))
    if len(check):
        fw2[:, check], X[check] = _prune(obs_uv[:, check], fw[:, check], np.arange(len(check)), R, t, sc, max2d,
                                         min(1.5 * max2d, LOO_PX), uvp[:, check], Xel[check], sigma[check],
                                         sup[check])
    counts["rejected_2d"] += int(((fw > 0) & (fw2 == 0) & ((fw > 0).sum(0) >= 2)[None, :]).sum())
    measured = face & ((fw2 > 0).sum(0) >= 2) & np.isfinite(X).all(1)
    # Remove Bad 3D Points: disagreement with the neighbours (leave-one-out), twice, so that
    # a bad point does not spoil its neighbours' predictions
    if p.remove_bad_3d_points:
        for _ in range(2):
            Xel, sigma, sup = elastic_prediction(ctx.graph, np.where(known[:, None], Xk, X), Xcv,
                                                 (measured & ~lost) | known, weight=nbw)
            sigma = sigma + drift
            before = fw2 > 0
            fw2, X, ok = consistent_views(obs_uv, fw2, X, Xel, sigma, measured & sup, R, t, sc, max_mm=reach)
            ok &= _plausible(ctx, X, Xcv, measured & ~sup, max3d)
            fw2[:, ~ok] = 0.0
            X[~ok] = np.nan
            counts["rejected_3d"] += int((before & (fw2 == 0)).sum())
            measured = face & ((fw2 > 0).sum(0) >= 2) & np.isfinite(X).all(1)
            if np.all(ok):
                break
    # a point lost for a while comes back only when two frames in a row agree on where it is
    # (relative to its neighbours): a chance pair of stray detections does not
    back = measured & (ctx.lost > CONFIRM_AFTER)
    ctx.pending_age += 1
    # ... and only where no other lost point has a similar claim (lost neighbours drift alike)
    if np.any(back):
        others = np.flatnonzero(face & lost)
        bi = np.flatnonzero(back)
        pr = Xel[others]
        d = np.linalg.norm(X[bi][:, None, :] - pr[None, :, :], axis=-1)         # (b, L)
        d = np.where(np.isfinite(d), d, np.inf)
        own = d[np.arange(len(bi)), np.searchsorted(others, bi)]
        d[np.arange(len(bi)), np.searchsorted(others, bi)] = np.inf
        rival = d.min(axis=1) if d.shape[1] else np.full(len(bi), np.inf)
        contested = (rival < REACQUIRE_RATIO * own) & (own > REACQUIRE_FREE_MM)
        fw2[:, bi[contested]] = 0.0
        measured[bi[contested]] = False
        back[bi[contested]] = False
    if np.any(back):
        Xe, _, _ = elastic_prediction(ctx.graph, np.where(known[:, None], Xk, X), Xcv, (measured & ~lost) | known,
                                      weight=nbw)
        off = X - Xe
        with np.errstate(invalid="ignore"):
            confirmed = back & (np.linalg.norm(off - ctx.pending, axis=1) <= CONFIRM_MM) \
                & (ctx.pending_age <= CONFIRM_WITHIN)
        # the sighting agrees with the previous one carried by the neighbours' motion since
        Xnb = np.where(((measured & ~lost) | known)[:, None], np.where(known[:, None], Xk, X), np.nan)
        bi = np.flatnonzero(back)
        Xt, okt = transfer(ctx.pending_X[bi], ctx.pending_nb[bi], Xnb[ctx.graph.index[bi]], ctx.graph.weight[bi])
        dt = np.linalg.norm(X[bi] - Xt, axis=1)
        with np.errstate(invalid="ignore"):
            confirmed[bi] |= okt & (dt <= CARRY_CONFIRM_MM)
        # ... by the same cameras: a point seen by one camera, put on its ray by a different
        # stray detection in another camera each time, would agree with itself along that ray
        views = (fw2 > 0).T                                                  # (T, C)
        confirmed &= (views == ctx.pending_cams).all(1)
        # three or more views agreeing (leave-one-out) are not a chance pair of stray detections
        confirmed |= back & (views.sum(1) >= CONFIRM_VIEWS)
        fresh = back & ~confirmed
        ctx.pending = np.where(fresh[:, None], off, ctx.pending)
        ctx.pending_X = np.where(back[:, None], X, ctx.pending_X)
        ctx.pending_nb[back] = Xnb[ctx.graph.index[back]]
        ctx.pending_cams[back] = views[back]
        ctx.pending_age = np.where(fresh, 0, ctx.pending_age)
        fw2[:, fresh] = 0.0
        measured &= ~fresh
    if adjust and np.any(measured):
        R, t, gb, X = _adjust_cameras(ctx, dets, Xbc, gb, np.where(fw2 > 0, obs_g, -1), measured, X, R, t, max2d,
                                      counts, uv=obs_uv, weight=fw2)
        obs_g[:, brim] = gb
    Xel, sigma, sup2 = elastic_prediction(ctx.graph, np.where(known[:, None], Xk, X), Xcv,
                                          (measured & ~lost) | known, weight=nbw)
    nv = (fw2 > 0).sum(0)
    recon = np.where(measured, np.uint8(Recon.MULTI_VIEW), np.uint8(Recon.NONE)).astype(np.uint8)
    Xout = np.where(measured[:, None], X, np.nan)
    one = face & (nv == 1)
    if np.any(one):
        cam1 = np.argmax(fw2[:, one], axis=0)
        idx1 = np.flatnonzero(one)
        ok = np.zeros(len(idx1), bool)
        if p.allow_single_sensor_tracking:
            Xs, ok = single_sensor(obs_uv[cam1, idx1], cam1, R, t, Xel[idx1], p.single_sensor_tracking_threshold)
            # it continues a track (or restarts one lost a moment ago), it does not start one
            ok &= sup2[idx1] & (ctx.lost[idx1] <= SS_RESTART_WITHIN)
            Xout[idx1[ok]] = Xs[ok]
            recon[idx1[ok]] = Recon.SINGLE_SENSOR
        fw2[cam1[~ok], idx1[~ok]] = 0.0
        counts["single_sensor"] = int(ok.sum())
    keep = np.where(face[None, :], fw2 > 0, obs_g >= 0)
    obs_g = np.where(keep, obs_g, -1)
    obs_src = np.where(keep, obs_src, np.uint8(ObsSource.NONE)).astype(np.uint8)
    obs_raw = np.where(keep[..., None], obs_raw, np.nan)
    obs_q = np.where(keep & (obs_src == ObsSource.PATCH), obs_q, np.nan).astype(np.float32)
    # brim points: fixed positions wherever seen
    if len(brim):
        nb = keep[:, brim].sum(0)
        Xout[brim] = np.where((nb > 0)[:, None], ctx.brim_X[brim], np.nan)
        recon[brim] = np.where(nb >= 2, Recon.MULTI_VIEW, np.where(nb == 1, Recon.SINGLE_SENSOR, Recon.NONE))
        counts["brim_obs"] = int(nb.sum())

    # ------------------------------------------------------------------ 5. state update
    # a single-sensor position is exact only across its ray: it and the unmeasured points move
    # with their neighbours (their own velocity would carry any depth error on and on)
    multi = face & (recon == Recon.MULTI_VIEW)
    single = face & (recon == Recon.SINGLE_SENSOR)
    vn, vsup = ctx.graph.average(motion.v + (Xout - Xcv), multi & ~lost)   # neighbours' new velocities
    # a point measured again after a gap starts afresh (its prediction had drifted): at the
    # measurement, moving like its neighbours. A point not measured goes where its neighbours'
    # motion since it was last seen takes it (failing that, it moves with them frame by frame)
    back = multi & lost
    carry = np.where((single | back)[:, None], Xout, Xel)
    sup2 = sup2 | single | back
    Xnow = np.where(known[:, None], Xk, np.where(multi[:, None], Xout, np.nan))
    gone = np.flatnonzero(face & ~multi & ~single)
    if len(gone):
        Xt, okt = transfer(ctx.last_X[gone], ctx.last_nb[gone], Xnow[ctx.graph.index[gone]], ctx.graph.weight[gone],
                            min_translate=1)
        carry[gone[okt]] = Xt[okt]
        sup2[gone[okt]] = True
    motion.step(multi & ~lost, Xout, carried_x=carry, carried_v=np.where(vsup[:, None], vn, 0.0), carried=sup2)
    ctx.last_X[multi] = Xout[multi]
    ctx.last_nb[multi] = Xnow[ctx.graph.index[multi]]
    meas_face = multi | single
    ctx.lost = np.where(meas_face | ctx.is_brim | ctx.context, 0, ctx.lost + 1)
    update_templates(ctx, dets, images, app, keep, obs_g, obs_raw)
    blob = keep & (obs_g >= 0)
    gb = obs_g[blob]
    ctx.size[blob] = np.stack([dets.major[gb], dets.minor[gb]], axis=1)
    ctx.R, ctx.t = R, t

    counts["points"] = int(face.sum())
    counts["multi_view"] = int((face & (recon == Recon.MULTI_VIEW)).sum())
    counts["lost"] = int((face & (recon == Recon.NONE)).sum())
    counts["blob_obs"] = int((keep & (obs_src == ObsSource.BLOB)).sum())
    counts["patch_obs"] = int((keep & (obs_src == ObsSource.PATCH)).sum())
    obs_det = dets.idx[obs_g].astype(np.int32)
    return FrameOutput(xyz=Xout, recon=recon, obs_xy=obs_raw.transpose(1, 0, 2).astype(np.float32),
                       obs_det=obs_det.T.copy(), obs_src=obs_src.T.copy(), obs_q=obs_q.T.copy(), counts=counts)


def _adjust_cameras(ctx: StepContext, dets: FrameDetections, Xbc: np.ndarray, gb: np.ndarray, g: np.ndarray,
                    points: np.ndarray, X: np.ndarray, R: np.ndarray, t: np.ndarray, max2d: float, counts: dict, *,
                    uv: np.ndarray | None = None, weight: np.ndarray | None = None) -> tuple:
    """Per-frame camera re-estimation (one bundle-adjustment step), then Remove Bad 2D
    Projections on the brim. Returns ``R, t, gb, X`` (``X`` updated for ``points``)."""
    sc = ctx.cams.scale
    use_b = gb >= 0
    uv = dets.uv[g] if uv is None else uv
    w = np.where(points[None, :] & (g >= 0), 1.0 if weight is None else weight, 0.0)
    R, t, Xn = bundle_frame(Xbc, dets.uv[gb], use_b, uv, w, X, R, t, sc, iterations=1)
    X = np.where(points[:, None], Xn, X)
    res = reprojection_fixed(Xbc, dets.uv[gb], use_b, R, t, sc)
    bad = use_b & (res > max2d)
    if np.any(bad):
        counts["rejected_2d"] += int(bad.sum())
        gb = np.where(bad, -1, gb)
    return R, t, gb, X


def _reclaim(ctx: StepContext, dets: FrameDetections, strong: np.ndarray, weak: np.ndarray, anchors: np.ndarray,
             Xa: np.ndarray, tent: np.ndarray, claimed: np.ndarray, R: np.ndarray,
             t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~.track_assign.reclaim`, then anchors left with one view stop being anchors
    (updates ``anchors`` and ``Xa`` in place). Returns ``(dropped, claimants)``."""
    weakened, claimants = reclaim(dets, strong, weak, Xa, tent, claimed, R, t, ctx.cams)
    dropped = weakened & anchors & ((tent >= 0).sum(0) < 2)
    anchors &= ~dropped
    Xa[dropped] = np.nan
    return dropped, claimants


def _plausible(ctx: StepContext, X: np.ndarray, Xcv: np.ndarray, check: np.ndarray, max3d: float) -> np.ndarray:
    """For points without matched neighbours: within reach of their own motion model.

    The reach is the Max Allowed 3D Point Error plus the distance moved in the last frame,
    growing by :data:`LOST_SIGMA_MM` per frame a point has been lost (it has drifted).
    """
    reach = max3d + np.linalg.norm(ctx.motion.v, axis=1) + GATE * np.minimum(LOST_SIGMA_MM * ctx.lost,
                                                                              LOST_SIGMA_CAP_MM)
    with np.errstate(invalid="ignore"):
        return ~check | (np.linalg.norm(X - Xcv, axis=1) <= reach)


def _prune(uv: np.ndarray, w0: np.ndarray, sel: np.ndarray, R: np.ndarray, t: np.ndarray, sc: np.ndarray,
           max_px: float, loo_px: float, pred_uv: np.ndarray, Xel: np.ndarray | None = None,
           sigma: np.ndarray | None = None, sup: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~.track_reject.prune_views` of the points ``sel`` only (the others get no views)."""
    T = w0.shape[1]
    w = np.zeros_like(w0)
    X = np.full((T, 3), np.nan)
    if len(sel):
        sg = None if sigma is None else sigma[sel] if sup is None else np.where(sup[sel], sigma[sel], np.nan)
        ws, Xs, _ = prune_views(uv[:, sel], w0[:, sel], R, t, sc, max_px, loo_px=loo_px, pred_uv=pred_uv[:, sel],
                                Xel=None if Xel is None else Xel[sel], sigma=sg)
        w[:, sel] = ws
        X[sel] = Xs
    return w, X


def _anchor(new: np.ndarray, X: np.ndarray, w: np.ndarray, g: np.ndarray, anchors: np.ndarray, Xa: np.ndarray,
            tent: np.ndarray, claimed: np.ndarray, keep_all: bool) -> None:
    """Make ``new`` points anchors (updates the arrays in place) with their consistent views —
    or, with ``keep_all`` (Remove Bad 2D Projections off), every view they matched."""
    anchors |= new
    Xa[new] = X[new]
    kept = g[:, new] if keep_all else np.where(w[:, new] > 0, g[:, new], -1)
    tent[:, new] = kept
    claimed[kept[kept >= 0]] = True
