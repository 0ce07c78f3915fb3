"""Undoable changes to a take.

An operation in ``carapost.ops`` computes its result *without* touching the take and returns a
:class:`Change`; whoever owns the take applies it with :meth:`Change.redo` (the GUI through a
``QUndoStack``, the CLI and the API through :class:`~carapost.ops.stack.UndoStack`). A change
records only what it touches — the slices of the arrays for the frames, points and cameras
affected, the detection tables of the frames it replaced — so undoing a tracking run over a long
take is cheap. :func:`take_diff` compares two takes (used by the tests of every operation).
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from carapost.model.detections import DETECTION_FIELDS, Detections
from carapost.model.take import POINT_ARRAYS, Take

__all__ = [
    "Change",
    "ArrayPatch",
    "AttributeChange",
    "DetectionFramesChange",
    "DetectionsReplace",
    "PointsAdded",
    "PointsRemoved",
    "Composite",
    "take_diff",
]


class Change(ABC):
    """Base class: ``redo`` applies the change to a take, ``undo`` reverts it."""

    text: str = ""

    @abstractmethod
    def redo(self, take: Take) -> None:
        """Apply the change to ``take``."""

    @abstractmethod
    def undo(self, take: Take) -> None:
        """Revert the change on ``take``."""

    @property
    def nbytes(self) -> int:
        """Approximate memory held for undo."""
        return 0


Index = tuple[Any, ...]


@dataclass
class ArrayPatch(Change):
    """Replace ``getattr(take, name)[index]`` by ``new``; the old values are captured at creation.

    ``index`` is a tuple of slices and/or integer arrays usable both to read and to write.
    """

    name: str
    index: Index
    old: np.ndarray
    new: np.ndarray
    text: str = ""

    @classmethod
    def capture(cls, take: Take, name: str, index: Index, new: np.ndarray, text: str = "") -> "ArrayPatch":
        arr = getattr(take, name)
        old = np.array(arr[index], copy=True)
        new = np.asarray(new, dtype=arr.dtype)
        if new.shape != old.shape:
            new = np.broadcast_to(new, old.shape).copy()
        return cls(name, index, old, np.array(new, copy=True), text)

    def redo(self, take: Take) -> None:
        getattr(take, self.name)[self.index] = self.new

    def undo(self, take: Take) -> None:
        getattr(take, self.name)[self.index] = self.old

    @property
    def nbytes(self) -> int:
        return self.old.nbytes + self.new.nbytes


@dataclass
class AttributeChange(Change):
    """Replace a (small) attribute of the take — labels, sticks, brim, parameters, ranges, cameras.

    ``path`` is a dotted attribute path (``"params.tracking"``, ``"cameras.2.frame_offset"``).
    """

    path: str
    old: Any
    new: Any
    text: str = ""

    @classmethod
    def capture(cls, take: Take, path: str, new: Any, text: str = "") -> "AttributeChange":
        return cls(path, copy.deepcopy(_get_path(take, path)), copy.deepcopy(new), text)

    def redo(self, take: Take) -> None:
        _set_path(take, self.path, copy.deepcopy(self.new))

    def undo(self, take: Take) -> None:
        _set_path(take, self.path, copy.deepcopy(self.old))


def _get_path(obj: Any, path: str) -> Any:
    for part in path.split("."):
        obj = obj[int(part)] if part.isdigit() else getattr(obj, part)
    return obj


def _set_path(obj: Any, path: str, value: Any) -> None:
    *head, last = path.split(".")
    for part in head:
        obj = obj[int(part)] if part.isdigit() else getattr(obj, part)
    if last.isdigit():
        obj[int(last)] = value
    else:
        setattr(obj, last, value)


Table = Mapping[str, np.ndarray]


@dataclass
class DetectionFramesChange(Change):
    """Replace the detections of some frames of one camera (and remap attached observations).

    ``new`` maps frame -> detection table; the old tables and ``detected`` flags are captured.
    Observations attached to a replaced frame's detections are detached unless ``remap`` gives,
    per frame, the new index of every old detection (-1 = gone).
    """

    camera: int
    old: dict[int, dict[str, np.ndarray]]
    old_detected: dict[int, bool]
    new: dict[int, dict[str, np.ndarray]]
    obs_patches: list[ArrayPatch] = field(default_factory=list)
    text: str = ""

    @classmethod
    def capture(cls, take: Take, camera: int, new: Mapping[int, Table], text: str = "",
                remap: Mapping[int, np.ndarray] | None = None) -> "DetectionFramesChange":
        det = take.detections[camera]
        old = {f: {k: v.copy() for k, v in det.frame(f).items()} for f in new}
        old_detected = {f: bool(det.detected[f]) for f in new}
        patches = []
        frames = np.array(sorted(new), dtype=np.int64)
        if len(frames) and take.n_points:
            od = take.obs_det[frames, :, camera]
            nd = od.copy()
            for i, f in enumerate(frames):
                m = od[i] >= 0
                if remap is not None and f in remap:
                    nd[i, m] = np.asarray(remap[f])[od[i, m]]
                else:
                    nd[i, m] = -1
            gone = (od >= 0) & (nd < 0)
            if np.any(od != nd):
                idx = (frames, slice(None), camera)
                patches.append(ArrayPatch.capture(take, "obs_det", idx, nd))
                if np.any(gone):
                    xy = np.where(gone[..., None], np.nan, take.obs_xy[frames, :, camera])
                    src = np.where(gone, 0, take.obs_src[frames, :, camera])
                    patches.append(ArrayPatch.capture(take, "obs_xy", idx, xy))
                    patches.append(ArrayPatch.capture(take, "obs_src", idx, src))
        copied = {f: {k: np.asarray(t.get(k, np.zeros(len(t["x"]))), dtype=dt).copy()
                      for k, dt in DETECTION_FIELDS.items()} for f, t in new.items()}
        return cls(camera, old, old_detected, copied, patches, text)

    def redo(self, take: Take) -> None:
        take.detections[self.camera] = take.detections[self.camera].with_frames(self.new)
        for p in self.obs_patches:
            p.redo(take)

    def undo(self, take: Take) -> None:
        det = take.detections[self.camera].with_frames(self.old)
        for f, flag in self.old_detected.items():
            det.detected[f] = flag
        take.detections[self.camera] = det
        for p in reversed(self.obs_patches):
            p.undo(take)

    @property
    def nbytes(self) -> int:
        tables = list(self.old.values()) + list(self.new.values())
        return sum(a.nbytes for t in tables for a in t.values()) + sum(p.nbytes for p in self.obs_patches)


@dataclass
class DetectionsReplace(Change):
    """Replace a camera's whole detection set (e.g. "Remove Unused Detections")."""

    camera: int
    old: Detections
    new: Detections
    obs_patches: list[ArrayPatch] = field(default_factory=list)
    text: str = ""

    def redo(self, take: Take) -> None:
        take.detections[self.camera] = self.new.copy()
        for p in self.obs_patches:
            p.redo(take)

    def undo(self, take: Take) -> None:
        take.detections[self.camera] = self.old.copy()
        for p in reversed(self.obs_patches):
            p.undo(take)


