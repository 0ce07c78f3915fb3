"""BVH export: every point as an animated root joint (Biovision hierarchy format).

BVH has no notion of a free marker, so each exported point is its own one-joint hierarchy::

    HIERARCHY
    ROOT Nose_Tip
    {
    	OFFSET 0.000000 0.000000 0.000000
    	CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
    	End Site
    	{
    		OFFSET 0.000000 0.000000 0.000000
    	}
    }
    ROOT Chin
    ...
    MOTION
    Frames: 300
    Frame Time: 0.0166666667
    <one line per frame: 6 numbers per point, in ROOT order>

The root's position channels carry the point's position (Export section: axes, units, raw /
stabilized, points); the rotation channels are zero (they are there because every BVH
reader expects a root to have six channels, as in all real BVH files). BVH cannot leave a
value out, so a gap holds the point's last position (leading gaps its first one; a point
never reconstructed stays at the origin). Export to C3D, FBX, TRC or CSV to keep the gaps.
Names are the point names with white space replaced by ``_``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from carapost.model.params import ExportParameters
from carapost.model.take import Take

from .atomic import atomic_write_bytes
from .export import hold_gaps, prepare_export

__all__ = ["export_bvh", "bvh_text"]

_DECIMALS = {"mm": 6, "cm": 7, "m": 9, "in": 8}


def bvh_text(take: Take, *, options: ExportParameters | None = None,
             selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
             points: np.ndarray | list[int] | None = None, rotation_channels: bool = True) -> str:
    """The BVH text of a take (see :func:`export_bvh`)."""
    data = prepare_export(take, options=options, selection=selection, points=points, frames=frames)
    N, K = data.n_frames, data.n_points
    chans = ("CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation" if rotation_channels
             else "CHANNELS 3 Xposition Yposition Zposition")
    zero = "OFFSET 0.000000 0.000000 0.000000"
    out = ["HIERARCHY"]
    for name in data.names:
        out += [f"ROOT {'_'.join(name.split()) or '_'}", "{", f"\t{zero}", f"\t{chans}", "\tEnd Site", "\t{",
                f"\t\t{zero}", "\t}", "}"]
    out += ["MOTION", f"Frames: {N}", f"Frame Time: {1.0 / data.frame_rate:.10f}"]
    xyz = hold_gaps(data.xyz, data.valid)                                       # (N, K, 3)
    per = np.concatenate([xyz, np.zeros((N, K, 3))], axis=2) if rotation_channels else xyz
    dec = _DECIMALS[data.units]
    fmt = " ".join([f"%.{dec}f"] * per.shape[1] * per.shape[2]) + "\n"
    body = "".join(fmt % tuple(row) for row in per.reshape(N, -1).tolist())
    return "\n".join(out) + "\n" + body


def export_bvh(take: Take, path: str | os.PathLike, *, options: ExportParameters | None = None,
               selection: np.ndarray | list[int] | None = None, frames: tuple[int, int] | None = None,
               points: np.ndarray | list[int] | None = None, rotation_channels: bool = True) -> None:
    """Write a take's points as a BVH file (one animated root joint per point), atomically.

    Parameters
    ----------
    take : Take
    path : path-like
    options : ExportParameters, optional
        Points, raw / stabilized data, up axis, units (default ``take.params.export``).
    selection, frames, points
        As :func:`carapost.io.export.prepare_export`.
    rotation_channels : bool
        Give each root the usual six channels (zero rotations); ``False`` writes only the three
        position channels.

    Raises
    ------
    ValueError
        Nothing to export, bad range or selection (the message names the file).
    """
    path = Path(path)
    try:
        text = bvh_text(take, options=options, selection=selection, frames=frames, points=points,
                        rotation_channels=rotation_channels)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    atomic_write_bytes(path, text.encode("utf-8"))
