"""Seeds files: hand-matched brim and face seed points as JSON, and snapping them to detections.

A seeds file records correspondences a user matches by hand on one frame — brim dots (for
solving the brim) and face markers (for Initialize 3D) — in raw pixels, cameras keyed by
channel (0-based) as strings::

    {"frame": 0,
     "brim": [{"brim_index": 3, "xy": {"0": [612.4, 88.1], "1": [610.0, 140.2]}}],
     "face": [{"name": "Nose_Tip", "xy": {"0": [640.2, 401.7], "2": [655.0, 398.3]}}]}

``"frame"`` defaults to 0, ``"brim"`` and ``"face"`` to empty lists; ``"name"`` is optional
(it becomes the point's label). Unknown keys are ignored (a newer writer may add some).
``carapost.synth.seeds_for`` writes this structure for synthetic takes.

:func:`snap_seeds` ties each seed position to the nearest detection within a few pixels and
reports every miss (camera, entry, distance to the nearest detection) instead of guessing.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .atomic import atomic_write_bytes

__all__ = ["SeedsFileError", "BrimSeed", "FaceSeed", "Seeds", "SeedMiss", "SnappedSeeds", "read_seeds",
           "write_seeds", "seeds_from_dict", "snap_seeds"]


_CAMERA_KEY = re.compile(r"[0-9]+")


class SeedsFileError(ValueError):
    """A seeds file that cannot be read or is malformed; the message names the file and entry."""


@dataclass(frozen=True)
class BrimSeed:
    """A brim dot matched by hand: its index in the brim model and its position per camera (px)."""

    brim_index: int
    xy: dict[int, tuple[float, float]]


@dataclass(frozen=True)
class FaceSeed:
    """A face marker matched by hand: optional label and position per camera (px)."""

    name: str | None
    xy: dict[int, tuple[float, float]]


@dataclass(frozen=True)
class Seeds:
    """The content of a seeds file."""

    frame: int = 0
    brim: tuple[BrimSeed, ...] = ()
    face: tuple[FaceSeed, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (cameras keyed by strings, sorted numerically)."""
        def xy(d: Mapping[int, tuple[float, float]]) -> dict[str, list[float]]:
            return {str(c): [float(v[0]), float(v[1])] for c, v in sorted(d.items())}
        face = []
        for f in self.face:
            e: dict[str, Any] = {"xy": xy(f.xy)}
            if f.name is not None:
                e = {"name": f.name, **e}
            face.append(e)
        return {"frame": int(self.frame),
                "brim": [{"brim_index": int(b.brim_index), "xy": xy(b.xy)} for b in self.brim],
                "face": face}


def _fail(source: str, where: str, msg: str) -> SeedsFileError:
    return SeedsFileError(f"{source}: {where}: {msg}" if where else f"{source}: {msg}")


def _int(v: Any) -> int | None:
    if isinstance(v, bool):
        return None
    if isinstance(v, int):
        return v
    if isinstance(v, float) and v.is_integer():
        return int(v)
    return None


def _parse_xy(obj: Any, source: str, where: str) -> dict[int, tuple[float, float]]:
    if not isinstance(obj, Mapping):
        raise _fail(source, where, f'"xy" must be an object mapping camera to [x, y], got {type(obj).__name__}')
    if not obj:
        raise _fail(source, where, '"xy" names no camera')
    out: dict[int, tuple[float, float]] = {}
    for key, val in obj.items():
        if isinstance(key, bool) or not _CAMERA_KEY.fullmatch(str(key).strip()):
            raise _fail(source, where, f"camera key {key!r} is not a channel number (0, 1, ...)")
        cam = int(str(key).strip())
        if cam in out:
            raise _fail(source, where, f"camera {cam} is given twice")
        if (not isinstance(val, Sequence) or isinstance(val, str) or len(val) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in val)):
            raise _fail(source, where, f"camera {cam}: position must be [x, y], got {val!r}")
        x, y = float(val[0]), float(val[1])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise _fail(source, where, f"camera {cam}: position must be finite, got {val!r}")
        out[cam] = (x, y)
    return out


