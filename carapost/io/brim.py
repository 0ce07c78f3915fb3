"""Calibration brim models: our JSON format, the default brims, and an SVG writer.

JSON format (``docs/formats/brim.md``)::

    {"format": "carapost-brim", "format_version": 1, "name": "v2.0", "version": "2.0",
     "units": "mm", "description": "...",
     "dots": [{"xyz": [-50.0, 12.0, 0.0], "radius": 2.25, "polarity": "black"}, ...]}

The brim frame is the world frame once a brim is solved: ``X`` along the card, ``Y`` up the
card, ``Z`` out of the card towards the cameras (``Z = 0`` on a planar card). Dot ``i`` of
the model is the ``i``-th entry of ``dots`` (and the ``i``-th circle of its SVG).
"""

from __future__ import annotations

import json
import math
import os
from importlib import resources
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from carapost.model.take import BrimModel

from .atomic import atomic_write_text

__all__ = [
    "BRIM_FORMAT",
    "BRIM_FORMAT_VERSION",
    "DEFAULT_BRIMS",
    "BrimFormatError",
    "load_default_brim",
    "load_brim_json",
    "save_brim_json",
    "brim_to_dict",
    "brim_from_dict",
    "write_brim_svg",
    "brim_svg_text",
    "bend_brim",
    "flatten_brim",
]

BRIM_FORMAT = "carapost-brim"
BRIM_FORMAT_VERSION = 1
#: Versions of the default brims shipped in ``carapost/resources/brims``.
DEFAULT_BRIMS = ("v1.0", "v1.1", "v2.0")
_POLARITY = {"black": -1, "white": 1, -1: -1, 1: 1}


class BrimFormatError(ValueError):
    """A brim file that cannot be read; the message names the file and the problem."""


# ------------------------------------------------------------------------------ JSON
def brim_to_dict(brim: BrimModel, *, version: str = "", description: str = "") -> dict:
    """The JSON-ready dictionary of a brim model."""
    xyz = np.asarray(brim.xyz, dtype=float)
    rad = np.asarray(brim.radius, dtype=float)
    pol = np.asarray(brim.polarity, dtype=int)
    dots = [{"xyz": [round(float(c), 6) for c in p], "radius": round(float(r), 6),
             "polarity": "white" if q > 0 else "black"} for p, r, q in zip(xyz, rad, pol)]
    d: dict = {"format": BRIM_FORMAT, "format_version": BRIM_FORMAT_VERSION, "name": brim.name,
               "version": version, "units": "mm"}
    if description:
        d["description"] = description
    d["dots"] = dots
    return d


def brim_from_dict(d: dict, *, source: str = "<dict>") -> BrimModel:
    """A :class:`BrimModel` from the JSON dictionary; ``source`` names the file in errors."""
    def bad(msg: str) -> BrimFormatError:
        return BrimFormatError(f"{source}: {msg}")

    if not isinstance(d, dict):
        raise bad("not a brim model (expected a JSON object)")
    if d.get("format") != BRIM_FORMAT:
        raise bad(f"not a brim model (format is {d.get('format')!r}, expected {BRIM_FORMAT!r})")
    ver = d.get("format_version")
    if not isinstance(ver, int) or ver < 1:
        raise bad(f"invalid format_version {ver!r}")
    if ver > BRIM_FORMAT_VERSION:
        raise bad(f"format_version {ver} is newer than this program reads ({BRIM_FORMAT_VERSION})")
    if d.get("units", "mm") != "mm":
        raise bad(f"units must be 'mm', got {d.get('units')!r}")
    dots = d.get("dots")
    if not isinstance(dots, list) or len(dots) == 0:
        raise bad("'dots' must be a non-empty list")
    xyz = np.empty((len(dots), 3))
    rad = np.empty(len(dots))
    pol = np.empty(len(dots), np.int8)
    for i, dot in enumerate(dots):
        try:
            p = np.asarray(dot["xyz"], dtype=float)
            r = float(dot["radius"])
            q = dot.get("polarity", "black")
        except (KeyError, TypeError, ValueError) as exc:
            raise bad(f"dot {i}: needs 'xyz' (3 numbers) and 'radius' ({exc})") from None
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise bad(f"dot {i}: 'xyz' must be 3 finite numbers, got {dot['xyz']!r}")
        if not (math.isfinite(r) and r > 0):
            raise bad(f"dot {i}: radius must be positive, got {r}")
        if q not in _POLARITY:
            raise bad(f"dot {i}: polarity must be 'black' or 'white', got {q!r}")
        xyz[i], rad[i], pol[i] = p, r, _POLARITY[q]
    name = d.get("name") or d.get("version") or "brim"
    if not isinstance(name, str):
        raise bad(f"name must be a string, got {name!r}")
    return BrimModel(name=name, xyz=xyz, radius=rad, polarity=pol)


