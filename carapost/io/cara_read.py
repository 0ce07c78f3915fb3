"""Read a ``.cara`` file's content into a :class:`~carapost.model.take.Take`.

Reading goes through :class:`CaraDoc`, a view of the open file that migrations
(:mod:`carapost.io.cara_migrate`) can patch in memory — replace, add or drop a dataset —
before :func:`build_take` turns it into a take. Only paths this version knows are read, so
datasets added by a newer minor version are ignored without being loaded.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from carapost.core.camera import Intrinsics
from carapost.model.detections import DETECTION_FIELDS, Detections
from carapost.model.params import Parameters
from carapost.model.take import POINT_ARRAYS, BrimModel, CameraInfo, Keyframes, PointTable, SourceRef, Take

from .cara_schema import BLOSC_FILTER_ID, CaraError

__all__ = ["CaraDoc", "build_take"]

_REQUIRED = object()


class CaraDoc:
    """An open ``.cara`` file as seen by the reader, with in-memory patches from migrations.

    Parameters
    ----------
    f : h5py.File
        Open for reading.
    path : Path
        The file's path, for error messages.

    Keys are HDF5 paths without the leading slash, e.g. ``"tracks/xyz"``.
    """

    def __init__(self, f: h5py.File, path: Path) -> None:
        self.f = f
        self.path = path
        self._patched: dict[str, np.ndarray] = {}
        self._attr_patches: dict[str, dict[str, Any]] = {}

    # ---------------------------------------------------------------------- datasets
    def has(self, key: str) -> bool:
        """Whether the dataset or group ``key`` exists (after patches)."""
        return key in self._patched or key in self.f

    def is_dataset(self, key: str) -> bool:
        return key in self._patched or isinstance(self.f.get(key), h5py.Dataset)

    def array(self, key: str, dtype: type | np.dtype | None = None, *,
              ndim: int | None = None, trailing: tuple[int, ...] | None = None) -> np.ndarray:
        """A numeric dataset as an array, optionally checked and cast.

        Parameters
        ----------
        key : str
            Dataset path.
        dtype : dtype, optional
            Cast to this dtype (no copy if it already has it); the stored data must be numeric.
        ndim, trailing : optional
            Expected number of dimensions and shape after the first axis.

        Raises
        ------
        CaraError
            If the dataset is missing, not numeric, of the wrong shape, or unreadable.
        """
        if key in self._patched:
            arr = self._patched[key]
        else:
            ds = self._dataset(key)
            if ds.dtype.kind not in "biuf":
                raise self.error(f"dataset '/{key}' has type {ds.dtype}, expected numbers")
            arr = self._read(ds)
        if ndim is not None and arr.ndim != ndim:
            raise self.error(f"dataset '/{key}' has shape {arr.shape}, expected {ndim} dimensions")
        if trailing is not None and arr.shape[1:] != tuple(trailing):
            raise self.error(f"dataset '/{key}' has shape {arr.shape}, expected (n, "
                             f"{', '.join(map(str, trailing))})")
        if dtype is not None and arr.dtype != dtype:
            arr = arr.astype(dtype)
        return arr

    def strings(self, key: str) -> list[str]:
        """A 1-D string dataset as a list of ``str``."""
        ds = self._dataset(key)
        if ds.dtype.kind not in "OSU" or ds.ndim != 1:
            raise self.error(f"dataset '/{key}' is not a list of text")
        return [str(s) for s in self._read(ds.asstr())]

    def text(self, key: str) -> str:
        """A scalar string dataset."""
        ds = self._dataset(key)
        if ds.dtype.kind not in "OSU" or ds.ndim != 0:
            raise self.error(f"dataset '/{key}' is not text")
        return str(self._read(ds.asstr()))

    def put(self, key: str, arr: np.ndarray) -> None:
        """Replace or add a numeric dataset (used by migrations)."""
        self._patched[key] = arr

    # --------------------------------------------------------------------- attributes
    def attrs(self, key: str) -> dict[str, Any]:
        """All attributes of the group or dataset ``key`` ("" for the root), after patches."""
        obj = self.f if key == "" else self.f.get(key)
        out: dict[str, Any] = dict(obj.attrs) if obj is not None else {}
        out.update(self._attr_patches.get(key, {}))
        return out

    def set_attr(self, key: str, name: str, value: Any) -> None:
        """Patch an attribute (used by migrations)."""
        self._attr_patches.setdefault(key, {})[name] = value

    def attr(self, key: str, name: str, default: Any = _REQUIRED) -> Any:
        """One attribute; raises :class:`CaraError` if it is required and missing."""
        attrs = self.attrs(key)
        if name not in attrs:
            if default is _REQUIRED:
                where = f"'/{key}'" if key else "the root group"
                raise self.error(f"attribute '{name}' of {where} is missing (the file is incomplete)")
            return default
        return attrs[name]

    def int_attr(self, key: str, name: str, default: Any = _REQUIRED) -> int:
        value = self.attr(key, name, default)
        try:
            return int(value)
        except (TypeError, ValueError):
            raise self.error(f"attribute '{name}' of '/{key}' must be a whole number, got {value!r}") from None

    def float_attr(self, key: str, name: str, default: Any = _REQUIRED) -> float:
        value = self.attr(key, name, default)
        try:
            return float(value)
        except (TypeError, ValueError):
            raise self.error(f"attribute '{name}' of '/{key}' must be a number, got {value!r}") from None

    def str_attr(self, key: str, name: str, default: Any = _REQUIRED) -> str:
        value = self.attr(key, name, default)
        if isinstance(value, bytes):
            value = value.decode("utf-8", "replace")
        if not isinstance(value, str):
            raise self.error(f"attribute '{name}' of '/{key}' must be text, got {value!r}")
        return value

    def tuple_attr(self, key: str, name: str, n: int, kind: type, default: Any = _REQUIRED) -> tuple:
        value = self.attr(key, name, default)
        arr = np.asarray(value)
        if arr.shape != (n,) or arr.dtype.kind not in "biuf":
            raise self.error(f"attribute '{name}' of '/{key}' must hold {n} numbers, got {value!r}")
        return tuple(kind(v) for v in arr)

    # -------------------------------------------------------------------------- misc
    def error(self, problem: str) -> CaraError:
        return CaraError(f"{self.path}: {problem}")

    def _dataset(self, key: str) -> h5py.Dataset:
        obj = self.f.get(key)
        if obj is None:
            raise self.error(f"dataset '/{key}' is missing (the file is incomplete or damaged)")
        if not isinstance(obj, h5py.Dataset):
            raise self.error(f"'/{key}' is not a dataset")
        return obj

    def _read(self, ds: Any) -> Any:
        try:
            return ds[()]
        except OSError as e:
            name = getattr(ds, "name", None) or "a dataset"
            if not h5py.h5z.filter_avail(BLOSC_FILTER_ID) and _uses_blosc(ds):
                raise self.error(f"'{name}' is compressed with Blosc, which needs the 'hdf5plugin' "
                                 "package: pip install hdf5plugin") from None
            raise self.error(f"cannot read '{name}': the file is truncated or damaged ({e})") from None


def _uses_blosc(ds: Any) -> bool:
    """Whether a dataset (or an ``asstr()`` view of one) is stored with the Blosc filter."""
    dset = getattr(ds, "_dset", ds)
    plist = dset.id.get_create_plist()
    return any(plist.get_filter(i)[0] == BLOSC_FILTER_ID for i in range(plist.get_nfilters()))


# ------------------------------------------------------------------------------ building
def build_take(doc: CaraDoc) -> Take:
    """Build the take from a (migrated) current-version document.

    Raises
    ------
    CaraError
        Missing or malformed parts, or arrays that break the take's array contract.
    """
    F = doc.int_attr("take", "n_frames")
    if F < 1:
        raise doc.error(f"the take has {F} frames")
    C = doc.int_attr("cameras", "count")
    if C < 0:
        raise doc.error(f"the take has {C} cameras")
    cameras = [_camera(doc, c) for c in range(C)]
    points = _points(doc)
    arrays = {}
    for name, (_, dtype, _) in POINT_ARRAYS.items():
        arrays[name] = doc.array(f"tracks/{name}", dtype)
    detections = [_detections(doc, c, F) for c in range(C)]
    caddies = doc.array("take/caddies", np.int64, ndim=2, trailing=(2,))
    try:
        metadata = json.loads(doc.text("take/metadata"))
        if not isinstance(metadata, dict):
            raise ValueError("not an object")
    except ValueError as e:
        raise doc.error(f"'/take/metadata' is not a JSON object of text ({e})") from None
    try:
        params = Parameters.from_dict(_params(doc))
    except ValueError as e:
        raise doc.error(f"bad parameter in '/params': {e}") from None
    brim = None
    if doc.has("brim"):
        brim = BrimModel(name=doc.str_attr("brim", "name", ""),
                         xyz=doc.array("brim/xyz", np.float64, ndim=2, trailing=(3,)),
                         radius=doc.array("brim/radius", np.float64, ndim=1),
                         polarity=doc.array("brim/polarity", np.int8, ndim=1),
                         svg=doc.text("brim/svg") if doc.has("brim/svg") else "")
    take = Take(
        cameras=cameras, n_frames=F, frame_rate=doc.float_attr("take", "frame_rate"),
        R=doc.array("poses/R", np.float64), t=doc.array("poses/t", np.float64),
        detections=detections, points=points,
        keyframes=Keyframes(frame=doc.array("keyframes/frame", np.int32, ndim=1),
                            point_id=doc.array("keyframes/point_id", np.int64, ndim=1),
                            camera=doc.array("keyframes/camera", np.int16, ndim=1),
                            xy=doc.array("keyframes/xy", np.float32, ndim=2, trailing=(2,)),
                            pattern=doc.array("keyframes/pattern", np.float32, ndim=2, trailing=(4,)),
                            search=doc.array("keyframes/search", np.float32, ndim=2, trailing=(4,))),
        labels=doc.strings("labels"),
        sticks=doc.array("sticks/pairs", np.int64, ndim=2, trailing=(2,)),
        stick_colours=doc.array("sticks/colours", np.uint8, ndim=2, trailing=(3,)),
        brim=brim, params=params,
        caddies=[(int(a), int(b)) for a, b in caddies],
        active_range=doc.tuple_attr("take", "active_range", 2, int),
        view_range=doc.tuple_attr("take", "view_range", 2, int),
        current_frame=doc.int_attr("take", "current_frame", 0),
        start_timecode=doc.str_attr("take", "start_timecode", "00:00:00:00"),
        first_frame_number=doc.int_attr("take", "first_frame_number", 0),
        name=doc.str_attr("take", "name", ""),
        rom_path=doc.str_attr("take", "rom_path", ""),
        next_point_id=doc.int_attr("take", "next_point_id"),
        metadata={str(k): str(v) for k, v in metadata.items()},
        **arrays,
    )
    kf = take.keyframes
    if not len(kf.frame) == len(kf.point_id) == len(kf.camera) == len(kf.xy) == len(kf.pattern) == len(kf.search):
        raise doc.error("the keyframe arrays in '/keyframes' differ in length")
    if len(take.sticks) != len(take.stick_colours):
        raise doc.error("'/sticks/pairs' and '/sticks/colours' differ in length")
    try:
        take.check()
    except ValueError as e:
        raise doc.error(f"inconsistent take: {e}") from None
    return take


def _camera(doc: CaraDoc, c: int) -> CameraInfo:
    key = f"cameras/{c}"
    if not doc.has(key):
        raise doc.error(f"group '/{key}' is missing (the file is incomplete or damaged)")
    centre = doc.attr(key, "distortion_centre", None)
    try:
        intr = Intrinsics(
            focal_length=doc.float_attr(key, "focal_length"),
            principal_point=doc.tuple_attr(key, "principal_point", 2, float),
            sensor_size=doc.tuple_attr(key, "sensor_size", 2, int),
            aspect=doc.float_attr(key, "aspect", 1.0),
            skew=doc.float_attr(key, "skew", 0.0),
            radial=doc.tuple_attr(key, "radial", 3, float),
            distortion_centre=None if centre is None else doc.tuple_attr(key, "distortion_centre", 2, float),
        )
    except ValueError as e:
        if isinstance(e, CaraError):
            raise
        raise doc.error(f"camera {c}: {e}") from None
    source = None
    skey = f"{key}/source"
    if doc.has(skey):
        source = SourceRef(path=doc.str_attr(skey, "path"), relpath=doc.str_attr(skey, "relpath", ""),
                           kind=doc.str_attr(skey, "kind", "pico"))
    return CameraInfo(name=doc.str_attr(key, "name", ""), channel=doc.int_attr(key, "channel", c),
                      intrinsics=intr, image_size=doc.tuple_attr(key, "image_size", 2, int, (0, 0)),
                      source=source, frame_offset=doc.int_attr(key, "frame_offset", 0),
                      rotation=doc.int_attr(key, "rotation", 0), device_id=doc.str_attr(key, "device_id", ""))


def _points(doc: CaraDoc) -> PointTable:
    ids = doc.array("points/ids", np.int64, ndim=1)
    table = PointTable(ids=ids, labels=doc.strings("points/labels"),
                       kind=doc.array("points/kind", np.uint8, ndim=1),
                       brim_index=doc.array("points/brim_index", np.int32, ndim=1),
                       colour=doc.array("points/colour", np.uint8, ndim=2, trailing=(3,)))
    n = len(ids)
    if not len(table.labels) == len(table.kind) == len(table.brim_index) == len(table.colour) == n:
        raise doc.error("the point table arrays in '/points' differ in length")
    return table


def _detections(doc: CaraDoc, c: int, F: int) -> Detections:
    key = f"detections/{c}"
    ptr = doc.array(f"{key}/frame_ptr", np.int64, ndim=1)
    detected = doc.array(f"{key}/detected", np.bool_, ndim=1)
    fields = {k: doc.array(f"{key}/{k}", dt, ndim=1) for k, dt in DETECTION_FIELDS.items()}
    if len(ptr) != F + 1 or len(detected) != F:
        raise doc.error(f"camera {c}'s detections cover {len(ptr) - 1} frames, the take has {F}")
    N = len(fields["x"])
    if ptr[0] != 0 or ptr[-1] != N or np.any(np.diff(ptr) < 0):
        raise doc.error(f"camera {c}'s detection frame pointers are inconsistent with its {N} detections")
    if any(len(a) != N for a in fields.values()):
        raise doc.error(f"camera {c}'s detection arrays differ in length")
    return Detections(frame_ptr=ptr, detected=detected, **fields)


def _params(doc: CaraDoc) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    if not doc.has("params"):
        raise doc.error("group '/params' is missing (the file is incomplete or damaged)")
    for section in doc.f["params"]:
        values = {}
        for k, v in doc.attrs(f"params/{section}").items():
            if isinstance(v, np.generic):
                v = v.item()
            elif isinstance(v, bytes):
                v = v.decode("utf-8", "replace")
            values[k] = v
        out[section] = values
    return out
