"""Point editing: the Edit menu's Merge, Delete, Split, Clear, Detach and Create commands.

Selections are explicit arguments: point columns, detections as ``(camera, frame, index)``
triples, and the explicit camera selection of the Selection pane. Every function returns a
change and leaves the take untouched.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from carapost.core.triangulate import triangulate
from carapost.model.take import ObsSource, PointKind, Recon, Take

from .change import ArrayPatch, Change, Composite, DetectionsReplace, PointsAdded, PointsRemoved

__all__ = [
    "DetectionRef",
    "PointBlock",
    "merge",
    "delete_points",
    "delete_detections",
    "split_point",
    "clear_points",
    "create_points_from_detections",
    "clear_active_range",
    "remove_interpolated",
    "owner_of_detections",
]

DetectionRef = tuple[int, int, int]  # (camera, frame, index within the frame)
OBS_ARRAYS = ("obs_xy", "obs_det", "obs_src", "obs_q")


class PointBlock:
    """Editable copies of the per-point arrays for some frames and point columns.

    Edit the copies, call :meth:`retriangulate`, then :meth:`patches` for the undoable change.
    """

    def __init__(self, take: Take, frames: Sequence[int] | np.ndarray, cols: Sequence[int] | np.ndarray) -> None:
        self.take = take
        self.frames = np.asarray(frames, dtype=np.int64)
        self.cols = np.asarray(cols, dtype=np.int64)
        self.index = (self.frames[:, None], self.cols[None, :])
        self.arrays = {name: getattr(take, name)[self.index].copy()
                       for name in OBS_ARRAYS + ("xyz", "recon")}

    def detach(self, mask: np.ndarray) -> None:
        """Remove the observations where ``mask (F', P', C)`` is true."""
        a = self.arrays
        a["obs_xy"][mask] = np.nan
        a["obs_det"][mask] = -1
        a["obs_src"][mask] = ObsSource.NONE
        a["obs_q"][mask] = np.nan

    def attach(self, fi: int, pj: int, camera: int, det: int, xy: np.ndarray) -> None:
        a = self.arrays
        a["obs_xy"][fi, pj, camera] = xy
        a["obs_det"][fi, pj, camera] = det
        a["obs_src"][fi, pj, camera] = ObsSource.BLOB
        a["obs_q"][fi, pj, camera] = np.nan

    def retriangulate(self) -> None:
        """Triangulate every (frame, point) seen by >= 2 cameras; a point left with fewer
        views loses its multi-view position (interpolated or single-sensor ones are kept)."""
        take = self.take
        a = self.arrays
        xy = a["obs_xy"].astype(float)
        n_views = np.isfinite(xy[..., 0]).sum(-1)
        res = triangulate(xy, take.intrinsics(), take.R[self.frames][:, None], take.t[self.frames][:, None])
        multi = n_views >= 2
        a["xyz"] = np.where(multi[..., None], res.xyz, a["xyz"])
        a["recon"] = np.where(multi & np.isfinite(res.xyz).all(-1), np.uint8(Recon.MULTI_VIEW), a["recon"])
        lost = ~multi & (a["recon"] == Recon.MULTI_VIEW)
        a["xyz"][lost] = np.nan
        a["recon"][lost] = Recon.NONE

    def patches(self, text: str = "") -> list[Change]:
        out: list[Change] = []
        for name, new in self.arrays.items():
            old = getattr(self.take, name)[self.index]
            if not np.array_equal(old, new, equal_nan=new.dtype.kind == "f"):
                out.append(ArrayPatch.capture(self.take, name, self.index, new))
        return out


def owner_of_detections(take: Take, dets: Iterable[DetectionRef]) -> list[tuple[DetectionRef, int]]:
    """The point column each detection is attached to (-1 if unused)."""
    out = []
    for c, f, i in dets:
        hits = np.flatnonzero(take.obs_det[f, :, c] == i)
        out.append(((c, f, i), int(hits[0]) if len(hits) else -1))
    return out


def _check_dets(take: Take, dets: Sequence[DetectionRef]) -> None:
    for c, f, i in dets:
        if not (0 <= c < take.n_cameras and 0 <= f < take.n_frames and 0 <= i < take.detections[c].count(f)):
            raise ValueError(f"detection {i} of camera {c} in frame {f} does not exist")


def merge(take: Take, points: Sequence[int] = (), detections: Sequence[DetectionRef] = (), *,
          frame: int | None = None) -> Composite:
    """"Merge (M)": merge the selected points and/or detections into one point.

    * Detections only (in >= 2 cameras): a new point is created from them (a seed).
    * One point and detections: the detections are attached to the point (replacing its
      observation in those cameras in that frame).
    * Several points: the others are merged into the first (in every frame, the first point's
      observations win where both have one) and deleted.

    Detections attached to another point are detached from it first. Positions are
    re-triangulated where observations changed.

    Raises
    ------
    ValueError
        For an empty selection, detections from different frames, or two detections of one
        camera.
    """
    points = [int(p) for p in points]
    detections = [tuple(int(v) for v in d) for d in detections]
    _check_dets(take, detections)  # type: ignore[arg-type]
    if not points and len(detections) < 2:
        raise ValueError("Merge needs at least two detections, or a point and detections, or two points")
    frames_d = {f for _, f, _ in detections}
    if len(frames_d) > 1:
        raise ValueError("Merge: the selected detections must all be in the current frame")
    cams = [c for c, _, _ in detections]
    if len(set(cams)) != len(cams):
        raise ValueError("Merge: select at most one detection per camera")
    # Detach the detections from their current owners.
    changes = _detach_from_owners(take, detections, keep=points[:1])
    if not points:
        f0 = detections[0][1]
        arrays = _empty_columns(take, 1)
        for c, f, i in detections:
            arrays["obs_xy"][f, 0, c] = take.detections[c].xy(f)[i]
            arrays["obs_det"][f, 0, c] = i
            arrays["obs_src"][f, 0, c] = ObsSource.BLOB
        res = triangulate(arrays["obs_xy"][f0:f0 + 1].astype(float), take.intrinsics(), take.R[f0:f0 + 1][:, None],
                          take.t[f0:f0 + 1][:, None])
        if np.isfinite(res.xyz).all():
            arrays["xyz"][f0] = res.xyz[0]
            arrays["recon"][f0] = Recon.MULTI_VIEW
        add = PointsAdded(1, int(PointKind.FACE), [""], np.full(1, -1, np.int32), arrays)
        # The detach patches were captured against the current take; apply them first.
        return Composite(changes + [add], f"Merge: new point from {len(detections)} detections")
    target = points[0]
    others = [p for p in points[1:] if p != target]
    frames = np.arange(take.n_frames) if others else np.array([detections[0][1]])
    blk = PointBlock(take, frames, [target])
    a = blk.arrays
    for p in others:
        free = ~np.isfinite(a["obs_xy"][:, 0, :, 0])  # (F, C): cameras the target lacks
        for name in OBS_ARRAYS:
            a[name][:, 0][free] = getattr(take, name)[:, p][free]
        fill = ~np.isfinite(a["xyz"][:, 0]).all(-1) & np.isfinite(take.xyz[:, p]).all(-1)
        a["xyz"][fill, 0] = take.xyz[fill, p]
        a["recon"][fill, 0] = take.recon[fill, p]
    for c, f, i in detections:
        blk.attach(int(np.flatnonzero(frames == f)[0]), 0, c, i, take.detections[c].xy(f)[i])
    blk.retriangulate()
    changes += blk.patches()
    if others:
        changes.append(PointsRemoved(np.array(sorted(others))))
    return Composite(changes, f"Merge: {len(points)} point(s), {len(detections)} detection(s)")


def _detach_from_owners(take: Take, detections: Sequence[DetectionRef], keep: Sequence[int] = ()) -> list[Change]:
    """Patches detaching the detections from the points they belong to (except ``keep``)."""
    owners = [(d, p) for d, p in owner_of_detections(take, detections) if p >= 0 and p not in keep]
    if not owners:
        return []
    frames = sorted({d[1] for d, _ in owners})
    cols = sorted({p for _, p in owners})
    blk = PointBlock(take, frames, cols)
    mask = np.zeros(blk.arrays["obs_det"].shape, bool)
    for (c, f, _), p in owners:
        mask[frames.index(f), cols.index(p), c] = True
    blk.detach(mask)
    blk.retriangulate()
    return blk.patches()


def _empty_columns(take: Take, n: int) -> dict[str, np.ndarray]:
    from carapost.model.take import POINT_ARRAYS

    out = {}
    for name, (trail, dtype, fill) in POINT_ARRAYS.items():
        shape = (take.n_frames, n) + tuple(take.n_cameras if d == "C" else d for d in trail)
        out[name] = np.full(shape, fill, dtype=dtype)
    return out


def delete_points(take: Take, points: Sequence[int]) -> PointsRemoved:
    """"Delete Selected (Ctrl+D)" for points: remove them for the whole take."""
    cols = np.unique(np.asarray(points, dtype=np.int64))
    if len(cols) == 0:
        raise ValueError("Delete Selected: no points selected")
    if cols.min() < 0 or cols.max() >= take.n_points:
        raise ValueError("Delete Selected: a selected point does not exist")
    return PointsRemoved(cols, text=f"Delete {len(cols)} point(s)")


def delete_detections(take: Take, detections: Sequence[DetectionRef]) -> Composite:
    """"Delete Selected (Ctrl+D)" for detections: remove them (and detach them from points)."""
    _check_dets(take, detections)
    changes: list[Change] = []
    for c in sorted({d[0] for d in detections}):
        det = take.detections[c]
        keep = np.ones(len(det), bool)
        for cc, f, i in detections:
            if cc == c:
                keep[det.frame_ptr[f] + i] = False
        new, remap = det.select(keep)
        od = take.obs_det[..., c]
        f, p = np.nonzero(od >= 0)
        patches = []
        if len(f):
            nd = od.copy()
            nd[f, p] = remap[det.frame_ptr[f] + od[f, p]]
            gone = (od >= 0) & (nd < 0)
            idx = (slice(None), slice(None), c)
            patches.append(ArrayPatch.capture(take, "obs_det", idx, nd))
            if np.any(gone):
                patches.append(ArrayPatch.capture(take, "obs_xy", idx, np.where(gone[..., None], np.nan,
                                                                                 take.obs_xy[..., c, :])))
                patches.append(ArrayPatch.capture(take, "obs_src", idx, np.where(gone, 0, take.obs_src[..., c])))
        changes.append(DetectionsReplace(c, det.copy(), new, patches))
    return Composite(changes, f"Delete {len(detections)} detection(s)")


def split_point(take: Take, point: int, frame: int) -> Composite:
    """"Split Selected Point": from ``frame`` on, the point's data moves to a new point."""
    if not 0 <= point < take.n_points:
        raise ValueError(f"Split: point {point} does not exist")
    if not 0 < frame < take.n_frames:
        raise ValueError("Split: choose a frame after the first")
    arrays = _empty_columns(take, 1)
    for name in arrays:
        arrays[name][frame:, 0] = getattr(take, name)[frame:, point]
    blk = PointBlock(take, np.arange(frame, take.n_frames), [point])
    for name, arr in blk.arrays.items():
        arr[...] = _empty_columns(take, 1)[name][frame:]
    kind = int(take.points.kind[point])
    add = PointsAdded(1, kind, [""], take.points.brim_index[point:point + 1].copy(), arrays)
    return Composite(blk.patches() + [add], f"Split {take.points.name(point)} at frame {frame}")