@dataclass
class PointsAdded(Change):
    """Append points (columns) with given per-point data; undo removes them again."""

    n: int
    kind: int
    labels: list[str]
    brim_index: np.ndarray
    arrays: dict[str, np.ndarray]  # name -> values (F, n, ...) for the new columns (others stay empty)
    first_id: int = -1
    text: str = ""

    def redo(self, take: Take) -> None:
        from carapost.model.take import PointKind

        if self.first_id < 0:
            self.first_id = take.next_point_id
        take.next_point_id = self.first_id  # a redo after an undo gives the same ids again
        cols = take.add_points(self.n, kind=PointKind(self.kind), labels=list(self.labels),
                               brim_index=self.brim_index)
        for name, values in self.arrays.items():
            getattr(take, name)[:, cols] = values

    def undo(self, take: Take) -> None:
        ids = np.arange(self.first_id, self.first_id + self.n)
        take.remove_points(np.flatnonzero(np.isin(take.points.ids, ids)))
        take.next_point_id = self.first_id


@dataclass
class PointsRemoved(Change):
    """Delete points (with their sticks and keyframes); undo restores them in place."""

    columns: np.ndarray
    saved_points: Any = None
    saved_arrays: dict[str, np.ndarray] = field(default_factory=dict)
    saved_sticks: tuple[np.ndarray, np.ndarray] | None = None
    saved_keyframes: Any = None
    text: str = ""

    def redo(self, take: Take) -> None:
        cols = np.asarray(self.columns, np.int64)
        self.saved_points = take.points.copy()
        self.saved_arrays = {name: getattr(take, name)[:, cols].copy() for name in POINT_ARRAYS}
        self.saved_sticks = (take.sticks.copy(), take.stick_colours.copy())
        self.saved_keyframes = take.keyframes.copy()
        take.remove_points(cols)

    def undo(self, take: Take) -> None:
        cols = np.asarray(self.columns, np.int64)
        P = len(self.saved_points)
        keep = np.ones(P, bool)
        keep[cols] = False
        for name in POINT_ARRAYS:
            cur = getattr(take, name)
            full = np.empty((cur.shape[0], P) + cur.shape[2:], dtype=cur.dtype)
            full[:, keep] = cur
            full[:, cols] = self.saved_arrays[name]
            setattr(take, name, full)
        take.points = self.saved_points.copy()
        take.sticks, take.stick_colours = (a.copy() for a in self.saved_sticks)
        take.keyframes = self.saved_keyframes.copy()


