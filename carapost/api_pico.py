"""Reading ``.pico`` camera files from scripts (the reference guide's PyPico).

A :class:`Pico` gives one camera file's capture metadata (logger name, description and unique
id, camera name and channel, frame rate, start timecode, image size, the blob parameters set at
capture) and random access to its frames as 8-bit grayscale arrays. :meth:`Pico.take_files`
lists the other cameras of the same take (``NAME_0.pico`` ... ``NAME_3.pico``).

Examples
--------
>>> import carapost.api as cp
>>> with cp.Pico("Example_0.pico") as pico:              # doctest: +SKIP
...     print(pico.camera_name, pico.n_frames, pico.frame_rate, pico.start_timecode)
...     first = pico.frame(0)                               # (height, width) uint8
...     for image in pico.frames(10, 20):                   # frames 10..20 inclusive
...         ...
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from carapost.io.pico import PicoError, PicoMetadata, PicoReader, take_files
from carapost.model.params import BlobParameters

from .core.timecode import TimeBase

__all__ = ["Pico", "PicoError"]


class Pico:
    """One ``.pico`` file: capture metadata and frames.

    Parameters
    ----------
    path : str or path-like
        A ``NAME_<channel>.pico`` file.

    Attributes
    ----------
    path : Path
    metadata : PicoMetadata
        Everything recorded at capture (a copy; editing it changes nothing on disk).
    n_frames, width, height : int
    frame_rate : float
        Hz.
    warnings : list of str
        Problems found while opening (a damaged file is recovered frame by frame).

    Raises
    ------
    PicoError
        (a ``ValueError``) The file is missing, not a ``.pico`` file, damaged beyond recovery
        or written by a newer major version; the message names the file.

    Examples
    --------
    >>> pico = Pico("Example_0.pico")                      # doctest: +SKIP
    >>> pico.logger_name, pico.channel, pico.blob_parameters()["Black Threshold"]  # doctest: +SKIP
    ('Logger1', 0, 0.4)
    >>> img = pico[5]                                       # doctest: +SKIP
    >>> pico.close()                                        # doctest: +SKIP
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self._reader = PicoReader(path)
        self.path = self._reader.path

    # ------------------------------------------------------------------------ metadata
    @property
    def metadata(self) -> PicoMetadata:
        """Everything recorded at capture (a copy: editing it changes nothing on disk)."""
        return self._reader.meta.copy()

    @property
    def n_frames(self) -> int:
        """Frames in the file."""
        return int(self._reader.n_frames)

    @property
    def width(self) -> int:
        """Image width, pixels."""
        return int(self._reader.width)

    @property
    def height(self) -> int:
        """Image height, pixels."""
        return int(self._reader.height)

    @property
    def frame_rate(self) -> float:
        """Frames per second."""
        return float(self._reader.frame_rate)

    @property
    def warnings(self) -> list[str]:
        """Problems found while opening (a damaged file is recovered frame by frame)."""
        return list(self._reader.warnings)

    @property
    def logger_name(self) -> str:
        """Name of the logger that recorded the file."""
        return self._reader.meta.logger_name

    @property
    def logger_description(self) -> str:
        """Description of the logger."""
        return self._reader.meta.logger_description

    @property
    def logger_id(self) -> str:
        """The logger's unique id."""
        return self._reader.meta.logger_id

    @property
    def camera_name(self) -> str:
        """Name of the camera (sensor)."""
        return self._reader.meta.camera_name

    @property
    def channel(self) -> int:
        """0-based camera channel."""
        return int(self._reader.meta.channel)

    @property
    def start_timecode(self) -> str:
        """SMPTE timecode of frame 0."""
        return self._reader.meta.start_timecode

    @property
    def rotation(self) -> int:
        """Display rotation, degrees clockwise (never changes pixel coordinates)."""
        return int(self._reader.meta.rotation)

    @property
    def time(self) -> TimeBase:
        """Frame index <-> timecode conversions for this file (see :class:`TimeBase`)."""
        return TimeBase(self.frame_rate, self.start_timecode)

    def blob_parameters(self) -> dict[str, Any]:
        """The Blob Parameters recorded at capture, by the guide's labels (``{}`` if none)."""
        raw = self._reader.meta.blob_parameters
        if not raw:
            return {}
        sec = BlobParameters.from_dict(raw)
        return {f.metadata["label"]: getattr(sec, f.name) for f in sec.fields()}

    def info(self) -> dict[str, Any]:
        """The metadata as a plain dict (file, frames, size, rate, names, timecode, blob parameters)."""
        m = self._reader.meta
        return {"file": str(self.path), "frames": self.n_frames, "width": self.width, "height": self.height,
                "frame_rate": self.frame_rate, "logger_name": m.logger_name,
                "logger_description": m.logger_description, "logger_id": m.logger_id,
                "camera_name": m.camera_name, "channel": int(m.channel), "start_timecode": m.start_timecode,
                "rotation": int(m.rotation), "codec": self._reader.codec, "blob_parameters": self.blob_parameters()}

    def take_files(self) -> list[Path]:
        """Every ``NAME_<n>.pico`` of this file's take, in channel order (``_10`` after ``_9``)."""
        return take_files(self.path)

    # -------------------------------------------------------------------------- frames
    def frame(self, index: int) -> np.ndarray:
        """Frame ``index`` (0-based) as a ``(height, width)`` uint8 array.

        Raises
        ------
        IndexError
            ``index`` outside ``0 .. n_frames - 1``.
        PicoError
            The frame is damaged.
        """
        return self._reader.read(index)

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[np.ndarray]:
        """Iterate over frames ``start .. end`` inclusive (default: to the last frame)."""
        if end is None and self.n_frames == 0:
            return
        stop = self.n_frames - 1 if end is None else int(end)
        if not 0 <= int(start) <= stop < self.n_frames:
            raise IndexError(f"{self.path}: frames {start}..{stop} outside 0..{self.n_frames - 1}")
        for i in range(int(start), stop + 1):
            yield self._reader.read(i)

    def verify(self) -> list[int]:
        """Check every frame's checksum; returns the indices of damaged frames."""
        return self._reader.verify()

    def __getitem__(self, index: int) -> np.ndarray:
        return self.frame(index)

    def __len__(self) -> int:
        return self.n_frames

    def __iter__(self) -> Iterator[np.ndarray]:
        return self.frames()

    # ------------------------------------------------------------------------- closing
    def close(self) -> None:
        """Close the file."""
        self._reader.close()

    def __enter__(self) -> "Pico":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"Pico({str(self.path)!r}, camera={self.camera_name!r}, channel={self.channel}, "
                f"frames={self.n_frames}, {self.width}x{self.height}, {self.frame_rate:g} Hz)")