def load_brim_json(path: str | os.PathLike) -> BrimModel:
    """Read a brim model from our JSON format.

    Raises
    ------
    BrimFormatError
        If the file is not valid JSON or not a valid brim model (message names the file).
    FileNotFoundError
        If the file does not exist.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise BrimFormatError(f"{path}: not a text file ({exc})") from None
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BrimFormatError(f"{path}: invalid JSON ({exc})") from None
    return brim_from_dict(d, source=str(path))


def _write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)


def save_brim_json(path: str | os.PathLike, brim: BrimModel, *, version: str = "", description: str = "") -> Path:
    """Write a brim model as JSON (atomically). Returns the path."""
    path = Path(path)
    _check(brim)
    _write_text(path, _dumps(brim_to_dict(brim, version=version, description=description)))
    return path


def _dumps(d: dict) -> str:
    """JSON text with one line per dot (readable and diff-friendly)."""
    head = {k: v for k, v in d.items() if k != "dots"}
    lines = ["{"] + [f" {json.dumps(k)}: {json.dumps(v)}," for k, v in head.items()]
    dots = [f"  {json.dumps(dot, separators=(', ', ': '))}" for dot in d["dots"]]
    lines.append(' "dots": [')
    lines.append(",\n".join(dots))
    lines += [" ]", "}", ""]
    return "\n".join(lines)


def _check(brim: BrimModel) -> None:
    xyz = np.asarray(brim.xyz, dtype=float)
    n = len(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or n == 0:
        raise ValueError(f"brim {brim.name!r}: xyz must be (N, 3) with N > 0, got {xyz.shape}")
    if np.shape(brim.radius) != (n,) or np.shape(brim.polarity) != (n,):
        raise ValueError(f"brim {brim.name!r}: radius and polarity must have {n} entries")


def load_default_brim(version: str = "v2.0") -> BrimModel:
    """One of the project's default brim models: ``"v1.0"``, ``"v1.1"`` or ``"v2.0"``.

    ``"2.0"`` and ``"V2.0"`` are accepted too. The layouts are documented in
    ``docs/formats/brim.md``.
    """
    v = str(version).strip().lower()
    if not v.startswith("v"):
        v = "v" + v
    if v not in DEFAULT_BRIMS:
        raise ValueError(f"unknown default brim {version!r}; choose one of {', '.join(DEFAULT_BRIMS)}")
    res = resources.files("carapost").joinpath("resources", "brims", f"{v}.json")
    d = json.loads(res.read_text(encoding="utf-8"))
    return brim_from_dict(d, source=f"default brim {v}")


# ------------------------------------------------------------------------ geometry
def bend_brim(brim: BrimModel, radius: float, *, name: str | None = None) -> BrimModel:
    """Bend a planar brim onto a vertical cylinder (axis along ``Y``) of ``radius`` mm.

    The card keeps its layout as arc length: a dot at ``(X, Y, 0)`` moves to
    ``(r sin(X / r), Y, r cos(X / r) - r)`` (the sides curve back, away from the cameras).
    """
    if not radius > 0:
        raise ValueError(f"curvature radius must be positive, got {radius}")
    xyz = np.asarray(brim.xyz, dtype=float)
    if np.any(np.abs(xyz[:, 2]) > 1e-9):
        raise ValueError(f"brim {brim.name!r} is not planar; cannot bend it")
    a = xyz[:, 0] / radius
    out = np.c_[radius * np.sin(a), xyz[:, 1], radius * np.cos(a) - radius]
    return BrimModel(name=name or f"{brim.name}-curved", xyz=out, radius=np.array(brim.radius, float),
                     polarity=np.array(brim.polarity, np.int8))


def flatten_brim(xyz: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The flat layout ``(N, 2)`` of a brim's dots, and the fitted cylinder radius.

    A planar brim (all ``Z`` within 1e-6 mm of 0) gives its ``(X, Y)`` and ``None``. A curved
    brim is fitted with a cylinder whose axis is parallel to ``Y``; ``X`` becomes the arc
    length along the card, measured from the point of the arc straight in front of (or behind)
    the cylinder's axis.
    """
    xyz = np.asarray(xyz, dtype=float)
    if np.all(np.abs(xyz[:, 2]) < 1e-6):
        return xyz[:, :2].copy(), None
    x, z = xyz[:, 0], xyz[:, 2]
    # algebraic circle fit in the XZ plane: x^2 + z^2 + D x + E z + F = 0
    A = np.c_[x, z, np.ones_like(x)]
    sol, *_ = np.linalg.lstsq(A, -(x * x + z * z), rcond=None)
    xc, zc = -sol[0] / 2, -sol[1] / 2
    r = float(np.sqrt(max(xc * xc + zc * zc - sol[2], 0.0)))
    if not np.isfinite(r) or r <= 0 or len(xyz) < 3:
        raise ValueError("cannot flatten the brim: its dots do not lie on a vertical cylinder")
    # angle from the axis point of the arc (the arc bulges towards +Z or towards -Z)
    if zc < float(np.mean(z)):
        ang = np.arctan2(x - xc, z - zc)
    else:
        ang = np.arctan2(x - xc, zc - z)
    s = r * ang
    return np.c_[s, xyz[:, 1]], r


