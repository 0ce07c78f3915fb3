"""Facial marker sets: 35, 80 or 156 named markers placed on the synthetic face.

Layouts follow the usual facial marker sets: markers along the brows, on the upper and lower
lids, around the lips and mouth corners, along the nasolabial folds and the jawline, down the
midline of the nose, and a spread of markers over the forehead and cheeks; the denser sets add
markers where faces move most (around the mouth and the eyes, on the cheeks).

Names: ``<Region>_<Side>[_<i>]`` with side ``L`` (actor's left, head ``+x``) or ``R``, and
``i`` counted from the midline outwards (or top to bottom); midline markers have no side
(``Nose_Tip``, ``Lip_Upper_C``). Positions are material coordinates ``(u, v)`` mm on the face
of :mod:`carapost.synth.face`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .expressions import LID_LO, LID_UP
from .face import EYE, MOUTH_HALF_WIDTH, NOSE_TIP, lip_line

__all__ = ["MarkerSet", "marker_set", "EYELID_REGIONS"]

#: Name prefixes of the markers that blinks hide.
EYELID_REGIONS = ("Lid_Upper",)

# Markers per region for each set: midline markers (name -> (u, v)) and per-side counts.
_MIDLINE = {
    35: ["Forehead_C", "Nose_Bridge", "Nose_Tip", "Philtrum", "Lip_Upper_C", "Lip_Lower_C", "Chin"],
    80: ["Forehead_C", "Nose_Bridge", "Nose_Tip", "Philtrum", "Lip_Upper_C", "Lip_Lower_C", "Mentolabial_C",
         "Chin"],
    156: ["Forehead_C_1", "Forehead_C_2", "Nose_Bridge", "Nose_Mid", "Nose_Tip", "Philtrum", "Lip_Upper_C",
          "Lip_Lower_C", "Mentolabial_C", "Chin"],
}
_SIDE_COUNTS = {
    #            35  80  156
    "Brow": (3, 4, 6),
    "Lid_Upper": (1, 1, 2),
    "Lid_Lower": (0, 1, 2),
    "Eye_Outer": (0, 1, 2),
    "Nose_Ala": (1, 1, 1),
    "Nose_Side": (0, 0, 1),
    "NLF": (1, 3, 5),
    "Mouth_Corner": (1, 1, 1),
    "Lip_Upper": (1, 2, 3),
    "Lip_Lower": (1, 2, 3),
    "Mentolabial": (0, 1, 2),
    "Chin": (0, 1, 3),
    "Jaw": (2, 5, 10),
    "Forehead": (1, 3, 8),
    "Cheek": (2, 10, 24),
}
_SET_INDEX = {35: 0, 80: 1, 156: 2}

_MIDLINE_UV = {
    "Forehead_C": (0.0, 44.0),
    "Forehead_C_1": (0.0, 32.0),
    "Forehead_C_2": (0.0, 56.0),
    "Nose_Bridge": (0.0, 4.0),
    "Nose_Mid": (0.0, -16.0),
    "Nose_Tip": NOSE_TIP,
    "Philtrum": (0.0, -53.0),
    "Lip_Upper_C": (0.0, float(lip_line(0.0)) + 5.0),
    "Lip_Lower_C": (0.0, float(lip_line(0.0)) - 5.5),
    "Mentolabial_C": (0.0, -85.0),
    "Chin": (0.0, -101.0),
}

_CHEEK = np.array([(22, -16), (50, -12), (62, -30), (63, -58), (52, -78), (37, -76), (31, -60), (21, -44)], float)
_FOREHEAD = np.array([(6, 27), (46, 27), (52, 44), (42, 60), (6, 62)], float)


@dataclass(frozen=True)
class MarkerSet:
    """Names and material coordinates of a marker set.

    Attributes
    ----------
    names : list of str (M,)
    uv : float array (M, 2)
        Material coordinates, mm.
    eyelid : dict
        ``{"L": indices, "R": indices}`` of the markers hidden by the blink of each eye.
    """

    names: list[str]
    uv: np.ndarray
    eyelid: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)


def _curve(points: np.ndarray, n: int, *, margin: float = 0.0) -> np.ndarray:
    """``n`` points evenly spaced by arc length along a polyline (ends inset by ``margin``)."""
    if n == 0:
        return np.zeros((0, 2))
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.r_[0.0, np.cumsum(seg)]
    if n == 1:
        s = np.array([0.5 * cum[-1]])
    else:
        s = np.linspace(margin, cum[-1] - margin, n)
    return np.c_[np.interp(s, cum, points[:, 0]), np.interp(s, cum, points[:, 1])]


def _inside(poly: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test, ``p (N, 2)``."""
    x, y = p[:, 0], p[:, 1]
    inside = np.zeros(len(p), bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0)):
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < xc)
    return inside


