"""Shared pieces of the command implementations: opening inputs, parsing ranges."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from carapost.ops.session import Session

__all__ = ["open_session", "parse_frames", "parse_cameras"]


def open_session(inputs: Sequence[str], calibration: str | None = None) -> Session:
    """A ``.cara`` project, or camera sources (``.pico``/video/image folders) with a calibration.

    A single ``.pico`` stands for its whole take (``TAKE_0.pico`` ... ``TAKE_3.pico``).
    """
    if not inputs:
        raise ValueError("no input given")
    if len(inputs) == 1 and inputs[0].lower().endswith(".cara"):
        return Session.open(inputs[0])
    paths = list(inputs)
    if len(paths) == 1 and paths[0].lower().endswith(".pico"):
        from carapost.io.pico import take_files

        paths = [str(p) for p in take_files(paths[0])]
    name = Path(paths[0]).stem.rsplit("_", 1)[0]
    return Session.from_sources(paths, calibration, name=name)


def parse_frames(spec: str | None, n_frames: int) -> list[int]:
    """``"a:b"`` (inclusive), ``"a"``, or None for all frames."""
    if spec is None:
        return list(range(n_frames))
    try:
        if ":" in spec:
            a, b = spec.split(":", 1)
            lo = int(a) if a else 0
            hi = int(b) if b else n_frames - 1
        else:
            lo = hi = int(spec)
    except ValueError:
        raise ValueError(f"frames must be 'a:b' or a frame number, got {spec!r}") from None
    if not 0 <= lo <= hi < n_frames:
        raise ValueError(f"frames {spec} outside the take's 0..{n_frames - 1}")
    return list(range(lo, hi + 1))


def parse_cameras(spec: str | None, n_cameras: int) -> list[int] | None:
    """``"0,2"`` -> [0, 2]; None for all cameras."""
    if spec is None:
        return None
    try:
        cams = [int(x) for x in spec.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"cameras must be a comma-separated list of channels, got {spec!r}") from None
    bad = [c for c in cams if not 0 <= c < n_cameras]
    if bad:
        raise ValueError(f"camera(s) {bad} do not exist (the take has {n_cameras})")
    return cams
