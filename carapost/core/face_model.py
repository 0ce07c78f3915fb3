"""A learned face model that recovers occluded markers (seed 001, section 5.4 "Face model").

The model is a set of *basis faces* ``B_i`` — whole-face marker configurations taken from a
take (or from a range-of-motion take of the same actor and marker set) — and a face is a
linear combination ``F = sum_i w_i B_i``. Following the seed:

* **Choosing the basis** (:func:`build_face_model`): the complete frames (every model marker
  present) are rigidly aligned to their mean shape (generalized Procrustes, removing head
  motion), principal component analysis gives the main modes of motion, and for each of the
  leading components the frame with the largest absolute projection onto it — the most
  *extreme* face along that mode — becomes a basis face (by default the extreme faces at both
  ends of each mode: see :func:`build_face_model`). Neutral faces and duplicates drop out.
* **Fitting** (:func:`fit_face_model`): the markers visible in a frame are fitted with weights
  constrained to ``0 <= w_i <= 1`` (bounded least squares), so the model *interpolates*
  between known faces instead of extrapolating; missing markers are removed from both ``F``
  and ``B`` for the fit and read back from the full basis. Here the frame's rigid pose
  relative to the model frame is estimated at the same time (alternating a weighted Kabsch
  fit and the weight fit).
* **Filling** (:func:`face_model_fill`): the model's prediction of a missing marker, optionally
  corrected by the model's offset at the known samples either side of the gap (blended
  linearly across it) so the filled trajectory joins the data without a jump.

Array contract: ``xyz (F, P, 3)`` mm, NaN gaps; masks ``(F, P)`` bool; a model covers a subset
of the point columns (``FaceModel.points``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gapfill import GapFillResult, _last_known, weighted_rigid_fit

__all__ = ["FaceModel", "FaceFit", "build_face_model", "fit_face_model", "face_model_fill", "procrustes_align",
           "bounded_quadratic"]


@dataclass
class FaceModel:
    """Basis faces of one actor and marker set.

    Attributes
    ----------
    points : int array (M,)
        Point columns (of the take the model was built from) the model covers.
    basis : float64 array (K, M, 3)
        Basis faces in the model frame, mm.
    frames : int array (K,)
        Frame each basis face was taken from.
    reference : float64 array (M, 3)
        Mean aligned shape (centroid at the origin): the model frame.
    components : int
        Principal components used to choose the basis.
    explained : float
        Share of the shape variance those components explain, 0..1.
    n_complete : int
        Complete frames the model was learnt from.
    """

    points: np.ndarray
    basis: np.ndarray
    frames: np.ndarray
    reference: np.ndarray
    components: int
    explained: float
    n_complete: int

    @property
    def n_bases(self) -> int:
        return int(self.basis.shape[0])


@dataclass
class FaceFit:
    """Result of :func:`fit_face_model` for some frames.

    Attributes
    ----------
    frames : int array (N,)
    xyz : float64 array (N, M, 3)
        The model's face in each frame, in the take's coordinates, mm (NaN where the frame
        could not be fitted: fewer than ``min_visible`` model markers).
    weights : float64 array (N, K)
    rms : float64 array (N,)
        RMS distance between the fitted face and the visible markers, mm.
    """

    frames: np.ndarray
    xyz: np.ndarray
    weights: np.ndarray
    rms: np.ndarray


def procrustes_align(shapes: np.ndarray, *, iterations: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Generalized Procrustes alignment (rotation and translation, no scaling).

    Parameters
    ----------
    shapes : array (N, M, 3)
        Complete shapes (no NaN).
    iterations : int

    Returns
    -------
    aligned : array (N, M, 3)
        Every shape rigidly moved onto the mean shape.
    mean : array (M, 3)
        The mean aligned shape, centroid at the origin.
    """
    shapes = np.asarray(shapes, dtype=float)
    N, M, _ = shapes.shape
    ref = shapes[0] - shapes[0].mean(0)
    w = np.ones((N, M))
    aligned = shapes
    for _ in range(max(1, iterations)):
        R, t = weighted_rigid_fit(shapes, np.broadcast_to(ref, shapes.shape), w)
        aligned = np.einsum("nij,nmj->nmi", R, shapes) + t[:, None]
        new = aligned.mean(0)
        new -= new.mean(0)
        if np.abs(new - ref).max() < 1e-9:
            ref = new
            break
        ref = new
    return aligned, ref


