"""Blob detection over a range of frames, on several cores, with progress and cancel.

Frames are detected by a pool of threads: OpenCV and the large numpy operations release the
GIL, so threads scale on the detector without pickling frames or the reader (a video decoder
usually cannot be shared with another process). ``read_frame`` is only ever called by one
thread at a time. ``progress`` and ``cancel`` are called from the calling thread only.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait

import numpy as np

from ..model.params import BlobParameters
from .blobs import detect_blobs

__all__ = ["detect_frames"]


def detect_frames(read_frame: Callable[[int], np.ndarray], frames: Sequence[int], params: BlobParameters,
                  *, mask: np.ndarray | None = None, workers: int = 2,
                  progress: Callable[[int, int], None] | None = None,
                  cancel: Callable[[], bool] | None = None) -> dict[int, dict[str, np.ndarray]]:
    """Detect blobs in many frames.

    Parameters
    ----------
    read_frame : callable ``frame -> uint8 (H, W)``
        Returns the grayscale image of a frame. Called by one thread at a time.
    frames : sequence of int
        Frames to detect (duplicates are detected once).
    params : BlobParameters
    mask : bool (H, W), optional
        Pixels to ignore, as in :func:`carapost.core.blobs.detect_blobs`.
    workers : int
        Number of threads (1 = run in the calling thread).
    progress : callable ``(done, total) -> None``, optional
        Called after every finished frame, from the calling thread.
    cancel : callable ``() -> bool``, optional
        Polled from the calling thread; when it returns True no new frame is started, the
        frames already running are finished, and what is done is returned.

    Returns
    -------
    dict of int to dict
        ``{frame: detection table}`` for every finished frame, in frame order (all frames
        unless cancelled).

    Raises
    ------
    ValueError
        If ``workers < 1``, or from ``read_frame`` / the detector (bad image); frames not yet
        started are then abandoned.
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    todo = list(dict.fromkeys(int(f) for f in frames))
    total = len(todo)
    results: dict[int, dict[str, np.ndarray]] = {}

    def cancelled() -> bool:
        return bool(cancel is not None and cancel())

    if workers == 1 or total <= 1:
        for f in todo:
            if cancelled():
                break
            results[f] = detect_blobs(read_frame(f), params, mask=mask)
            if progress is not None:
                progress(len(results), total)
        return dict(sorted(results.items()))

    read_lock = threading.Lock()

    def job(f: int) -> dict[str, np.ndarray]:
        with read_lock:
            image = read_frame(f)
        return detect_blobs(image, params, mask=mask)

    pending: dict[Future, int] = {}
    next_i = 0
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="detect") as pool:
        try:
            while next_i < total or pending:
                stop = cancelled()
                # Keep a couple of frames queued per worker so no thread waits for the reader.
                while not stop and next_i < total and len(pending) < 2 * workers:
                    pending[pool.submit(job, todo[next_i])] = todo[next_i]
                    next_i += 1
                if stop:
                    next_i = total
                    for fut in [f for f in pending if f.cancel()]:
                        del pending[fut]
                    if not pending:
                        break
                done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                for fut in done:
                    f = pending.pop(fut)
                    results[f] = fut.result()
                    if progress is not None:
                        progress(len(results), total)
        except BaseException:
            for fut in pending:
                fut.cancel()
            raise
    return dict(sorted(results.items()))
