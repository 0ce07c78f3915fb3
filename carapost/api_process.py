"""Processing takes from scripts (the reference guide's PyCaraProcess).

:class:`CaraProcess` is one open take with its undo history: create it from a take's ``.pico``
files (or videos / image folders) and a calibration, or open a ``.cara`` project; detect blobs;
read and set properties; solve the brim, initialize, fill gaps, stabilize; save. Every method
runs the same operation (:mod:`carapost.ops`) as the GUI's menu entry of the same name, and every
edit is undoable (:meth:`CaraProcess.undo`). Read the results through :attr:`CaraProcess.data`
(a live :class:`~carapost.api_export.CaraExport`).

Points are given by column index or by name (label, or ``Point_<id>``); cameras ("sensors")
by 0-based channel; frames by 0-based index, ranges inclusive.

Examples
--------
>>> import carapost.api as cp
>>> take = cp.CaraProcess.from_pico("Example_0.pico")        # doctest: +SKIP
>>> take.set_property("Blob Parameters", "Black Threshold", 0.3)   # doctest: +SKIP
>>> take.detect_blobs()                                       # all sensors, all frames   # doctest: +SKIP
True
>>> take.detect_blobs([0, 2], 10, 50)                         # sensors 0 and 2, frames 10..50   # doctest: +SKIP
True
>>> take.save("Example_b.cara")                               # doctest: +SKIP
"""

from __future__ import annotations

import os
import weakref
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from carapost.io.pico import CALIBRATION_EXTENSIONS, find_calibration, take_files, take_name
from carapost.model.params import PRESETS
from carapost.ops.session import Session

from .api_export import CaraExport
from .api_steps import ProcessingSteps, _ops

__all__ = ["CaraProcess", "find_calibration", "default_properties", "CALIBRATION_EXTENSIONS"]

ProgressFn = Callable[[int, int], None]
CancelFn = Callable[[], bool]


def _section_info(sec: Any) -> dict[str, dict[str, Any]]:
    out = {}
    for f in sec.fields():
        md = f.metadata
        out[md["label"]] = {"value": getattr(sec, f.name), "default": f.default, "unit": md["unit"], "min": md["lo"],
                            "max": md["hi"], "choices": md["choices"], "help": md["help"]}
    return out


def default_properties(*, info: bool = False) -> dict[str, dict[str, Any]]:
    """Every property group with its default values: ``{group title: {label: value}}``.

    With ``info=True`` each property maps to a dict of ``value``, ``default``, ``unit``,
    ``min``, ``max``, ``choices`` and ``help`` instead of its bare value.
    """
    from carapost.model.params import Parameters

    return {sec.title: (_section_info(sec) if info else {f.metadata["label"]: getattr(sec, f.name)
                                                         for f in sec.fields()})
            for _, sec in Parameters().sections()}


def _pico_session(pico_path: str | os.PathLike, calibration: str | os.PathLike | None, find: bool) -> Session:
    paths = take_files(pico_path)
    if calibration is None and find:
        calibration = find_calibration(paths[0])
    return Session.from_sources(paths, calibration, name=take_name(paths[0]))


