"""Reading a solved take from scripts, for custom exports (the reference guide's PyCaraExport).

:class:`CaraExport` opens a ``.cara`` project (or any ``.c3d`` file, as a take without video)
and answers questions about it: the points (names, labels, face or brim), their 3D positions
``xyz (F, P, 3)`` in millimetres with NaN in gaps, how each sample was reconstructed, the
calibration brim, the cameras (intrinsics and per-frame poses), the 2D tracks, the frame rate
and the time conversions (frame index, burnt-in frame number, SMPTE timecode). It never
changes the take: every array it returns is a read-only view (``.copy()`` it to edit).

Array contract (``F`` frames, ``P`` points, ``C`` cameras): positions mm, 2D coordinates raw
(distorted) sensor pixels, NaN for missing, point columns in the take's order.

Examples
--------
>>> import carapost.api as cp
>>> exp = cp.CaraExport("Example.cara")                       # doctest: +SKIP
>>> for i in exp.face_points:                                  # doctest: +SKIP
...     print(exp.point_names[i], exp.xyz[0, i])              # frame 0, mm
>>> exp.frame_to_timecode(100), exp.frame_to_number(100)      # doctest: +SKIP
('10:00:01:40', 1100)
>>> exp.export("Example.fbx")                                 # doctest: +SKIP
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from carapost.core.camera import Intrinsics, camera_centre
from carapost.io.export import export_take, load_for_export
from carapost.model.take import BrimModel, CameraInfo, ObsSource, PointKind, Recon, Take

from .core.timecode import TimeBase

__all__ = ["CaraExport", "PointInfo", "Recon", "ObsSource", "PointKind"]


class PointInfo(NamedTuple):
    """One point of a take.

    Attributes
    ----------
    index : int
        Column in the point arrays (``xyz[:, index]``).
    id : int
        Stable point id (never reused in the take).
    name : str
        Label, else a generated ``Point_<id>`` / ``Brim_<id>``.
    label : str
        Assigned label ("" when unlabelled).
    kind : str
        ``"face"`` or ``"brim"``.
    brim_index : int
        Brim dot of a brim point, -1 for a face point.
    """

    index: int
    id: int
    name: str
    label: str
    kind: str
    brim_index: int


def _ro(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v


class CaraExport:
    """Read-only access to a take's points, cameras, 2D tracks and times.

    Parameters
    ----------
    source : str, path-like or Take
        A ``.cara`` project or a ``.c3d`` file; or a :class:`~carapost.model.take.Take`
        already in memory (e.g. ``CaraProcess.take``), which is then read live, not copied.

    Raises
    ------
    ValueError
        The file is missing, damaged or of another type (``CaraError`` / ``ExportError``; the
        message names the file).

    Examples
    --------
    >>> exp = CaraExport("Example.cara")                     # doctest: +SKIP
    >>> exp.n_frames, exp.n_points, exp.frame_rate            # doctest: +SKIP
    (600, 112, 60.0)
    >>> nose = exp.point_index("Nose")                        # doctest: +SKIP
    >>> exp.trajectory(nose).shape                            # (F, 3) mm   # doctest: +SKIP
    (600, 3)
    >>> exp.tracks_2d(0)[:, nose]                             # (F, 2) px in camera 0   # doctest: +SKIP
    """

    def __init__(self, source: str | os.PathLike | Take) -> None:
        if isinstance(source, Take):
            self._take = source
            self.path: Path | None = None
        else:
            self.path = Path(source)
            self._take = load_for_export(self.path)

    @classmethod
    def from_take(cls, take: Take) -> "CaraExport":
        """A read-only view of a take in memory."""
        return cls(take)

    @property
    def take(self) -> Take:
        """The underlying take (the data model; treat it as read-only)."""
        return self._take

    # --------------------------------------------------------------------------- sizes
    @property
    def name(self) -> str:
        """Take name."""
        return self._take.name

    @property
    def n_frames(self) -> int:
        """Frames ``F`` in the take."""
        return self._take.n_frames

    @property
    def n_points(self) -> int:
        """Points ``P`` (face and brim)."""
        return self._take.n_points

    @property
    def n_cameras(self) -> int:
        """Cameras ``C`` (0 for a take read from a C3D file)."""
        return self._take.n_cameras

    @property
    def frame_rate(self) -> float:
        """Frames per second."""
        return float(self._take.frame_rate)

    @property
    def active_range(self) -> tuple[int, int]:
        """Inclusive frame indices of the active range."""
        a, b = self._take.active_range
        return int(a), int(b)

    # -------------------------------------------------------------------------- points
    @property
    def point_names(self) -> list[str]:
        """Display name of every point: its label, else ``Point_<id>`` / ``Brim_<id>``."""
        return self._take.points.names()

    @property
    def labels(self) -> list[str]:
        """Label of every point ("" = unlabelled)."""
        return list(self._take.points.labels)

    @property
    def label_list(self) -> list[str]:
        """The take's label list (the Labelling pane), assigned or not."""
        return list(self._take.labels)

    @property
    def point_ids(self) -> np.ndarray:
        """Stable point ids, int64 (P,)."""
        return _ro(self._take.points.ids)

    @property
    def point_kinds(self) -> np.ndarray:
        """uint8 (P,): :class:`PointKind` ``FACE`` (0) or ``BRIM`` (1)."""
        return _ro(self._take.points.kind)

    @property
    def face_points(self) -> np.ndarray:
        """Columns of the face points, int64 (K,)."""
        return self._take.face_points()

    @property
    def brim_points(self) -> np.ndarray:
        """Columns of the brim points, int64 (B,), in column order."""
        return self._take.brim_points()

    @property
    def brim_indices(self) -> np.ndarray:
        """Brim dot index of every point, int32 (P,); -1 for face points."""
        return _ro(self._take.points.brim_index)

    @property
    def point_colours(self) -> np.ndarray:
        """Display colour of every point, uint8 (P, 3) RGB."""
        return _ro(self._take.points.colour)

    def points(self) -> list[PointInfo]:
        """Every point as a :class:`PointInfo` (index, id, name, label, kind, brim index)."""
        pts = self._take.points
        names = pts.names()
        return [PointInfo(i, int(pts.ids[i]), names[i], pts.labels[i],
                          "brim" if pts.kind[i] == PointKind.BRIM else "face", int(pts.brim_index[i]))
                for i in range(len(pts))]

    def point_index(self, point: int | str) -> int:
        """The column of a point given by column index or by name / label.

        Raises
        ------
        KeyError
            No point of that name, or the index is out of range.
        """
        if isinstance(point, (int, np.integer)) and not isinstance(point, bool):
            if not 0 <= int(point) < self.n_points:
                raise KeyError(f"point index {point} out of range 0..{self.n_points - 1}")
            return int(point)
        names = self.point_names
        if point in names:
            return names.index(point)
        raise KeyError(f"no point named {point!r}")

    @property
    def sticks(self) -> np.ndarray:
        """Sticks as pairs of point columns, int64 (S, 2)."""
        ids = self._take.points.ids
        sk = self._take.sticks
        if len(sk) == 0:
            return np.zeros((0, 2), np.int64)
        order = np.argsort(ids)
        return order[np.searchsorted(ids[order], sk)].astype(np.int64)

    # ---------------------------------------------------------------------------- 3D data
    @property
    def xyz(self) -> np.ndarray:
        """Point positions, float64 (F, P, 3), mm, NaN in gaps (world frame: the brim's)."""
        return _ro(self._take.xyz)

    @property
    def xyz_stabilized(self) -> np.ndarray:
        """Stabilized positions, float64 (F, P, 3), mm (all NaN until the take is stabilized)."""
        return _ro(self._take.xyz_stabilized)

    @property
    def reconstruction(self) -> np.ndarray:
        """How each sample was obtained, uint8 (F, P): :class:`Recon` ``NONE`` (0, gap),
        ``INTERPOLATED`` (1), ``SINGLE_SENSOR`` (2), ``MULTI_VIEW`` (3)."""
        return _ro(self._take.recon)

    def trajectory(self, point: int | str, *, stabilized: bool = False) -> np.ndarray:
        """One point's positions over the take, (F, 3) mm (by column or name)."""
        data = self._take.xyz_stabilized if stabilized else self._take.xyz
        return _ro(data[:, self.point_index(point)])

    def positions(self, frame: int, *, stabilized: bool = False) -> np.ndarray:
        """Every point's position in one frame, (P, 3) mm."""
        data = self._take.xyz_stabilized if stabilized else self._take.xyz
        return _ro(data[self._frame(frame)])

    def _frame(self, frame: int) -> int:
        f = int(frame)
        if not 0 <= f < self.n_frames:
            raise IndexError(f"frame {frame} outside the take (0..{self.n_frames - 1})")
        return f

    # ----------------------------------------------------------------------------- brim
    @property
    def brim(self) -> BrimModel | None:
        """The calibration brim model (dot centres in the brim frame, mm), or None."""
        return self._take.brim

    # -------------------------------------------------------------------------- cameras
    @property
    def cameras(self) -> list[CameraInfo]:
        """Per camera: name, channel, intrinsics, image size, source file, frame offset."""
        return list(self._take.cameras)

    @property
    def camera_names(self) -> list[str]:
        """Name of every camera."""
        return [c.name for c in self._take.cameras]

    def source_path(self, camera: int) -> Path | None:
        """The camera's video file (``.pico``, video or image folder) if it can be found: the
        relative path from the ``.cara`` folder first, then the absolute path; else None."""
        src = self._take.cameras[self._camera(camera)].source
        if src is None:
            return None
        return src.resolve(self.path.parent if self.path is not None else None)

    def intrinsics(self, camera: int) -> Intrinsics:
        """The camera's XCP intrinsics (focal length px, principal point, aspect, skew, radial)."""
        return self._take.cameras[self._camera(camera)].intrinsics

    @property
    def R(self) -> np.ndarray:
        """World-to-camera rotations per frame, float64 (F, C, 3, 3); NaN where unsolved."""
        return _ro(self._take.R)

    @property
    def t(self) -> np.ndarray:
        """Translations per frame, float64 (F, C, 3), mm (``X_cam = R X + t``)."""
        return _ro(self._take.t)

    def camera_poses(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``R (C, 3, 3)``, ``t (C, 3)`` of one frame."""
        f = self._frame(frame)
        return _ro(self._take.R[f]), _ro(self._take.t[f])

    @property
    def camera_positions(self) -> np.ndarray:
        """Camera centres in the world, float64 (F, C, 3), mm."""
        return camera_centre(self._take.R, self._take.t)

    def _camera(self, camera: int) -> int:
        c = int(camera)
        if not 0 <= c < self.n_cameras:
            raise IndexError(f"camera {camera} does not exist (the take has {self.n_cameras})")
        return c

    # ------------------------------------------------------------------------ 2D tracks
    @property
    def observations(self) -> np.ndarray:
        """2D observation of every point in every camera, float32 (F, P, C, 2), raw px."""
        return _ro(self._take.obs_xy)

    @property
    def observation_sources(self) -> np.ndarray:
        """uint8 (F, P, C): :class:`ObsSource` (blob, patch, target, keyframe; 0 none)."""
        return _ro(self._take.obs_src)

    def tracks_2d(self, camera: int) -> np.ndarray:
        """The 2D tracks of every point in one camera, float32 (F, P, 2), raw px, NaN untracked."""
        return _ro(self._take.obs_xy[:, :, self._camera(camera)])

    def detections(self, camera: int, frame: int) -> dict[str, np.ndarray]:
        """The blob detections of a camera in a frame: arrays ``x, y, major, minor, angle,
        polarity, score`` (N,) in raw px / radians (``polarity`` -1 black, 1 white)."""
        return self._take.detections[self._camera(camera)].frame(self._frame(frame))

    def n_detections(self, camera: int | None = None, frame: int | None = None) -> int:
        """Number of blob detections of one camera (or all) in one frame (or all)."""
        cams = range(self.n_cameras) if camera is None else [self._camera(camera)]
        dets = self._take.detections
        if frame is None:
            return int(sum(len(dets[c]) for c in cams))
        f = self._frame(frame)
        return int(sum(dets[c].count(f) for c in cams))

    def detected_frames(self, camera: int) -> np.ndarray:
        """Frames in which blob detection has run for a camera, int64 (N,)."""
        return np.flatnonzero(self._take.detections[self._camera(camera)].detected)

    # ----------------------------------------------------------------------------- time
    @property
    def start_timecode(self) -> str:
        """SMPTE timecode of frame index 0."""
        return self._take.start_timecode

    @property
    def first_frame_number(self) -> int:
        """Burnt-in frame number of frame index 0."""
        return int(self._take.first_frame_number)

    @property
    def time(self) -> TimeBase:
        """The take's :class:`TimeBase` (frame rate, start timecode, first frame number;
        drop-frame at 29.97 / 59.94 Hz)."""
        return TimeBase(self._take.frame_rate, self._take.start_timecode, self._take.first_frame_number)

    def frame_to_number(self, frame: Any) -> Any:
        """Burnt-in frame number(s) of frame index(es)."""
        return self.time.frame_to_number(frame)

    def number_to_frame(self, number: Any) -> Any:
        """Frame index(es) of burnt-in frame number(s)."""
        return self.time.number_to_frame(number)

    def frame_to_timecode(self, frame: Any) -> Any:
        """SMPTE timecode(s) of frame index(es)."""
        return self.time.frame_to_timecode(frame)

    def timecode_to_frame(self, timecode: Any) -> Any:
        """Frame index(es) of SMPTE timecode(s)."""
        return self.time.timecode_to_frame(timecode)

    def number_to_timecode(self, number: Any) -> Any:
        """SMPTE timecode(s) of burnt-in frame number(s)."""
        return self.time.number_to_timecode(number)

    def timecode_to_number(self, timecode: Any) -> Any:
        """Burnt-in frame number(s) of SMPTE timecode(s)."""
        return self.time.timecode_to_number(timecode)

    # ---------------------------------------------------------------------------- export
    def export(self, path: str | os.PathLike, *, properties: Mapping[str, Any] | None = None,
               **kwargs: Any) -> Path:
        """Write the take with the built-in exporter chosen by extension.

        Parameters
        ----------
        path : path-like
            ``.c3d .fbx .xcp .csv .trc .bvh .bva`` (written atomically).
        properties : dict, optional
            Overrides of the take's Export properties by label, e.g. ``{"Units": "cm",
            "Up Axis": "Z", "Include Brim Points": False}`` (the take is not changed).
        **kwargs
            Options of :func:`carapost.io.export.export_take`: ``frames=(a, b)`` inclusive,
            ``points=[columns]``, ``selection=[columns]``, FBX ``version`` (7400 / 7500), CSV
            ``kind="2d"``, XCP ``frame``, ...

        Returns
        -------
        Path
            The file written.

        Raises
        ------
        ValueError
            (``ExportError``) Unknown extension, option or property value; missing folder;
            nothing to export. The message names the file.
        """
        if properties:
            opts = type(self._take.params.export).from_dict(self._take.params.export.to_dict())
            for name, value in properties.items():
                try:
                    opts.set(name, value)
                except KeyError as exc:
                    raise ValueError(str(exc.args[0])) from None
            kwargs["options"] = opts
        export_take(self._take, path, **kwargs)
        return Path(path)

    def summary(self) -> dict[str, Any]:
        """Counts and times as a JSON-ready dict."""
        face, brim = self.face_points, self.brim_points
        valid = np.isfinite(self._take.xyz).all(-1)
        return {"name": self.name, "file": str(self.path) if self.path else None, "frames": self.n_frames,
                "frame_rate": self.frame_rate, "cameras": self.camera_names, "face_points": int(len(face)),
                "brim_points": int(len(brim)), "labelled": int(sum(1 for lab in self.labels if lab)),
                "face_samples_filled": float(valid[:, face].mean()) if len(face) else 0.0,
                "start_timecode": self.start_timecode, "first_frame_number": self.first_frame_number,
                "brim": self.brim.name if self.brim is not None else None}

    def __repr__(self) -> str:
        where = f"{str(self.path)!r}" if self.path else "<take>"
        return (f"CaraExport({where}, frames={self.n_frames}, points={self.n_points}, cameras={self.n_cameras}, "
                f"{self.frame_rate:g} Hz)")
