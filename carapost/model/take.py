"""The take: cameras, frames, detections, points and everything attached to them.

Array contract (``F`` frames, ``C`` cameras, ``P`` points; NaN / -1 for missing):

=================  =======================  ===============================================
attribute          shape, dtype             meaning
=================  =======================  ===============================================
``R``              (F, C, 3, 3) float64     world-to-camera rotation per frame
``t``              (F, C, 3) float64        translation per frame, mm (``X_cam = R X + t``)
``xyz``            (F, P, 3) float64        point positions, mm
``recon``          (F, P) uint8             :class:`Recon` reconstruction type
``obs_xy``         (F, P, C, 2) float32     2D observation of each point per camera, raw px
``obs_det``        (F, P, C) int32          attached detection (index within the frame) or -1
``obs_src``        (F, P, C) uint8          :class:`ObsSource` of the observation
``obs_q``          (F, P, C) float32        target-track match quality 0..1 (NaN if none)
``xyz_stabilized`` (F, P, 3) float64        stabilized positions (NaN until stabilized)
=================  =======================  ===============================================

Detections are per camera (:class:`~carapost.model.detections.Detections`, CSR).
Points are columns of the arrays; :class:`PointTable` holds their ids, labels and kinds.
Ids are stable (never reused) so sticks, selections and undo refer to points by id.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import numpy as np

from carapost.core.camera import Intrinsics

from .detections import Detections
from .params import Parameters

__all__ = [
    "Recon",
    "ObsSource",
    "PointKind",
    "SourceRef",
    "CameraInfo",
    "PointTable",
    "BrimModel",
    "Keyframes",
    "Take",
    "POINT_ARRAYS",
    "check_caddies",
]


class Recon(IntEnum):
    """How a point's 3D position in a frame was obtained."""

    NONE = 0           #: no position (a gap)
    INTERPOLATED = 1   #: predicted / interpolated, no detection constrains it
    SINGLE_SENSOR = 2  #: constrained to the ray of a single detection
    MULTI_VIEW = 3     #: triangulated from two or more views


class ObsSource(IntEnum):
    """Where a 2D observation came from (the Selected Point pane's colours)."""

    NONE = 0
    BLOB = 1      #: a matched blob detection
    PATCH = 2     #: grey-level patch tracking
    TARGET = 3    #: the Target Tracker between keyframes
    KEYFRAME = 4  #: a user-placed target-track keyframe


class PointKind(IntEnum):
    FACE = 0
    BRIM = 1


@dataclass
class SourceRef:
    """Where a camera's images come from.

    Attributes
    ----------
    path : str
        Absolute path of the ``.pico`` file, video file or image folder when last saved.
    relpath : str
        The same, relative to the ``.cara`` file's folder ("" if unknown).
    kind : str
        ``"pico"``, ``"video"`` or ``"images"``.
    """

    path: str
    relpath: str = ""
    kind: str = "pico"

    def resolve(self, cara_dir: str | Path | None = None) -> Path | None:
        """The existing file this reference points to, trying the relative path first."""
        candidates = []
        if cara_dir is not None and self.relpath:
            candidates.append(Path(cara_dir) / self.relpath)
        candidates.append(Path(self.path))
        if cara_dir is not None:
            candidates.append(Path(cara_dir) / Path(self.path).name)
        for c in candidates:
            if c.exists():
                return c
        return None


@dataclass
class CameraInfo:
    """One camera (sensor) of a take.

    Attributes
    ----------
    name : str
        Camera name (from the ``.pico`` metadata or the calibration).
    channel : int
        0-based channel.
    intrinsics : Intrinsics
    image_size : tuple of int
        (width, height) in pixels.
    source : SourceRef or None
    frame_offset : int
        "Increment Image Sequence Offset": take frame ``f`` shows source frame ``f + offset``.
    rotation : int
        Display rotation in degrees clockwise (0, 90, 180, 270); never changes pixel coordinates.
    device_id : str
    """

    name: str
    channel: int
    intrinsics: Intrinsics
    image_size: tuple[int, int] = (0, 0)
    source: SourceRef | None = None
    frame_offset: int = 0
    rotation: int = 0
    device_id: str = ""


