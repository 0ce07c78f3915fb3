"""Convert camera sources (video files, image folders, other ``.pico`` files) to a ``.pico`` take."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from carapost.io.pico import PicoMetadata, PicoWriter
from carapost.io.sources import FrameSource, OffsetSource, open_source

__all__ = ["convert_to_pico"]


def convert_to_pico(sources: Sequence[str | os.PathLike | FrameSource], out_dir: str | os.PathLike,
                    take_name: str, *, codec: str = "jpeg", quality: int = 92,
                    frame_offsets: Sequence[int] | None = None, max_frames: int | None = None,
                    metadata: dict[str, Any] | None = None,
                    progress: Callable[[int, int], object] | None = None,
                    cancel: Callable[[], bool] | None = None) -> list[Path]:
    """Write one ``<take_name>_<c>.pico`` per source (channel ``c`` = position in ``sources``).

    Take frame ``f`` of camera ``c`` is source frame ``f + frame_offsets[c]`` (as
    :class:`~carapost.io.sources.OffsetSource`). The take has the frames every camera covers
    from take frame 0: ``N = min_c(n_frames_c - offset_c)``, capped at ``max_frames``; a
    negative offset gives black leading frames for that camera.

    Parameters
    ----------
    sources : sequence of path or FrameSource
        Video files, image folders or ``.pico`` files (paths are opened and closed here;
        sources passed open are left open).
    out_dir : path
        Output folder (created if missing).
    take_name : str
        File name prefix, e.g. ``"ROM"`` -> ``ROM_0.pico``, ``ROM_1.pico``, ...
    codec, quality
        As :class:`~carapost.io.pico.PicoWriter`.
    frame_offsets : sequence of int, optional
        Per-camera frame offsets (default all 0).
    max_frames : int, optional
        Convert at most this many take frames.
    metadata : dict, optional
        :class:`~carapost.io.pico.PicoMetadata` fields applied to every camera (e.g.
        ``logger_name``, ``start_timecode``, ``blob_parameters``).
    progress : callable(done, total), optional
        Called after every frame; ``total`` counts frames over all cameras.
    cancel : callable() -> bool, optional
        Polled before every frame; when it returns True the file being written is discarded
        (nothing half-written is left) and the files already finished are kept.

    Returns
    -------
    list of Path
        The finished files, in channel order (shorter than ``sources`` if cancelled).

    Raises
    ------
    ValueError
        Bad arguments, unreadable sources (the message names the file), or no common frames.
    """
    if not sources:
        raise ValueError("convert_to_pico: no sources given")
    if not take_name or any(ch in take_name for ch in "/\\:") or take_name != take_name.strip():
        raise ValueError(f"convert_to_pico: invalid take name {take_name!r}")
    offsets = [0] * len(sources) if frame_offsets is None else [int(o) for o in frame_offsets]
    if len(offsets) != len(sources):
        raise ValueError(f"convert_to_pico: {len(offsets)} frame offsets for {len(sources)} sources")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"convert_to_pico: max_frames must be >= 1, got {max_frames!r}")
    overrides = dict(metadata or {})
    bad = set(overrides) - set(PicoMetadata.__dataclass_fields__) | ({"channel", "width", "height"} & set(overrides))
    if bad:
        raise ValueError(f"convert_to_pico: metadata cannot set {', '.join(sorted(bad))}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    opened: list[FrameSource] = []
    srcs: list[FrameSource] = []
    try:
        for s in sources:
            if isinstance(s, (str, os.PathLike)):
                src = open_source(s)
                opened.append(src)
            else:
                src = s
            srcs.append(src)
        n = min(src.n_frames - off for src, off in zip(srcs, offsets))
        if max_frames is not None:
            n = min(n, max_frames)
        if n < 1:
            raise ValueError("convert_to_pico: with these frame offsets the sources share no frames")
        total, done = n * len(srcs), 0
        written: list[Path] = []
        for channel, (src, off) in enumerate(zip(srcs, offsets)):
            meta = _camera_meta(src, channel, off, overrides)
            view = OffsetSource(src, off, rotation=0, n_frames=n)
            path = out / f"{take_name}_{channel}.pico"
            writer = PicoWriter(path, meta, codec=codec, quality=quality)
            try:
                for f in range(n):
                    if cancel is not None and cancel():
                        writer.abort()
                        return written
                    writer.write(view.read(f))
                    done += 1
                    if progress is not None:
                        progress(done, total)
                writer.close()
            except BaseException:
                writer.abort()
                raise
            written.append(path)
        return written
    finally:
        for src in opened:
            src.close()


def _camera_meta(src: FrameSource, channel: int, offset: int, overrides: dict[str, Any]) -> PicoMetadata:
    d = src.meta.to_dict()
    d.update(overrides)
    d.update(channel=channel, width=src.width, height=src.height)
    d.setdefault("frame_rate", src.frame_rate)
    extra = dict(d.get("extra") or {})
    extra.update(source_path=str(src.path), source_kind=src.kind, source_offset=offset)
    d["extra"] = extra
    return PicoMetadata.from_dict(d)
