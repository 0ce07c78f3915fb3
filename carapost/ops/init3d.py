"""Initialize 3D, seeds and bundle adjustment as undoable operations.

* :func:`add_seed_points` turns snapped seeds (a seeds file, or the user's Merge clicks) into
  points — the seeds Initialize 3D grows from.
* :func:`initialize_3d_op` is "Initialize 3D" (seeded) and, with ``auto=True``, the automatic
  initialization that needs no seeds.
* :func:`bundle_current_frame` / :func:`bundle_sequence` are "Bundle Current Frame
  [Unconstrained]" / "Bundle Sequence [Unconstrained]".
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from carapost.core.auto_init import auto_initialize
from carapost.core.bundle import bundle_adjust
from carapost.core.init3d import Init3DResult, initialize_3d
from carapost.io.seeds import SnappedSeeds
from carapost.model.take import ObsSource, PointKind, Recon, Take

from .change import ArrayPatch, AttributeChange, Change, Composite, PointsAdded
from .points import PointBlock, _empty_columns

__all__ = ["add_seed_points", "initialize_3d_op", "bundle_current_frame", "bundle_sequence", "seed_columns"]


def _frame_detections(take: Take, frame: int) -> list[dict[str, np.ndarray]]:
    return [{k: np.asarray(v) for k, v in take.detections[c].frame(frame).items()} for c in range(take.n_cameras)]


def add_seed_points(take: Take, frame: int, snapped: SnappedSeeds) -> Composite:
    """New points from the face seeds of a seeds file (named seeds become labelled points and
    join the Labelling pane's list)."""
    seeds = snapped.face
    if not seeds:
        raise ValueError("the seeds file has no face seed matched in two or more cameras")
    n = len(seeds)
    arrays = _empty_columns(take, n)
    for j, (_, cams) in enumerate(seeds):
        for c, i in cams.items():
            arrays["obs_xy"][frame, j, c] = take.detections[c].xy(frame)[i]
            arrays["obs_det"][frame, j, c] = i
            arrays["obs_src"][frame, j, c] = ObsSource.BLOB
    labels = [name or "" for name, _ in seeds]
    changes: list[Change] = [PointsAdded(n, int(PointKind.FACE), labels, np.full(n, -1, np.int32), arrays)]
    new_labels = [lab for lab in labels if lab and lab not in take.labels]
    if new_labels:
        changes.append(AttributeChange.capture(take, "labels", take.labels + new_labels, ""))
    return Composite(changes, f"Add {n} seed points")


def seed_columns(take: Take, frame: int) -> np.ndarray:
    """Face points with a detection in at least two cameras in ``frame`` (Initialize 3D's seeds)."""
    face = take.face_points()
    return face[(take.obs_det[frame, face] >= 0).sum(-1) >= 2]


def _brim_inputs(take: Take, frame: int) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """The brim model (if any) and per-camera masks of detections attached to brim points."""
    masks = [np.zeros(take.detections[c].count(frame), bool) for c in range(take.n_cameras)]
    for col in take.brim_points():
        for c in range(take.n_cameras):
            i = int(take.obs_det[frame, col, c])
            if i >= 0:
                masks[c][i] = True
    return (take.brim.xyz if take.brim is not None else None), masks


def initialize_3d_op(take: Take, frame: int, *, auto: bool = False, bundle: bool = True) -> Composite:
    """"Initialize 3D" on ``frame``: grow points from the seeds (or, with ``auto``, from nothing).

    Seeds are the face points already matched in two or more cameras in the frame. The frame's
    camera poses are replaced by the bundled ones.

    Raises
    ------
    ValueError
        No camera poses (solve the brim first), no detections, or no seeds when not ``auto``.
    """
    if not np.isfinite(take.R[frame]).all() or not np.isfinite(take.t[frame]).all():
        raise ValueError(f"Initialize 3D: the cameras have no pose in frame {frame}; solve the calibration brim "
                         "or import a calibration first")
    if not any(take.detections[c].count(frame) for c in range(take.n_cameras)):
        raise ValueError(f"Initialize 3D: no detections in frame {frame}; detect blobs first")
    dets = _frame_detections(take, frame)
    brim_xyz, exclude = _brim_inputs(take, frame)
    caddies = take.caddies
    seeds_cols = seed_columns(take, frame)
    kw = dict(caddies=caddies, exclude=exclude, brim_xyz=brim_xyz, bundle=bundle)
    if auto:
        pa = take.params.init3d
        if pa.auto_min_views > take.n_cameras:
            raise ValueError(f"Initialize 3D: Automatic Min Views ({pa.auto_min_views}) exceeds the take's "
                             f"{take.n_cameras} cameras")
        res = auto_initialize(dets, take.intrinsics(), take.R[frame], take.t[frame], pa, min_views=pa.auto_min_views,
                              max_reprojection_px=pa.auto_max_reprojection_error, **kw)
        seeds_cols = seeds_cols[:0]
    else:
        if len(seeds_cols) == 0:
            raise ValueError("Initialize 3D: no seed points; merge 5-10 markers matched in two or more cameras "
                             "(or use automatic initialization)")
        seeds = [{c: int(take.obs_det[frame, p, c]) for c in range(take.n_cameras) if take.obs_det[frame, p, c] >= 0}
                 for p in seeds_cols]
        res = initialize_3d(dets, take.intrinsics(), take.R[frame], take.t[frame], seeds, take.params.init3d, **kw)
    return _apply_result(take, frame, res, seeds_cols, auto)


def _apply_result(take: Take, frame: int, res: Init3DResult, seed_cols: np.ndarray, auto: bool) -> Composite:
    changes: list[Change] = []
    n_seed = len(seed_cols)
    # Seeds: the result's first rows, in order (attachments may have grown, positions refined).
    if n_seed:
        blk = PointBlock(take, [frame], seed_cols)
        blk.detach(np.ones(blk.arrays["obs_det"].shape, bool))
        _fill(blk.arrays, 0, np.arange(n_seed), res, np.arange(n_seed), take)
        changes += blk.patches()
    # Brim observations found by Initialize 3D.
    brim_cols = take.brim_points()
    if len(brim_cols) and res.brim_det_index.shape[0]:
        blk = PointBlock(take, [frame], brim_cols)
        dots = take.points.brim_index[brim_cols]
        for j, b in enumerate(dots):
            for c in range(take.n_cameras):
                i = int(res.brim_det_index[b, c])
                if i >= 0 and blk.arrays["obs_det"][0, j, c] < 0:
                    blk.attach(0, j, c, i, take.detections[c].xy(frame)[i])
        nv = (blk.arrays["obs_det"][0] >= 0).sum(-1)
        blk.arrays["recon"][0] = np.where(nv >= 2, Recon.MULTI_VIEW, blk.arrays["recon"][0])
        changes += blk.patches()
    # New points.
    new = np.arange(n_seed, len(res.xyz))
    if len(new):
        arrays = _empty_columns(take, len(new))
        _fill(arrays, frame, np.arange(len(new)), res, new, take)
        changes.append(PointsAdded(len(new), int(PointKind.FACE), [""] * len(new), np.full(len(new), -1, np.int32),
                                   arrays))
    # The frame's refined camera poses.
    changes.append(ArrayPatch.capture(take, "R", (frame,), res.R))
    changes.append(ArrayPatch.capture(take, "t", (frame,), res.t))
    what = "Automatic initialization" if auto else "Initialize 3D"
    return Composite(changes, f"{what}: {len(new)} new points ({n_seed} seeds) in frame {frame}")


def _fill(arrays: dict[str, np.ndarray], frame: int, dst: np.ndarray, res: Init3DResult, src: np.ndarray,
          take: Take) -> None:
    """Write result rows ``src`` into point columns ``dst`` of ``arrays`` at ``frame``."""
    det = res.det_index[src]            # (n, C)
    has = det >= 0
    arrays["obs_det"][frame, dst] = np.where(has, det, -1)
    arrays["obs_xy"][frame, dst] = np.where(has[..., None], res.xy[src], np.nan)
    arrays["obs_src"][frame, dst] = np.where(has, ObsSource.BLOB, ObsSource.NONE)
    arrays["obs_q"][frame, dst] = np.nan
    ok = np.isfinite(res.xyz[src]).all(-1) & (has.sum(-1) >= 2)
    arrays["xyz"][frame, dst] = np.where(ok[:, None], res.xyz[src], np.nan)
    arrays["recon"][frame, dst] = np.where(ok, Recon.MULTI_VIEW, Recon.NONE)


def bundle_sequence(take: Take, frames: Sequence[int] | np.ndarray, *, text: str | None = None,
                    loss: str = "soft_l1") -> Composite:
    """"Bundle Sequence [Unconstrained]": refine the frames' camera poses and multi-view points
    against their detections; the brim dots stay at the brim model (they pin the world frame)."""
    frames = np.asarray(frames, dtype=np.int64)
    if len(frames) == 0:
        raise ValueError("Bundle: no frames")
    obs = take.obs_xy[frames].astype(float)
    xyz = take.xyz[frames].copy()
    fixed = take.points.kind == PointKind.BRIM
    if take.brim is not None:
        cols = take.brim_points()
        xyz[:, cols] = take.brim.xyz[take.points.brim_index[cols]]
    free = ~fixed
    # Only multi-view points move; others keep their (interpolated / single-sensor) positions.
    multi = (np.isfinite(obs[..., 0]).sum(-1) >= 2)
    obs_used = np.where((multi | fixed[None])[..., None, None], obs, np.nan)
    res = bundle_adjust(obs_used, take.intrinsics(), take.R[frames], take.t[frames], xyz, fixed_points=fixed,
                        loss=loss, f_scale=1.0)
    new_xyz = np.where((multi & free[None])[..., None], res.xyz, take.xyz[frames])
    recon = np.where(multi & free[None] & np.isfinite(res.xyz).all(-1), np.uint8(Recon.MULTI_VIEW), take.recon[frames])
    changes: list[Change] = [ArrayPatch.capture(take, "R", (frames,), res.R),
                             ArrayPatch.capture(take, "t", (frames,), res.t),
                             ArrayPatch.capture(take, "xyz", (frames,), new_xyz),
                             ArrayPatch.capture(take, "recon", (frames,), recon)]
    rms = ", ".join(f"{r:.3f}" for r in res.rms_per_camera)
    return Composite(changes, text or f"Bundle Sequence [Unconstrained]: {len(frames)} frames, RMS per camera {rms} px")


def bundle_current_frame(take: Take, frame: int) -> Composite:
    """"Bundle Current Frame [Unconstrained]"."""
    ch = bundle_sequence(take, [frame])
    ch.text = ch.text.replace("Bundle Sequence [Unconstrained]: 1 frames", f"Bundle Current Frame [Unconstrained]: frame {frame}")
    return ch