def _spread(poly: np.ndarray, n: int, existing: np.ndarray) -> np.ndarray:
    """``n`` points inside ``poly`` spread by farthest-point sampling, away from ``existing``."""
    if n == 0:
        return np.zeros((0, 2))
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1e-9, 1.0), np.arange(lo[1], hi[1] + 1e-9, 1.0))
    cand = np.c_[gx.ravel(), gy.ravel()]
    cand = cand[_inside(poly, cand)]
    # stay a little inside the outline
    d_edge = np.full(len(cand), np.inf)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        ab = b - a
        t = np.clip(((cand - a) @ ab) / (ab @ ab), 0.0, 1.0)
        d_edge = np.minimum(d_edge, np.linalg.norm(cand - (a + t[:, None] * ab), axis=1))
    cand = cand[d_edge > 3.0]
    if len(existing):
        dmin = np.min(np.linalg.norm(cand[:, None, :] - existing[None, :, :], axis=2), axis=1)
    else:
        dmin = np.full(len(cand), np.inf)
    # half-weight the outline so points do not all hug it
    dmin = np.minimum(dmin, 2.0 * d_edge[d_edge > 3.0])
    chosen = []
    for _ in range(n):
        k = int(np.argmax(dmin))
        chosen.append(cand[k])
        dmin = np.minimum(dmin, np.linalg.norm(cand - cand[k], axis=1))
    pts = np.array(chosen)
    # order top to bottom, then medial to lateral, for stable readable names
    order = np.lexsort((pts[:, 0], -np.round(pts[:, 1] / 6.0)))
    return pts[order]


