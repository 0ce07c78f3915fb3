"""Write a :class:`~carapost.model.take.Take` into an open HDF5 file (schema ``CARA_VERSION``).

Only :func:`carapost.io.cara.save_take` should call this: it handles the atomic replace.
The layout is documented in ``docs/formats/cara.md``.
"""

from __future__ import annotations

import json
import os
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from carapost import __version__
from carapost.model.detections import DETECTION_FIELDS, Detections
from carapost.model.params import Parameters
from carapost.model.take import POINT_ARRAYS, CameraInfo, Take

from .cara_schema import CARA_VERSION, FORMAT, STR_DTYPE, dataset_kwargs

__all__ = ["write_take", "source_paths"]


def write_take(f: h5py.File, take: Take, cara_dir: Path) -> None:
    """Write every part of ``take`` into the empty file ``f``.

    Parameters
    ----------
    f : h5py.File
        Open for writing, empty.
    take : Take
        Checked by the caller (:meth:`Take.check`); not modified.
    cara_dir : Path
        Absolute folder of the final ``.cara`` file, for the sources' relative paths.
    """
    f.attrs["format"] = FORMAT
    f.attrs["version_major"] = np.int64(CARA_VERSION[0])
    f.attrs["version_minor"] = np.int64(CARA_VERSION[1])
    f.attrs["writer"] = f"carapost {__version__}"
    f.attrs["saved_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    _write_take_group(f.create_group("take"), take)
    cams = f.create_group("cameras")
    cams.attrs["count"] = np.int64(take.n_cameras)
    for c, cam in enumerate(take.cameras):
        _write_camera(cams.create_group(str(c)), cam, cara_dir)
    poses = f.create_group("poses")
    _array(poses, "R", take.R, np.float64, per_frame=True)
    _array(poses, "t", take.t, np.float64, per_frame=True)
    _write_points(f.create_group("points"), take)
    tracks = f.create_group("tracks")
    for name, (_, dtype, _) in POINT_ARRAYS.items():
        _array(tracks, name, getattr(take, name), dtype, per_frame=True)
    dets = f.create_group("detections")
    for c, det in enumerate(take.detections):
        _write_detections(dets.create_group(str(c)), det)
    kf = take.keyframes
    g = f.create_group("keyframes")
    _array(g, "frame", kf.frame, np.int32)
    _array(g, "point_id", kf.point_id, np.int64)
    _array(g, "camera", kf.camera, np.int16)
    _array(g, "xy", kf.xy, np.float32)
    _array(g, "pattern", kf.pattern, np.float32)
    _array(g, "search", kf.search, np.float32)
    _strings(f, "labels", take.labels)
    g = f.create_group("sticks")
    _array(g, "pairs", np.asarray(take.sticks).reshape(-1, 2), np.int64)
    _array(g, "colours", np.asarray(take.stick_colours).reshape(-1, 3), np.uint8)
    if take.brim is not None:
        g = f.create_group("brim")
        g.attrs["name"] = take.brim.name
        _array(g, "xyz", take.brim.xyz, np.float64)
        _array(g, "radius", take.brim.radius, np.float64)
        _array(g, "polarity", take.brim.polarity, np.int8)
        g.create_dataset("svg", data=take.brim.svg, dtype=STR_DTYPE)
    _write_params(f.create_group("params"), take.params)


def source_paths(path: str, cara_dir: Path) -> tuple[str, str]:
    """The absolute path of a source and its path relative to ``cara_dir`` (POSIX separators).

    The relative path is ``""`` when there is none (another drive on Windows).
    """
    absolute = os.path.abspath(path)
    try:
        rel = Path(os.path.relpath(absolute, cara_dir)).as_posix()
    except ValueError:
        rel = ""
    return absolute, rel


# --------------------------------------------------------------------------------- parts
def _array(g: h5py.Group, name: str, arr: np.ndarray, dtype: type | np.dtype, *,
           per_frame: bool = False) -> None:
    a = np.ascontiguousarray(arr, dtype=dtype)
    g.create_dataset(name, data=a, **dataset_kwargs(a, per_frame=per_frame))


def _strings(g: h5py.Group, name: str, values: list[str]) -> None:
    g.create_dataset(name, data=np.array(list(values), dtype=object).reshape(-1), dtype=STR_DTYPE)


def _write_take_group(g: h5py.Group, take: Take) -> None:
    g.attrs["name"] = take.name
    g.attrs["n_frames"] = np.int64(take.n_frames)
    g.attrs["frame_rate"] = np.float64(take.frame_rate)
    g.attrs["active_range"] = np.asarray(take.active_range, np.int64)
    g.attrs["view_range"] = np.asarray(take.view_range, np.int64)
    g.attrs["current_frame"] = np.int64(take.current_frame)
    g.attrs["start_timecode"] = take.start_timecode
    g.attrs["first_frame_number"] = np.int64(take.first_frame_number)
    g.attrs["rom_path"] = take.rom_path
    g.attrs["next_point_id"] = np.int64(take.next_point_id)
    _array(g, "caddies", np.asarray(take.caddies, np.int32).reshape(-1, 2), np.int32)
    g.create_dataset("metadata", data=json.dumps(dict(take.metadata), ensure_ascii=False),
                     dtype=STR_DTYPE)


def _write_camera(g: h5py.Group, cam: CameraInfo, cara_dir: Path) -> None:
    g.attrs["name"] = cam.name
    g.attrs["channel"] = np.int64(cam.channel)
    g.attrs["image_size"] = np.asarray(cam.image_size, np.int64)
    g.attrs["frame_offset"] = np.int64(cam.frame_offset)
    g.attrs["rotation"] = np.int64(cam.rotation)
    g.attrs["device_id"] = cam.device_id
    intr = cam.intrinsics
    g.attrs["focal_length"] = np.float64(intr.focal_length)
    g.attrs["principal_point"] = np.asarray(intr.principal_point, np.float64)
    g.attrs["sensor_size"] = np.asarray(intr.sensor_size, np.int64)
    g.attrs["aspect"] = np.float64(intr.aspect)
    g.attrs["skew"] = np.float64(intr.skew)
    g.attrs["radial"] = np.asarray(intr.radial, np.float64)
    if intr.distortion_centre is not None:
        g.attrs["distortion_centre"] = np.asarray(intr.distortion_centre, np.float64)
    if cam.source is not None:
        s = g.create_group("source")
        absolute, rel = source_paths(cam.source.path, cara_dir)
        s.attrs["path"] = absolute
        s.attrs["relpath"] = rel
        s.attrs["kind"] = cam.source.kind


def _write_points(g: h5py.Group, take: Take) -> None:
    pts = take.points
    _array(g, "ids", pts.ids, np.int64)
    _strings(g, "labels", pts.labels)
    _array(g, "kind", pts.kind, np.uint8)
    _array(g, "brim_index", pts.brim_index, np.int32)
    _array(g, "colour", np.asarray(pts.colour).reshape(-1, 3), np.uint8)


def _write_detections(g: h5py.Group, det: Detections) -> None:
    _array(g, "frame_ptr", det.frame_ptr, np.int64)
    _array(g, "detected", det.detected, np.bool_)
    for k, dtype in DETECTION_FIELDS.items():
        _array(g, k, getattr(det, k), dtype)


def _write_params(g: h5py.Group, params: Parameters) -> None:
    for section, values in params.to_dict().items():
        s = g.create_group(section)
        for key, value in values.items():
            s.attrs[key] = value
