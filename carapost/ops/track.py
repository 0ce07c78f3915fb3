"""The Process menu's tracking commands: Track Forwards / Backwards [Sequence] / [Single Frame].

Each runs the automatic tracker (:func:`carapost.core.tracking.track`) from the current frame
without touching the take, and returns one undoable change holding the frames it wrote: the
tracked points' positions and observations, the re-estimated camera poses, and the blob
detections of frames that had not been detected yet ("performs blob detection if it hasn't
already been done"). A cancelled run keeps the frames finished so far.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from carapost.core.tracking import DetectFn, TrackResult, track
from carapost.model.params import TrackingParameters
from carapost.model.take import Take

from .change import ArrayPatch, CancelFn, Change, Composite, DetectionFramesChange, ProgressFn

__all__ = [
    "track_sequence",
    "track_forwards_sequence",
    "track_backwards_sequence",
    "track_forwards_single_frame",
    "track_backwards_single_frame",
    "result_change",
    "blob_detector",
]

ImageFn = Callable[[int, int], np.ndarray]  # (camera, frame) -> (H, W) uint8
_AUTO = "auto"
_POINT_ARRAYS = ("xyz", "recon", "obs_xy", "obs_det", "obs_src", "obs_q")


def blob_detector(take: Take, image: ImageFn) -> DetectFn:
    """Detect blobs of a frame with the take's Blob Parameters (for frames not detected yet)."""
    from carapost.core.blobs import detect_blobs

    params = take.params.blobs

    def detect(camera: int, frame: int) -> dict[str, np.ndarray]:
        return detect_blobs(image(camera, frame), params)

    return detect


def track_sequence(take: Take, image: ImageFn | None, frame: int, *, direction: int = 1,
                   n_frames: int | None = None, points: Sequence[int] | np.ndarray | None = None,
                   params: TrackingParameters | None = None, detect: DetectFn | str | None = _AUTO,
                   progress: ProgressFn | None = None, cancel: CancelFn | None = None,
                   text: str | None = None) -> Composite:
    """Track points from ``frame`` forwards (``direction=1``) or backwards (``-1``).

    Parameters
    ----------
    take : Take
        Not modified: apply the returned change.
    image : callable ``(camera, frame) -> uint8 (H, W)`` or None
        The video (e.g. :meth:`Session.image <carapost.ops.session.Session.image>`); without
        it the tracker matches blobs by position and size only.
    frame : int
        The current frame, whose points are tracked.
    direction : {1, -1}
    n_frames : int, optional
        Frames to track (default: to the end / the start of the take).
    points : sequence of int, optional
        The selected point columns (default: all points, as when none is selected).
    params : TrackingParameters, optional
        Default: the take's Tracking Parameters.
    detect : callable, "auto" or None
        Blob detection for frames not detected yet; "auto" detects with the take's Blob
        Parameters when ``image`` is given.
    progress, cancel : callables
        ``progress(done, total)`` after each frame; ``cancel()`` stops after the current frame,
        keeping the frames done.
    text : str, optional
        The history entry's text.

    Returns
    -------
    Composite
        Empty if there was nothing to track (e.g. at the last frame going forwards).

    Raises
    ------
    ValueError
        If the frame is outside the take, there are no points with a position at the frame,
        or the frame has no camera poses.
    """
    if not 0 <= frame < take.n_frames:
        raise ValueError(f"frame {frame} is outside the take (0..{take.n_frames - 1})")
    cols = np.arange(take.n_points) if points is None else np.asarray(points, np.int64).reshape(-1)
    if len(cols) and (cols.min() < 0 or cols.max() >= take.n_points):
        raise ValueError(f"point columns must be within 0..{take.n_points - 1}")
    if not np.isfinite(take.xyz[frame, cols]).all(-1).any():
        raise ValueError(f"no point has a 3D position at frame {frame}: initialize 3D (or track to this "
                         f"frame) first")
    if detect == _AUTO:
        detect = blob_detector(take, image) if image is not None else None
    res = track(take, frame, direction=direction, n_frames=n_frames, image=image, params=params, points=cols,
                detect=detect, progress=progress, cancel=cancel)  # type: ignore[arg-type]
    if text is None:
        way = "Forwards" if direction > 0 else "Backwards"
        what = "Single Frame" if n_frames == 1 else "Sequence"
        text = f"Track {way} [{what}]"
    return result_change(take, res, text)


def result_change(take: Take, res: TrackResult, text: str = "Track") -> Composite:
    """The undoable change writing a :class:`~carapost.core.tracking.TrackResult` into ``take``."""
    changes: list[Change] = []
    for c in sorted(res.detections):
        tables = res.detections[c]
        if tables:
            changes.append(DetectionFramesChange.capture(take, c, tables))
    frames = np.asarray(res.frames, np.int64)
    if len(frames) and len(res.points):
        idx = (frames[:, None], np.asarray(res.points, np.int64)[None, :])
        for name in _POINT_ARRAYS:
            changes.append(ArrayPatch.capture(take, name, idx, getattr(res, name)))
    if len(frames) and res.cameras_updated:
        changes.append(ArrayPatch.capture(take, "R", (frames,), res.R))
        changes.append(ArrayPatch.capture(take, "t", (frames,), res.t))
    tot = res.report.get("totals", {})
    n_ok = tot.get("multi_view", 0) + tot.get("single_sensor", 0)
    summary = f"{text}: {len(frames)} frames, {len(res.points)} points, {n_ok} point-frames reconstructed"
    if res.report.get("cancelled"):
        summary += " (cancelled)"
    return Composite(changes, summary)


def track_forwards_sequence(take: Take, image: ImageFn | None, frame: int, **kw) -> Composite:
    """"Track Forwards [Sequence]": from ``frame`` to the end of the take."""
    return track_sequence(take, image, frame, direction=1, text="Track Forwards [Sequence]", **kw)


def track_backwards_sequence(take: Take, image: ImageFn | None, frame: int, **kw) -> Composite:
    """"Track Backwards [Sequence]": from ``frame`` to the start of the take."""
    return track_sequence(take, image, frame, direction=-1, text="Track Backwards [Sequence]", **kw)


def track_forwards_single_frame(take: Take, image: ImageFn | None, frame: int, **kw) -> Composite:
    """"Track Forwards [Single Frame]": into the next frame."""
    return track_sequence(take, image, frame, direction=1, n_frames=1, text="Track Forwards [Single Frame]", **kw)


def track_backwards_single_frame(take: Take, image: ImageFn | None, frame: int, **kw) -> Composite:
    """"Track Backwards [Single Frame]": into the previous frame."""
    return track_sequence(take, image, frame, direction=-1, n_frames=1, text="Track Backwards [Single Frame]",
                          **kw)
