"""Blob preview: the blobs the current Blob Parameters would detect, computed in the background.

Camera views ask :meth:`BlobPreviewer.get` while painting; a missing result is computed on a
worker thread (the newest requests first, stale ones dropped) and ``ready`` asks the views to
repaint. Nothing is stored in the take.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from PySide6.QtCore import QObject, Signal

from carapost.core.blobs import detect_blobs

from ..document import Document

__all__ = ["BlobPreviewer"]

log = logging.getLogger("carapost")


class BlobPreviewer(QObject):
    """Cached background blob detection for the preview overlay.

    Signals
    -------
    ready(int, int)
        A preview for ``(camera, frame)`` is available.
    """

    ready = Signal(int, int)
    _done = Signal(object, object)

    def __init__(self, doc: Document, parent: QObject | None = None, max_items: int = 64) -> None:
        super().__init__(parent)
        self.doc = doc
        self.max_items = max_items
        self._cache: OrderedDict[tuple, dict[str, np.ndarray]] = OrderedDict()
        self._pending: set[tuple] = set()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="carapost-preview")
        self._closed = False
        self._done.connect(self._store)   # queued: results are stored on the GUI thread
        doc.sessionChanged.connect(self.clear)

    def _key(self, camera: int, frame: int) -> tuple:
        params = self.doc.take.params.blobs
        return (id(self.doc.session), camera, frame, tuple(sorted(params.to_dict().items())))

    def get(self, camera: int, frame: int) -> dict[str, np.ndarray] | None:
        """The preview detections of a camera frame, or None (then computed in the background)."""
        if self._closed or not self.doc.has_take:
            return None
        key = self._key(camera, frame)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        if key not in self._pending:
            img = self.doc.image(camera, frame)
            if img is None:
                return None
            self._pending.add(key)
            params = self.doc.take.params.blobs
            fut = self._pool.submit(detect_blobs, img, params)
            fut.add_done_callback(lambda f, k=key: self._finished(k, f))
        return None

    def _finished(self, key: tuple, fut) -> None:  # type: ignore[no-untyped-def]  # worker thread
        try:
            table = fut.result()
        except Exception as exc:  # noqa: BLE001 - a preview failure must not break painting
            log.warning("blob preview of camera %d frame %d failed: %s", key[1], key[2], exc)
            table = {k: np.zeros(0) for k in ("x", "y", "major", "minor", "angle")}
        self._done.emit(key, table)

    def _store(self, key: tuple, table: dict[str, np.ndarray]) -> None:
        self._pending.discard(key)
        if self._closed:
            return
        self._cache[key] = table
        while len(self._cache) > self.max_items:
            self._cache.popitem(last=False)
        self.ready.emit(key[1], key[2])

    def clear(self) -> None:
        self._cache.clear()

    def shutdown(self) -> None:
        self._closed = True
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._cache.clear()
