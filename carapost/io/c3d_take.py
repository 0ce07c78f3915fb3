"""Open existing marker data (a C3D file from any system) as a take without video.

:func:`take_from_c3d` turns the 3D trajectories of a C3D file into a :class:`Take`, so gap
filling, labelling, stabilization and export work on data CaraPost did not track:

* every *marker* of the file becomes a face point labelled with its C3D label (model outputs
  listed in ``POINT:ANGLES``, ``FORCES``, ``MOMENTS``, ``POWERS``, ``SCALARS``, ``REACTIONS`` are
  left out); positions in millimetres, NaN where the file marks a sample invalid;
* ``recon`` is ``MULTI_VIEW`` wherever a sample is valid, except for files written by CaraPost,
  whose ``CARAPOST`` group restores the reconstruction types, point ids, kinds (face / brim) and
  brim dot indices; CaraPost's generated names (``Point_<id>``, ``Brim_<id>``) become unlabelled
  points again;
* the frame rate is kept, and the first frame: ``first_frame_number`` is the C3D first frame
  minus one (C3D counts from 1, CaraPost from 0), or the CaraPost frame number stored by
  CaraPost, so exporting the take to C3D again writes the same frame numbers;
* the take has no cameras and ``metadata["no_video"] = "1"``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from carapost.model.take import PointKind, Recon, Take

from .c3d import read_c3d

__all__ = ["take_from_c3d"]


def take_from_c3d(path: str | os.PathLike, *, reader: str = "carapost") -> Take:
    """A take holding the marker trajectories of a C3D file.

    Parameters
    ----------
    path : path-like
        Any C3D file (Vicon, Qualisys, Motion Analysis, CaraPost...).
    reader : str
        Passed to :func:`carapost.io.c3d.read_c3d`.

    Returns
    -------
    Take
        No cameras, ``n_frames`` = the file's frames, labelled points, ``xyz`` in mm
        (NaN gaps), ``recon`` as described in the module docstring, ``name`` = the file stem,
        ``metadata`` with the source path and ``no_video``.

    Raises
    ------
    C3DError
        The file cannot be read (see :func:`read_c3d`).
    ValueError
        The file has no frames, no markers or no frame rate (the message names the file).
    """
    path = Path(path)
    d = read_c3d(path, reader=reader)
    if d.n_frames < 1:
        raise ValueError(f"{path}: the C3D file holds no frames")
    if not d.frame_rate > 0:
        raise ValueError(f"{path}: the C3D file has no frame rate (POINT:RATE)")
    ours = d.point_ids is not None
    idx = np.arange(d.n_points) if ours else d.marker_indices()
    if idx.size == 0:
        raise ValueError(f"{path}: the C3D file holds no markers")
    take = Take.new([], d.n_frames, d.frame_rate, name=path.stem)
    kind = d.kind[idx] if ours and d.kind is not None else np.zeros(idx.size, np.uint8)
    labels = [d.labels[int(i)] for i in idx]
    if ours:
        ids = d.point_ids[idx].astype(np.int64)
        generated = [f"{'Brim' if k == PointKind.BRIM else 'Point'}_{int(i)}" for k, i in zip(kind, ids)]
        labels = ["" if lab == gen else lab for lab, gen in zip(labels, generated)]
    face = kind != PointKind.BRIM
    order = np.concatenate([np.flatnonzero(face), np.flatnonzero(~face)])  # add_points is per kind
    take.add_points(int(face.sum()), kind=PointKind.FACE, labels=[labels[k] for k in np.flatnonzero(face)])
    if (~face).any():
        bi = d.brim_index[idx][~face] if d.brim_index is not None else np.full(int((~face).sum()), -1)
        take.add_points(int((~face).sum()), kind=PointKind.BRIM, labels=[labels[k] for k in np.flatnonzero(~face)],
                        brim_index=np.asarray(bi, np.int32))
    src = idx[order]
    xyz = d.xyz[:, src]
    valid = np.isfinite(xyz).all(-1)
    take.xyz = np.where(valid[..., None], xyz, np.nan)
    if ours and d.recon is not None:
        take.recon = np.where(valid, d.recon[:, src], Recon.NONE).astype(np.uint8)
        take.recon[valid & (take.recon == Recon.NONE)] = Recon.MULTI_VIEW
    else:
        take.recon = np.where(valid, Recon.MULTI_VIEW, Recon.NONE).astype(np.uint8)
    if ours:
        take.points.ids = d.point_ids[src].astype(np.int64)
        take.next_point_id = int(take.points.ids.max()) + 1 if take.n_points else 0
        take.first_frame_number = int(d.first_frame_number if d.first_frame_number is not None
                                      else max(d.first_frame - 1, 0))
    else:
        take.first_frame_number = max(int(d.first_frame) - 1, 0)
    take.metadata.update({"source": str(path), "source_format": "c3d", "no_video": "1"})
    if d.stabilized:
        take.metadata["c3d_stabilized"] = "1"
    take.check()
    return take
