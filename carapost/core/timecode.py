"""Time conversions: zero-based frame index, burnt-in frame number and SMPTE timecode.

* **Frame index**: 0 for the take's first frame (what every array uses).
* **Burnt-in frame number**: the capture's own frame counter, ``first_frame_number + index``.
* **Timecode**: ``HH:MM:SS:FF`` (``;`` before the frames for drop-frame) counted from the take's
  start timecode at the nominal rate ``round(frame_rate)``. Rates of 29.97 and 59.94 use SMPTE
  drop-frame counting (frame numbers 0-1, or 0-3 at 59.94, are skipped at the start of every
  minute except every tenth), so that the timecode follows wall-clock time.
"""

from __future__ import annotations

import re

__all__ = ["Timecode", "parse_timecode", "format_timecode", "is_drop_frame"]

_TC = re.compile(r"^\s*(\d{1,2})[:.](\d{2})[:.](\d{2})([:;.])(\d{2,3})\s*$")


def is_drop_frame(frame_rate: float) -> bool:
    """Drop-frame counting applies to the NTSC rates 29.97 and 59.94."""
    return abs(frame_rate - 30000 / 1001) < 0.01 or abs(frame_rate - 60000 / 1001) < 0.01


def _nominal(frame_rate: float) -> int:
    if not frame_rate > 0:
        raise ValueError(f"frame rate must be positive, got {frame_rate}")
    return int(round(frame_rate))


def parse_timecode(text: str, frame_rate: float) -> int:
    """Frames since 00:00:00:00 for a timecode string at ``frame_rate``.

    Raises
    ------
    ValueError
        For a malformed timecode or a frame field beyond the rate.
    """
    m = _TC.match(text)
    if not m:
        raise ValueError(f"timecode must look like HH:MM:SS:FF, got {text!r}")
    hh, mm, ss, ff = int(m.group(1)), int(m.group(2)), int(m.group(3)), int(m.group(5))
    fps = _nominal(frame_rate)
    if mm > 59 or ss > 59 or ff >= fps:
        raise ValueError(f"timecode {text!r} is out of range at {frame_rate:g} fps")
    total = ((hh * 60 + mm) * 60 + ss) * fps + ff
    if is_drop_frame(frame_rate):
        drop = 2 * fps // 30
        minutes = hh * 60 + mm
        total -= drop * (minutes - minutes // 10)
    return total


def format_timecode(frames: int, frame_rate: float) -> str:
    """Timecode string for ``frames`` since 00:00:00:00 (wraps at 24 hours)."""
    fps = _nominal(frame_rate)
    sep = ":"
    if is_drop_frame(frame_rate):
        sep = ";"
        drop = 2 * fps // 30
        per_10min = fps * 600 - drop * 9
        per_min = fps * 60 - drop
        d, m = divmod(frames, per_10min)
        frames += drop * 9 * d + (drop * ((m - drop) // per_min) if m > drop else 0)
    frames %= fps * 86400
    ff = frames % fps
    s = frames // fps
    return f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}{sep}{ff:02d}"


class Timecode:
    """Conversions for one take: its frame rate, start timecode and first burnt-in frame number.

    >>> tc = Timecode(60.0, "10:00:00:00", first_frame_number=1000)
    >>> tc.to_timecode(61)
    '10:00:01:01'
    >>> tc.to_frame_number(61), tc.from_frame_number(1061), tc.from_timecode("10:00:01:01")
    (1061, 61, 61)
    """

    def __init__(self, frame_rate: float, start_timecode: str = "00:00:00:00", first_frame_number: int = 0) -> None:
        self.frame_rate = float(frame_rate)
        self.start = parse_timecode(start_timecode, frame_rate)
        self.first_frame_number = int(first_frame_number)

    def to_timecode(self, index: int) -> str:
        return format_timecode(self.start + int(index), self.frame_rate)

    def from_timecode(self, text: str) -> int:
        return parse_timecode(text, self.frame_rate) - self.start

    def to_frame_number(self, index: int) -> int:
        return self.first_frame_number + int(index)

    def from_frame_number(self, number: int) -> int:
        return int(number) - self.first_frame_number

    def to_seconds(self, index: int) -> float:
        return int(index) / self.frame_rate
