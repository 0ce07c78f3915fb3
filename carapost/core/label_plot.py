"""Inspection plots of labelled markers (seed 002 saves one every N frames), drawn with OpenCV.

:func:`render_markers` draws one frame as three orthographic views (X-Y, X-Z, Y-Z) side by
side on a common scale, with sticks, marker names, the markers relabelled in that frame in red
and a list of notes (e.g. ``"Brow_L_1 <- Marker_27"``). It returns an image array; saving it
is the caller's business (``cv2.imwrite``).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

__all__ = ["render_markers"]

_BG = (255, 255, 255)
_AXES = ((0, 1, "X", "Y"), (0, 2, "X", "Z"), (1, 2, "Y", "Z"))


def render_markers(xyz: np.ndarray, names: Sequence[str], *, sticks: np.ndarray | None = None,
                   highlight: np.ndarray | None = None, notes: Sequence[str] = (), title: str = "",
                   limits: np.ndarray | None = None, size: tuple[int, int] = (1500, 640),
                   show_names: bool = True) -> np.ndarray:
    """Draw one frame of labelled markers.

    Parameters
    ----------
    xyz : float (M, 3)
        Positions, mm; NaN markers are not drawn.
    names : sequence of str (M,)
    sticks : int (S, 2), optional
        Marker pairs joined by lines.
    highlight : bool (M,), optional
        Markers drawn in red (e.g. relabelled in this frame).
    notes : sequence of str
        Lines of text listed on the right (at most 40 shown).
    title : str
    limits : float (3, 2), optional
        ``[[xmin, xmax], [ymin, ymax], [zmin, zmax]]`` in mm (default: the frame's bounding box
        with a 10 % margin); keep them fixed to compare frames.
    size : (int, int)
        Image width and height, pixels.
    show_names : bool

    Returns
    -------
    uint8 (H, W, 3)
        BGR image.
    """
    X = np.asarray(xyz, np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] != len(names):
        raise ValueError(f"xyz must have shape ({len(names)}, 3), got {X.shape}")
    W, H = int(size[0]), int(size[1])
    img = np.full((H, W, 3), 255, np.uint8)
    ok = np.isfinite(X).all(1)
    hl = np.zeros(len(X), bool) if highlight is None else np.asarray(highlight, bool)
    if limits is None:
        if ok.any():
            lo, hi = X[ok].min(0), X[ok].max(0)
        else:
            lo, hi = np.zeros(3), np.ones(3)
        pad = 0.1 * np.maximum(hi - lo, 1.0)
        lim = np.stack([lo - pad, hi + pad], 1)
    else:
        lim = np.asarray(limits, np.float64).reshape(3, 2)
    notes_w = 260 if notes else 0
    top = 40
    pw = (W - notes_w) // 3
    ph = H - top - 10
    span = np.maximum(lim[:, 1] - lim[:, 0], 1e-6)
    scale = min(min((pw - 30) / span[a], (ph - 30) / span[b]) for a, b, _, _ in _AXES)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(img, title, (10, 28), font, 0.8, (0, 0, 0), 2, cv2.LINE_AA)
    sk = np.zeros((0, 2), np.int64) if sticks is None else np.asarray(sticks, np.int64).reshape(-1, 2)
    for k, (a, b, na, nb) in enumerate(_AXES):
        # centre the limits' box in the panel
        x0 = k * pw + 5 + 0.5 * (pw - 10 - span[a] * scale)
        y0 = top + ph - 0.5 * (ph - span[b] * scale)
        cv2.rectangle(img, (k * pw + 5, top), (k * pw + pw - 5, top + ph), (200, 200, 200), 1)
        cv2.putText(img, f"{na}-{nb}", (k * pw + 12, top + 20), font, 0.5, (90, 90, 90), 1, cv2.LINE_AA)
        u = np.round(x0 + (X[:, a] - lim[a, 0]) * scale)
        v = np.round(y0 - (X[:, b] - lim[b, 0]) * scale)
        uv = np.stack([u, v], 1)
        for i, j in sk:
            if ok[i] and ok[j]:
                cv2.line(img, (int(uv[i, 0]), int(uv[i, 1])), (int(uv[j, 0]), int(uv[j, 1])), (170, 170, 170), 1,
                         cv2.LINE_AA)
        for m in np.flatnonzero(ok):
            p = (int(uv[m, 0]), int(uv[m, 1]))
            col = (0, 0, 220) if hl[m] else (60, 60, 60)
            cv2.circle(img, p, 3, col, -1, cv2.LINE_AA)
            if show_names and (len(X) <= 150 or hl[m]):
                cv2.putText(img, names[m], (p[0] + 4, p[1] - 3), font, 0.3, col, 1, cv2.LINE_AA)
    if notes:
        x = W - notes_w + 5
        cv2.putText(img, "Remaps:", (x, top + 15), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        for i, line in enumerate(list(notes)[:40]):
            cv2.putText(img, line[:40], (x, top + 35 + 14 * i), font, 0.38, (0, 0, 200), 1, cv2.LINE_AA)
    return img
