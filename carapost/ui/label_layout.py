"""Placing point labels so they do not cover each other (Qt-free, numpy).

The camera and 3D views label selected, pre-selected or all points. Labels of neighbouring
points (the brim's dots are a few pixels apart when zoomed out) must not be drawn on top of
each other. :func:`place_labels` gives each label, in priority order, the cheapest of a set of
candidate positions around its point: eight directions (right-above first, as before) on
``rings`` rings one label height apart. A candidate is allowed if it stays inside the view and
overlaps no label already placed; its cost is the number of other points' marks it covers plus
half a unit per ring, so a label moves out only to uncover marks. A label with no allowed
candidate is left out (``placed`` False) rather than drawn over another one; the caller draws a
leader line when a label sits away from its point.
"""

from __future__ import annotations

import numpy as np

__all__ = ["place_labels", "CANDIDATES"]

#: Candidate offsets of a label's top-left corner in units of (label width, label height),
#: relative to the mark's box; tried in order (right-above, right-below, left-above, ...).
CANDIDATES = np.array([
    # dx_w, dx_m, dy_h, dy_m : x = ax + dx_w*w + dx_m*m, y = ay + dy_h*h + dy_m*m
    (0.0, 1.0, -1.0, -0.6),   # right, above
    (0.0, 1.0, 0.0, 0.6),     # right, below
    (-1.0, -1.0, -1.0, -0.6),  # left, above
    (-1.0, -1.0, 0.0, 0.6),   # left, below
    (0.0, 1.2, -0.5, 0.0),    # right, centred
    (-1.0, -1.2, -0.5, 0.0),  # left, centred
    (-0.5, 0.0, -1.0, -1.2),  # above, centred
    (-0.5, 0.0, 0.0, 1.2),    # below, centred
])


def place_labels(anchors: np.ndarray, sizes: np.ndarray, *, mark: float, bounds: tuple[float, float],
                 obstacles: np.ndarray | None = None, rings: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Top-left corners of labels that do not overlap each other.

    Parameters
    ----------
    anchors : (N, 2) float
        Screen positions (px) of the labelled points, in priority order (earlier labels get
        the better places). Rows with NaN are never placed.
    sizes : (N, 2) float
        Width and height (px) of each label's box (text plus its padding).
    mark : float
        Half-size (px) of the point marks; labels keep clear of the mark.
    bounds : (width, height)
        The view; labels are kept inside it.
    obstacles : (M, 2) float, optional
        Marks (px) labels should rather not cover (each a square of half-size ``mark``);
        default: the anchors (pass every drawn mark, anchors included). A label covers a mark
        only when every free candidate position would, and never covers another label.
    rings : int
        Candidate rings: ring ``k`` moves the candidates ``k`` label heights further out.

    Returns
    -------
    corners : (N, 2) float
        Top-left corner of each label (NaN where not placed).
    placed : (N,) bool

    Raises
    ------
    ValueError
        If anchors and sizes differ in length.
    """
    anchors = np.asarray(anchors, float).reshape(-1, 2)
    sizes = np.asarray(sizes, float).reshape(-1, 2)
    if len(anchors) != len(sizes):
        raise ValueError(f"place_labels: {len(anchors)} anchors but {len(sizes)} label sizes")
    n = len(anchors)
    corners = np.full((n, 2), np.nan)
    placed = np.zeros(n, bool)
    if n == 0:
        return corners, placed
    W, H = float(bounds[0]), float(bounds[1])
    m = float(mark)
    obs = anchors if obstacles is None else np.asarray(obstacles, float).reshape(-1, 2)
    obs = obs[np.isfinite(obs).all(1)]
    # every candidate box of every label at once: (n, K, 4)
    ring = np.repeat(np.arange(rings, dtype=float), len(CANDIDATES))
    cand = np.tile(CANDIDATES, (rings, 1))
    w, h = sizes[:, 0:1], sizes[:, 1:2]
    extra = ring[None, :] * h
    xs = anchors[:, 0:1] + cand[None, :, 0] * w + cand[None, :, 1] * (m + extra)
    ys = anchors[:, 1:2] + cand[None, :, 2] * h + cand[None, :, 3] * (m + extra) + np.sign(cand[None, :, 3]) * extra * 0.3
    boxes = np.stack([xs, ys, xs + w, ys + h], -1)
    ok = (boxes[..., 0] >= 0) & (boxes[..., 1] >= 0) & (boxes[..., 2] <= W) & (boxes[..., 3] <= H)
    ok &= np.isfinite(anchors).all(1)[:, None]
    # marks each candidate covers (its own point's mark excluded): prefer free places close by
    cover = np.zeros(boxes.shape[:2])
    if len(obs):
        hit = ((obs[None, None, :, 0] - m < boxes[..., 2:3]) & (obs[None, None, :, 0] + m > boxes[..., 0:1]) &
               (obs[None, None, :, 1] - m < boxes[..., 3:4]) & (obs[None, None, :, 1] + m > boxes[..., 1:2]))
        cover = hit.sum(-1) - (hit & (np.abs(obs[None, None, :, :] - anchors[:, None, None, :]) < 1e-9).all(-1)).any(-1)
    cost = np.where(ok, cover + ring[None, :] * 0.5, np.inf)
    labels = np.zeros((n, 4))
    count = 0
    for i in np.flatnonzero(np.isfinite(cost).any(1)):
        c = cost[i]
        if count:
            b, lab = boxes[i], labels[:count]
            inter = ((lab[None, :, 0] < b[:, 2:3]) & (lab[None, :, 2] > b[:, 0:1]) &
                     (lab[None, :, 1] < b[:, 3:4]) & (lab[None, :, 3] > b[:, 1:2])).any(1)
            c = np.where(inter, np.inf, c)
        k = int(np.argmin(c))
        if not np.isfinite(c[k]):
            continue
        corners[i] = boxes[i, k, :2]
        placed[i] = True
        labels[count] = boxes[i, k]
        count += 1
    return corners, placed