@dataclass
class Composite(Change):
    """Several changes applied as one history entry (in order; undone in reverse)."""

    changes: list[Change]
    text: str = ""

    def redo(self, take: Take) -> None:
        for c in self.changes:
            c.redo(take)

    def undo(self, take: Take) -> None:
        for c in reversed(self.changes):
            c.undo(take)

    @property
    def nbytes(self) -> int:
        return sum(c.nbytes for c in self.changes)

    def __bool__(self) -> bool:
        return bool(self.changes)


def take_diff(a: Take, b: Take, *, ignore_sources: bool = False) -> list[str]:
    """Names of the parts in which two takes differ (empty list = equal; NaN equals NaN).

    ``ignore_sources`` skips the cameras' source references (whose relative paths are filled in
    when a take is saved).
    """
    out = []
    for name in list(POINT_ARRAYS) + ["R", "t"]:
        x, y = getattr(a, name), getattr(b, name)
        if x.shape != y.shape or not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
            out.append(name)
    if len(a.detections) != len(b.detections) or not all(
            d.equals(e) for d, e in zip(a.detections, b.detections)):
        out.append("detections")
    pa, pb = a.points, b.points
    if (not np.array_equal(pa.ids, pb.ids) or pa.labels != pb.labels or not np.array_equal(pa.kind, pb.kind)
            or not np.array_equal(pa.brim_index, pb.brim_index) or not np.array_equal(pa.colour, pb.colour)):
        out.append("points")
    for name in ("sticks", "stick_colours"):
        if not np.array_equal(getattr(a, name), getattr(b, name)):
            out.append(name)
    ka, kb = a.keyframes, b.keyframes
    if any(not np.array_equal(getattr(ka, f), getattr(kb, f)) for f in ("frame", "point_id", "camera", "xy",
                                                                       "pattern", "search")):
        out.append("keyframes")
    for name in ("labels", "caddies", "active_range", "view_range", "n_frames", "next_point_id", "params",
                 "rom_path", "metadata"):
        if getattr(a, name) != getattr(b, name):
            out.append(name)
    if (a.brim is None) != (b.brim is None) or (a.brim is not None and b.brim is not None and (
            a.brim.name != b.brim.name or not np.array_equal(a.brim.xyz, b.brim.xyz))):
        out.append("brim")
    for i, (ca, cb) in enumerate(zip(a.cameras, b.cameras)):
        if ignore_sources:
            ca, cb = dataclasses.replace(ca, source=None), dataclasses.replace(cb, source=None)
        if ca != cb:
            out.append(f"cameras.{i}")
    return out


def compose(changes: Sequence[Change | None], text: str) -> Composite:
    """A :class:`Composite` of the non-empty changes."""
    return Composite([c for c in changes if c is not None], text)


def apply_all(take: Take, changes: Sequence[Change]) -> None:
    for c in changes:
        c.redo(take)


ProgressFn = Callable[[int, int], None]
CancelFn = Callable[[], bool]