def seeds_from_dict(data: Any, *, source: str = "<seeds>") -> Seeds:
    """Validate the JSON structure of a seeds file.

    Parameters
    ----------
    data : dict
        Parsed JSON.
    source : str
        File name used in error messages.

    Returns
    -------
    Seeds

    Raises
    ------
    SeedsFileError
        Naming ``source`` and the offending entry (``brim[2]``, ``face[0] ("Nose_Tip")``).
    """
    if not isinstance(data, Mapping):
        raise _fail(source, "", f"the top level must be a JSON object, got {type(data).__name__}")
    frame = data.get("frame", 0)
    fi = _int(frame)
    if fi is None or fi < 0:
        raise _fail(source, "", f'"frame" must be a non-negative whole number, got {frame!r}')
    brim_raw = data.get("brim", [])
    face_raw = data.get("face", [])
    for key, val in (("brim", brim_raw), ("face", face_raw)):
        if not isinstance(val, list):
            raise _fail(source, "", f'"{key}" must be a list, got {type(val).__name__}')
    brim: list[BrimSeed] = []
    seen_b: dict[int, int] = {}
    for i, e in enumerate(brim_raw):
        where = f"brim[{i}]"
        if not isinstance(e, Mapping):
            raise _fail(source, where, f"expected an object, got {type(e).__name__}")
        if "brim_index" not in e:
            raise _fail(source, where, 'missing "brim_index"')
        bi = _int(e["brim_index"])
        if bi is None or bi < 0:
            raise _fail(source, where, f'"brim_index" must be a non-negative whole number, got {e["brim_index"]!r}')
        if bi in seen_b:
            raise _fail(source, where, f"brim dot {bi} is already seeded by brim[{seen_b[bi]}]")
        seen_b[bi] = i
        if "xy" not in e:
            raise _fail(source, where, 'missing "xy"')
        brim.append(BrimSeed(bi, _parse_xy(e["xy"], source, where)))
    face: list[FaceSeed] = []
    seen_f: dict[str, int] = {}
    for i, e in enumerate(face_raw):
        where = f"face[{i}]"
        if not isinstance(e, Mapping):
            raise _fail(source, where, f"expected an object, got {type(e).__name__}")
        name = e.get("name")
        if name is not None:
            if not isinstance(name, str) or not name.strip():
                raise _fail(source, where, f'"name" must be a non-empty string, got {name!r}')
            name = name.strip()
            where = f'{where} ("{name}")'
            if name in seen_f:
                raise _fail(source, where, f"the name is already used by face[{seen_f[name]}]")
            seen_f[name] = i
        if "xy" not in e:
            raise _fail(source, where, 'missing "xy"')
        face.append(FaceSeed(name, _parse_xy(e["xy"], source, where)))
    return Seeds(frame=fi, brim=tuple(brim), face=tuple(face))


