"""The processing steps of :class:`~carapost.api_process.CaraProcess`: ranges, calibration brim,
Initialize 3D, the pipeline, tracking, point and label edits, gap filling, stabilization.

Each method runs one operation of :mod:`carapost.ops` (the GUI's menu entry of the same name) and
pushes its change on the take's undo stack; it returns the history text (or the operation's
report). :class:`ProcessingSteps` is not used on its own: :class:`CaraProcess` inherits it.
"""

from __future__ import annotations

import importlib
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from carapost.model.take import Take
from carapost.ops.change import Change
from carapost.ops.session import Session

from .api_export import CaraExport

__all__ = ["ProcessingSteps"]

log = logging.getLogger("carapost")

ProgressFn = Callable[[int, int], None]
CancelFn = Callable[[], bool]


def _ops(name: str) -> Any:
    """``carapost.ops.<name>``, imported on first use (keeps ``import carapost.api`` fast:
    scripts start in a fraction of a second whatever they use)."""
    return importlib.import_module(f"carapost.ops.{name}")


def _direction(direction: str | int) -> int:
    way = {"forwards": 1, "forward": 1, "backwards": -1, "backward": -1, 1: 1, -1: -1}.get(
        direction.lower() if isinstance(direction, str) else direction)
    if way is None:
        raise ValueError(f"direction must be 'forwards' or 'backwards', got {direction!r}")
    return way


