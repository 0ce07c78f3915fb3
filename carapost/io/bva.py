"""BVA export: Biovision segmented animation, one segment per point (seed 003's format).

Each point is a *segment* block, TAB-separated, one line per frame::

    Segment: Nose_Tip
    Frames: 300
    Frame Time: 0.016667
    XTRAN	YTRAN	ZTRAN	XROT	YROT	ZROT	XSCALE	YSCALE	ZSCALE
    INCHES	INCHES	INCHES	DEGREES	DEGREES	DEGREES	INCHES	INCHES	INCHES
    0.0225	0.57	10.0837	0	0	0	1	1	1
    ...

Translation is the point's position; rotation 0 and scale 1 (markers have neither). The BVA
convention is Y up, in inches (``units="in"``, default) or millimetres (``units="mm"``, unit
word ``MILLIMETERS``); the Export section's *Up Axis* ``Z`` rotates the data for Z-up packages
instead (seed 003's import-time choice, made at export). BVA has no missing values: a gap holds
the last position (leading gaps the first; never-seen points stay at 0). Seed 003's figure labels
the scale columns ``DEGREES``; the Biovision specification (and this writer) uses the length
unit, and BVA readers ignore it for scale.

2D mode (``camera=c``): the segments are one camera's 2D tracks in pixels, the way seed 003
used After Effects' tracker data: ``XTRAN = x``, ``YTRAN = H - y`` (image ``y`` points down,
3D ``y`` up: subtract the image height and negate, as the paper does), ``ZTRAN = 0``; unit word
``PIXELS``. Coordinates are raw pixels (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from carapost.model.params import ExportParameters
from carapost.model.take import Take

from .atomic import atomic_write_bytes
from .export import frame_range, hold_gaps, prepare_export, select_points, unique_names

__all__ = ["export_bva", "bva_text"]

_UNIT_WORD = {"in": "INCHES", "mm": "MILLIMETERS"}


def _block(name: str, frame_time: float, trans: np.ndarray, unit_word: str, decimals: int) -> str:
    N = trans.shape[0]
    lines = [f"Segment: {'_'.join(name.split()) or '_'}", f"Frames: {N}", f"Frame Time: {frame_time:.6f}",
             "\t".join(["XTRAN", "YTRAN", "ZTRAN", "XROT", "YROT", "ZROT", "XSCALE", "YSCALE", "ZSCALE"]),
             "\t".join([unit_word] * 3 + ["DEGREES"] * 3 + [unit_word] * 3)]
    fmt = f"%.{decimals}f\t%.{decimals}f\t%.{decimals}f\t0\t0\t0\t1\t1\t1\n"
    return "\n".join(lines) + "\n" + "".join(fmt % tuple(r) for r in trans.tolist())


def bva_text(take: Take, *, options: ExportParameters | None = None,
             selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
             points: np.ndarray | list[int] | None = None, units: str = "in", camera: int | None = None) -> str:
    """The BVA text of a take (see :func:`export_bva`)."""
    if camera is None:
        if units not in _UNIT_WORD:
            raise ValueError(f"BVA units must be 'in' or 'mm', got {units!r}")
        data = prepare_export(take, options=options, selection=selection, points=points, frames=frames,
                              units=units)
        xyz = hold_gaps(data.xyz, data.valid)
        dec = 6 if units == "in" else 4
        return "".join(_block(n, 1.0 / data.frame_rate, xyz[:, k], _UNIT_WORD[units], dec)
                       for k, n in enumerate(data.names))
    c = int(camera)
    if not 0 <= c < take.n_cameras:
        raise ValueError(f"camera must be in 0..{take.n_cameras - 1}, got {camera}")
    cam = take.cameras[c]
    H = int(cam.image_size[1]) or int(cam.intrinsics.sensor_size[1])
    if H <= 0:
        raise ValueError(f"camera {c} ({cam.name}): image height unknown, cannot flip y")
    idx = select_points(take, options=options, selection=selection, points=points)
    fr = frame_range(take, frames)
    xy = take.obs_xy[fr[0]:fr[-1] + 1][:, idx, c].astype(float)                 # (N, K, 2)
    trans = np.stack([xy[..., 0], H - xy[..., 1], np.zeros(xy.shape[:2])], axis=-1)
    valid = np.isfinite(xy).all(-1)
    trans = hold_gaps(np.where(valid[..., None], trans, np.nan), valid)
    names = unique_names([take.points.name(int(i)) for i in idx])
    return "".join(_block(n, 1.0 / take.frame_rate, trans[:, k], "PIXELS", 4) for k, n in enumerate(names))


def export_bva(take: Take, path: str | os.PathLike, *, options: ExportParameters | None = None,
               selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
               points: np.ndarray | list[int] | None = None, units: str = "in", camera: int | None = None) -> None:
    """Write a take's points as a BVA file (one segment per point), atomically.

    Parameters
    ----------
    take : Take
    path : path-like
    options : ExportParameters, optional
        Points, raw / stabilized data, up axis (default ``take.params.export``); the BVA unit
        is ``units``, not the options' units.
    selection, frames, points
        As :func:`carapost.io.export.prepare_export`.
    units : {"in", "mm"}
        Inches (the BVA convention) or millimetres.
    camera : int, optional
        Write this camera's 2D tracks instead (pixels, image ``y`` flipped).

    Raises
    ------
    ValueError
        Nothing to export, bad range, selection, units or camera (the message names the file).
    """
    path = Path(path)
    try:
        text = bva_text(take, options=options, selection=selection, frames=frames, points=points, units=units,
                        camera=camera)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    atomic_write_bytes(path, text.encode("utf-8"))
