"""The Process menu's ROM commands: Load ROM, Initialize from ROM, Initialize from ROM [Brim Only].

*Load ROM* reads and checks a solved ``.cara`` take (normally a range-of-motion take of the same
actor, marker set and camera rig) and remembers its path in the take. *Initialize from ROM*
finds the ROM frame's points in the current frame (:func:`carapost.core.rom_init.match_rom_frame`,
the tracker with the *Initialize From ROM Parameters*) and carries everything over as one
undoable change: the cameras' calibration (intrinsics from the ROM, poses re-estimated from the
brim), the brim model and brim points, the face points (a new set, as the guide says: running it
twice gives two sets), their labels and the sticks between them. The current frame's blobs are
detected first when they have not been. *[Brim Only]* carries the calibration and the brim.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from carapost.core.rom_init import RomMatch, check_rom, match_rom_frame
from carapost.model.take import POINT_ARRAYS, PointKind, Take

from .change import (ArrayPatch, AttributeChange, Change, Composite, DetectionFramesChange, PointsAdded,
                     PointsRemoved)

__all__ = ["read_rom", "load_rom", "initialize_from_rom", "initialize_from_rom_brim_only"]

ImageFn = Callable[[int, int], np.ndarray]   # (camera, frame) -> uint8 (H, W)


def read_rom(path: str | os.PathLike, *, n_cameras: int | None = None) -> Take:
    """Read a ROM ``.cara`` file and check it can initialize a take.

    Parameters
    ----------
    path : str or PathLike
    n_cameras : int, optional
        The take's camera count (the ROM must have as many).

    Returns
    -------
    Take
        The ROM take.

    Raises
    ------
    ValueError
        The file cannot be read as a ``.cara`` project, or the take in it has no cameras, no
        brim, no solved frame with brim points, or a different number of cameras. The message
        names the file.
    """
    from carapost.io.cara import load_take

    try:
        rom = load_take(path).take
    except (ValueError, OSError) as exc:  # CaraError is a ValueError: one message naming the file
        msg = str(exc)
        raise ValueError(msg if str(path) in msg else f"{path}: {msg}") from None
    if n_cameras is not None and rom.n_cameras != n_cameras:
        raise ValueError(f"{path}: the ROM take has {rom.n_cameras} cameras but the take has {n_cameras}: "
                         f"a ROM must come from the same camera rig")
    if not _solved_frames(rom):
        try:
            check_rom(rom, 0, name=str(path))
        except ValueError as exc:
            raise ValueError(f"not a usable ROM: {exc}") from None
        raise ValueError(f"{path}: not a usable ROM: no frame has both camera poses and brim points")
    return rom


def _solved_frames(rom: Take) -> list[int]:
    """Frames of ``rom`` that :func:`check_rom` accepts."""
    if rom.n_cameras == 0 or rom.brim is None or len(rom.brim_points()) == 0:
        return []
    poses = np.isfinite(rom.R).all((2, 3)).any(1) & np.isfinite(rom.t).all(2).any(1)
    brim = np.isfinite(rom.xyz[:, rom.brim_points()]).all(-1).any(1)
    return np.flatnonzero(poses & brim).tolist()


def load_rom(take: Take, path: str | os.PathLike, *, rom: Take | None = None) -> AttributeChange:
    """"Load ROM": remember the ROM take used by Initialize from ROM.

    Parameters
    ----------
    take : Take
        Not modified: apply the returned change.
    path : str or PathLike
        The ROM ``.cara`` file.
    rom : Take, optional
        The ROM already read by :func:`read_rom` (e.g. in a worker thread); read otherwise.

    Returns
    -------
    AttributeChange
        Sets ``take.rom_path`` (undoable).

    Raises
    ------
    ValueError
        The file is not a usable ROM for this take (see :func:`read_rom`).
    """
    if rom is None:
        read_rom(path, n_cameras=take.n_cameras)
    elif rom.n_cameras != take.n_cameras:
        raise ValueError(f"{path}: the ROM take has {rom.n_cameras} cameras but the take has {take.n_cameras}")
    path = os.path.abspath(os.fspath(path))
    return AttributeChange.capture(take, "rom_path", path, f"Load ROM {os.path.basename(path)}")


def initialize_from_rom(take: Take, image: ImageFn | None, frame: int, *, brim_only: bool = False,
                        rom: Take | None = None, rom_image: ImageFn | None = None) -> Composite:
    """"Initialize from ROM" (``brim_only``: "Initialize from ROM [Brim Only]") in ``frame``.

    Parameters
    ----------
    take : Take
        Not modified: apply the returned change.
    image : callable ``(camera, frame) -> uint8 (H, W)`` or None
        The take's video: used to detect the frame's blobs if they have not been detected
        (with the Blob Parameters) and, with ``rom_image``, for appearance checks.
    frame : int
        The frame to initialize (the current frame).
    brim_only : bool
        Carry only the calibration and the brim.
    rom : Take, optional
        The ROM take (default: read from ``take.rom_path``, set by :func:`load_rom`).
    rom_image : callable, optional
        The ROM take's video.

    Returns
    -------
    Composite
        One history entry whose text counts the points found. The match report (found and
        not-found points) is in its ``report`` attribute.

    Raises
    ------
    ValueError
        No ROM loaded, the ROM is unusable (no poses or brim in the ROM Frame Index, another
        camera rig), the frame is outside the take, or the frame has no detections and no
        video to detect them in.
    """
    what = "Initialize from ROM [Brim Only]" if brim_only else "Initialize from ROM"
    if not 0 <= frame < take.n_frames:
        raise ValueError(f"{what}: frame {frame} is outside the take (0..{take.n_frames - 1})")
    if rom is None:
        if not take.rom_path:
            raise ValueError(f"{what}: no ROM take has been loaded: use Process > Load ROM first")
        rom = read_rom(take.rom_path, n_cameras=take.n_cameras)
    if rom.n_cameras != take.n_cameras:
        raise ValueError(f"{what}: the ROM take has {rom.n_cameras} cameras but the take has {take.n_cameras}")
    rom_frame = int(take.params.rom.rom_frame_index)
    check_rom(rom, rom_frame, name=f"the ROM take {os.path.basename(take.rom_path) or rom.name}".rstrip())
    changes: list[Change] = []
    tables = []
    for c in range(take.n_cameras):
        det = take.detections[c]
        if det.detected[frame] or det.count(frame) > 0:
            tables.append(det.frame(frame))
            continue
        if image is None:
            raise ValueError(f"{what}: frame {frame} has no blob detections in camera {c} and there is no video "
                             f"to detect them in: Detect Blobs [Current Frame] first")
        from carapost.core.blobs import detect_blobs

        tb = {k: np.asarray(v) for k, v in detect_blobs(image(c, frame), take.params.blobs).items()}
        changes.append(DetectionFramesChange.capture(take, c, {frame: tb}))
        tables.append(tb)
    new_image = (lambda c, _f: image(c, frame)) if image is not None else None
    sizes = [cam.image_size for cam in take.cameras]
    match = match_rom_frame(rom, rom_frame, tables, brim_only=brim_only, tracking=take.params.tracking,
                            rom_params=take.params.rom, image=new_image, rom_image=rom_image, image_size=sizes)
    changes += _carry_over(take, rom, frame, match)
    r = match.report
    text = f"{what}: {r['found_brim']} of {r['brim']} brim points"
    if not brim_only:
        text += f", {r['found_face']} of {r['face']} face points"
    text += f" found (ROM frame {rom_frame})"
    out = Composite(changes, text)
    out.report = r  # type: ignore[attr-defined]
    return out


def initialize_from_rom_brim_only(take: Take, image: ImageFn | None, frame: int, **kw) -> Composite:
    """"Initialize from ROM [Brim Only]"."""
    return initialize_from_rom(take, image, frame, brim_only=True, **kw)


def _carry_over(take: Take, rom: Take, frame: int, match: RomMatch) -> list[Change]:
    """The changes writing ``match`` into ``take``: calibration, brim, points, labels, sticks."""
    F, C = take.n_frames, take.n_cameras
    changes: list[Change] = []
    # Cameras: the ROM's intrinsics; the frame's poses as re-estimated, and the same poses in
    # every frame that holds no 3D data yet (the world is now the ROM's brim frame).
    for c in range(C):
        if take.cameras[c].intrinsics != rom.cameras[c].intrinsics:
            changes.append(AttributeChange.capture(take, f"cameras.{c}.intrinsics", rom.cameras[c].intrinsics))
    has_data = np.isfinite(take.xyz).all(-1).any(1) if take.n_points else np.zeros(F, bool)
    frames = np.flatnonzero(~has_data | (np.arange(F) == frame))
    changes.append(ArrayPatch.capture(take, "R", (frames,), np.broadcast_to(match.R, (len(frames), C, 3, 3))))
    changes.append(ArrayPatch.capture(take, "t", (frames,), np.broadcast_to(match.t, (len(frames), C, 3))))
    # Brim: the ROM's model replaces the take's (and its brim points, which would compete).
    old_brim = take.brim_points()
    if len(old_brim):
        changes.append(PointsRemoved(old_brim))
    changes.append(AttributeChange.capture(take, "brim", rom.brim))
    # Points: the ROM's, in ROM order, face points first then brim points.
    cols = match.rom_points
    kinds = rom.points.kind[cols]
    first = take.next_point_id
    new_ids = np.full(rom.n_points, -1, np.int64)
    for kind in (PointKind.FACE, PointKind.BRIM):
        sel = np.flatnonzero(kinds == kind)
        if not len(sel):
            continue
        rc = cols[sel]
        arrays = _point_arrays(F, C, len(sel), frame, match, sel)
        if kind == PointKind.BRIM:
            # brim points sit at their model position in every frame (as after a brim solve)
            arrays["xyz"][:] = rom.brim.xyz[rom.points.brim_index[rc]][None]   # type: ignore[union-attr]
        labels = [rom.points.labels[i] for i in rc]
        changes.append(PointsAdded(len(sel), int(kind), labels, rom.points.brim_index[rc].copy(), arrays,
                                   first_id=first))
        new_ids[rc] = np.arange(first, first + len(sel))
        first += len(sel)
    # Labels and sticks of the points carried over.
    names = list(take.labels) + [lab for lab in dict.fromkeys(list(rom.labels) + rom.points.labels)
                                 if lab and lab not in take.labels]
    if names != take.labels:
        changes.append(AttributeChange.capture(take, "labels", names))
    if len(rom.sticks):
        # sticks hold point ids: ROM id -> ROM column -> the new point's id (-1: not carried)
        order = np.argsort(rom.points.ids)
        pos = np.clip(np.searchsorted(rom.points.ids[order], rom.sticks), 0, max(rom.n_points - 1, 0))
        col = order[pos]
        ends = np.where(rom.points.ids[col] == rom.sticks, new_ids[col], -1)
        keep = (ends >= 0).all(1)
        if keep.any():
            changes.append(AttributeChange.capture(take, "sticks", np.concatenate([take.sticks, ends[keep]])))
            changes.append(AttributeChange.capture(
                take, "stick_colours", np.concatenate([take.stick_colours, rom.stick_colours[keep]])))
    return changes


def _point_arrays(F: int, C: int, n: int, frame: int, match: RomMatch, sel: np.ndarray) -> dict[str, np.ndarray]:
    """Full ``(F, n, ...)`` arrays of new points, holding ``match``'s rows ``sel`` at ``frame``."""
    out = {}
    for name, (trail, dtype, fill) in POINT_ARRAYS.items():
        shape = (F, n) + tuple(C if d == "C" else d for d in trail)
        out[name] = np.full(shape, fill, dtype=dtype)
    for name in ("xyz", "recon", "obs_xy", "obs_det", "obs_src", "obs_q"):
        out[name][frame] = getattr(match, name)[sel]
    return out