@dataclass
class PointTable:
    """Per-point metadata, one entry per column of the point arrays.

    Attributes
    ----------
    ids : int64 array (P,)
        Stable point ids.
    labels : list of str
        Label of each point ("" = unlabelled).
    kind : uint8 array (P,)
        :class:`PointKind`.
    brim_index : int32 array (P,)
        Index of the brim dot for brim points, -1 for face points.
    colour : uint8 array (P, 3)
        Display colour.
    """

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    labels: list[str] = field(default_factory=list)
    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    brim_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    colour: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))

    def __len__(self) -> int:
        return len(self.ids)

    def index_of(self, point_id: int) -> int:
        hits = np.flatnonzero(self.ids == point_id)
        if len(hits) == 0:
            raise KeyError(f"no point with id {point_id}")
        return int(hits[0])

    def name(self, index: int) -> str:
        """Display name: the label, else a stable generated name."""
        lab = self.labels[index]
        if lab:
            return lab
        prefix = "Brim" if self.kind[index] == PointKind.BRIM else "Point"
        return f"{prefix}_{int(self.ids[index])}"

    def names(self) -> list[str]:
        return [self.name(i) for i in range(len(self))]

    def copy(self) -> "PointTable":
        return PointTable(self.ids.copy(), list(self.labels), self.kind.copy(), self.brim_index.copy(),
                          self.colour.copy())


@dataclass
class BrimModel:
    """A calibration brim: dot positions in the brim frame.

    Attributes
    ----------
    name : str
        E.g. ``"v2.0"`` or the SVG file name.
    xyz : float64 array (N, 3)
        Dot centres, mm, in the brim frame (the world frame once solved).
    radius : float64 array (N,)
        Dot radii, mm.
    polarity : int8 array (N,)
        1 white dots, -1 black dots.
    svg : str
        The SVG source text if imported from SVG ("" otherwise).
    """

    name: str
    xyz: np.ndarray
    radius: np.ndarray
    polarity: np.ndarray
    svg: str = ""

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class Keyframes:
    """Target-track keyframes: one row per (frame, point, camera).

    ``pattern`` and ``search`` are boxes ``(x0, y0, x1, y1)`` in raw pixels; ``xy`` is the
    keyed position. Rows refer to points by id.
    """

    frame: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    point_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    camera: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int16))
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    pattern: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))
    search: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))

    def __len__(self) -> int:
        return len(self.frame)

    def copy(self) -> "Keyframes":
        return Keyframes(self.frame.copy(), self.point_id.copy(), self.camera.copy(), self.xy.copy(),
                         self.pattern.copy(), self.search.copy())


#: Per-point arrays of a take (first axis frames, second axis points) and their fill values.
POINT_ARRAYS: dict[str, tuple[tuple[int, ...], type, object]] = {
    # name: (trailing shape after (F, P) with C meaning cameras, dtype, missing value)
    "xyz": ((3,), np.float64, np.nan),
    "recon": ((), np.uint8, 0),
    "obs_xy": (("C", 2), np.float32, np.nan),
    "obs_det": (("C",), np.int32, -1),
    "obs_src": (("C",), np.uint8, 0),
    "obs_q": (("C",), np.float32, np.nan),
    "xyz_stabilized": ((3,), np.float64, np.nan),
}



def check_caddies(caddies: Sequence[Sequence[int]], n_cameras: int) -> list[tuple[int, int]]:
    """``caddies`` as a list of camera pairs, checked: each names two different cameras of
    ``n_cameras``, and no camera is in two caddies.

    Raises
    ------
    ValueError
        Naming the offending caddy or cameras.
    """
    pairs = [(int(a), int(b)) for a, b in caddies]
    for a, b in pairs:
        if not (0 <= a < n_cameras and 0 <= b < n_cameras) or a == b:
            raise ValueError(f"caddy ({a}, {b}) does not name two of the {n_cameras} cameras")
    used = [c for pair in pairs for c in pair]
    twice = sorted({c for c in used if used.count(c) > 1})
    if twice:
        raise ValueError(f"camera(s) {twice} are in two caddies: {pairs}")
    return pairs