def bounded_quadratic(G: np.ndarray, h: np.ndarray, *, lo: float = 0.0, hi: float = 1.0,
                      max_iter: int | None = None, init: np.ndarray | None = None) -> np.ndarray:
    """Batched box-constrained least squares: ``min 1/2 w^T G w - h^T w`` with ``lo <= w <= hi``.

    For a least-squares problem ``min |A w - y|^2`` pass ``G = A^T A`` and ``h = A^T y``. A
    primal active-set method (bounded-variable least squares, as Stark and Parker's BVLS)
    run on all problems at once: start with every variable at its lower bound, free the
    variable that most violates the optimality conditions, solve for the free variables,
    step back to the box where the solution leaves it, repeat.

    Parameters
    ----------
    G : array (N, K, K)
        Symmetric positive (semi-)definite matrices.
    h : array (N, K)
    lo, hi : float
        Bounds (``lo < hi``).
    max_iter : int, optional
        Iteration cap (default ``4 K + 20``).
    init : array (N, K), optional
        A starting point (e.g. the solution of a similar problem): it is clipped to the box,
        variables on a bound start fixed there, the others free.

    Returns
    -------
    w : array (N, K)
    """
    G = np.asarray(G, dtype=float)
    h = np.asarray(h, dtype=float)
    N, K = h.shape
    if max_iter is None:
        max_iter = 4 * K + 20
    scale = np.maximum(np.einsum("nkk->n", G) / max(K, 1), 1e-300)
    ridge = 1e-12 * scale
    tol = 1e-9 * scale * max(1.0, hi - lo)
    if init is None:
        w = np.full((N, K), float(lo))
        status = np.full((N, K), -1, np.int8)     # -1 at lo, +1 at hi, 0 free
    else:
        w = np.clip(np.asarray(init, dtype=float), lo, hi)
        status = np.where(w <= lo, -1, np.where(w >= hi, 1, 0)).astype(np.int8)
    active = np.ones(N, bool)
    eye = np.eye(K, dtype=bool)
    # True: the free variables are optimal, check the fixed ones; False: solve for the free ones
    need_kkt = (status != 0).all(1)
    for _ in range(max_iter):
        if not active.any():
            break
        # 1. optimality of the fixed variables, for problems whose free set is solved
        chk = active & need_kkt
        if chk.any():
            g = np.einsum("nkl,nl->nk", G[chk], w[chk]) - h[chk]
            st = status[chk]
            viol = np.where(st == -1, -g, np.where(st == 1, g, -np.inf))
            k = np.argmax(viol, axis=1)
            vmax = viol[np.arange(len(k)), k]
            rows = np.flatnonzero(chk)
            release = vmax > tol[chk]
            status[rows[release], k[release]] = 0
            active[rows[~release]] = False
            need_kkt[rows[release]] = False
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        # 2. solve for the free variables with the fixed ones at their bounds
        free = status[idx] == 0
        Gi = G[idx]
        pair = free[:, :, None] & free[:, None, :]
        A = np.where(pair, Gi, 0.0) + np.where(eye, np.where(free, ridge[idx, None], 1.0)[:, :, None], 0.0)
        wf = np.where(free, 0.0, w[idx])
        rhs = np.where(free, h[idx] - np.einsum("nkl,nl->nk", Gi, wf), w[idx])
        z = np.linalg.solve(A, rhs[..., None])[..., 0]
        out = free & ((z < lo) | (z > hi))
        inside = ~out.any(1)
        # inside the box: accept, then check the fixed variables next round
        ok = idx[inside]
        w[ok] = z[inside]
        need_kkt[ok] = True
        # outside: step towards z until the first free variable reaches a bound; fix those
        bad = ~inside
        if bad.any():
            wb, zb, ob = w[idx[bad]], z[bad], out[bad]
            d = zb - wb
            with np.errstate(divide="ignore", invalid="ignore"):
                lim = np.where(d < 0, (lo - wb) / d, (hi - wb) / d)
            lim = np.where(ob, lim, np.inf)
            alpha = np.clip(lim.min(1), 0.0, 1.0)
            wn = wb + alpha[:, None] * d
            fr = status[idx[bad]] == 0
            at_lo = fr & (wn <= lo + 1e-12 * (hi - lo))
            at_hi = fr & (wn >= hi - 1e-12 * (hi - lo))
            # the limiting variables are fixed even if rounding left them a hair inside
            hit = ob & (lim <= alpha[:, None] + 1e-12)
            at_lo |= hit & (d < 0)
            at_hi |= hit & (d > 0)
            wn = np.where(at_lo, lo, np.where(at_hi, hi, np.clip(wn, lo, hi)))
            st = status[idx[bad]]
            st[at_lo] = -1
            st[at_hi] = 1
            status[idx[bad]] = st
            w[idx[bad]] = wn
            need_kkt[idx[bad]] = False
    return w


