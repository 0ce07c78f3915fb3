"""Blob and patch matching for the frame-to-frame tracker.

* :class:`FrameDetections` — one frame's detections of every camera, flattened (one global
  index per detection), with their normalised and corrected coordinates and a single k-d
  tree over all cameras (each camera's detections are offset far apart, so one query serves
  every camera).
* :func:`query_candidates` — the nearest detections of each predicted projection, gated by
  distance, polarity and blob size (the *Blob Size Difference Threshold*).
* :func:`greedy_assign` — conflict resolution: two projections never take the same detection;
  cheap pairs win (vectorised as rounds of mutual best matches: every projection proposes its
  cheapest free detection, every detection keeps its cheapest proposer).
* :class:`PatchSampler`, :func:`search_patch` — appearance: normalised cross-correlation of
  *Patch Match Size* patches (sub-pixel, bilinear) and the grey-level patch tracking fallback.

Shapes: ``C`` cameras, ``T`` points, ``G`` detections of the frame (all cameras), ``K``
candidates per projection.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .track_cameras import CameraSet

__all__ = ["FrameDetections", "frame_detections", "Candidates", "query_candidates", "greedy_assign",
           "size_compatible", "neighbour_support", "PatchSampler", "search_patch"]

_OFFSET = 1.0e6  # separation of the cameras' detections in the shared k-d tree, px


@dataclass
class FrameDetections:
    """One frame's detections of all cameras, flattened.

    Every array has ``G + 1`` rows: the last is padding for "no detection" (index -1).

    Attributes
    ----------
    cam, idx : int arrays (G,)
        Camera of each detection and its index within that camera's frame.
    raw : array (G, 2)
        Raw pixels.
    uv : array (G, 2)
        Normalised coordinates.
    pc : array (G, 2)
        Corrected pixels.
    major, minor : arrays (G,)
        Ellipse semi-axes, px.
    polarity : int8 array (G,)
    start : int array (C + 1,)
        ``start[c]:start[c + 1]`` are camera ``c``'s detections.
    tree : cKDTree
        Over ``pc`` with camera ``c`` shifted by ``c * 1e6`` px in x.
    n : int
        ``G``.
    """

    cam: np.ndarray
    idx: np.ndarray
    raw: np.ndarray
    uv: np.ndarray
    pc: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    polarity: np.ndarray
    start: np.ndarray
    tree: cKDTree
    n: int

    def __len__(self) -> int:
        return self.n

    def gid(self, camera: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Global ids of (camera, index within frame) pairs; -1 where ``index < 0``."""
        return np.where(index >= 0, self.start[camera] + index, -1)


def frame_detections(tables: Sequence[Mapping[str, np.ndarray] | None], cams: CameraSet) -> FrameDetections:
    """Flatten one frame's detection tables (one per camera; ``None`` = camera unusable).

    Every per-detection array has one extra *padding* row at the end (NaN coordinates and
    sizes, polarity 0, camera and index -1), so indexing with ``-1`` ("no detection") yields
    missing values without a mask.
    """
    C = len(cams)
    counts = np.array([0 if tb is None else len(tb["x"]) for tb in tables], np.int64)
    start = np.zeros(C + 1, np.int64)
    np.cumsum(counts, out=start[1:])
    G = int(start[-1])
    raw = np.full((G + 1, 2), np.nan)
    uv = np.full((G + 1, 2), np.nan)
    major = np.full(G + 1, np.nan, np.float32)
    minor = np.full(G + 1, np.nan, np.float32)
    pol = np.zeros(G + 1, np.int8)
    for c, tb in enumerate(tables):
        if tb is None or counts[c] == 0:
            continue
        s = slice(start[c], start[c + 1])
        raw[s, 0] = tb["x"]
        raw[s, 1] = tb["y"]
        uv[s] = cams.normalise(c, raw[s])
        major[s] = tb["major"]
        minor[s] = tb["minor"]
        pol[s] = tb["polarity"]
    cam = np.append(np.repeat(np.arange(C), counts), -1)
    idx = np.append(np.arange(G) - start[cam[:G]], -1)
    camz = np.maximum(cam, 0)
    pc = np.empty((G + 1, 2))
    pc[:, 0] = cams.f[camz] * uv[:, 0] + cams.skew[camz] * uv[:, 1] + cams.pp[camz, 0]
    pc[:, 1] = cams.fy[camz] * uv[:, 1] + cams.pp[camz, 1]
    key = pc[:G].copy()
    key[:, 0] += cam[:G] * _OFFSET
    key = np.where(np.isfinite(key), key, -1e12)  # a NaN detection can never be near anything
    return FrameDetections(cam, idx, raw, uv, pc, major, minor, pol, start, cKDTree(key), G)