@dataclass
class Take:
    """A take: everything CaraPost knows about one capture.

    Build one with :meth:`Take.new`; the arrays follow the module's array contract.
    """

    cameras: list[CameraInfo]
    n_frames: int
    frame_rate: float
    R: np.ndarray
    t: np.ndarray
    detections: list[Detections]
    points: PointTable
    xyz: np.ndarray
    recon: np.ndarray
    obs_xy: np.ndarray
    obs_det: np.ndarray
    obs_src: np.ndarray
    obs_q: np.ndarray
    xyz_stabilized: np.ndarray
    keyframes: Keyframes = field(default_factory=Keyframes)
    labels: list[str] = field(default_factory=list)
    sticks: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    stick_colours: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    brim: BrimModel | None = None
    params: Parameters = field(default_factory=Parameters)
    caddies: list[tuple[int, int]] = field(default_factory=lambda: [(0, 1), (2, 3)])
    active_range: tuple[int, int] = (0, 0)
    view_range: tuple[int, int] = (0, 0)
    current_frame: int = 0
    start_timecode: str = "00:00:00:00"
    first_frame_number: int = 0
    name: str = ""
    rom_path: str = ""
    next_point_id: int = 0
    metadata: dict[str, str] = field(default_factory=dict)

    # ----------------------------------------------------------------------- construction
    @classmethod
    def new(cls, cameras: list[CameraInfo], n_frames: int, frame_rate: float, *,
            R: np.ndarray | None = None, t: np.ndarray | None = None, name: str = "",
            caddies: list[tuple[int, int]] | None = None) -> "Take":
        """An empty take (no points, no detections) with the given cameras.

        A take without cameras holds marker data only (e.g. opened from a C3D file).

        ``R (C, 3, 3)``/``t (C, 3)`` static poses or ``(F, C, ...)`` per-frame poses; NaN
        (unsolved) if omitted.
        """
        if n_frames < 1:
            raise ValueError(f"a take needs at least one frame, got {n_frames}")
        if frame_rate <= 0:
            raise ValueError(f"frame rate must be positive, got {frame_rate}")
        C = len(cameras)
        Rf = np.full((n_frames, C, 3, 3), np.nan)
        tf = np.full((n_frames, C, 3), np.nan)
        if R is not None:
            Rf[...] = np.broadcast_to(np.asarray(R, float), Rf.shape)
        if t is not None:
            tf[...] = np.broadcast_to(np.asarray(t, float), tf.shape)
        if caddies is None:
            caddies = [pair for pair in [(0, 1), (2, 3)] if max(pair) < C]
        caddies = check_caddies(caddies, C)
        take = cls(cameras=cameras, n_frames=n_frames, frame_rate=float(frame_rate), R=Rf, t=tf,
                   detections=[Detections.empty(n_frames) for _ in cameras], points=PointTable(),
                   caddies=list(caddies), active_range=(0, n_frames - 1), view_range=(0, n_frames - 1),
                   name=name, **_empty_point_arrays(n_frames, 0, C))
        return take

    # ----------------------------------------------------------------------------- sizes
    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def frame_time(self, frame: int | np.ndarray) -> float | np.ndarray:
        """Seconds from the first frame."""
        return np.asarray(frame) / self.frame_rate

    # ---------------------------------------------------------------------------- points
    def add_points(self, n: int, *, kind: PointKind = PointKind.FACE, labels: list[str] | None = None,
                   brim_index: np.ndarray | None = None) -> np.ndarray:
        """Append ``n`` empty points; returns their column indices."""
        if n < 0:
            raise ValueError("cannot add a negative number of points")
        P0 = self.n_points
        ids = np.arange(self.next_point_id, self.next_point_id + n, dtype=np.int64)
        self.next_point_id += n
        pts = self.points
        pts.ids = np.concatenate([pts.ids, ids])
        pts.labels = pts.labels + (list(labels) if labels is not None else [""] * n)
        pts.kind = np.concatenate([pts.kind, np.full(n, int(kind), np.uint8)])
        bi = np.full(n, -1, np.int32) if brim_index is None else np.asarray(brim_index, np.int32)
        pts.brim_index = np.concatenate([pts.brim_index, bi])
        pts.colour = np.concatenate([pts.colour, _default_colours(ids, kind)])
        new = _empty_point_arrays(self.n_frames, n, self.n_cameras)
        for name, arr in new.items():
            setattr(self, name, np.concatenate([getattr(self, name), arr], axis=1))
        return np.arange(P0, P0 + n)

    def remove_points(self, indices: np.ndarray | list[int]) -> None:
        """Delete points (columns) and the sticks and keyframes that refer to them."""
        indices = np.asarray(indices, dtype=np.int64)
        keep = np.ones(self.n_points, bool)
        keep[indices] = False
        gone = self.points.ids[~keep]
        pts = self.points
        self.points = PointTable(pts.ids[keep], [lab for lab, k in zip(pts.labels, keep) if k], pts.kind[keep],
                                 pts.brim_index[keep], pts.colour[keep])
        for name in POINT_ARRAYS:
            setattr(self, name, getattr(self, name)[:, keep])
        if len(self.sticks):
            sk = ~np.isin(self.sticks, gone).any(axis=1)
            self.sticks, self.stick_colours = self.sticks[sk], self.stick_colours[sk]
        kf = self.keyframes
        if len(kf):
            k = ~np.isin(kf.point_id, gone)
            self.keyframes = Keyframes(kf.frame[k], kf.point_id[k], kf.camera[k], kf.xy[k], kf.pattern[k],
                                       kf.search[k])

    def face_points(self) -> np.ndarray:
        return np.flatnonzero(self.points.kind == PointKind.FACE)

    def brim_points(self) -> np.ndarray:
        return np.flatnonzero(self.points.kind == PointKind.BRIM)

    # ---------------------------------------------------------------------------- derived
    def n_views(self) -> np.ndarray:
        """Cameras contributing an observation to each point, (F, P)."""
        return np.isfinite(self.obs_xy[..., 0]).sum(-1)

    def poses(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``R (C, 3, 3)``, ``t (C, 3)`` of a frame."""
        return self.R[frame], self.t[frame]

    def intrinsics(self) -> list[Intrinsics]:
        return [c.intrinsics for c in self.cameras]

    def check(self) -> None:
        """Raise ``ValueError`` if the arrays break the contract (used after loading)."""
        F, C, P = self.n_frames, self.n_cameras, self.n_points
        if self.R.shape != (F, C, 3, 3) or self.t.shape != (F, C, 3):
            raise ValueError(f"camera poses have shapes {self.R.shape}, {self.t.shape}; expected "
                             f"({F}, {C}, 3, 3), ({F}, {C}, 3)")
        for name, (trail, dtype, _) in POINT_ARRAYS.items():
            shape = (F, P) + tuple(C if d == "C" else d for d in trail)
            arr = getattr(self, name)
            if arr.shape != shape:
                raise ValueError(f"{name} has shape {arr.shape}, expected {shape}")
        if len(self.detections) != C or any(d.n_frames != F for d in self.detections):
            raise ValueError("detections do not match the cameras and frames")
        if len(self.points.labels) != P or len(self.points.kind) != P:
            raise ValueError("point table does not match the point arrays")
        a, b = self.active_range
        if not 0 <= a <= b < F:
            raise ValueError(f"active range {self.active_range} outside 0..{F - 1}")


def _empty_point_arrays(F: int, P: int, C: int) -> dict[str, np.ndarray]:
    out = {}
    for name, (trail, dtype, fill) in POINT_ARRAYS.items():
        shape = (F, P) + tuple(C if d == "C" else d for d in trail)
        out[name] = np.full(shape, fill, dtype=dtype)
    return out


def _default_colours(ids: np.ndarray, kind: PointKind) -> np.ndarray:
    if kind == PointKind.BRIM:
        return np.tile(np.array([[80, 160, 255]], np.uint8), (len(ids), 1))
    # A fixed palette cycled by id: stable across sessions.
    palette = np.array([[255, 200, 0], [0, 220, 120], [255, 110, 80], [180, 120, 255], [0, 200, 255],
                        [255, 120, 200], [200, 255, 80]], np.uint8)
    return palette[ids % len(palette)]