def _left_side(counts: dict[str, int], midline: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Left-side markers (u > 0) region by region."""
    ex, ey = EYE
    out: list[tuple[str, np.ndarray]] = []
    # brows: an arch above the eye, medial to lateral
    bu = np.linspace(12.0, 50.0, 40)
    brow = np.c_[bu, 15.0 + 5.0 * np.sin(np.pi * (bu - 10.0) / 42.0)]
    out.append(("Brow", _curve(brow, counts["Brow"], margin=1.0)))
    # upper lid: 2.5 mm above the lid margin at the middle of the eye, lower lid 2.5 mm below,
    # both offsets shrinking with the lid towards the corners (2.2 mm for the pairs at +-6 mm)
    for name, dv, k in (("Lid_Upper", LID_UP + 2.5, counts["Lid_Upper"]),
                        ("Lid_Lower", -(LID_LO + 2.5), counts["Lid_Lower"])):
        du = np.array([0.0]) if k == 1 else np.linspace(-6.0, 6.0, k)
        s = np.sqrt(np.clip(1.0 - (du / 13.0) ** 2, 0, None))
        out.append((name, np.c_[ex + du, ey + dv * s + (0.0 if dv > 0 else 0.0)] if k else np.zeros((0, 2))))
    k = counts["Eye_Outer"]
    eo = np.array([(49.0, 1.0)]) if k == 1 else np.array([(49.0, 6.0), (50.0, -4.0)])[:k]
    out.append(("Eye_Outer", eo))
    out.append(("Nose_Ala", np.array([(16.5, NOSE_TIP[1] - 5.0)])[: counts["Nose_Ala"]]))
    out.append(("Nose_Side", np.array([(9.5, -17.0)])[: counts["Nose_Side"]]))
    # nasolabial fold, from beside the ala towards the mouth corner (slightly lateral of the groove)
    nv = np.linspace(-46.0, -76.0, 30)
    nlf = np.c_[21.0 + 0.45 * (-45.0 - nv), nv]
    out.append(("NLF", _curve(nlf, counts["NLF"], margin=2.0)))
    corner = MOUTH_HALF_WIDTH + 2.5
    out.append(("Mouth_Corner", np.array([(corner, float(lip_line(corner)) - 0.5)])))
    for name, dv, k in (("Lip_Upper", 5.0, counts["Lip_Upper"]), ("Lip_Lower", -5.5, counts["Lip_Lower"])):
        lu = np.linspace(6.0, 19.0, k) if k > 1 else np.array([12.0] * k)
        out.append((name, np.c_[lu, lip_line(lu) + dv * (1.0 - 0.35 * (lu / MOUTH_HALF_WIDTH) ** 2)]))
    k = counts["Mentolabial"]
    ment = np.array([(12.0, -85.0), (23.0, -82.0)]) if k > 1 else np.array([(14.0, -85.0)])
    out.append(("Mentolabial", ment[:k]))
    k = counts["Chin"]
    out.append(("Chin", {0: np.zeros((0, 2)), 1: np.array([(15.0, -99.0)]),
                         3: np.array([(13.0, -95.0), (24.0, -92.0), (12.0, -107.0)])}[k]))
    jaw = np.array([(18.0, -109.0), (34.0, -103.0), (47.0, -93.0), (56.0, -80.0), (62.0, -64.0), (65.0, -48.0)])
    out.append(("Jaw", _curve(jaw, counts["Jaw"], margin=3.0) if counts["Jaw"] > 2 else
                np.array([(40.0, -99.0), (58.0, -76.0)])[: counts["Jaw"]]))
    placed = np.concatenate([p for _, p in out if len(p)] + [midline])
    fh = _spread(_FOREHEAD, counts["Forehead"], placed)
    placed = np.concatenate([placed, fh])
    out.append(("Forehead", fh))
    out.append(("Cheek", _spread(_CHEEK, counts["Cheek"], placed)))
    return out


def marker_set(n_markers: int) -> MarkerSet:
    """The named marker layout with ``n_markers`` markers (35, 80 or 156)."""
    if n_markers not in _SET_INDEX:
        raise ValueError(f"marker sets have 35, 80 or 156 markers, not {n_markers}")
    si = _SET_INDEX[n_markers]
    counts = {k: v[si] for k, v in _SIDE_COUNTS.items()}
    mid_names = _MIDLINE[n_markers]
    mid_uv = np.array([_MIDLINE_UV[n] for n in mid_names], float)
    names = list(mid_names)
    uvs = [mid_uv]
    eyelid: dict[str, list[int]] = {"L": [], "R": []}
    for region, pts in _left_side(counts, mid_uv):
        for side, sgn in (("L", 1.0), ("R", -1.0)):
            for i, (pu, pv) in enumerate(pts):
                name = f"{region}_{side}" if len(pts) == 1 else f"{region}_{side}_{i + 1}"
                if region in EYELID_REGIONS:
                    eyelid[side].append(len(names))
                names.append(name)
                uvs.append(np.array([[sgn * pu, pv]]))
    uv = np.concatenate(uvs)
    if len(names) != n_markers:  # pragma: no cover - a layout table error
        raise AssertionError(f"marker layout for {n_markers} produced {len(names)} markers")
    return MarkerSet(names=names, uv=uv, eyelid={k: np.array(v, int) for k, v in eyelid.items()})