def _choose_columns(present: np.ndarray, min_frames: int) -> np.ndarray:
    """The largest set of columns (most present first) with at least ``min_frames`` frames in
    which all of them are present."""
    order = np.argsort(-present.sum(0), kind="stable")
    complete = np.logical_and.accumulate(present[:, order], axis=1).sum(0)  # (P,) for each prefix
    ok = np.flatnonzero(complete >= min_frames)
    if not len(ok):
        return np.zeros(0, np.int64)
    return np.sort(order[: ok[-1] + 1])


def build_face_model(xyz: np.ndarray, *, points: np.ndarray | None = None, frames: np.ndarray | None = None,
                     n_components: int | None = None, variance: float = 0.99, max_bases: int = 40,
                     both_ends: bool = True, min_frames: int | None = None) -> FaceModel:
    """Learn a face model from the complete frames of a take (or a ROM take).

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm, NaN gaps.
    points : int array, optional
        Columns the model covers. By default the largest set of columns (most often present
        first) that still leaves ``min_frames`` complete frames.
    frames : int array, optional
        Frames to learn from (default all).
    n_components : int, optional
        Principal components to use; by default the fewest explaining ``variance``.
    variance : float
        Share of the aligned shape variance to explain, 0..1.
    max_bases : int
        Upper bound on the number of components (and so of basis faces per end).
    both_ends : bool
        Also take the most extreme face at the *other* end of each component (largest
        positive and most negative projection). The seed takes only the largest absolute
        projection — one face per component — but ``k`` faces span only a ``k - 1``
        dimensional family of faces with interpolating weights, too few for ``k`` modes;
        both ends span each mode's whole range (see ``docs/gap-filling.md``). False gives
        the seed's choice exactly.
    min_frames : int, optional
        Complete frames required (default ``max(10, 5 % of the frames)``).

    Returns
    -------
    FaceModel

    Raises
    ------
    ValueError
        Too few complete frames or markers (fewer than 3 markers, or fewer complete frames
        than ``min_frames``).
    """
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"xyz must have shape (F, P, 3), got {xyz.shape}")
    if not 0 < variance <= 1:
        raise ValueError(f"variance must be within (0, 1], got {variance}")
    F, P, _ = xyz.shape
    fr = np.arange(F) if frames is None else np.asarray(frames, dtype=np.int64)
    sub = xyz[fr]
    present = np.isfinite(sub).all(-1)
    if min_frames is None:
        min_frames = max(10, int(0.05 * len(fr)))
    if points is None:
        cols = _choose_columns(present, min_frames)
    else:
        cols = np.unique(np.asarray(points, dtype=np.int64))
    if len(cols) < 3:
        raise ValueError(f"a face model needs at least 3 markers present together in {min_frames} frames")
    complete = present[:, cols].all(1)
    n_complete = int(complete.sum())
    if n_complete < max(min_frames, 2):
        raise ValueError(f"a face model needs at least {max(min_frames, 2)} frames with all {len(cols)} model "
                         f"markers present; found {n_complete}")
    src_frames = fr[complete]
    aligned, ref = procrustes_align(sub[complete][:, cols])
    D = aligned.reshape(n_complete, -1)
    mean = D.mean(0)
    U, S, Vt = np.linalg.svd(D - mean, full_matrices=False)
    var = S ** 2
    total = var.sum()
    if n_components is None:
        if total <= 0:
            k = 1
        else:
            k = int(np.searchsorted(np.cumsum(var) / total, variance - 1e-12) + 1)
    else:
        k = int(n_components)
    k = max(1, min(k, max_bases, len(S)))
    explained = float(var[:k].sum() / total) if total > 0 else 1.0
    proj = (D - mean) @ Vt[:k].T                       # (n, k) projections on the components
    picks = list(np.argmax(np.abs(proj), axis=0))
    if both_ends:
        picks += list(np.argmax(proj, axis=0)) + list(np.argmin(proj, axis=0))
    idx = np.array(sorted(set(int(i) for i in picks)), dtype=np.int64)
    return FaceModel(points=cols, basis=aligned[idx].copy(), frames=src_frames[idx], reference=ref,
                     components=k, explained=explained, n_complete=n_complete)


