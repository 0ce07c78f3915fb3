"""Properties, ranges, camera offsets and rotations, and point information."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from carapost.core.camera import camera_centre
from carapost.model.params import PRESETS, Parameters
from carapost.model.take import Take, check_caddies

from .change import AttributeChange, Composite

__all__ = [
    "set_property",
    "restore_properties",
    "apply_preset",
    "apply_settings",
    "set_caddies",
    "parse_caddies",
    "format_caddies",
    "set_active_range",
    "set_view_range",
    "increment_image_sequence_offset",
    "rotate_sensors",
    "point_information",
    "distance_between_points",
]


def set_property(take: Take, group: str, name: str, value: Any) -> AttributeChange:
    """Set one property (validated; the take is unchanged if the value is rejected)."""
    section = take.params.section(group)
    key = next(k for k, s in take.params.sections() if s is section)
    new = type(section).from_dict(section.to_dict())
    new.set(name, value)
    new.validate()  # cross-field rules (e.g. Min Radius <= Max Radius)
    label = new.field_by_label(name).metadata["label"]
    return AttributeChange.capture(take, f"params.{key}", new, f"{section.title}: {label} = {value}")


def restore_properties(take: Take) -> AttributeChange:
    """"Restore Properties To Defaults"."""
    return AttributeChange.capture(take, "params", Parameters(), "Restore Properties To Defaults")


def apply_preset(take: Take, preset: str) -> AttributeChange:
    """The guide's parameter sets for marker-set densities: ``"default"``, ``"dense"`` (156), ``"sparse"`` (35)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    return AttributeChange.capture(take, "params", PRESETS[preset](take.params), f"Preset: {preset}")


def set_caddies(take: Take, caddies: Sequence[tuple[int, int]]) -> AttributeChange:
    """The camera pairs that are caddies (two cameras on one side of a head-mounted rig:
    Initialize 3D grows two-view points within each); none for cameras standing around a
    room, where every point must be seen by more cameras.

    Raises
    ------
    ValueError
        A camera that does not exist, a pair of one camera, or a camera in two caddies
        (:func:`carapost.model.take.check_caddies`).
    """
    try:
        pairs = check_caddies(caddies, take.n_cameras)
    except ValueError as exc:
        raise ValueError(f"caddies: {exc}") from None
    return AttributeChange.capture(take, "caddies", pairs, f"Caddies: {format_caddies(pairs)}")


def parse_caddies(spec: str | None) -> list[tuple[int, int]] | None:
    """``"0-1,2-3"`` -> [(0, 1), (2, 3)]; ``"none"`` (or nothing) -> []; None: keep the take's."""
    if spec is None:
        return None
    if spec.strip().lower() in ("none", ""):
        return []
    try:
        return [(int(a), int(b)) for a, b in (pair.split("-") for pair in spec.split(",") if pair.strip())]
    except ValueError:
        raise ValueError(f"caddies must be camera pairs like 0-1,2-3, or none; got {spec!r}") from None


def format_caddies(caddies: Sequence[tuple[int, int]]) -> str:
    """The inverse of :func:`parse_caddies`: ``"0-1,2-3"`` or ``"none"``."""
    return ",".join(f"{a}-{b}" for a, b in caddies) or "none"


def apply_settings(session: Any, *, preset: str | None = None, settings: Sequence[tuple[str, str, str]] = (),
                   caddies: Sequence[tuple[int, int]] | None = None) -> None:
    """Apply a parameter preset, then single properties ``(group, property, value)``, then the
    caddies to a :class:`~carapost.ops.session.Session`'s take (each an undoable change, as in
    the Properties pane; the command line's ``--preset``, ``--set``, ``--caddies``).

    Raises
    ------
    ValueError
        ``"settings: ..."``: an unknown preset, group or property, or a value the property
        refuses (what was applied before stays applied).
    """
    take = session.take
    try:
        if preset is not None:
            session.apply(apply_preset(take, preset))
        for group, name, value in settings:
            session.apply(set_property(take, group, name, value))
        if caddies is not None:
            session.apply(set_caddies(take, caddies))
    except KeyError as exc:              # unknown group or property: the message lists the known ones
        raise ValueError(f"settings: {exc.args[0]}") from None
    except ValueError as exc:
        raise ValueError(f"settings: {exc}") from None


