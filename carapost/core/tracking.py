"""The automatic tracker: follow every 3D point from frame to frame.

The reference guide's "Tracking algorithm", for each frame step (forwards or backwards):

1. **Predict** each point's 3D position (a constant-velocity Kalman filter per point,
   :class:`~.track_predict.MotionModel`) and project it into every camera.
2. **Match** detections in rounds (:mod:`.track_step`). Round 0 takes the un-refined
   prediction within the *Face Point Tracking Distance* (brim: *Brim Point Tracking
   Distance*) and keeps only matches that are unambiguous — a candidate whose displacement
   the point's neighbours' candidates agree on, or else the clearly nearest one. Every point
   then confirmed in two cameras corrects its neighbours' predictions (**elastic
   prediction**: the neighbours' mean surprise, weighted toward neighbours that move alike),
   which are searched within a radius set by that prediction's uncertainty and capped by the
   *Face Point Max Elastic Prediction Distance*. Every match must pass the polarity, the
   *Blob Size Difference Threshold* and, with images, the *Patch Match Threshold* on the
   normalised cross-correlation of *Patch Match Size* patches with the previous frame; a
   detection goes to one point (cheapest first). Where no blob matches, the previous frame's
   patch is searched for (grey-level patch tracking, source PATCH).
3. **Reconstruct**: each frame's camera poses are re-estimated by a bundle adjustment of the
   cameras with the brim's dots fixed and the matched face points free (the brim alone, a
   small card above the face, leaves the poses poorly determined where the face is); the
   points are triangulated.
4. **Reject** observations reprojecting worse than the *Max Allowed 2D Projection Error*
   (*Remove Bad 2D Projections*), points disagreeing with their neighbours by more than the
   *Max Allowed 3D Point Error* or their joint uncertainty (*Remove Bad 3D Points*); with
   *Allow Single Sensor Tracking* a point left with one camera is put on that camera's ray
   where it passes within the *Single Sensor Tracking Threshold* of its prediction.

A lost point moves with its neighbours and is re-acquired when it reappears (after a longer
loss only once three cameras, or two sightings by the same cameras, agree). :func:`track` is pure: it reads the take and returns a
:class:`TrackResult`; :mod:`carapost.ops.track` turns it into an undoable change. See
``docs/tracking.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from carapost.model.params import TrackingParameters
from carapost.model.take import PointKind, Recon, Take

from .track_cameras import CameraSet
from .track_match import PatchSampler, frame_detections
from .track_predict import MotionModel, NeighbourGraph
from .track_step import FrameOutput, StepContext, track_frame

__all__ = ["TrackResult", "track", "ImageFn", "DetectFn"]

ImageFn = Callable[[int, int], np.ndarray]                      # (camera, frame) -> uint8 (H, W)
DetectFn = Callable[[int, int], Mapping[str, np.ndarray]]      # (camera, frame) -> detection table


@dataclass
class TrackResult:
    """What :func:`track` computed (``n`` frames written, ``T`` points tracked, ``C`` cameras).

    Attributes
    ----------
    frames : list of int
        Frames written, in tracking order (the start frame is not among them).
    points : int array (T,)
        Point columns of the take that were tracked (those with a start position).
    xyz : array (n, T, 3)
    recon : uint8 array (n, T)
    obs_xy : float32 array (n, T, C, 2)
    obs_det : int32 array (n, T, C)
    obs_src : uint8 array (n, T, C)
    obs_q : float32 array (n, T, C)
        The take's point arrays for ``frames`` x ``points`` (``obs_q`` holds the patch match
        score of PATCH observations).
    R : array (n, C, 3, 3)
    t : array (n, C, 3)
        Camera poses of the frames (re-estimated from the brim when brim points are tracked).
    cameras_updated : bool
        Whether the poses were re-estimated (otherwise they are the take's).
    detections : dict
        ``{camera: {frame: table}}`` for frames whose blobs were detected during tracking.
    report : dict
        Per-frame counts (``"per_frame"``: list of dicts), totals, ``"cancelled"``, timing.
    """

    frames: list[int]
    points: np.ndarray
    xyz: np.ndarray
    recon: np.ndarray
    obs_xy: np.ndarray
    obs_det: np.ndarray
    obs_src: np.ndarray
    obs_q: np.ndarray
    R: np.ndarray
    t: np.ndarray
    cameras_updated: bool
    detections: dict[int, dict[int, dict[str, np.ndarray]]] = field(default_factory=dict)
    report: dict = field(default_factory=dict)


def track(take: Take, start_frame: int, *, direction: int = 1, n_frames: int | None = None,
          image: ImageFn | None = None, params: TrackingParameters | None = None,
          points: Sequence[int] | np.ndarray | None = None, detect: DetectFn | None = None,
          progress: Callable[[int, int], None] | None = None,
          cancel: Callable[[], bool] | None = None) -> TrackResult:
    """Track points from ``start_frame`` forwards or backwards through the take.

    Parameters
    ----------
    take : Take
        Not modified. The start frame must hold the points' positions, their attached
        detections and the camera poses (after Initialize 3D or a previous tracking run).
    start_frame : int
    direction : {1, -1}
        Forwards or backwards.
    n_frames : int, optional
        Frames to track (default: to the end / start of the take).
    image : callable ``(camera, frame) -> uint8 (H, W)``, optional
        The video; without it, appearance checks and patch tracking are skipped.
    params : TrackingParameters, optional
        Default: the take's Tracking Parameters.
    points : sequence of int, optional
        Point columns to track (default all). Detections attached to the other points are
        left to them; camera poses are re-estimated only when brim points are tracked.
    detect : callable ``(camera, frame) -> detection table``, optional
        Blob detection for frames not detected yet (they are skipped for that camera if
        ``detect`` is None).
    progress : callable ``(done, total)``, optional
    cancel : callable ``() -> bool``, optional
        Polled after every frame; the frames finished so far are returned.

    Returns
    -------
    TrackResult

    Raises
    ------
    ValueError
        If the start frame, direction, points or frame count are invalid, or the start frame
        has no camera poses.
    """
    params = take.params.tracking if params is None else params
    F, C = take.n_frames, take.n_cameras
    if direction not in (1, -1):
        raise ValueError(f"direction must be 1 (forwards) or -1 (backwards), got {direction!r}")
    if not 0 <= start_frame < F:
        raise ValueError(f"start frame {start_frame} is outside the take (0..{F - 1})")
    if C == 0:
        raise ValueError("the take has no cameras to track in")
    last = F - 1 if direction > 0 else 0
    available = abs(last - start_frame)
    if n_frames is None:
        n_frames = available
    if n_frames < 0:
        raise ValueError(f"n_frames must not be negative, got {n_frames}")
    n_frames = min(int(n_frames), available)
    frames = [start_frame + direction * (k + 1) for k in range(n_frames)]
    cols = _tracked_columns(take, start_frame, points)
    # the other points known at the start frame guide the tracked ones (re-tracking a selection)
    known0 = np.isfinite(take.xyz[start_frame]).all(-1) & (take.points.kind == PointKind.FACE)
    context = np.setdiff1d(np.flatnonzero(known0), cols)
    all_cols = np.concatenate([cols, context])

    ctx = _start(take, start_frame, direction, all_cols, image, params, n_context=len(context))
    T = len(cols)
    nc = len(context)
    n = len(frames)
    out_xyz = np.full((n, T, 3), np.nan)
    out_recon = np.zeros((n, T), np.uint8)
    out_xy = np.full((n, T, C, 2), np.nan, np.float32)
    out_det = np.full((n, T, C), -1, np.int32)
    out_src = np.zeros((n, T, C), np.uint8)
    out_q = np.full((n, T, C), np.nan, np.float32)
    out_R = np.empty((n, C, 3, 3))
    out_t = np.empty((n, C, 3))
    new_dets: dict[int, dict[int, dict[str, np.ndarray]]] = {}
    per_frame: list[dict] = []
    others = np.setdiff1d(np.arange(take.n_points), cols)
    t_start = time.perf_counter()
    done = 0
    cancelled = False
    for k, f in enumerate(frames):
        t0 = time.perf_counter()
        tables = []
        for c in range(C):
            det = take.detections[c]
            if det.detected[f] or det.count(f) > 0:
                tables.append(det.frame(f) if ctx.cam_ok[c] else None)
            elif detect is not None:
                tb = {key: np.asarray(v) for key, v in detect(c, f).items()}
                new_dets.setdefault(c, {})[f] = tb
                tables.append(tb if ctx.cam_ok[c] else None)
            else:
                tables.append(None)
        images = [image(c, f) if ctx.cam_ok[c] else None for c in range(C)] if image is not None else None
        dets = frame_detections(tables, ctx.cams)
        claimed = np.zeros(len(dets) + 1, bool)
        if len(others):
            od = take.obs_det[f, others]                                     # (P', C)
            p_, c_ = np.nonzero(od >= 0)
            g = dets.gid(c_, od[p_, c_])
            g = g[(g >= 0) & (g < len(dets))]
            claimed[g] = True
        fixed_pose = None
        if not ctx.has_brim:
            Rf, tf = take.R[f], take.t[f]
            okf = np.isfinite(Rf).all((1, 2)) & np.isfinite(tf).all(1)
            fixed_pose = (np.where(okf[:, None, None], Rf, ctx.R), np.where(okf[:, None], tf, ctx.t))
        context_X = None
        if nc:
            context_X = np.concatenate([np.full((T, 3), np.nan), take.xyz[f, context]])
            _context_motion(ctx, take, context, f, direction, T)
        res: FrameOutput = track_frame(ctx, dets, claimed, images, fixed_pose, context_X)
        out_xyz[k], out_recon[k] = res.xyz[:T], res.recon[:T]
        out_xy[k], out_det[k] = res.obs_xy[:T], res.obs_det[:T]
        out_src[k], out_q[k] = res.obs_src[:T], res.obs_q[:T]
        out_R[k], out_t[k] = ctx.R, ctx.t
        res.counts["frame"] = f
        res.counts["seconds"] = time.perf_counter() - t0
        per_frame.append(res.counts)
        done = k + 1
        if progress is not None:
            progress(done, n)
        if cancel is not None and cancel() and done < n:
            cancelled = True
            break
    elapsed = time.perf_counter() - t_start
    frames = frames[:done]
    report = _summary(per_frame, elapsed, cancelled)
    for c in list(new_dets):
        new_dets[c] = {f: tb for f, tb in new_dets[c].items() if f in set(frames)}
    return TrackResult(frames=frames, points=cols, xyz=out_xyz[:done], recon=out_recon[:done],
                       obs_xy=out_xy[:done], obs_det=out_det[:done], obs_src=out_src[:done], obs_q=out_q[:done],
                       R=out_R[:done], t=out_t[:done], cameras_updated=ctx.has_brim,
                       detections={c: d for c, d in new_dets.items() if d}, report=report)


def _tracked_columns(take: Take, frame: int, points: Sequence[int] | np.ndarray | None) -> np.ndarray:
    P = take.n_points
    if points is None:
        cols = np.arange(P)
    else:
        cols = np.unique(np.asarray(points, dtype=np.int64).reshape(-1))
        if len(cols) and (cols.min() < 0 or cols.max() >= P):
            raise ValueError(f"point columns must be within 0..{P - 1}, got {cols.min()}..{cols.max()}")
    known = np.isfinite(take.xyz[frame, cols]).all(-1)
    return cols[known]


def _context_motion(ctx: StepContext, take: Take, context: np.ndarray, f: int, direction: int, T: int) -> None:
    """Set the motion state of the context points from the take (their previous two frames)."""
    fp, fpp = f - direction, f - 2 * direction
    x = take.xyz[fp, context]
    v = np.zeros_like(x)
    if 0 <= fpp < take.n_frames:
        v = np.nan_to_num(x - take.xyz[fpp, context], nan=0.0)
    ctx.motion.x[T:] = x
    ctx.motion.v[T:] = v


def _start(take: Take, f0: int, direction: int, cols: np.ndarray, image: ImageFn | None,
           params: TrackingParameters, n_context: int = 0) -> StepContext:
    """The tracker's state at the start frame (the last ``n_context`` of ``cols`` are context
    points: known, not tracked)."""
    C = take.n_cameras
    R0, t0 = take.R[f0].copy(), take.t[f0].copy()
    cam_ok = np.isfinite(R0).all((1, 2)) & np.isfinite(t0).all(1)
    if not np.any(cam_ok) and len(cols):
        raise ValueError(f"frame {f0} has no camera poses: solve the calibration brim or load a calibration first")
    R0[~cam_ok] = np.eye(3)
    t0[~cam_ok] = 0.0
    cams = CameraSet(take.intrinsics())
    T = len(cols)
    X0 = take.xyz[f0, cols].copy()
    is_brim = take.points.kind[cols] == PointKind.BRIM
    od = take.obs_det[f0, cols]                                             # (T, C)
    oxy = take.obs_xy[f0, cols].astype(float)                               # (T, C, 2)
    # polarity and blob size of each point from its attached detections
    pol_votes = np.zeros(T)
    size = np.full((C, T, 2), np.nan)
    for c in range(C):
        det = take.detections[c]
        m = od[:, c] >= 0
        if not np.any(m):
            continue
        fr = det.frame(f0)
        i = od[m, c]
        i_ok = i < len(fr["x"])
        rows = np.flatnonzero(m)[i_ok]
        i = i[i_ok]
        pol_votes[rows] += fr["polarity"][i]
        size[c, rows, 0] = fr["major"][i]
        size[c, rows, 1] = fr["minor"][i]
    polarity = np.sign(pol_votes).astype(np.int8)
    # velocity from the frame before the start (in the tracking direction) when it is known
    fp = f0 - direction
    v0 = None
    if 0 <= fp < take.n_frames:
        Xp = take.xyz[fp, cols]
        good = (take.recon[fp, cols] >= Recon.SINGLE_SENSOR) & (take.recon[f0, cols] >= Recon.SINGLE_SENSOR)
        v0 = np.where(good[:, None], X0 - Xp, np.nan)
        v0[is_brim] = 0.0
    face = ~is_brim
    motion = MotionModel(np.where(face[:, None], X0, np.nan), v0)
    graph = NeighbourGraph(X0, face)
    sampler = PatchSampler(params.patch_match_size)
    S2 = sampler.size ** 2
    tmpl = np.zeros((C, T, S2), np.float32)
    fresh = np.zeros((C, T), bool)
    if image is not None:
        for c in range(C):
            m = np.isfinite(oxy[:, c]).all(1) & cam_ok[c]
            if np.any(m):
                p, inside = sampler.sample(image(c, f0), oxy[m, c])
                a, good = sampler.normalise(p, inside)
                tmpl[c, m] = a
                fresh[c, np.flatnonzero(m)[good]] = True
    image_size = np.array([cam.image_size if cam.image_size[0] > 0 else cam.intrinsics.sensor_size
                           for cam in take.cameras], float).reshape(C, 2)
    context = np.zeros(T, bool)
    context[T - n_context:] = True
    return StepContext(params=params, cams=cams, cam_ok=cam_ok, image_size=image_size, R=R0, t=t0,
                       is_brim=is_brim, brim_X=np.where(is_brim[:, None], X0, np.nan), polarity=polarity,
                       size=size, motion=motion, graph=graph, sampler=sampler, tmpl=tmpl, fresh=fresh,
                       lost=np.zeros(T, np.int64), has_brim=bool(np.any(is_brim)), context=context)


def _summary(per_frame: list[dict], elapsed: float, cancelled: bool) -> dict:
    keys = [k for k in (per_frame[0] if per_frame else {}) if k not in ("frame", "seconds")]
    totals = {k: int(sum(p[k] for p in per_frame)) for k in keys}
    n = len(per_frame)
    return {"per_frame": per_frame, "totals": totals, "frames": n, "cancelled": cancelled,
            "seconds": elapsed, "frames_per_second": n / elapsed if elapsed > 0 else float("inf")}