def clear_points(take: Take, points: Sequence[int], frames: Sequence[int] | np.ndarray, *,
                 cameras: Sequence[int] | None = None, text: str = "") -> Composite:
    """"Clear Selected" / "Detach Detections" over frames.

    With ``cameras`` (the explicit camera selection or the active view), the selected points'
    observations in those cameras are detached and the points re-triangulated; without, all
    their 2D and 3D information in those frames is removed. Detections are never deleted.
    """
    cols = np.unique(np.asarray(points, dtype=np.int64))
    if len(cols) == 0:
        raise ValueError(f"{text or 'Clear'}: select at least one point")
    blk = PointBlock(take, frames, cols)
    mask = np.zeros(blk.arrays["obs_det"].shape, bool)
    if cameras is None:
        mask[...] = True
    else:
        mask[..., list(cameras)] = True
    blk.detach(mask)
    if cameras is None:
        blk.arrays["xyz"][...] = np.nan
        blk.arrays["recon"][...] = Recon.NONE
    else:
        blk.retriangulate()
    return Composite(blk.patches(), text or f"Clear {len(cols)} point(s)")


def create_points_from_detections(take: Take, detections: Sequence[DetectionRef]) -> Composite:
    """"Create Points From Detections": one new point per selected detection, attached to it."""
    _check_dets(take, detections)
    if not detections:
        raise ValueError("Create Points From Detections: select detections first")
    n = len(detections)
    arrays = _empty_columns(take, n)
    for j, (c, f, i) in enumerate(detections):
        arrays["obs_xy"][f, j, c] = take.detections[c].xy(f)[i]
        arrays["obs_det"][f, j, c] = i
        arrays["obs_src"][f, j, c] = ObsSource.BLOB
    changes = _detach_from_owners(take, detections)
    changes.append(PointsAdded(n, int(PointKind.FACE), [""] * n, np.full(n, -1, np.int32), arrays))
    return Composite(changes, f"Create {n} point(s) from detections")