def size_compatible(maj_a: np.ndarray, min_a: np.ndarray, maj_b: np.ndarray, min_b: np.ndarray,
                    threshold: float) -> np.ndarray:
    """Blob Size Difference Threshold: relative width and height differences both within it.

    The relative difference of two sizes is ``|a - b| / max(a, b)`` (0 = equal, 1 = one is
    zero); ``threshold`` 1 accepts anything, 0 only identical sizes. Unknown sizes (NaN) pass.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        d1 = np.abs(maj_a - maj_b) / np.maximum(maj_a, maj_b)
        d2 = np.abs(min_a - min_b) / np.maximum(min_a, min_b)
    return ~((d1 > threshold + 1e-9) | (d2 > threshold + 1e-9))


@dataclass
class Candidates:
    """Candidate detections of ``Q`` queried projections (``K`` nearest each).

    Attributes
    ----------
    query : int array (Q,)
        Flat ``c * T + t`` index of each queried projection.
    det : int array (Q, K)
        Global detection ids (-1 = none).
    dist : array (Q, K)
        Distance, corrected px (inf where ``det`` is -1).
    ok : bool array (Q, K)
        Passes every gate (distance, polarity, size, not claimed).
    nearest, second : arrays (Q,)
        Distances to the nearest and second-nearest unclaimed detections of compatible
        polarity, whatever their size or distance (inf if none): how ambiguous a match is.
    taken : array (Q,)
        Distance to the nearest claimed detection of compatible polarity (inf if none among
        the ``K``): where it is much nearer than any free one, the point is probably hidden
        behind the point that claimed it.
    """

    query: np.ndarray
    det: np.ndarray
    dist: np.ndarray
    ok: np.ndarray
    nearest: np.ndarray
    second: np.ndarray
    taken: np.ndarray | None = None


def query_candidates(dets: FrameDetections, pred_pc: np.ndarray, active: np.ndarray, radius: np.ndarray, *,
                     claimed: np.ndarray, polarity: np.ndarray, size: np.ndarray, size_threshold: float,
                     forbid: np.ndarray | None = None, k: int = 4) -> Candidates:
    """Nearest detections of predicted projections, with the tracker's gates applied.

    Parameters
    ----------
    dets : FrameDetections
    pred_pc : array (C, T, 2)
        Predicted projections, corrected px.
    active : bool array (C, T)
        Which projections to query.
    radius : array (T,) or (C, T)
        Search radius of each projection, px.
    claimed : bool array (G,)
        Detections already taken (by other points or earlier rounds).
    polarity : int array (T,)
        Point polarity (0 = unknown, matches any).
    size : array (C, T, 2)
        Last matched blob (major, minor) of each point in each camera (NaN = unknown).
    size_threshold : float
        Blob Size Difference Threshold.
    forbid : int array (C, T), optional
        A detection each projection may not take (e.g. one that failed the patch match).
    k : int
        Candidates kept per projection.

    Returns
    -------
    Candidates
    """
    C, T = active.shape
    q = np.flatnonzero(active.ravel())
    G = len(dets)
    if len(q) == 0 or G == 0:
        e = np.zeros((len(q), k))
        inf = np.full(len(q), np.inf)
        return Candidates(q, np.full((len(q), k), -1), np.full_like(e, np.inf), e.astype(bool), inf, inf.copy(),
                          inf.copy())
    cq, tq = np.divmod(q, T)
    pts = pred_pc.reshape(-1, 2)[q].copy()
    pts[:, 0] += cq * _OFFSET
    radius = np.asarray(radius, float)
    rad = radius[tq] if radius.ndim == 1 else radius.reshape(-1)[q]
    kk = min(k, G)
    dist, j = dets.tree.query(pts, k=kk, distance_upper_bound=float(np.max(rad)) + 1e-9)
    dist = dist.reshape(len(q), kk)
    j = j.reshape(len(q), kk)
    found = j < G          # missing neighbours come back as G: the padding row
    pol_ok = (polarity[tq][:, None] == 0) | (dets.polarity[j] == polarity[tq][:, None])
    free = found & ~claimed[j] & pol_ok
    if forbid is not None:
        free &= j != forbid.reshape(-1)[q][:, None]
    sz = size.reshape(-1, 2)[q]
    ok = free & (dist <= rad[:, None]) & size_compatible(sz[:, 0:1], sz[:, 1:2], dets.major[j], dets.minor[j],
                                                       size_threshold)
    dfree = np.where(free, dist, np.inf)
    dfree.sort(axis=1)
    second = dfree[:, 1] if kk > 1 else np.full(len(q), np.inf)
    det = np.where(found, j, -1)
    taken = np.where(found & claimed[j] & pol_ok, dist, np.inf).min(axis=1)
    return Candidates(q, det, np.where(ok, dist, np.inf), ok, dfree[:, 0].copy(), second, taken)


def greedy_assign(query: np.ndarray, det: np.ndarray, cost: np.ndarray, n_det: int) -> np.ndarray:
    """Assign detections to queries, cheapest pairs first, each detection at most once.

    Parameters
    ----------
    query : int array (Q,)
        Query ids (only used for their number).
    det : int array (Q, K)
        Candidate detection ids.
    cost : array (Q, K)
        Pair costs; ``inf`` = not allowed.
    n_det : int
        Number of detections (ids are ``0..n_det-1``).

    Returns
    -------
    int array (Q,)
        The detection given to each query, -1 for none.
    """
    Q = len(query)
    out = np.full(Q, -1, np.int64)
    if Q == 0 or cost.size == 0:
        return out
    cost = cost.copy()
    taken = np.zeros(n_det + 1, bool)
    rows = np.arange(Q)
    for _ in range(64):
        best = np.argmin(cost, axis=1)
        bc = cost[rows, best]
        live = np.isfinite(bc)
        if not np.any(live):
            break
        lq = rows[live]
        ld = det[lq, best[live]]
        lc = bc[live]
        # each detection's cheapest live query wins it
        order = np.lexsort((lc, ld))
        ds = ld[order]
        first = np.ones(len(ds), bool)
        first[1:] = ds[1:] != ds[:-1]
        win = lq[order[first]]
        wd = ds[first]
        out[win] = wd
        taken[wd] = True
        cost[win] = np.inf
        cost[taken[np.where(det >= 0, det, n_det)]] = np.inf
    return out


def neighbour_support(dets: FrameDetections, cand: Candidates, pred_pc: np.ndarray, neighbours: np.ndarray,
                      weights: np.ndarray, *, rows: np.ndarray | None = None, tol_px: float = 3.0,
                      tol_rel: float = 0.2) -> np.ndarray:
    """How well each candidate's displacement agrees with the neighbours' candidates.

    Skin moves smoothly: between two frames, neighbouring markers move by similar amounts in
    the image. A candidate detection implies a displacement from the point's prediction; it
    is supported by a neighbour that has a candidate with a similar displacement (within
    ``tol_px + tol_rel * |displacement|``). This finds the right detections even when the
    prediction is off by a marker spacing (an expression starting or stopping within a
    frame), where the nearest detection is a neighbour's.

    Parameters
    ----------
    dets : FrameDetections
    cand : Candidates
        From :func:`query_candidates` on ``pred_pc``.
    pred_pc : array (C, T, 2)
        Predicted projections, corrected px.
    neighbours, weights : arrays (T, k)
        The neighbour graph (:class:`~.track_predict.NeighbourGraph`).
    rows : bool array (Q,), optional
        Queries to compute the support of (others: NaN).

    Returns
    -------
    array (Q, K)
        Support of each candidate in ``[0, 1]`` (weighted fraction of the point's neighbours
        queried in the same camera that agree); NaN where the point has no such neighbour.
    """
    C, T = pred_pc.shape[:2]
    Q, K = cand.det.shape
    if Q == 0:
        return np.zeros((0, K))
    ok = cand.ok
    out = np.full((Q, K), np.nan)
    r = np.arange(Q) if rows is None else np.flatnonzero(rows)
    if len(r) == 0:
        return out
    # only the gated candidates take part: compact them to the front of each row (Km <= K)
    order = np.argsort(~ok, axis=1, kind="stable")
    Km = max(int(ok.sum(1).max()), 1)
    order = order[:, :Km]
    rows_q = np.arange(Q)[:, None]
    okc = ok[rows_q, order]                                                 # (Q, Km)
    detc = cand.det[rows_q, order]
    d = dets.pc[np.where(okc, detc, -1)]                                    # (Q, Km, 2) NaN where not ok
    d -= pred_pc.reshape(-1, 2)[cand.query][:, None, :]
    # displacements per flat projection, x and y apart (contiguous for the broadcasts below)
    dispx = np.full((C * T, Km), np.nan, np.float32)
    dispy = np.full((C * T, Km), np.nan, np.float32)
    dispx[cand.query] = d[..., 0]
    dispy[cand.query] = d[..., 1]
    queried = np.zeros(C * T, bool)
    queried[cand.query] = True
    qc, qt = np.divmod(cand.query[r], T)
    nb = qc[:, None] * T + neighbours[qt]                                   # (R, kn) flat ids
    w = weights[qt] * queried[nb]
    mx, my = dispx[cand.query[r]], dispy[cand.query[r]]                     # (R, Km)
    tx, ty = dispx[nb], dispy[nb]                                           # (R, kn, Km)
    tol = tol_px + tol_rel * np.sqrt(mx * mx + my * my)                     # (R, Km)
    tol2 = (tol * tol)[:, None, :]
    agree = np.zeros(tx.shape, bool)                                        # (R, kn, Km)
    # one of the neighbour's candidates at a time (no (R, kn, Km, Km) array, no reduction
    # over a short axis)
    with np.errstate(invalid="ignore"):
        for j in range(Km):
            dx = mx[:, None, :] - tx[:, :, j:j + 1]
            dy = my[:, None, :] - ty[:, :, j:j + 1]
            dx *= dx
            dy *= dy
            dx += dy
            agree |= dx <= tol2
    sw = w.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sup = np.einsum("qnk,qn->qk", agree.astype(np.float32), w.astype(np.float32)) / sw[:, None]
    res = np.where(ok[r], np.nan, 0.0)                                      # (R, K)
    rr, jj = np.nonzero(okc[r])
    res[rr, order[r][rr, jj]] = np.where(sw[rr] > 0, sup[rr, jj], np.nan)
    out[r] = res
    return out


class PatchSampler:
    """Sub-pixel grey-level patches of *Patch Match Size* pixels and their normalised form.

    Parameters
    ----------
    size : int
        Patch side, px (the guide's Patch Match Size).
    """

    def __init__(self, size: int) -> None:
        if size < 3:
            raise ValueError(f"Patch Match Size must be at least 3 px, got {size}")
        self.size = int(size)
        self.offsets = (np.arange(self.size) - (self.size - 1) / 2.0).astype(np.float32)

    def sample(self, image: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear patches centred on raw positions.

        Parameters
        ----------
        image : uint8 (H, W)
        xy : array (n, 2)
            Raw-pixel centres.

        Returns
        -------
        patches : float32 (n, S, S)
        inside : bool (n,)
            The whole patch lies inside the image.
        """
        S = self.size
        n = len(xy)
        if n == 0:
            return np.zeros((0, S, S), np.float32), np.zeros(0, bool)
        H, W = image.shape
        xy = np.asarray(xy, np.float32)
        half = (S - 1) / 2.0
        inside = (np.isfinite(xy).all(1) & (xy[:, 0] - half >= 0) & (xy[:, 1] - half >= 0)
                  & (xy[:, 0] + half <= W - 1) & (xy[:, 1] + half <= H - 1))
        xs = np.where(inside, xy[:, 0], half)
        ys = np.where(inside, xy[:, 1], half)
        mapx = np.broadcast_to((xs[:, None] + self.offsets[None, :])[:, None, :], (n, S, S)).reshape(n * S, S)
        mapy = np.broadcast_to((ys[:, None] + self.offsets[None, :])[:, :, None], (n, S, S)).reshape(n * S, S)
        out = cv2.remap(image, np.ascontiguousarray(mapx), np.ascontiguousarray(mapy), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(n, S, S).astype(np.float32), inside

    @staticmethod
    def normalise(patches: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Zero-mean, unit-norm flattened patches ``(n, S*S)``; flat or invalid patches are
        marked invalid (and zero)."""
        n = len(patches)
        a = patches.reshape(n, -1)
        a = a - a.mean(axis=1, keepdims=True)
        norm = np.sqrt(np.einsum("ij,ij->i", a, a))
        good = valid & (norm > 1e-3 * a.shape[1])
        a *= np.where(good, 1.0 / np.where(good, norm, 1.0), 0.0)[:, None]
        return a, good


def search_patch(image: np.ndarray, template: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, float]:
    """Grey-level patch tracking: find a template near a predicted position.

    Normalised cross-correlation (``cv2.matchTemplate``, ``TM_CCOEFF_NORMED``) of the template
    over every position within ``radius`` of ``centre``, with a parabolic sub-pixel peak.

    Parameters
    ----------
    image : uint8 (H, W)
    template : float32 (S, S)
        The previous frame's patch (any offset/scale of grey levels).
    centre : array (2,)
        Predicted raw position.
    radius : float
        Search radius, px.

    Returns
    -------
    xy : array (2,)
        Raw position of the best match (NaN if the window leaves no room).
    score : float
        Its normalised cross-correlation (-1..1; -1 if nothing was searched).
    """
    S = template.shape[0]
    half = (S - 1) / 2.0
    H, W = image.shape
    r = int(np.ceil(radius))
    cx, cy = int(round(float(centre[0]))), int(round(float(centre[1])))
    x0 = max(cx - r - int(np.floor(half)), 0)
    y0 = max(cy - r - int(np.floor(half)), 0)
    x1 = min(cx + r + int(np.ceil(half)) + 1, W)
    y1 = min(cy + r + int(np.ceil(half)) + 1, H)
    if x1 - x0 < S + 2 or y1 - y0 < S + 2:
        return np.array([np.nan, np.nan]), -1.0
    win = image[y0:y1, x0:x1].astype(np.float32)
    res = cv2.matchTemplate(win, np.ascontiguousarray(template, np.float32), cv2.TM_CCOEFF_NORMED)
    # positions farther than the radius from the prediction (and flat, undefined scores) lose
    px = np.arange(res.shape[1]) + (x0 + half - float(centre[0]))
    py = np.arange(res.shape[0]) + (y0 + half - float(centre[1]))
    outside = (py * py)[:, None] + (px * px)[None, :] > radius * radius
    res[outside | ~np.isfinite(res)] = -1.0
    _, score, _, (ix, iy) = cv2.minMaxLoc(res)
    dx = _parabola(res, iy, ix, 0)
    dy = _parabola(res, iy, ix, 1)
    return np.array([x0 + ix + half + dx, y0 + iy + half + dy]), float(score)


def _parabola(res: np.ndarray, iy: int, ix: int, axis: int) -> float:
    """Sub-pixel offset of a correlation peak along one axis (0 at the border)."""
    if axis == 0:
        if not 0 < ix < res.shape[1] - 1:
            return 0.0
        a, b, c = res[iy, ix - 1], res[iy, ix], res[iy, ix + 1]
    else:
        if not 0 < iy < res.shape[0] - 1:
            return 0.0
        a, b, c = res[iy - 1, ix], res[iy, ix], res[iy + 1, ix]
    den = a - 2 * b + c
    if den >= 0 or a <= -1 or c <= -1:
        return 0.0
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
