"""Per-camera blob detections in CSR form.

A camera's detections for all frames live in flat arrays; ``frame_ptr[f]:frame_ptr[f + 1]``
is frame ``f``'s slice. A detection is addressed by ``(frame, index within the frame)`` —
the index stored in ``Take.obs_det`` — so replacing one frame's detections never renumbers
another frame's.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

__all__ = ["DETECTION_FIELDS", "Detections", "BLACK", "WHITE"]

BLACK = -1
WHITE = 1

#: Per-detection arrays and their dtypes. Coordinates are raw pixels; ``major``/``minor`` are
#: the ellipse semi-axes in pixels (``major`` is the guide's "radius": the longest axis);
#: ``angle`` is the major axis direction in radians from +x towards +y; ``polarity`` is
#: ``WHITE`` (1) or ``BLACK`` (-1); ``score`` is the detector's probability 0..1.
DETECTION_FIELDS: dict[str, type] = {
    "x": np.float32,
    "y": np.float32,
    "major": np.float32,
    "minor": np.float32,
    "angle": np.float32,
    "polarity": np.int8,
    "score": np.float32,
}


@dataclass
class Detections:
    """All detections of one camera.

    Attributes
    ----------
    frame_ptr : int64 array (F + 1,)
    x, y, major, minor, angle, score : float32 arrays (N,)
    polarity : int8 array (N,)
    detected : bool array (F,)
        Whether blob detection has run on the frame (an empty frame may still be detected).
    """

    frame_ptr: np.ndarray
    x: np.ndarray
    y: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    angle: np.ndarray
    polarity: np.ndarray
    score: np.ndarray
    detected: np.ndarray

    @classmethod
    def empty(cls, n_frames: int) -> "Detections":
        arrays = {k: np.zeros(0, dtype=dt) for k, dt in DETECTION_FIELDS.items()}
        return cls(frame_ptr=np.zeros(n_frames + 1, dtype=np.int64), detected=np.zeros(n_frames, bool),
                   **arrays)

    @classmethod
    def from_frames(cls, n_frames: int, frames: Mapping[int, Mapping[str, np.ndarray]]) -> "Detections":
        """Build from per-frame tables ``{frame: {"x": ..., "y": ..., ...}}``; other frames empty."""
        out = cls.empty(n_frames)
        return out.with_frames(frames)

    @property
    def n_frames(self) -> int:
        return len(self.frame_ptr) - 1

    def __len__(self) -> int:
        return int(self.frame_ptr[-1])

    def count(self, frame: int) -> int:
        return int(self.frame_ptr[frame + 1] - self.frame_ptr[frame])

    def counts(self) -> np.ndarray:
        """Detections per frame, (F,)."""
        return np.diff(self.frame_ptr)

    def frame(self, frame: int) -> dict[str, np.ndarray]:
        """Frame ``frame``'s detections as a dict of arrays (views, do not modify)."""
        a, b = self.frame_ptr[frame], self.frame_ptr[frame + 1]
        return {k: getattr(self, k)[a:b] for k in DETECTION_FIELDS}

    def xy(self, frame: int) -> np.ndarray:
        """Centres of frame ``frame``'s detections, (n, 2) float64 raw pixels."""
        a, b = self.frame_ptr[frame], self.frame_ptr[frame + 1]
        return np.stack([self.x[a:b], self.y[a:b]], axis=1).astype(float)

    def frame_of(self) -> np.ndarray:
        """Frame index of every detection, (N,)."""
        return np.repeat(np.arange(self.n_frames), self.counts())

    def with_frames(self, frames: Mapping[int, Mapping[str, np.ndarray]]) -> "Detections":
        """A new object with the given frames' detections replaced (and marked detected)."""
        if not frames:
            return self.copy()
        counts = self.counts().copy()
        for f, table in frames.items():
            if not 0 <= f < self.n_frames:
                raise IndexError(f"frame {f} outside 0..{self.n_frames - 1}")
            n = len(table["x"])
            for k in DETECTION_FIELDS:
                if len(table.get(k, table["x"])) != n:
                    raise ValueError(f"detection field {k!r} of frame {f} has the wrong length")
            counts[f] = n
        ptr = np.zeros(self.n_frames + 1, dtype=np.int64)
        np.cumsum(counts, out=ptr[1:])
        keep = np.ones(self.n_frames, bool)
        keep[list(frames)] = False
        old_frame = self.frame_of()
        old_sel = keep[old_frame]
        new_frame_of = np.repeat(np.arange(self.n_frames), counts)
        arrays = {}
        for k, dt in DETECTION_FIELDS.items():
            arr = np.empty(int(ptr[-1]), dtype=dt)
            arr[keep[new_frame_of]] = getattr(self, k)[old_sel]
            for f, table in frames.items():
                if k in table:
                    arr[ptr[f]:ptr[f + 1]] = np.asarray(table[k], dtype=dt)
                else:
                    arr[ptr[f]:ptr[f + 1]] = 0
            arrays[k] = arr
        detected = self.detected.copy()
        detected[list(frames)] = True
        return Detections(frame_ptr=ptr, detected=detected, **arrays)

    def select(self, keep: np.ndarray) -> tuple["Detections", np.ndarray]:
        """Keep the detections where ``keep (N,)`` is true.

        Returns the new detections and the map ``old index within frame -> new index within
        frame`` as a flat array (N,) (``-1`` for removed ones), for remapping ``obs_det``.
        """
        keep = np.asarray(keep, bool)
        frame_of = self.frame_of()
        counts = np.bincount(frame_of[keep], minlength=self.n_frames)
        ptr = np.zeros(self.n_frames + 1, dtype=np.int64)
        np.cumsum(counts, out=ptr[1:])
        csum = np.cumsum(keep) - 1  # new flat index of kept detections
        new_within = np.where(keep, csum - ptr[frame_of], -1)
        arrays = {k: getattr(self, k)[keep] for k in DETECTION_FIELDS}
        return Detections(frame_ptr=ptr, detected=self.detected.copy(), **arrays), new_within

    def copy(self) -> "Detections":
        return Detections(frame_ptr=self.frame_ptr.copy(), detected=self.detected.copy(),
                          **{k: getattr(self, k).copy() for k in DETECTION_FIELDS})

    def equals(self, other: "Detections") -> bool:
        return (np.array_equal(self.frame_ptr, other.frame_ptr)
                and np.array_equal(self.detected, other.detected)
                and all(np.array_equal(getattr(self, k), getattr(other, k)) for k in DETECTION_FIELDS))


def stack_tables(tables: Iterable[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate detection tables field by field."""
    tables = list(tables)
    return {k: np.concatenate([np.asarray(t[k], dtype=dt) for t in tables]) if tables else np.zeros(0, dt)
            for k, dt in DETECTION_FIELDS.items()}
