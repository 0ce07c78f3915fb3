"""``carapost info FILE``: summarise a .pico, calibration, .cara, .c3d, video or image folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["file_info", "format_info"]

CALIBRATION_SUFFIXES = (".xcp", ".qca", ".toml")


def file_info(path: str | Path) -> dict[str, Any]:
    """A JSON-able summary of a file CaraPost can read.

    Raises
    ------
    ValueError
        If the file does not exist or is of an unknown kind (the message names the file).
    """
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: no such file or folder")
    name = p.name.lower()
    if name.endswith(".cara"):
        return _cara_info(p)
    if name.endswith(".c3d"):
        from carapost.io.c3d import info_c3d

        return {"kind": "c3d", "path": str(p), **info_c3d(p)}
    if name.endswith(CALIBRATION_SUFFIXES) or name.endswith(".qca.txt"):
        return _calibration_info(p)
    from carapost.io.sources import open_source

    src = open_source(p)
    try:
        m = src.meta
        out: dict[str, Any] = {"kind": src.kind, "path": str(p), "frames": src.n_frames, "width": src.width,
                               "height": src.height, "frame_rate": src.frame_rate, "camera_name": m.camera_name,
                               "channel": m.channel, "start_timecode": m.start_timecode, "rotation": m.rotation}
        if src.kind == "pico":
            out.update(logger_name=m.logger_name, logger_description=m.logger_description, logger_id=m.logger_id,
                       codec=getattr(src, "codec", ""), blob_parameters=m.blob_parameters)
        if src.warnings:
            out["warnings"] = list(src.warnings)
        return out
    finally:
        src.close()


def _calibration_info(p: Path) -> dict[str, Any]:
    from carapost.io.calibration import load_calibration

    cal = load_calibration(p)
    cams = []
    for c in cal.cameras:
        i = c.intrinsics
        cams.append({"name": c.name, "device_id": c.device_id, "sensor_size": list(i.sensor_size),
                     "focal_length_px": i.focal_length, "principal_point": list(i.principal_point),
                     "radial": list(i.radial), "keyframes": int(len(c.frames)),
                     "image_error_px": float(np.nanmean(c.image_error)) if len(c.image_error) else None})
    return {"kind": f"calibration ({cal.format})", "path": str(p), "cameras": cams}


def _cara_info(p: Path) -> dict[str, Any]:
    from carapost.io.cara import load_take
    from carapost.model.take import PointKind

    res = load_take(p)
    t = res.take
    face = t.points.kind == PointKind.FACE
    nv = t.n_views()
    tracked = np.isfinite(t.xyz).all(-1)
    return {"kind": "cara", "path": str(p), "name": t.name, "frames": t.n_frames, "frame_rate": t.frame_rate,
            "cameras": [c.name for c in t.cameras], "face_points": int(face.sum()), "brim_points": int((~face).sum()),
            "labelled_points": int(sum(1 for lab in t.points.labels if lab)),
            "detections": [int(len(d)) for d in t.detections],
            "frames_detected": [int(d.detected.sum()) for d in t.detections],
            "tracked_fraction": float(tracked[:, face].mean()) if face.any() else 0.0,
            "multi_view_fraction": float((nv[:, face] >= 2).mean()) if face.any() else 0.0,
            "brim": t.brim.name if t.brim is not None else None,
            "missing_sources": res.missing_sources, "messages": res.messages}


def format_info(info: dict[str, Any]) -> str:
    """Human-readable lines of :func:`file_info`'s summary."""
    lines = [f"{info['path']}: {info['kind']}"]
    for k, v in info.items():
        if k in ("path", "kind"):
            continue
        if k == "cameras" and v and isinstance(v[0], dict):
            lines.append(f"  cameras: {len(v)}")
            for c in v:
                lines.append(f"    {c['name'] or c['device_id']}: {c['sensor_size'][0]}x{c['sensor_size'][1]}, "
                             f"f={c['focal_length_px']:.2f} px, pp=({c['principal_point'][0]:.1f}, "
                             f"{c['principal_point'][1]:.1f}), keyframes={c['keyframes']}")
        elif isinstance(v, float):
            lines.append(f"  {k}: {v:.4g}")
        elif isinstance(v, list) and len(v) > 12:
            lines.append(f"  {k}: {v[:12]} ... ({len(v)} in all)")
        else:
            lines.append(f"  {k}: {v}")
    return "\n".join(lines)