def fit_face_model(model: FaceModel, xyz: np.ndarray, frames: np.ndarray, known: np.ndarray | None = None, *,
                   iterations: int = 3, min_visible: int = 3) -> FaceFit:
    """Fit the model to the visible markers of some frames.

    Parameters
    ----------
    model : FaceModel
    xyz : array (F, P, 3)
        Positions of the take, mm (the model's ``points`` index its columns).
    frames : int array (N,)
        Frames to fit.
    known : bool array (F, P), optional
        Samples that may be used (default: finite ones).
    iterations : int
        Alternations of the pose fit and the weight fit.
    min_visible : int
        Frames with fewer visible model markers are not fitted (NaN).

    Returns
    -------
    FaceFit
    """
    xyz = np.asarray(xyz, dtype=float)
    frames = np.asarray(frames, dtype=np.int64)
    cols = model.points
    X = xyz[frames][:, cols]                         # (N, M, 3)
    vis = np.isfinite(X).all(-1)
    if known is not None:
        vis &= np.asarray(known, dtype=bool)[frames][:, cols]
    N, M = vis.shape
    K = model.n_bases
    B = model.basis                                  # (K, M, 3)
    Gm = np.einsum("kmd,lmd->mkl", B, B).reshape(M, K * K)   # per-marker Gram contributions
    G = (vis.astype(float) @ Gm).reshape(N, K, K)             # B_V^T B_V for every frame
    Xz = np.where(vis[..., None], X, 0.0)
    w8 = vis.astype(float)
    out = np.full((N, M, 3), np.nan)
    weights = np.full((N, K), np.nan)
    rms = np.full(N, np.nan)
    ok = vis.sum(1) >= max(3, min_visible)
    if not ok.any():
        return FaceFit(frames, out, weights, rms)
    # initial pose: model frame -> take, from the reference shape
    shape = np.broadcast_to(model.reference, (N, M, 3)).copy()
    W = np.zeros((N, K))
    for it in range(max(1, iterations)):
        R, t = weighted_rigid_fit(shape, Xz, w8)            # model -> take
        Y = np.einsum("nji,nmj->nmi", R, Xz - t[:, None])   # visible markers in the model frame
        Y = np.where(vis[..., None], Y, 0.0)
        h = np.einsum("kmd,nmd->nk", B, Y)
        W[ok] = bounded_quadratic(G[ok], h[ok], init=W[ok] if it else None)
        shape = np.einsum("nk,kmd->nmd", W, B)
    R, t = weighted_rigid_fit(shape, Xz, w8)
    face = np.einsum("nij,nmj->nmi", R, shape) + t[:, None]
    d2 = np.where(vis, ((face - Xz) ** 2).sum(-1), 0.0)
    out[ok] = face[ok]
    weights[ok] = W[ok]
    rms[ok] = np.sqrt(d2[ok].sum(1) / vis[ok].sum(1))
    return FaceFit(frames, out, weights, rms)