def read_seeds(path: str | os.PathLike) -> Seeds:
    """Read and validate a seeds file.

    Raises
    ------
    SeedsFileError
        The file cannot be read, is not UTF-8 JSON, or an entry is malformed (the message
        names the file, and the entry).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise SeedsFileError(f"{path}: cannot read the seeds file ({e.strerror or e})") from e
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise SeedsFileError(f"{path}: not UTF-8 text (byte {e.start})") from e
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise SeedsFileError(f"{path}: not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}") from e
    return seeds_from_dict(data, source=str(path))


def write_seeds(path: str | os.PathLike, seeds: Seeds | Mapping[str, Any]) -> None:
    """Write a seeds file atomically (validated first; a dict is accepted too)."""
    path = Path(path)
    if not isinstance(seeds, Seeds):
        seeds = seeds_from_dict(seeds, source=str(path))
    text = json.dumps(seeds.to_dict(), indent=1) + "\n"
    try:
        atomic_write_bytes(path, text.encode("utf-8"))
    except OSError as e:
        raise SeedsFileError(f"{path}: cannot write the seeds file ({e.strerror or e})") from e


# --------------------------------------------------------------------------------------
# Snapping to detections
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SeedMiss:
    """A seed position with no detection close enough.

    Attributes
    ----------
    kind : {"brim", "face"}
    entry : int
        Index in the seeds' ``brim`` or ``face`` list.
    label : str
        ``"brim dot 3"`` or the face seed's name (``"face seed 2"`` when unnamed).
    camera : int
    distance : float
        Distance to the nearest detection, px (``inf`` if the camera has none).
    """

    kind: str
    entry: int
    label: str
    camera: int
    distance: float


@dataclass
class SnappedSeeds:
    """Seeds tied to detection indices.

    Attributes
    ----------
    brim : dict brim_index -> {camera: detection index}
    face : list of (name or None, {camera: detection index})
        Face seeds matched in at least two cameras, in file order.
    messages : list of str
        One line per miss, conflict or dropped entry.
    misses : list of SeedMiss
    """

    brim: dict[int, dict[int, int]] = field(default_factory=dict)
    face: list[tuple[str | None, dict[int, int]]] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)
    misses: list[SeedMiss] = field(default_factory=list)

    @property
    def face_seeds(self) -> list[dict[int, int]]:
        """The face seeds as :func:`carapost.core.init3d.initialize_3d` takes them."""
        return [d for _, d in self.face]

    @property
    def face_names(self) -> list[str | None]:
        return [n for n, _ in self.face]


def _det_xy(det: Any, camera: int) -> np.ndarray:
    if isinstance(det, Mapping):
        xy = np.stack([np.asarray(det["x"], float).ravel(), np.asarray(det["y"], float).ravel()], axis=1)
    else:
        xy = np.asarray(det, float)
        if xy.size == 0:
            xy = xy.reshape(0, 2)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"camera {camera}: detections must be an (n, 2) array, got shape {xy.shape}")
    return xy


def snap_seeds(seeds: Seeds | Mapping[str, Any], detections_xy: Sequence[Any], *,
               radius_px: float = 3.0) -> SnappedSeeds:
    """Snap every seed position to the nearest detection within ``radius_px``.

    Parameters
    ----------
    seeds : Seeds or the JSON dict
    detections_xy : per camera, array (n_c, 2) (or a table with ``"x"``, ``"y"``)
        Detection centres of the seeds' frame, raw px.
    radius_px : float
        Largest distance from a seed position to its detection.

    Returns
    -------
    SnappedSeeds
        A position with no detection within the radius is reported as a miss (with the
        distance to the nearest detection), never guessed. Two seeds snapping to the same
        detection lose that camera (reported). Face seeds left with fewer than two cameras
        and brim seeds left with none are dropped (reported).
    """
    if not isinstance(seeds, Seeds):
        seeds = seeds_from_dict(seeds)
    if not radius_px > 0:
        raise ValueError(f"radius_px must be positive, got {radius_px}")
    xys = [_det_xy(d, c) for c, d in enumerate(detections_xy)]
    trees = [cKDTree(x) if len(x) else None for x in xys]
    out = SnappedSeeds()
    # (kind, entry, label, camera, detection)
    hits: list[tuple[str, int, str, int, int]] = []
    entries: list[tuple[str, int, str, dict[int, tuple[float, float]]]] = (
        [("brim", i, f"brim dot {b.brim_index}", b.xy) for i, b in enumerate(seeds.brim)]
        + [("face", i, f.name if f.name is not None else f"face seed {i}", f.xy) for i, f in enumerate(seeds.face)])
    for kind, i, label, pos in entries:
        for cam, (x, y) in sorted(pos.items()):
            if cam >= len(xys):
                out.messages.append(f"{label}: camera {cam} does not exist ({len(xys)} cameras); ignored")
                continue
            tree = trees[cam]
            if tree is None:
                d, j = math.inf, -1
            else:
                d, j = tree.query([x, y])
                d, j = float(d), int(j)
            if d > radius_px:
                out.misses.append(SeedMiss(kind, i, label, cam, d))
                near = "no detections" if tree is None else f"nearest detection {d:.1f} px away"
                out.messages.append(f"{label}: camera {cam}: no detection within {radius_px:g} px of "
                                    f"({x:.1f}, {y:.1f}) ({near})")
                continue
            hits.append((kind, i, label, cam, j))
    # conflicts: one detection claimed by two seeds
    owners: dict[tuple[int, int], list[int]] = {}
    for k, (_, _, _, cam, j) in enumerate(hits):
        owners.setdefault((cam, j), []).append(k)
    bad = set()
    for (cam, j), ks in owners.items():
        if len(ks) > 1:
            bad.update(ks)
            names = ", ".join(hits[k][2] for k in ks)
            out.messages.append(f"camera {cam}: detection {j} is the nearest to several seeds ({names}); "
                                f"not used for any of them")
    snapped: dict[tuple[str, int], dict[int, int]] = {}
    for k, (kind, i, _, cam, j) in enumerate(hits):
        if k not in bad:
            snapped.setdefault((kind, i), {})[cam] = j
    for i, b in enumerate(seeds.brim):
        m = snapped.get(("brim", i), {})
        if m:
            out.brim[b.brim_index] = m
        else:
            out.messages.append(f"brim dot {b.brim_index}: matched in no camera; dropped")
    for i, f in enumerate(seeds.face):
        m = snapped.get(("face", i), {})
        label = f.name if f.name is not None else f"face seed {i}"
        if len(m) >= 2:
            out.face.append((f.name, m))
        else:
            out.messages.append(f"{label}: matched in {len(m)} camera(s), a face seed needs 2; dropped")
    return out