def clear_active_range(take: Take) -> Composite:
    """"Clear Active Range": detach every detection from every point in the active range."""
    a, b = take.active_range
    if take.n_points == 0:
        return Composite([], "Clear Active Range")
    return clear_points(take, np.arange(take.n_points), np.arange(a, b + 1), text="Clear Active Range")


def remove_interpolated(take: Take, points: Sequence[int] | None = None) -> Composite:
    """"Remove Interpolated 3D Points": in the active range, delete the positions of the selected
    points (all if none) where fewer than two cameras constrain them."""
    a, b = take.active_range
    cols = np.arange(take.n_points) if not points else np.unique(np.asarray(points, dtype=np.int64))
    frames = np.arange(a, b + 1)
    idx = (frames[:, None], cols[None, :])
    xyz = take.xyz[idx].copy()
    recon = take.recon[idx].copy()
    interp = np.isin(recon, [Recon.INTERPOLATED, Recon.SINGLE_SENSOR])
    xyz[interp] = np.nan
    recon[interp] = Recon.NONE
    n = int(interp.sum())
    if n == 0:
        return Composite([], "Remove Interpolated 3D Points: nothing to remove")
    return Composite([ArrayPatch.capture(take, "xyz", idx, xyz), ArrayPatch.capture(take, "recon", idx, recon)],
                     f"Remove Interpolated 3D Points: {n} removed")