def face_model_fill(xyz: np.ndarray, fill: np.ndarray, model: FaceModel, *, known: np.ndarray | None = None,
                    anchor_blend: bool = True, forwards: bool = True, backwards: bool = True,
                    min_visible: int = 6) -> GapFillResult:
    """Fill gaps of the model's markers with the face model.

    Parameters
    ----------
    xyz : array (F, P, 3)
        Positions, mm, NaN gaps. Not modified.
    fill : bool array (F, P)
        Samples to (re)compute; those of columns outside the model are left alone.
    model : FaceModel
    known : bool array (F, P), optional
        Samples the fit may use (default ``finite & ~fill``).
    anchor_blend : bool
        Add the model's offset from the data at the last known sample before the gap and the
        first after it, blended linearly across the gap (``forwards``/``backwards`` choose
        which of the two are used). False gives the model's prediction as it is.
    forwards, backwards : bool
        As in :func:`~carapost.core.gapfill.fill_gaps`, for the anchor offsets.
    min_visible : int
        Frames with fewer visible model markers are not filled.

    Returns
    -------
    GapFillResult
        ``on_ray`` is all False (apply the single-sensor constraint afterwards).
    """
    xyz = np.asarray(xyz, dtype=float)
    F, P, _ = xyz.shape
    fill = np.asarray(fill, dtype=bool)
    if fill.shape != (F, P):
        raise ValueError(f"fill mask must have shape {(F, P)}, got {fill.shape}")
    finite = np.isfinite(xyz).all(-1)
    known = finite & ~fill if known is None else np.asarray(known, dtype=bool) & finite & ~fill
    out = xyz.copy()
    filled = np.zeros((F, P), bool)
    on_ray = np.zeros((F, P), bool)
    in_model = np.zeros(P, bool)
    in_model[model.points] = True
    todo = fill & in_model[None, :]
    if not todo.any():
        return GapFillResult(out, filled, on_ray)
    col_of = np.full(P, -1, np.int64)
    col_of[model.points] = np.arange(len(model.points))
    ff, pp = np.nonzero(todo)
    before, after = _last_known(known)
    a = before[ff, pp] if (anchor_blend and forwards) else np.full(len(ff), -1)
    b = after[ff, pp] if (anchor_blend and backwards) else np.full(len(ff), -1)
    need = np.unique(np.concatenate([ff, a[a >= 0], b[b >= 0]]))
    fit = fit_face_model(model, xyz, need, known, min_visible=min_visible)
    row = np.full(F, -1, np.int64)
    row[need] = np.arange(len(need))
    pred = fit.xyz[row[ff], col_of[pp]]
    if anchor_blend:
        off_a = np.zeros((len(ff), 3))
        off_b = np.zeros((len(ff), 3))
        ha, hb = a >= 0, b >= 0
        off_a[ha] = xyz[a[ha], pp[ha]] - fit.xyz[row[a[ha]], col_of[pp[ha]]]
        off_b[hb] = xyz[b[hb], pp[hb]] - fit.xyz[row[b[hb]], col_of[pp[hb]]]
        ha &= np.isfinite(off_a).all(-1)
        hb &= np.isfinite(off_b).all(-1)
        both = ha & hb
        wb = np.where(both, (ff - a) / np.where(both, b - a, 1), hb.astype(float))
        off = (1 - wb)[:, None] * np.where(ha[:, None], off_a, 0.0) + wb[:, None] * np.where(hb[:, None], off_b, 0.0)
        pred = pred + off
    good = np.isfinite(pred).all(-1)
    out[ff[good], pp[good]] = pred[good]
    filled[ff[good], pp[good]] = True
    return GapFillResult(out, filled, on_ray)
