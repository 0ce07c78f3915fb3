"""Time representations of a take: frame indices, burnt-in frame numbers and SMPTE timecode.

CaraPost counts time three ways (the reference guide's ``export_timecode.py`` converts between
them):

* the **frame index** ``f``: 0-based, ``0 .. n_frames - 1`` (what every array is indexed by);
* the **frame number** burnt into the video by the logger: ``first_frame_number + f``;
* the **timecode** ``"HH:MM:SS:FF"``: the take's start timecode plus ``f`` frames.

Timecode counts frames at the *nominal* rate (the frame rate rounded: 30 for 29.97). At
29.97 and 59.94 Hz the timecode is **drop-frame** by default (SMPTE 12M): the frame labels
``00`` and ``01`` (``00``-``03`` at 59.94) are skipped at the start of every minute except
minutes 0, 10, 20, ..., so the timecode keeps up with the wall clock; drop-frame timecode is
written with ``;`` before the frames (``"01:00:00;00"``). Other rates never drop frames.
A timecode runs modulo 24 hours.

This module is pure arithmetic (no files, no take) and is vectorised: every conversion accepts
a single value or an array / list of values and answers in kind.

Examples
--------
>>> tb = TimeBase(29.97, "00:59:59;28", first_frame_number=100)
>>> tb.frame_to_timecode([0, 1, 2])
['00:59:59;28', '00:59:59;29', '01:00:00;00']
>>> tb.timecode_to_frame("01:00:00;00")
2
>>> tb.frame_to_number(2)
102
>>> count_to_timecode(1800, 29.97)     # one minute of frames: labels ;00 and ;01 are skipped
'00:01:00;02'
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any, overload

import numpy as np

__all__ = [
    "TimecodeError",
    "TimeBase",
    "nominal_rate",
    "is_drop_frame_rate",
    "timecode_to_count",
    "count_to_timecode",
]

_TC = re.compile(r"^\s*(\d{1,2}):(\d{2}):(\d{2})([:;.,])(\d{2,3})\s*$")
_NTSC = (30000 / 1001, 60000 / 1001)


class TimecodeError(ValueError):
    """A timecode string or a frame rate is invalid; the message says which and why."""


def _check_rate(frame_rate: float) -> float:
    try:
        rate = float(frame_rate)
    except (TypeError, ValueError):
        raise TimecodeError(f"frame rate must be a number, got {frame_rate!r}") from None
    if not (math.isfinite(rate) and rate > 0):
        raise TimecodeError(f"frame rate must be a positive number, got {frame_rate!r}")
    return rate


def nominal_rate(frame_rate: float) -> int:
    """Frames per timecode second: the rate rounded to a whole number (29.97 -> 30).

    Raises
    ------
    TimecodeError
        If the rate is not a positive number.
    """
    return max(1, int(round(_check_rate(frame_rate))))


def is_drop_frame_rate(frame_rate: float) -> bool:
    """True for the NTSC rates 29.97 (30000/1001) and 59.94 (60000/1001) Hz (within 0.01 Hz)."""
    rate = _check_rate(frame_rate)
    return any(abs(rate - r) < 0.01 for r in _NTSC)


def _dropped(frame_rate: float, drop_frame: bool | None) -> int:
    """Frame labels skipped per minute (0 when not drop-frame)."""
    df = is_drop_frame_rate(frame_rate) if drop_frame is None else bool(drop_frame)
    if not df:
        return 0
    base = nominal_rate(frame_rate)
    if base % 30:
        raise TimecodeError(f"drop-frame timecode needs a 29.97 or 59.94 Hz take, not {frame_rate:g} Hz")
    return 2 * base // 30


def _day(frame_rate: float, drop: int) -> int:
    """Timecode frames in 24 hours."""
    base = nominal_rate(frame_rate)
    return 24 * 6 * (base * 600 - 9 * drop)


def timecode_to_count(timecode: str, frame_rate: float, *, drop_frame: bool | None = None) -> int:
    """Frames from ``00:00:00:00`` to ``timecode``.

    Parameters
    ----------
    timecode : str
        ``"HH:MM:SS:FF"``; ``;`` (or ``.``/``,``) before the frames is accepted either way.
    frame_rate : float
        Hz.
    drop_frame : bool, optional
        Default: drop-frame at 29.97 / 59.94 Hz.

    Raises
    ------
    TimecodeError
        Malformed timecode, a field out of range, or a label drop-frame timecode skips.
    """
    if not isinstance(timecode, str):
        raise TimecodeError(f"timecode must be text 'HH:MM:SS:FF', got {timecode!r}")
    m = _TC.match(timecode)
    if m is None:
        raise TimecodeError(f"timecode must look like 'HH:MM:SS:FF', got {timecode!r}")
    h, mi, s, ff = (int(m.group(i)) for i in (1, 2, 3, 5))
    base = nominal_rate(frame_rate)
    drop = _dropped(frame_rate, drop_frame)
    if h >= 24 or mi >= 60 or s >= 60 or ff >= base:
        raise TimecodeError(f"timecode {timecode!r} is out of range at {frame_rate:g} Hz "
                            f"(hours < 24, minutes and seconds < 60, frames < {base})")
    if drop and s == 0 and mi % 10 and ff < drop:
        raise TimecodeError(f"timecode {timecode!r} does not exist in drop-frame timecode: labels 00..{drop - 1:02d} "
                            "are skipped at the start of each minute not divisible by 10")
    minutes = 60 * h + mi
    return ((h * 60 + mi) * 60 + s) * base + ff - drop * (minutes - minutes // 10)


@overload
def count_to_timecode(count: int, frame_rate: float, *, drop_frame: bool | None = None) -> str: ...
@overload
def count_to_timecode(count: Sequence[int] | np.ndarray, frame_rate: float, *,
                      drop_frame: bool | None = None) -> list[str]: ...


def count_to_timecode(count: Any, frame_rate: float, *, drop_frame: bool | None = None) -> str | list[str]:
    """The timecode ``count`` frames after ``00:00:00:00`` (modulo 24 hours).

    Parameters
    ----------
    count : int or array of int
    frame_rate : float
        Hz.
    drop_frame : bool, optional
        Default: drop-frame at 29.97 / 59.94 Hz (written with ``;`` before the frames).

    Returns
    -------
    str, or list of str for an array input
    """
    base = nominal_rate(frame_rate)
    drop = _dropped(frame_rate, drop_frame)
    scalar = np.ndim(count) == 0
    n = np.mod(_as_int(count, "frame count"), _day(frame_rate, drop))
    if drop:
        per10 = base * 600 - 9 * drop
        per1 = base * 60 - drop
        tens, rem = np.divmod(n, per10)
        extra = np.where(rem > drop, (rem - drop) // per1, 0)
        n = n + drop * 9 * tens + drop * extra
    ff = n % base
    secs = n // base
    sep = ";" if drop else ":"
    out = [f"{h:02d}:{m:02d}:{s:02d}{sep}{f:02d}"
           for h, m, s, f in zip((secs // 3600).tolist(), (secs // 60 % 60).tolist(), (secs % 60).tolist(),
                                 ff.tolist())]
    return out[0] if scalar else out


def _as_int(values: Any, what: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(values))
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind == "f" and np.isfinite(arr).all() and (arr == np.round(arr)).all():
            return arr.astype(np.int64)
        raise TimecodeError(f"{what} must be whole numbers, got {values!r}")
    return arr.astype(np.int64)


class TimeBase:
    """Conversions between frame index, burnt-in frame number and timecode for one take.

    Parameters
    ----------
    frame_rate : float
        Hz, > 0.
    start_timecode : str
        Timecode of frame index 0 (``"HH:MM:SS:FF"``).
    first_frame_number : int
        Burnt-in frame number of frame index 0.
    drop_frame : bool, optional
        Default: drop-frame at 29.97 / 59.94 Hz.

    Raises
    ------
    TimecodeError
        Invalid rate or start timecode.

    Examples
    --------
    >>> tb = TimeBase(60.0, "10:00:00:00", first_frame_number=1000)
    >>> tb.frame_to_timecode(61), tb.frame_to_number(61), tb.number_to_frame(1061)
    ('10:00:01:01', 1061, 61)
    """

    def __init__(self, frame_rate: float, start_timecode: str = "00:00:00:00", first_frame_number: int = 0, *,
                 drop_frame: bool | None = None) -> None:
        self.frame_rate = _check_rate(frame_rate)
        self.drop_frame = is_drop_frame_rate(self.frame_rate) if drop_frame is None else bool(drop_frame)
        self._drop = _dropped(self.frame_rate, self.drop_frame)
        self._start = timecode_to_count(start_timecode, self.frame_rate, drop_frame=self.drop_frame)
        self.start_timecode = count_to_timecode(self._start, self.frame_rate, drop_frame=self.drop_frame)
        self.first_frame_number = int(first_frame_number)

    def __repr__(self) -> str:
        return (f"TimeBase({self.frame_rate:g}, {self.start_timecode!r}, first_frame_number={self.first_frame_number}"
                f"{', drop_frame=True' if self.drop_frame else ''})")

    @staticmethod
    def _out(arr: np.ndarray, scalar: bool) -> Any:
        return int(arr[0]) if scalar else arr

    # ------------------------------------------------------------------- frame numbers
    def frame_to_number(self, frame: Any) -> Any:
        """Burnt-in frame number(s) of frame index(es): ``first_frame_number + frame``."""
        return self._out(_as_int(frame, "frame index") + self.first_frame_number, np.ndim(frame) == 0)

    def number_to_frame(self, number: Any) -> Any:
        """Frame index(es) of burnt-in frame number(s) (may fall outside the take)."""
        return self._out(_as_int(number, "frame number") - self.first_frame_number, np.ndim(number) == 0)

    # ------------------------------------------------------------------------ timecode
    def frame_to_timecode(self, frame: Any) -> Any:
        """Timecode(s) of frame index(es): ``str`` for one frame, ``list[str]`` for several."""
        out = count_to_timecode(_as_int(frame, "frame index") + self._start, self.frame_rate,
                                drop_frame=self.drop_frame)
        return out[0] if np.ndim(frame) == 0 else out

    def timecode_to_frame(self, timecode: str | Sequence[str]) -> Any:
        """Frame index(es) of timecode(s); a take running past midnight is handled (the
        offset from the start is taken within half a day either way)."""
        scalar = isinstance(timecode, str)
        tcs = [timecode] if scalar else list(timecode)
        counts = np.array([timecode_to_count(tc, self.frame_rate, drop_frame=self.drop_frame) for tc in tcs],
                          np.int64)
        day = _day(self.frame_rate, self._drop)
        diff = np.mod(counts - self._start, day)
        diff = np.where(diff > day // 2, diff - day, diff)
        return self._out(diff, scalar)

    def number_to_timecode(self, number: Any) -> Any:
        """Timecode(s) of burnt-in frame number(s)."""
        return self.frame_to_timecode(self.number_to_frame(number))

    def timecode_to_number(self, timecode: str | Sequence[str]) -> Any:
        """Burnt-in frame number(s) of timecode(s)."""
        return self.frame_to_number(self.timecode_to_frame(timecode))

    def frame_to_seconds(self, frame: Any) -> Any:
        """Seconds from frame index 0 (real time: ``frame / frame_rate``)."""
        sec = np.asarray(frame, dtype=float) / self.frame_rate
        return float(sec) if np.ndim(frame) == 0 else sec