class ProcessingSteps:
    """Processing steps on ``self._session`` (a :class:`~carapost.ops.session.Session`)."""

    _session: Session

    @property
    def take(self) -> Take:
        """The data model. Change it only through this object's methods (they are undoable)."""
        return self._session.take

    @property
    def missing_sources(self) -> list[int]:
        """Cameras whose video file was not found (no detection possible on them)."""
        return self._session.missing

    # ------------------------------------------------------------------------ helpers
    def _camera(self, camera: int) -> int:
        c = int(camera)
        if not 0 <= c < self.take.n_cameras:
            raise ValueError(f"sensor {camera} does not exist (the take has {self.take.n_cameras} cameras)")
        return c

    def _frame(self, frame: int) -> int:
        f = int(frame)
        if not 0 <= f < self.take.n_frames:
            raise ValueError(f"frame {frame} is outside the take (0..{self.take.n_frames - 1})")
        return f

    def _points(self, points: Sequence[int | str] | int | str) -> list[int]:
        if isinstance(points, (int, str, np.integer)):
            points = [points]
        view = CaraExport(self.take)
        try:
            return [view.point_index(p) for p in points]
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None

    def _apply(self, change: Change | None) -> str:
        done = self._session.apply(change)
        return getattr(done, "text", "") if done is not None else ""

    # ------------------------------------------------------------------------- ranges
    @property
    def active_range(self) -> tuple[int, int]:
        """Inclusive frame indices processing applies to."""
        a, b = self.take.active_range
        return int(a), int(b)

    def set_active_range(self, start: int, end: int) -> str:
        """Set Active Range Start / End (inclusive frame indices)."""
        return self._apply(_ops("settings").set_active_range(self.take, int(start), int(end)))

    @property
    def current_frame(self) -> int:
        """The current frame (what Initialize 3D and tracking start from by default)."""
        return int(self.take.current_frame)

    @current_frame.setter
    def current_frame(self, frame: int) -> None:
        self.take.current_frame = self._frame(frame)

    # ---------------------------------------------------------------------------- brim
    def initialize_default_brim(self, version: str = "v2.0") -> str:
        """"Initialize Default Calibration Brim [v1.0 / v1.1 / v2.0]"."""
        return self._apply(_ops("brim").initialize_default_brim(self.take, version))

    def import_brim_svg(self, path: str | os.PathLike) -> str:
        """"Import Calibration Brim [svg]": a custom planar brim."""
        return self._apply(_ops("brim").import_brim_svg(self.take, path))

    def import_brim(self, path: str | os.PathLike) -> str:
        """A brim model from a file: ``.svg`` ("Import Calibration Brim [svg]") or a brim
        ``.json`` (as written by :func:`carapost.io.brim.save_brim_json`)."""
        p = Path(path)
        if p.suffix.lower() == ".svg":
            return self.import_brim_svg(p)
        if p.suffix.lower() == ".json":
            from carapost.io.brim import load_brim_json

            return self._apply(_ops("brim").set_brim(self.take, load_brim_json(p), f"Load brim {p.name}"))
        raise ValueError(f"{p}: a brim file must be .svg or .json")

    def solve_brim(self, frame: int, correspondences: Mapping[int, Mapping[int, int]], *,
                   all_frames: bool = True) -> list[str]:
        """"Solve Calibration Brim [Manual]" in ``frame``.

        Parameters
        ----------
        correspondences : ``{camera: {brim dot index: detection index}}``
            At least 4 dots per camera (detection indices within ``frame``).
        all_frames : bool
            Also give the solved poses to every frame that has none yet.

        Returns
        -------
        list of str
            The solver's messages (per camera).
        """
        change, res = _ops("brim").solve_brim_manual(self.take, self._frame(frame), correspondences,
                                                     all_frames=all_frames)
        self._apply(change)
        return list(res.messages)

    # ----------------------------------------------------------- 3D initialization
    def initialize_3d(self, frame: int | None = None, *, auto: bool = False) -> str:
        """"Initialize 3D" on ``frame`` (default the current frame): grow points from the seed
        points matched in two or more cameras, or from nothing with ``auto=True``."""
        f = self.current_frame if frame is None else self._frame(frame)
        return self._apply(_ops("init3d").initialize_3d_op(self.take, f, auto=auto))

    # ------------------------------------------------------------------------------ calibration
    def import_calibration(self, path: str | os.PathLike) -> str:
        """"Import XCP": the intrinsics and poses of a calibration file (``.xcp``, ``.toml`` or
        ``.qca``, one camera per channel) replace the take's, as one undoable step.

        Raises
        ------
        ValueError
            The file cannot be read or has a different number of cameras (the message names it).
        """
        from carapost.io.calibration import load_calibration

        try:
            calib = load_calibration(path)
        except OSError as exc:
            raise ValueError(f"{path}: {exc.strerror or exc}") from None
        return self._apply(_ops("calibrate").apply_calibration(self.take, calib))

    # ------------------------------------------------------------------------------ ROM
    def load_rom(self, path: str | os.PathLike) -> str:
        """"Load ROM": a solved ``.cara`` take of the same actor, marker set and camera rig,
        used by :meth:`initialize_from_rom`.

        Raises
        ------
        ValueError
            The file is missing or not a ``.cara`` project, or the take in it has no brim, no
            solved frame, or a different number of cameras (the message names the file).
        """
        rom_ops = _ops("rom")
        rom = rom_ops.read_rom(path, n_cameras=self.take.n_cameras)
        text = self._apply(rom_ops.load_rom(self.take, path, rom=rom))
        self._rom, self._rom_path = rom, self.take.rom_path     # cached while the path stays
        return text

    def initialize_from_rom(self, frame: int | None = None, *, brim_only: bool = False) -> str:
        """"Initialize from ROM" (``brim_only=True``: "Initialize from ROM [Brim Only]").

        Finds the loaded ROM's points of its *ROM Frame Index* in ``frame`` (default the current
        frame) with the tracking algorithm and the Initialize From ROM Parameters
        (``take.params.rom``: frame index, face and brim point tracking distances, max allowed
        3D point error), and carries over the cameras' calibration (poses re-estimated from
        the brim), the brim, the face points (a new set), their labels and sticks, as one
        undoable step. The frame's blobs are detected first if they have not been.

        Returns
        -------
        str
            The history entry: how many brim and face points were found.

        Raises
        ------
        ValueError
            No ROM loaded (:meth:`load_rom`), the ROM frame has no poses or brim, or the frame
            has no detections and no video.
        """
        f = self.current_frame if frame is None else self._frame(frame)
        image = self._session.image if not self.missing_sources else None
        rom = getattr(self, "_rom", None)
        if rom is not None and getattr(self, "_rom_path", None) != self.take.rom_path:
            rom = None
        change = _ops("rom").initialize_from_rom(self.take, image, f, brim_only=brim_only, rom=rom)
        report = getattr(change, "report", {})
        if report.get("not_found"):
            log.info("Initialize from ROM: not found: %s", ", ".join(report["not_found"]))
        return self._apply(change)

    def bundle(self, frames: Sequence[int] | int | None = None) -> str:
        """"Bundle Current Frame / Sequence [Unconstrained]": refine camera poses and
        multi-view points of one frame, a list of frames, or the active range (default)."""
        if frames is None:
            a, b = self.active_range
            return self._apply(_ops("init3d").bundle_sequence(self.take, np.arange(a, b + 1)))
        if isinstance(frames, (int, np.integer)):
            return self._apply(_ops("init3d").bundle_current_frame(self.take, self._frame(frames)))
        return self._apply(_ops("init3d").bundle_sequence(self.take, [self._frame(f) for f in frames]))

    def run_pipeline(self, *, report: Callable[..., None] | None = None, cancel: CancelFn | None = None,
                     **options: Any) -> dict[str, Any]:
        """The headless pipeline (what ``carapost process`` runs): detect, brim, seeds, bundle,
        Initialize 3D, exports. ``options`` are those of
        :class:`carapost.ops.pipeline.PipelineOptions` (``seeds=``, ``auto_init=``, ``brim=``,
        ``frame=``, ``detect=``, ``c3d=``, ``fbx=``, ...). Each stage is one undoable step.

        Returns
        -------
        dict
            The pipeline's summary (stages with timings and counts, files written).

        Raises
        ------
        PipelineError
            (a ``ValueError``) naming the stage that failed; earlier stages stay applied.
        """
        from carapost.ops.pipeline import PipelineOptions, run_pipeline

        return run_pipeline(self._session, PipelineOptions(**options), report=report, cancel=cancel)

    # ------------------------------------------------------------------------ tracking
    def track(self, frame: int | None = None, *, direction: str | int = "forwards", n_frames: int | None = None,
              points: Sequence[int | str] | None = None, progress: ProgressFn | None = None,
              cancel: CancelFn | None = None) -> str:
        """"Track Forwards / Backwards [Sequence]" (or ``[Single Frame]`` with ``n_frames=1``).

        The points with a 3D position at ``frame`` (default the current frame) are tracked
        through the take with the Tracking Parameters; frames not yet detected are detected on
        the way (with the Blob Parameters); camera poses are re-estimated per frame from the brim.

        Parameters
        ----------
        frame : int, optional
            Start frame (default :attr:`current_frame`).
        direction : {"forwards", "backwards"} or {1, -1}
        n_frames : int, optional
            Frames to track (default: to the end / the start of the take).
        points : points by column or name, optional
            Default all points.
        progress, cancel : callables
            ``progress(done, total)`` per frame; ``cancel() -> True`` stops (frames done are kept).

        Returns
        -------
        str
            The history entry, with the frames and point-frames reconstructed.

        Raises
        ------
        ValueError
            No point has a position at ``frame``, the frame has no camera poses, or a bad
            argument.
        """
        way = _direction(direction)
        f = self.current_frame if frame is None else self._frame(frame)
        cols = None if points is None else self._points(points)
        image = self._session.image if not self.missing_sources else None
        if image is None:
            log.warning("tracking without images (sensors %s have no video): blob matching by position and size only",
                        self.missing_sources)
        track_ops = _ops("track")
        kw: dict[str, Any] = {"points": cols, "progress": progress, "cancel": cancel}
        if n_frames == 1:
            op = track_ops.track_forwards_single_frame if way > 0 else track_ops.track_backwards_single_frame
        else:
            op = track_ops.track_forwards_sequence if way > 0 else track_ops.track_backwards_sequence
            if n_frames is not None:
                if int(n_frames) < 1:
                    raise ValueError(f"n_frames must be at least 1, got {n_frames}")
                kw["n_frames"] = int(n_frames)
        return self._apply(op(self.take, image, f, **kw))

    # ------------------------------------------------------------------ points, labels
    def merge(self, points: Sequence[int | str] = (), detections: Sequence[tuple[int, int, int]] = (), *,
              frame: int | None = None) -> str:
        """"Merge (M)": points and/or detections ``(camera, frame, index)`` into one point."""
        cols = self._points(points) if points else []
        return self._apply(_ops("points").merge(self.take, cols, list(detections), frame=frame))

    def delete_points(self, points: Sequence[int | str] | int | str) -> str:
        """Delete points (by column or name)."""
        return self._apply(_ops("points").delete_points(self.take, self._points(points)))

    def import_labels(self, path: str | os.PathLike) -> str:
        """"Import Labels From Text File" (``.txt``) or "From Cara File" (``.cara``)."""
        if str(path).lower().endswith(".cara"):
            return self._apply(_ops("labels").import_labels_from_cara(self.take, path))
        return self._apply(_ops("labels").import_labels_from_text(self.take, path))

    def assign_label(self, point: int | str, label: str) -> str:
        """Give a point a label (another point holding the label loses it)."""
        return self._apply(_ops("labels").assign_label(self.take, self._points(point)[0], label))

    def create_stick(self, point1: int | str, point2: int | str) -> str:
        """"Create Stick from Selected Point (S)": a stick between two points."""
        a, b = self._points([point1, point2])
        return self._apply(_ops("labels").create_stick(self.take, a, b))

    def create_stick_mesh(self, frame: int | None = None, *, max_edge_mm: float | None = None) -> str:
        """"Create Stick Mesh": a triangle mesh over the face points with 3D data in ``frame``
        (default the current frame); edges longer than ``max_edge_mm`` (default 3x the median
        edge) are dropped."""
        f = self.current_frame if frame is None else self._frame(frame)
        return self._apply(_ops("labels").create_stick_mesh(self.take, f, max_edge_mm=max_edge_mm))

    # ------------------------------------------------------------------ Target Tracker
    def add_target_track(self, camera: int, frame: int, xy: Sequence[float], *,
                         pattern: Sequence[float] | None = None, search: Sequence[float] | None = None) -> str:
        """"Add Target Track (Shift+A)": a new point keyed at ``xy`` (raw px) in one camera and
        frame; ``pattern`` / ``search`` boxes ``(x0, y0, x1, y1)`` default to the guide's sizes.
        The new point is the last column (``n_points - 1``)."""
        return self._apply(_ops("target").add_target_track(self.take, self._camera(camera), self._frame(frame),
                                                           xy, pattern=pattern, search=search))

    def add_keyframes(self, points: Sequence[int | str] | int | str, frame: int | None = None) -> str:
        """"Add Keyframe To Current Frame": key the points in every camera where they have a 2D
        position in ``frame`` (default the current frame)."""
        f = self.current_frame if frame is None else self._frame(frame)
        return self._apply(_ops("target").add_keyframes(self.take, self._points(points), f))

    def gaps_to_keys(self, points: Sequence[int | str] | int | str) -> str:
        """"Gaps To Keys": keyframes either side of every gap in the points' 2D tracks."""
        return self._apply(_ops("target").gaps_to_keys(self.take, self._points(points)))

    def clear_tracked_points(self, points: Sequence[int | str] | int | str) -> str:
        """"Clear Tracked Points": delete the points' 2D observations and keyframes (and the 3D
        positions resting on them)."""
        return self._apply(_ops("target").clear_tracked_points(self.take, self._points(points)))

    def target_track(self, points: Sequence[int | str] | int | str, frame: int | None = None, *,
                     direction: str | int = "forwards", to_end: bool = True, progress: ProgressFn | None = None,
                     cancel: CancelFn | None = None) -> dict[str, Any]:
        """The Target Tracker (Tracker pane): template-track the points from ``frame`` (default
        the current frame) in every camera where they have a 2D position, with the Tracker
        settings (break threshold, stop on next keyframe, ...).

        Parameters
        ----------
        direction : {"forwards", "backwards"} or {1, -1}
        to_end : bool
            Track to the end (start) of the take; False: one frame.

        Returns
        -------
        dict
            ``text`` (history entry), ``tracked`` (frames found per point and camera),
            ``stop_reasons``, ``keyframes_added``, ``cancelled``.
        """
        way = _direction(direction)
        f = self.current_frame if frame is None else self._frame(frame)
        change = _ops("target").track(self.take, self._points(points), f, self._session.image, direction=way,
                                      to_end=to_end, progress=progress, cancel=cancel)
        text = self._apply(change)
        rep = change.report
        out: dict[str, Any] = {"text": text}
        if rep is not None:
            out.update(tracked={(int(p), int(c)): int(n) for p, c, n in zip(rep.points, rep.cameras, rep.n_tracked)},
                       stop_reasons=list(rep.stop_reason), keyframes_added=int(rep.keyframes_added),
                       cancelled=bool(rep.cancelled))
        return out

    # ---------------------------------------------------- gaps, stabilization, alignment
    def interpolate_gaps(self, points: Sequence[int | str] | None = None, *, method: str | None = None) -> dict:
        """"Interpolate Gaps" of some points (default all) in the active range, with the
        Gap-Filling Parameters (``method`` default: their *Method*: ``"neighbours"``,
        ``"face_model"`` or ``"blink"``). Returns the report (``filled``, ``single_sensor``,
        ``unfilled``)."""
        cols = None if points is None else self._points(points)
        change = _ops("fill").interpolate_gaps(self.take, cols, method=method)
        self._apply(change)
        return dict(change.report)

    def stabilize(self, points: Sequence[int | str], *, assisted: bool = True,
                  base_frame: int | None = None) -> dict:
        """"Stabilize Data [Assisted]" (or ``[Manual]``) on >= 3 gap-free points over the active
        range; results go to ``xyz_stabilized``. Returns the report (stabilization error)."""
        op = _ops("fill").stabilize_assisted if assisted else _ops("fill").stabilize_manual
        change = op(self.take, self._points(points), base_frame=base_frame)
        self._apply(change)
        return dict(change.report)

    def align(self, points: Sequence[int | str], *, frame: int | None = None, data: str = "auto") -> dict:
        """"Align Data": the frame of three points (origin, x axis, xy plane) at ``frame``."""
        change = _ops("fill").align_data(self.take, self._points(points), frame=frame, data=data)
        self._apply(change)
        return dict(change.report)