class CaraProcess(ProcessingSteps):
    """One take being processed: its data, image sources, undo history and ``.cara`` file.

    Parameters
    ----------
    source : str, path-like or Session
        A ``.cara`` project (opened), one ``.pico`` file of a take (all the take's files are
        imported, see :meth:`from_pico`), or a :class:`~carapost.ops.session.Session` (used as
        it is: the caller keeps ownership of its files).

    Raises
    ------
    ValueError
        Missing, damaged or unsupported file (the message names it).

    Examples
    --------
    >>> take = CaraProcess("Example.cara")                       # doctest: +SKIP
    >>> take.n_frames, take.n_cameras, take.path                  # doctest: +SKIP
    (600, 4, PosixPath('Example.cara'))
    >>> with CaraProcess.from_pico("ROM_0.pico") as rom:          # closes the video files   # doctest: +SKIP
    ...     rom.detect_blobs(); rom.save("ROM.cara")
    """

    def __init__(self, source: str | os.PathLike | Session) -> None:
        if isinstance(source, Session):
            session = source
        else:
            p = Path(source)
            ext = p.suffix.lower()
            if ext == ".cara":
                session = Session.open(p)
            elif ext == ".pico":
                session = _pico_session(p, None, True)
            else:
                raise ValueError(f"{p}: open a .cara project or a .pico file (for videos or image folders use "
                                 "CaraProcess.from_sources)")
        self._session = session
        # Files this object opened close when it goes away, even without close() / ``with``;
        # a Session passed in stays its owner's to close.
        self._finalizer = None if isinstance(source, Session) else weakref.finalize(self, session.close)

    # ----------------------------------------------------------------------- creating
    @classmethod
    def open(cls, path: str | os.PathLike) -> "CaraProcess":
        """Open a ``.cara`` project. Cameras whose video is missing are in :attr:`missing_sources`."""
        return cls(Session.open(path))

    @classmethod
    def from_pico(cls, pico_path: str | os.PathLike, calibration: str | os.PathLike | None = None, *,
                  find: bool = True) -> "CaraProcess":
        """A new take from all ``.pico`` files of the take ``pico_path`` belongs to.

        Parameters
        ----------
        pico_path : path-like
            Any ``NAME_<channel>.pico`` of the take; ``NAME_0.pico`` ... are all imported.
        calibration : path-like, optional
            ``.xcp``, ``.toml`` or ``.qca``. Default: ``NAME.xcp`` (``.toml``, ``.qca``) next to
            the files if present (see :func:`find_calibration`), else none (cameras get a
            60-degree field-of-view guess and no pose until the brim is solved).
        find : bool
            Look for the calibration next to the files when none is given.
        """
        return cls(_pico_session(pico_path, calibration, find))

    @classmethod
    def from_sources(cls, paths: Sequence[str | os.PathLike], calibration: str | os.PathLike | None = None, *,
                     name: str | None = None, frame_offsets: Sequence[int] | None = None) -> "CaraProcess":
        """A new take from one source per camera (``.pico`` files, videos, image folders).

        Parameters
        ----------
        paths : sequence of path-like
            In channel order (``.pico`` files are ordered by their recorded channel).
        calibration : path-like, optional
            ``.xcp``, ``.toml`` or ``.qca`` with one camera per source.
        name : str, optional
            Take name (default: the first file's name without ``_<channel>``).
        frame_offsets : sequence of int, optional
            Per camera: take frame ``f`` shows source frame ``f + offset``.
        """
        if not paths:
            raise ValueError("no camera sources given")
        if name is None:
            stem = Path(paths[0]).stem
            name = stem.rsplit("_", 1)[0] if "_" in stem else stem
        return cls(Session.from_sources(list(paths), calibration, name=name, frame_offsets=frame_offsets))

    # -------------------------------------------------------------------------- state
    @property
    def session(self) -> Session:
        """The underlying :class:`~carapost.ops.session.Session` (shared with the CLI and GUI)."""
        return self._session

    @property
    def data(self) -> CaraExport:
        """A live read-only view of the take: points, xyz, cameras, 2D tracks, times."""
        return CaraExport(self.take)

    @property
    def name(self) -> str:
        """Take name (the ``.pico`` files' ``NAME``)."""
        return self.take.name

    @property
    def path(self) -> Path | None:
        """The ``.cara`` file, once opened or saved."""
        return self._session.path

    @property
    def n_frames(self) -> int:
        """Frames in the take."""
        return self.take.n_frames

    @property
    def n_cameras(self) -> int:
        """Cameras (sensors) in the take."""
        return self.take.n_cameras

    @property
    def n_points(self) -> int:
        """Points (face and brim) in the take."""
        return self.take.n_points

    @property
    def frame_rate(self) -> float:
        """Frames per second."""
        return float(self.take.frame_rate)

    @property
    def modified(self) -> bool:
        """True when the take differs from its last save."""
        return self._session.modified

    @property
    def messages(self) -> list[str]:
        """What happened while opening (migrations, missing or damaged sources)."""
        return list(self._session.messages)

    def image(self, camera: int, frame: int) -> np.ndarray:
        """The grayscale image ``(H, W) uint8`` of a camera at a take frame."""
        return self._session.image(self._camera(camera), self._frame(frame))

    # ------------------------------------------------------------------- blob detection
    def detect_blobs(self, sensors: Sequence[int] | None = None, start_frame: int | None = None,
                     end_frame: int | None = None, *, workers: int = 2, progress: ProgressFn | None = None,
                     cancel: CancelFn | None = None) -> bool:
        """Detect blobs (``detect_blobs()`` or ``detect_blobs(sensors, start, end)``).

        Parameters
        ----------
        sensors : list of int, optional
            Camera channels; default all.
        start_frame, end_frame : int, optional
            Inclusive frame range; default the whole take (a missing end means the last frame).
        workers : int
            Threads.
        progress : callable, optional
            ``progress(done, total)`` over images.
        cancel : callable, optional
            ``cancel() -> True`` stops early; the frames done are kept.

        Returns
        -------
        bool
            True when every requested image was processed, False when cancelled.

        Raises
        ------
        ValueError
            Unknown sensor, frames outside the take or ``start > end``, a camera without its
            video file, or invalid Blob Parameters.
        """
        a = 0 if start_frame is None else int(start_frame)
        b = self.n_frames - 1 if end_frame is None else int(end_frame)
        if not 0 <= a <= b < self.n_frames:
            raise ValueError(f"frames {a}..{b} must lie within 0..{self.n_frames - 1} with start <= end")
        cams = list(range(self.n_cameras)) if sensors is None else [self._camera(c) for c in sensors]
        gone = [c for c in cams if c in self.missing_sources]
        if gone:
            raise ValueError(f"sensor(s) {gone} have no video file: relocate them before detecting blobs")
        frames = list(range(a, b + 1))
        change = _ops("detect").detect_blobs(self.take, self._session.image, frames, cameras=cams, workers=workers,
                                             progress=progress, cancel=cancel, sources=self._session.sources)
        self._apply(change)
        return all(bool(self.take.detections[c].detected[a:b + 1].all()) for c in cams)

    def n_detections(self, sensor: int | None = None, frame: int | None = None) -> int:
        """Number of detections of one sensor (or all) in one frame (or all)."""
        cams = range(self.n_cameras) if sensor is None else [self._camera(sensor)]
        dets = self.take.detections
        if frame is None:
            return int(sum(len(dets[c]) for c in cams))
        f = self._frame(frame)
        return int(sum(dets[c].count(f) for c in cams))

    def remove_unused_detections(self) -> str:
        """"Remove Unused Detections": delete detections not attached to a point."""
        return self._apply(_ops("detect").remove_unused_detections(self.take))

    def read_blob_parameters_from_pico(self) -> str:
        """"Read Blob Parameters From Pico Files": the Blob Parameters recorded at capture."""
        src = next((s for s in self._session.sources if s is not None), None)
        params = src.source.meta.blob_parameters if src is not None else None
        return self._apply(_ops("detect").read_blob_parameters_from_pico(self.take, params))

    # ----------------------------------------------------------------------- properties
    def property_groups(self) -> list[str]:
        """Titles of the property groups (Properties-pane sections), e.g. ``"Blob Parameters"``."""
        return [sec.title for _, sec in self.take.params.sections()]

    def properties(self, group: str | None = None, *, info: bool = False) -> dict[str, Any]:
        """All properties: ``{group title: {property label: value}}``; or one group's
        ``{label: value}`` when ``group`` is given.

        With ``info=True`` each property maps to a dict of ``value``, ``default``, ``unit``,
        ``min``, ``max``, ``choices`` and ``help`` instead of its bare value.
        """
        def one(sec: Any) -> dict[str, Any]:
            return _section_info(sec) if info else {f.metadata["label"]: getattr(sec, f.name) for f in sec.fields()}

        if group is not None:
            return one(self._section(group))
        return {sec.title: one(sec) for _, sec in self.take.params.sections()}

    def property_info(self, group: str, name: str) -> dict[str, Any]:
        """A property's ``value``, ``default``, ``unit``, ``min``, ``max``, ``choices``, ``help``."""
        sec = self._section(group)
        try:
            label = sec.field_by_label(name).metadata["label"]
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None
        return {"group": sec.title, "name": label, **_section_info(sec)[label]}

    def _section(self, group: str) -> Any:
        try:
            return self.take.params.section(group)
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None

    def get_property(self, group: str, name: str) -> Any:
        """The value of a property, by group title and property label (case and spaces ignored).

        Raises
        ------
        ValueError
            Unknown group or property (the message lists the known ones).
        """
        sec = self._section(group)
        try:
            return sec.get(name)
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None

    def set_property(self, group: str, name: str, value: Any) -> str:
        """Set a property (undoable); e.g. ``set_property("Tracking Parameters",
        "Max Allowed 3D Point Error", 7)``.

        Raises
        ------
        ValueError
            Unknown group or property, or a value of the wrong type or outside the range
            (the take is then unchanged).
        """
        self._section(group)
        try:
            return self._apply(_ops("settings").set_property(self.take, group, name, value))
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None

    def restore_properties(self) -> str:
        """"Restore Properties To Defaults"."""
        return self._apply(_ops("settings").restore_properties(self.take))

    def apply_preset(self, preset: str) -> str:
        """The guide's parameter sets: ``"default"``, ``"dense"`` (156 markers), ``"sparse"`` (35)."""
        return self._apply(_ops("settings").apply_preset(self.take, preset))

    presets = tuple(PRESETS)

    # ------------------------------------------------------------------------ history
    def undo(self) -> None:
        """Undo the last change (IndexError if there is none)."""
        self._session.stack.undo()

    def redo(self) -> None:
        """Redo the last undone change (IndexError if there is none)."""
        self._session.stack.redo()

    @property
    def can_undo(self) -> bool:
        """True if there is a change to undo."""
        return self._session.stack.can_undo()

    @property
    def can_redo(self) -> bool:
        """True if there is an undone change to redo."""
        return self._session.stack.can_redo()

    def history(self) -> list[tuple[str, bool]]:
        """``(text, applied)`` of every change, oldest first (the History pane)."""
        return self._session.stack.history()

    def clear_history(self) -> None:
        """"Clear History": forget every change (frees their memory; no undo past this)."""
        self._session.stack.clear()

    # -------------------------------------------------------------------------- files
    def save(self, path: str | os.PathLike | None = None) -> Path:
        """Save (atomically) to ``path`` or the current file; returns the file written.

        Raises
        ------
        ValueError
            No path for a take never saved.
        """
        return self._session.save(path)

    def export(self, path: str | os.PathLike, *, properties: Mapping[str, Any] | None = None,
               **kwargs: Any) -> Path:
        """Export by extension (``.c3d .fbx .xcp .csv .trc .bvh .bva``); ``properties``
        overrides Export properties by label: see
        :meth:`CaraExport.export <carapost.api_export.CaraExport.export>`."""
        return self.data.export(path, properties=properties, **kwargs)

    def close(self) -> None:
        """Close the image sources (the take stays readable; detection and tracking need them)."""
        if self._finalizer is not None:
            self._finalizer()
        else:
            self._session.close()

    def __enter__(self) -> "CaraProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        where = f"{str(self.path)!r}" if self.path else "unsaved"
        return (f"CaraProcess({self.name!r}, {where}, frames={self.n_frames}, cameras={self.n_cameras}, "
                f"points={self.n_points}{', modified' if self.modified else ''})")