# ----------------------------------------------------------------------------- SVG
def brim_svg_text(brim: BrimModel, *, margin: float = 6.0) -> str:
    """SVG source of a brim: a card and one ``<circle>`` per dot in dot order (mm units).

    ``X`` runs along SVG ``x``; ``Y`` runs against SVG ``y`` (SVG ``y`` points down), so
    ``cx = X`` and ``cy = -Y``. A curved brim is written as its flattened layout (see
    :func:`flatten_brim`), noted in the ``<desc>``.
    """
    _check(brim)
    flat, r_cyl = flatten_brim(brim.xyz)
    rad = np.asarray(brim.radius, float)
    pol = np.asarray(brim.polarity, int)
    x0 = float(np.min(flat[:, 0] - rad)) - margin
    x1 = float(np.max(flat[:, 0] + rad)) + margin
    y0 = float(np.min(-flat[:, 1] - rad)) - margin
    y1 = float(np.max(-flat[:, 1] + rad)) + margin
    w, h = x1 - x0, y1 - y0
    black_dots = np.sum(pol < 0) >= np.sum(pol > 0)
    card = "#ffffff" if black_dots else "#000000"
    desc = f"CaraPost calibration brim {brim.name}: {len(flat)} dots, mm, X along x, Y = -y."
    if r_cyl is not None:
        desc += f" Curved brim (cylinder radius {r_cyl:.3f} mm) written as its flattened layout (x = arc length)."
    lines = [
        '<?xml version="1.0" encoding="UTF-8" standalone="no"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{w:.3f}mm" height="{h:.3f}mm" '
        f'viewBox="{x0:.3f} {y0:.3f} {w:.3f} {h:.3f}">',
        f"  <title>{escape(brim.name)}</title>",
        f"  <desc>{escape(desc)}</desc>",
        f'  <rect id="card" x="{x0:.3f}" y="{y0:.3f}" width="{w:.3f}" height="{h:.3f}" rx="3" fill="{card}"/>',
        '  <g id="dots">',
    ]
    for i, ((px, py), r, q) in enumerate(zip(flat, rad, pol)):
        fill = "#ffffff" if q > 0 else "#000000"
        lines.append(f'    <circle id="dot{i}" cx="{px:.4f}" cy="{-py:.4f}" r="{r:.4f}" fill="{fill}"/>')
    lines += ["  </g>", "</svg>", ""]
    return "\n".join(lines)


def write_brim_svg(path: str | os.PathLike, brim: BrimModel) -> Path:
    """Write a brim as SVG (see :func:`brim_svg_text`), atomically. Returns the path."""
    path = Path(path)
    _write_text(path, brim_svg_text(brim))
    return path
