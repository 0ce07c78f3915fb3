"""Blob detection of one take split across worker processes by frame range.

The frames to detect are cut into contiguous chunks (one video decoder per chunk reads its
frames in order); every chunk is a task that opens the take's camera sources itself, detects
all requested cameras of its frames and returns the detection tables. The tables are merged
into the same undoable change as :func:`carapost.ops.detect.detect_blobs` returns, so the two
are interchangeable; only where the work runs differs.

Why processes: :func:`carapost.core.detect_range.detect_frames` uses threads, which share the
decoder and avoid pickling, but the detector still holds the GIL for part of every frame. On
two cores, two processes run the detector about 1.9x as fast as one, two threads about 1.6x
(``benchmarks/bench_batch.py``; ``docs/batch.md``). Processes pay a start-up (a fork server,
~0.1-0.3 s per pool) and each opens its own sources, so threads stay the default for a few
frames and the GUI; processes pay off for long takes and farm jobs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from carapost.model.params import BlobParameters
from carapost.model.take import Take

from .batch_pool import Pool, limit_threads, open_pool
from .change import CancelFn, Composite, DetectionFramesChange, ProgressFn

__all__ = ["CameraSource", "DetectTask", "detect_task", "frame_chunks", "detect_chunk", "detect_split",
           "detect_blobs_split", "detections_change"]

Table = dict[str, np.ndarray]
Tables = dict[int, dict[int, Table]]  # camera -> frame -> detection table


@dataclass(frozen=True)
class CameraSource:
    """How a worker opens one camera's frames: the source file and the take's view of it."""

    path: str
    offset: int = 0
    rotation: int = 0


@dataclass(frozen=True)
class DetectTask:
    """Everything a worker needs to detect blobs of a take (picklable, no open files).

    Attributes
    ----------
    sources : tuple of CameraSource or None
        One per camera of the take (None: the camera has no video).
    n_frames : int
        Length of the take.
    params : BlobParameters
    cameras : tuple of int
        The cameras to detect.
    masks : tuple of (bool (H, W) array or None), or None
        Per camera of the take: pixels to ignore.
    """

    sources: tuple[CameraSource | None, ...]
    n_frames: int
    params: BlobParameters
    cameras: tuple[int, ...]
    masks: tuple[np.ndarray | None, ...] | None = None


def detect_task(take: Take, sources: Sequence[Any] | None = None, *, cameras: Sequence[int] | None = None,
                params: BlobParameters | None = None,
                masks: Sequence[np.ndarray | None] | None = None) -> DetectTask:
    """The :class:`DetectTask` of a take (its cameras' source files, offsets and rotations).

    Parameters
    ----------
    take : Take
    sources : sequence, optional
        A session's per-camera sources (``None`` marks a camera without video); default: every
        camera with a recorded source file.
    cameras : sequence of int, optional
        Default all cameras.
    params : BlobParameters, optional
        Default the take's Blob Parameters.
    masks : per-camera bool (H, W) or None, optional

    Raises
    ------
    ValueError
        A camera does not exist or has no video.
    """
    cams = tuple(range(take.n_cameras)) if cameras is None else tuple(int(c) for c in cameras)
    specs: list[CameraSource | None] = []
    for c, cam in enumerate(take.cameras):
        missing = cam.source is None or (sources is not None and sources[c] is None)
        specs.append(None if missing else CameraSource(str(cam.source.path), int(cam.frame_offset),  # type: ignore[union-attr]
                                                       int(cam.rotation)))
    for c in cams:
        if not 0 <= c < take.n_cameras:
            raise ValueError(f"camera {c} does not exist (the take has {take.n_cameras})")
        if specs[c] is None:
            raise ValueError(f"camera {c} ({take.cameras[c].name}) has no video: relocate its file")
    if masks is not None and len(masks) != take.n_cameras:
        raise ValueError(f"masks: expected one per camera ({take.n_cameras}), got {len(masks)}")
    return DetectTask(tuple(specs), int(take.n_frames), take.params.blobs if params is None else params, cams,
                      None if masks is None else tuple(masks))


def frame_chunks(frames: Sequence[int], n_chunks: int) -> list[list[int]]:
    """Split frames (sorted, duplicates dropped) into ``n_chunks`` contiguous runs of near-equal
    length; fewer when there are fewer frames. ``[]`` for no frames."""
    if n_chunks < 1:
        raise ValueError(f"n_chunks must be at least 1, got {n_chunks}")
    fs = sorted({int(f) for f in frames})
    if not fs:
        return []
    bounds = np.linspace(0, len(fs), min(n_chunks, len(fs)) + 1).round().astype(int)
    return [fs[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def detect_chunk(task: DetectTask, frames: Sequence[int], threads: int = 1) -> Tables:
    """Detect the task's cameras in ``frames`` (run in a worker; opens and closes the sources).

    OpenCV and BLAS are limited to ``threads`` threads while the chunk runs (restored
    afterwards), so that N workers on N cores do not oversubscribe them.

    Returns
    -------
    dict
        ``{camera: {frame: detection table}}``.

    Raises
    ------
    ValueError
        A source cannot be opened or a frame cannot be read; a frame outside the take.
    """
    from carapost.core.blobs import detect_blobs
    from carapost.io.sources import OffsetSource, open_source

    for f in frames:
        if not 0 <= int(f) < task.n_frames:
            raise ValueError(f"frame {f} is outside the take (0..{task.n_frames - 1})")
    out: Tables = {}
    with limit_threads(threads):
        for c in task.cameras:
            spec = task.sources[c]
            if spec is None:
                raise ValueError(f"camera {c} has no video")
            src = OffsetSource(open_source(spec.path), offset=spec.offset, rotation=spec.rotation,
                               n_frames=task.n_frames)
            mask = None if task.masks is None else task.masks[c]
            try:
                out[c] = {int(f): detect_blobs(src.read(int(f)), task.params, mask=mask) for f in frames}
            finally:
                src.source.close()
    return out


def detect_split(task: DetectTask, frames: Sequence[int], pool: Pool, *, chunks_per_worker: int = 2,
                 progress: ProgressFn | None = None, cancel: CancelFn | None = None) -> Tables:
    """Run :func:`detect_chunk` over frame chunks on ``pool``; merged tables.

    Parameters
    ----------
    task : DetectTask
    frames : sequence of int
    pool : Pool
        Where chunks run (see :mod:`carapost.ops.batch_pool`).
    chunks_per_worker : int
        More chunks balance the load and report progress more often; each chunk opens the sources.
    progress : callable ``(done, total)``, optional
        Images (frame x camera) finished, after each chunk.
    cancel : callable, optional
        Polled between chunks: chunks not started are dropped, running ones finish, and the
        frames done are returned.

    Returns
    -------
    dict
        ``{camera: {frame: table}}`` in frame order.

    Raises
    ------
    ValueError
        From a chunk (bad source, frame outside the take); the other chunks are cancelled.
    """
    chunks = frame_chunks(frames, max(1, pool.workers * chunks_per_worker))
    total = sum(len(ch) for ch in chunks) * len(task.cameras)
    pending = [pool.submit(detect_chunk, task, ch) for ch in chunks]
    merged: Tables = {c: {} for c in task.cameras}
    done_images = 0
    try:
        while pending:
            if cancel is not None and cancel():
                pool.cancel(pending)
            done, pending = pool.wait_any(pending)
            for h in done:
                if h.cancelled():
                    continue
                for c, tables in pool.result(h).items():
                    merged[c].update(tables)
                    done_images += len(tables)
                if progress is not None:
                    progress(done_images, total)
            pending = [h for h in pending if not h.cancelled()]
    except BaseException:
        pool.cancel(pending)
        raise
    return {c: dict(sorted(t.items())) for c, t in merged.items()}


def detections_change(take: Take, tables: Mapping[int, Mapping[int, Table]]) -> Composite:
    """The undoable change writing ``{camera: {frame: table}}`` into the take: the same change
    :func:`carapost.ops.detect.detect_blobs` returns."""
    changes = [DetectionFramesChange.capture(take, int(c), dict(t)) for c, t in sorted(tables.items()) if t]
    n = sum(len(tab["x"]) for ch in changes for tab in ch.new.values())
    frames = {f for t in tables.values() for f in t}
    what = "Current Frame" if len(frames) == 1 else "Active Range"
    return Composite(changes, f"Detect Blobs [{what}]: {n} detections")


def detect_blobs_split(take: Take, frames: Sequence[int], *, sources: Sequence[Any] | None = None,
                       workers: int = 2, pool: Pool | None = None, cameras: Sequence[int] | None = None,
                       params: BlobParameters | None = None, masks: Sequence[np.ndarray | None] | None = None,
                       progress: ProgressFn | None = None, cancel: CancelFn | None = None,
                       chunk_frames: int | None = None) -> Composite:
    """"Detect Blobs" with the frames split across worker processes.

    Parameters
    ----------
    take : Take
        Not modified: apply the returned change (e.g. ``session.apply``).
    frames : sequence of int
    sources : sequence, optional
        The session's sources (``session.sources``), to refuse cameras without video early.
    workers : int
        Processes started for this call (1 runs in this process); ignored with ``pool``.
    pool : Pool, optional
        An open pool to use (e.g. a :class:`~carapost.ops.batch_pool.DaskPool`); not closed.
    cameras, params, masks, progress, cancel
        As for :func:`carapost.ops.detect.detect_blobs`.
    chunk_frames : int, optional
        About how many frames a chunk holds (progress and cancel act between chunks); default
        two chunks per worker.

    Returns
    -------
    Composite
        One :class:`DetectionFramesChange` per camera, as ``detect_blobs`` returns.

    Raises
    ------
    ValueError
        Frames outside the take, unknown cameras, a camera without video, unreadable frames.
    """
    fs = sorted({int(f) for f in frames})
    bad = [f for f in fs if not 0 <= f < take.n_frames]
    if bad:
        raise ValueError(f"frame {bad[0]} is outside the take (0..{take.n_frames - 1})")
    task = detect_task(take, sources, cameras=cameras, params=params, masks=masks)
    own = pool is None
    p = open_pool(workers) if pool is None else pool
    try:
        per_worker = 2 if chunk_frames is None else max(2, -(-len(fs) // (max(1, p.workers) * chunk_frames)))
        tables = detect_split(task, fs, p, chunks_per_worker=per_worker, progress=progress, cancel=cancel)
    finally:
        if own:
            p.close()
    return detections_change(take, tables)
