"""A working session: one take, its open image sources, its undo history and its file.

The GUI, the command line and the scripting API all work through a :class:`Session`, so they
run the same code. Creating a take from camera sources ("Import Pico Files", videos or image
folders) and a calibration lives here too.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from carapost.core.camera import Intrinsics
from carapost.io.calibration import Calibration, load_calibration
from carapost.io.cara import load_take, save_take
from carapost.io.sources import FrameSource, OffsetSource, open_source
from carapost.model.params import BlobParameters
from carapost.model.take import CameraInfo, SourceRef, Take

from .change import Change
from .stack import UndoStack

__all__ = ["Session", "new_take"]

log = logging.getLogger("carapost")


def _channel_order(sources: Sequence[FrameSource]) -> list[int]:
    """Order sources by their metadata channel when the channels are distinct, else keep order."""
    channels = [s.meta.channel for s in sources]
    if len(set(channels)) == len(channels):
        return sorted(range(len(sources)), key=lambda i: channels[i])
    return list(range(len(sources)))


def new_take(sources: Sequence[FrameSource], calibration: Calibration | None = None, *, name: str = "",
             frame_offsets: Sequence[int] | None = None) -> Take:
    """A take for camera sources, with the calibration's intrinsics and poses if given.

    Cameras follow the sources' channel order; calibration camera ``i`` belongs to source ``i``
    (in channel order). The blob parameters recorded at capture (``.pico`` metadata) become the
    take's Blob Parameters.

    Raises
    ------
    ValueError
        If there are no sources, or the calibration has a different number of cameras.
    """
    if not sources:
        raise ValueError("a take needs at least one camera source")
    order = _channel_order(sources)
    srcs = [sources[i] for i in order]
    if calibration is not None and len(calibration.cameras) != len(srcs):
        raise ValueError(f"{calibration.source}: calibration has {len(calibration.cameras)} cameras but "
                         f"{len(srcs)} camera sources were given")
    offsets = list(frame_offsets) if frame_offsets is not None else [0] * len(srcs)
    n_frames = max(1, min(s.n_frames - off for s, off in zip(srcs, offsets)))
    cams = []
    for c, s in enumerate(srcs):
        if calibration is not None:
            intr = calibration.cameras[c].intrinsics
        else:  # a usable guess: 60-degree horizontal field of view, centred principal point
            intr = Intrinsics(s.width / (2 * np.tan(np.radians(30))), ((s.width - 1) / 2, (s.height - 1) / 2),
                              (s.width, s.height))
        name_c = s.meta.camera_name or (calibration.cameras[c].name if calibration is not None else "") or f"Camera {c}"
        cams.append(CameraInfo(name=name_c, channel=c, intrinsics=intr, image_size=(s.width, s.height),
                               source=SourceRef(str(Path(s.path).resolve()), "", s.kind),
                               frame_offset=int(offsets[c]), rotation=int(s.meta.rotation),
                               device_id=calibration.cameras[c].device_id if calibration is not None else ""))
    R = t = None
    if calibration is not None:
        R, t = calibration.poses(n_frames)
    take = Take.new(cams, n_frames, srcs[0].frame_rate, R=R, t=t, name=name)
    take.start_timecode = srcs[0].meta.start_timecode
    blob = srcs[0].meta.blob_parameters
    if blob:
        try:
            take.params.blobs = BlobParameters.from_dict(blob)  # type: ignore[assignment]
        except ValueError as exc:
            log.warning("%s: ignoring the blob parameters recorded at capture: %s", srcs[0].path, exc)
    meta = srcs[0].meta
    take.metadata.update({"logger_name": meta.logger_name, "logger_description": meta.logger_description,
                          "logger_id": meta.logger_id})
    return take


class Session:
    """A take with its sources, undo stack and file path.

    Attributes
    ----------
    take : Take
    path : Path or None
        The ``.cara`` file, once saved or opened.
    stack : UndoStack
    sources : list of OffsetSource or None
        One per camera (None where the source file is missing: see ``missing``).
    messages : list of str
        What happened while opening (migrations, missing sources, damaged files).
    """

    def __init__(self, take: Take, *, path: str | os.PathLike | None = None,
                 sources: Sequence[OffsetSource | None] | None = None, messages: Sequence[str] = ()) -> None:
        self.take = take
        self.path = Path(path) if path is not None else None
        self.stack = UndoStack(take)
        self.sources: list[OffsetSource | None] = list(sources) if sources is not None else [None] * take.n_cameras
        self.messages = list(messages)

    # ------------------------------------------------------------------------- creating
    @classmethod
    def from_sources(cls, paths: Sequence[str | os.PathLike], calibration: str | os.PathLike | Calibration | None = None,
                     *, name: str = "", frame_offsets: Sequence[int] | None = None) -> "Session":
        """Import camera sources (``.pico``, video files, image folders) with an optional calibration."""
        opened = [open_source(p) for p in paths]
        calib = load_calibration(calibration) if isinstance(calibration, (str, os.PathLike)) else calibration
        take = new_take(opened, calib, name=name, frame_offsets=frame_offsets)
        order = _channel_order(opened)
        srcs = [OffsetSource(opened[i], offset=take.cameras[c].frame_offset, rotation=take.cameras[c].rotation,
                             n_frames=take.n_frames) for c, i in enumerate(order)]
        messages = [f"{s.path}: {w}" for s in srcs for w in s.warnings]
        return cls(take, sources=srcs, messages=messages)

    @classmethod
    def open(cls, path: str | os.PathLike) -> "Session":
        """Open a ``.cara`` project; cameras whose video is missing are listed in ``missing``."""
        res = load_take(path)
        take = res.take
        sources: list[OffsetSource | None] = []
        messages = list(res.messages)
        for c, cam in enumerate(take.cameras):
            src = None
            if c not in res.missing_sources and cam.source is not None:
                try:
                    src = OffsetSource(open_source(cam.source.path), offset=cam.frame_offset, rotation=cam.rotation,
                                       n_frames=take.n_frames)
                    messages += [f"{src.path}: {w}" for w in src.warnings]
                except (ValueError, OSError) as exc:
                    messages.append(f"camera {c}: cannot open {cam.source.path}: {exc}")
            sources.append(src)
        return cls(take, path=path, sources=sources, messages=messages)

    # --------------------------------------------------------------------------- state
    @property
    def missing(self) -> list[int]:
        """Cameras without an image source ("Relocate Files" needed)."""
        return [c for c, s in enumerate(self.sources) if s is None]

    @property
    def modified(self) -> bool:
        return not self.stack.is_clean()

    def image(self, camera: int, frame: int) -> np.ndarray:
        """The (un-rotated) grayscale image of a camera at a take frame.

        Raises
        ------
        ValueError
            If the camera has no source (moved or deleted video).
        """
        src = self.sources[camera]
        if src is None:
            raise ValueError(f"camera {camera} ({self.take.cameras[camera].name}) has no video: relocate its file")
        return src.read(frame)

    def apply(self, change: Change | None) -> Change | None:
        """Apply a change through the undo stack (ignores ``None`` / empty changes)."""
        if change is None or (hasattr(change, "changes") and not change.changes):  # type: ignore[attr-defined]
            return None
        return self.stack.push(change)

    # ---------------------------------------------------------------------------- files
    def save(self, path: str | os.PathLike | None = None) -> Path:
        """Save the take (atomically) to ``path`` or the current file."""
        target = Path(path) if path is not None else self.path
        if target is None:
            raise ValueError("no file name: save with a path")
        save_take(self.take, target)
        self.path = target
        self.stack.set_clean()
        return target

    def close(self) -> None:
        for s in self.sources:
            if s is not None:
                s.source.close()

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
