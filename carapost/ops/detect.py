"""Blob detection operations (the Process menu's Detect Blobs entries and their Edit-menu kin)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from carapost.core.detect_range import detect_frames
from carapost.model.params import BlobParameters
from carapost.model.take import Take

from .change import ArrayPatch, AttributeChange, CancelFn, Composite, DetectionFramesChange, DetectionsReplace, \
    ProgressFn

__all__ = ["detect_blobs", "remove_unused_detections", "read_blob_parameters_from_pico"]

ImageFn = Callable[[int, int], np.ndarray]  # (camera, frame) -> (H, W) uint8

#: Images (frames x cameras) from which Detect Blobs starts worker processes: starting them and
#: opening the sources in each costs ~0.3 s, about four 1280x720 images.
PROCESS_MIN_IMAGES = 24


def detect_blobs(take: Take, image: ImageFn, frames: Sequence[int], *, cameras: Sequence[int] | None = None,
                 params: BlobParameters | None = None, masks: Sequence[np.ndarray | None] | None = None,
                 workers: int = 2, progress: ProgressFn | None = None, cancel: CancelFn | None = None,
                 sources: Sequence[object | None] | None = None) -> Composite:
    """"Detect Blobs [Current Frame]" / "[Active Range]": new detections for the given frames.

    Parameters
    ----------
    take : Take
        Not modified: the result is a change to apply.
    image : callable ``(camera, frame) -> uint8 (H, W)``
    frames : sequence of int
        The current frame, or the active range.
    cameras : sequence of int, optional
        The explicit camera selection (Selection pane); all cameras by default.
    params : BlobParameters, optional
        Default: the take's Blob Parameters.
    masks : per-camera bool (H, W) or None, optional
        Invalid regions to ignore.
    workers : int
        Threads or processes (both cores by default).
    sources : per-camera sources, optional
        The session's (``session.sources``). With them, at least ``PROCESS_MIN_IMAGES`` images to
        detect and more than one core, the frames are detected in worker processes
        (:func:`carapost.ops.split_detect.detect_blobs_split`): the detector holds the GIL for
        most of a frame, so threads gain little (``benchmarks/bench_batch.py``: two processes
        1.86x one, two threads 0.94x).
    progress, cancel : callables
        ``progress(done, total)`` over all cameras and frames; ``cancel()`` stops early and the
        frames finished so far are kept in the change.

    Returns
    -------
    Composite
        One :class:`DetectionFramesChange` per camera. Observations attached to replaced
        detections are detached (detections are not stable across detection runs).
    """
    params = take.params.blobs if params is None else params
    cams = list(range(take.n_cameras)) if cameras is None else [int(c) for c in cameras]
    for c in cams:
        if not 0 <= c < take.n_cameras:
            raise ValueError(f"camera {c} does not exist (the take has {take.n_cameras})")
    frames = [int(f) for f in frames]
    for f in frames:
        if not 0 <= f < take.n_frames:
            raise ValueError(f"frame {f} is outside the take (0..{take.n_frames - 1})")
    total = len(cams) * len(frames)
    if sources is not None and workers > 1 and total >= PROCESS_MIN_IMAGES and all(sources[c] is not None for c in cams):
        from .batch_pool import cpu_count
        from .split_detect import detect_blobs_split

        n = min(workers, cpu_count())
        if n > 1:
            return detect_blobs_split(take, frames, sources=sources, workers=n, cameras=cams, params=params,
                                      masks=masks, progress=progress, cancel=cancel, chunk_frames=10)
    changes = []
    done_before = 0
    for c in cams:
        def prog(done: int, _total: int, base: int = done_before) -> None:
            if progress is not None:
                progress(base + done, total)

        tables = detect_frames(lambda f, cam=c: image(cam, f), frames, params,
                               mask=None if masks is None else masks[c], workers=workers, progress=prog,
                               cancel=cancel)
        if tables:
            changes.append(DetectionFramesChange.capture(take, c, tables))
        done_before += len(frames)
        if cancel is not None and cancel():
            break
    n = sum(len(t["x"]) for ch in changes for t in ch.new.values())
    what = "Current Frame" if len(frames) == 1 else "Active Range"
    return Composite(changes, f"Detect Blobs [{what}]: {n} detections")


def remove_unused_detections(take: Take) -> Composite:
    """"Remove Unused Detections": delete every detection not attached to a point."""
    changes = []
    for c, det in enumerate(take.detections):
        used = np.zeros(len(det), bool)
        od = take.obs_det[..., c]  # (F, P)
        f, p = np.nonzero(od >= 0)
        used[det.frame_ptr[f] + od[f, p]] = True
        if used.all():
            continue
        new, remap = det.select(used)
        patches = []
        if len(f):
            nd = od.copy()
            nd[f, p] = remap[det.frame_ptr[f] + od[f, p]]
            patches.append(ArrayPatch.capture(take, "obs_det", (slice(None), slice(None), c), nd))
        changes.append(DetectionsReplace(c, det.copy(), new, patches))
    removed = sum(len(ch.old) - len(ch.new) for ch in changes)
    return Composite(changes, f"Remove Unused Detections: {removed} removed")


def read_blob_parameters_from_pico(take: Take, capture_params: dict | None) -> AttributeChange:
    """"Read Blob Parameters From Pico Files": restore the Blob Parameters recorded at capture.

    Raises
    ------
    ValueError
        If the sources recorded no blob parameters.
    """
    if not capture_params:
        raise ValueError("the camera files recorded no blob parameters at capture")
    return AttributeChange.capture(take, "params.blobs", BlobParameters.from_dict(capture_params),
                                   "Read Blob Parameters From Pico Files")
