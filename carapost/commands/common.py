"""Shared pieces of the command implementations: opening inputs, parsing ranges, checking outputs."""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from carapost.ops.session import Session
from carapost.ops.settings import parse_caddies

__all__ = ["open_session", "parse_frames", "parse_cameras", "parse_settings", "parse_caddies", "interrupt_cancels",
           "check_outputs", "add_settings_arguments"]


@contextmanager
def interrupt_cancels(what: str) -> Iterator[Callable[[], bool]]:
    """Within the block, the first Ctrl+C asks the running operation to stop (it keeps the frames
    it finished, and the command saves them); a second one interrupts at once.

    Yields the ``cancel()`` callable the operations poll."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    asked = threading.Event()

    def handler(signum, frame):  # type: ignore[no-untyped-def]
        if asked.is_set():
            raise KeyboardInterrupt
        asked.set()
        print(f"\n{what}: stopping after the current frame (Ctrl+C again to abort without saving)",
              file=sys.stderr)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield asked.is_set
    finally:
        signal.signal(signal.SIGINT, previous)


def open_session(inputs: Sequence[str], calibration: str | None = None) -> Session:
    """A ``.cara`` project, or camera sources (``.pico``/video/image folders) with a calibration.

    A single ``.pico`` stands for its whole take (``TAKE_0.pico`` ... ``TAKE_3.pico``).
    """
    if not inputs:
        raise ValueError("no input given")
    if len(inputs) == 1 and inputs[0].lower().endswith(".cara"):
        return Session.open(inputs[0])
    from carapost.io.pico import find_calibration, take_files, take_name

    paths = list(inputs)
    if len(paths) == 1 and paths[0].lower().endswith(".pico"):
        paths = [str(p) for p in take_files(paths[0])]
        if calibration is None:
            found = find_calibration(paths[0])
            calibration = str(found) if found is not None else None
    return Session.from_sources(paths, calibration, name=take_name(paths[0]))


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


def check_outputs(*paths: str | os.PathLike | None) -> None:
    """Fail before the work, not after it: each given output file's folder must exist and be
    writable, and the file must not be a folder (None entries are skipped).

    Raises
    ------
    ValueError
        Naming the first output that cannot be written and why.
    """
    for p in paths:
        if p is None:
            continue
        path = Path(p)
        folder = path.parent if str(path.parent) else Path(".")
        if path.is_dir():
            raise ValueError(f"{path}: cannot write: it is a folder")
        if not folder.is_dir():
            raise ValueError(f"{path}: cannot write: folder {folder} does not exist")
        if not os.access(folder, os.W_OK):
            raise ValueError(f"{path}: cannot write: folder {folder} is not writable")


def parse_settings(items: Sequence[str] | None) -> list[tuple[str, str, str]]:
    """``["blobs.white_threshold=0.05", "Blob Parameters.Find White Blobs=true"]`` ->
    ``[(group, property, value), ...]`` (checked against the take when applied)."""
    out = []
    for item in items or ():
        key, sep, value = item.partition("=")
        group, dot, name = key.rpartition(".")
        if not sep or not dot or not group.strip() or not name.strip():
            raise ValueError(f"--set wants GROUP.PROPERTY=VALUE (e.g. blobs.white_threshold=0.05), got {item!r}")
        out.append((group.strip(), name.strip(), value.strip()))
    return out


def add_settings_arguments(p: Any, *, caddies: bool = True) -> None:
    """``--preset``, ``--set GROUP.PROPERTY=VALUE`` and (with ``caddies``) ``--caddies`` on
    parser ``p`` (read back with :func:`parse_settings` and :func:`parse_caddies`)."""
    from carapost.model.params import PRESETS

    p.add_argument("--preset", choices=tuple(PRESETS),
                   help="the guide's parameter set for the marker density (dense: 156 markers, sparse: 35)")
    p.add_argument("--set", action="append", metavar="GROUP.PROPERTY=VALUE",
                   help="set a property as in the Properties pane, after --preset; repeatable, e.g. "
                        "--set blobs.find_white_blobs=true --set \"blobs.White Threshold=0.05\"")
    if not caddies:
        return
    p.add_argument("--caddies", metavar="PAIRS",
                   help="camera pairs on one side of the head rig, e.g. 0-1,2-3 (the default for four "
                        "cameras), or none for cameras standing around a room")