def _range(take: Take, start: int, end: int, what: str) -> tuple[int, int]:
    if not 0 <= start <= end < take.n_frames:
        raise ValueError(f"{what} {start}..{end} must lie within 0..{take.n_frames - 1} with start <= end")
    return int(start), int(end)


def set_active_range(take: Take, start: int, end: int) -> AttributeChange:
    """Set Active Range Start/End (Ctrl+1, Ctrl+2); Reset (Ctrl+3) is ``(0, n_frames - 1)``."""
    return AttributeChange.capture(take, "active_range", _range(take, start, end, "active range"),
                                   f"Active Range {start}-{end}")


def set_view_range(take: Take, start: int, end: int) -> AttributeChange:
    return AttributeChange.capture(take, "view_range", _range(take, start, end, "view range"), f"View Range {start}-{end}")


def increment_image_sequence_offset(take: Take, cameras: Sequence[int], step: int = 1) -> Composite:
    """"Increment Image Sequence Offset": the selected cameras' video moves ``step`` frames forward.

    Refused once a camera has 2D information (detections or observations), as the guide warns.
    """
    if not cameras:
        raise ValueError("Increment Image Sequence Offset: select one or more camera views")
    changes = []
    for c in cameras:
        if len(take.detections[c]) or (take.obs_det[..., c] >= 0).any():
            raise ValueError(f"camera {c} already has 2D information; clear its detections before changing the offset")
        changes.append(AttributeChange.capture(take, f"cameras.{c}.frame_offset", take.cameras[c].frame_offset + step, ""))
    return Composite(changes, f"Increment Image Sequence Offset: cameras {', '.join(map(str, cameras))}")


def rotate_sensors(take: Take, cameras: Sequence[int], clockwise: bool = True) -> Composite:
    """"Rotate Selected Sensors Clockwise/Anticlockwise" (display only; saved in the project)."""
    step = 90 if clockwise else 270
    changes = [AttributeChange.capture(take, f"cameras.{c}.rotation", (take.cameras[c].rotation + step) % 360, "")
               for c in cameras]
    return Composite(changes, f"Rotate sensors {', '.join(map(str, cameras))} {'clockwise' if clockwise else 'anticlockwise'}")


def point_information(take: Take, point: int, frame: int) -> dict[str, Any]:
    """"Get Point Information": 3D position, per-sensor blob dimensions, distances to the
    centroids of each caddy's cameras and of all cameras (mm)."""
    if not 0 <= point < take.n_points:
        raise ValueError(f"point {point} does not exist")
    X = take.xyz[frame, point]
    centres = camera_centre(take.R[frame], take.t[frame])  # (C, 3)
    info: dict[str, Any] = {"point": take.points.name(point), "id": int(take.points.ids[point]), "frame": frame,
                            "xyz_mm": X.tolist(), "reconstruction": int(take.recon[frame, point]), "sensors": {}}
    for c in range(take.n_cameras):
        i = int(take.obs_det[frame, point, c])
        if i >= 0:
            d = take.detections[c].frame(frame)
            info["sensors"][c] = {"detection": i, "major_px": float(d["major"][i]), "minor_px": float(d["minor"][i]),
                                  "xy_px": take.obs_xy[frame, point, c].tolist()}
    if np.isfinite(X).all():
        for k, (a, b) in enumerate(take.caddies):
            info[f"distance_to_caddy_{k}_mm"] = float(np.linalg.norm(X - centres[[a, b]].mean(0)))
        info["distance_to_cameras_mm"] = float(np.linalg.norm(X - np.nanmean(centres, axis=0)))
    return info


def distance_between_points(take: Take, p1: int, p2: int, frame: int) -> float:
    """"Distance Between Two Points" in the current frame, mm (NaN if either has no position)."""
    return float(np.linalg.norm(take.xyz[frame, p1] - take.xyz[frame, p2]))
