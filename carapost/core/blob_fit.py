"""Per-candidate stage of the blob detector: level search, local background, ellipse, centre.

All candidates of one patch size (whatever pyramid level they come from) are processed
together on a stack of square patches ``(N, S, S)`` (:func:`extract_patches`); nothing loops
over candidates in Python: each step is one call of a compiled kernel that loops over the
candidates and their pixels (:mod:`carapost.core.blob_kernels`, ``blob_kernels_outline``, ``blob_kernels_region``;
the numpy building blocks here — :func:`_plane_fit`, :func:`_flood`, :func:`_moments` — are
those of the numpy reference of steps 3-6 and of the kernels' tests). Steps 1-2 are
:func:`search_levels` (:func:`ring_search`, then :func:`level_search`; its :class:`LevelSearch`
is kept), steps 3-5 :func:`fit_outlines` (in
:mod:`carapost.core.blob_outline`, on patches cropped to the core's neighbourhood), so
that the detector can reject candidates after step 2 (the gate) and fit alternative outlines
(a core forced to a higher level) without repeating steps 1-2; :func:`fit_patches` runs both
on one image.

For each candidate (signed image: the blob is bright):

1. **Ring background.** A plane is fitted (robustly) to the ring of the patch outside the
   expected blob; ``d0 = patch - plane``. The peak ``P`` is the largest 3x3 mean of ``d0``
   near the candidate.
2. **Level search.** The flood level ``L`` of every pixel — the highest level ``t`` at which
   it is still connected to the peak through pixels of ``d0 >= t`` — is computed once by
   morphological reconstruction (repeated 3x3 dilation clipped by the smoothed patch). The
   component of the peak at level ``f P`` is ``L >= f P``, so all levels come for free. The
   *core* is the component at the lowest level ``f`` in 0.5 .. 0.9 that is still a blob:
   not touching the patch border, not bigger than the largest allowed blob, and not having
   just merged with something (its area more than doubles from the level above). At half
   contrast a dot on an eyebrow or a lip line joins the band; a few levels up it is alone.
3. **Local background.** A plane fitted (robustly) to a thin band 2-4 px around the core,
   leaving out other bright structures: the dot's own surround (skin, or the band it sits on,
   or both across the band's edge). ``d = patch - plane``; the contrast ``C`` is the peak of
   the 3x3 mean of ``d`` in the core.
4. **Ellipse and centre** from the soft half-contrast region ``q = clip(1.5 (d/C - 1/2) +
   1/2, 0, 1)`` around the core: its centroid is the centre (noise enters only through the
   edge pixels; blur is symmetric and does not move it); its second moments give the
   covariance ``Sigma``, and a uniform ellipse has ``Sigma = diag(a^2, b^2) / 4``, so the
   semi-axes are ``2 sqrt(eig(Sigma))``.
5. **Shape measurements** for the classifier (:mod:`carapost.core.blob_score`): mismatch with
   the moment ellipse, central asymmetry, residual around the elliptical radial profile.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from . import blob_kernels
from .blob_kernels import FLAT_HI as _FLAT_HI
from .blob_kernels import FLAT_LO as _FLAT_LO
from .blob_kernels import FP as _FP
from .blob_kernels import LEVELS
from .blob_patches import K3, MONO, MONO_INDEX, SEP, Patches, dot_rows, extract_patches, mosaic

__all__ = ["PatchFit", "fit_patches", "patch_half_size", "LEVELS", "LevelSearch", "RingSearch", "ring_search",
           "level_search", "search_levels"]

_FLOOD_ROUND = 4  # flood steps between convergence checks (:func:`_flood`, the numpy reference)
DEBUG: dict | None = None


@dataclass
class PatchFit:
    """Fit results in the coordinates of the pyramid level the patches came from.

    Attributes
    ----------
    x, y : float64 (N,)
        Centre (level px).
    major, minor : float64 (N,)
        Ellipse semi-axes (level px).
    angle : float64 (N,)
        Major-axis direction, radians from +x towards +y, in (-pi/2, pi/2].
    contrast : float64 (N,)
        Peak blob signal above the local background (grey levels).
    background : float64 (N,)
        Local background level of the (signed) level image at the centre (grey levels).
    rise : float64 (N,)
        Local background minus the ring background at the centre, over the contrast: how far
        the blob stands on a band brighter than its wider surround (an eyebrow, a lip line).
    noise : float64 (N,)
        Standard deviation of the local background residual (grey levels).
    ring_noise : float64 (N,)
        Standard deviation of the ring background residual (grey levels).
    core_level : float64 (N,)
        The level (fraction of the peak over the ring) of the core (:data:`LEVELS`).
    found_level : float64 (N,)
        The core level the search found (``core_level`` is higher for an alternative outline,
        ``min_core``).
    area_ratio : float64 (N,)
        Area of the core's component at the next level up over the core's area.
    shape_residual, asymmetry, profile_rms : float64 (N,)
        See :mod:`carapost.core.blob_score`.
    area : float64 (N,)
        Area of the soft half-contrast region (level px^2).
    ok : bool (N,)
        False where the candidate is rejected outright (no peak, no isolated core, masked or
        saturated pixels in or around it, degenerate background).
    border : bool (N,)
        Even the highest level's component reached the patch border or the size limit (the
        patch may be too small: a blob bigger than its candidate's scale).
    open : float64 (N,)
        The dot's contrast against its surround in its weakest direction, as a fraction of its
        full contrast (1 on clean skin, near 0 where it merges with something as dark).
    kept : float64 (N,)
        Fraction of the soft region kept by the trimming (1 for a clean ellipse).
    saturated : float64 (N,)
        Fraction of the blob's 2 px surround that is clipped (white blobs).
    """

    x: np.ndarray
    y: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    angle: np.ndarray
    contrast: np.ndarray
    background: np.ndarray
    rise: np.ndarray
    noise: np.ndarray
    ring_noise: np.ndarray
    core_level: np.ndarray
    found_level: np.ndarray
    area_ratio: np.ndarray
    shape_residual: np.ndarray
    asymmetry: np.ndarray
    profile_rms: np.ndarray
    area: np.ndarray
    ok: np.ndarray
    border: np.ndarray

    open: np.ndarray
    kept: np.ndarray
    saturated: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "PatchFit":
        f = {k: np.zeros(n) for k in cls.__dataclass_fields__ if k not in ("ok", "border")}
        return cls(**f, ok=np.zeros(n, bool), border=np.zeros(n, bool))


#: Patch half sizes: a few classes, so that candidates are fitted in few large batches.
_HALF_SIZES = np.array([8, 11, 14, 18, 25, 33, 49, 65])


def patch_half_size(radius: np.ndarray | float) -> np.ndarray:
    """Half side of the patches used for blobs of ``radius`` px (at the patch's level): at
    least ``1.5 radius + 5``, rounded up to one of a few classes."""
    need = np.ceil(1.5 * np.asarray(radius, float) + 5.0)
    k = np.searchsorted(_HALF_SIZES, need)
    return np.where(k < len(_HALF_SIZES), _HALF_SIZES[np.minimum(k, len(_HALF_SIZES) - 1)], need).astype(int)


def _plane_fit(p: np.ndarray, mask: np.ndarray, mono: np.ndarray,
               iters: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust least-squares plane per patch.

    Parameters
    ----------
    p : float32 (N, S, S)
    mask : bool (N, S, S)
        Pixels allowed in the fit.
    mono : float32 (S*S, 15)
        Monomials of the patch offsets.
    iters : int
        Reweighting passes: pixels beyond 2.5 sigma of the previous fit are dropped (lines,
        edges, unresolved neighbours).

    Returns
    -------
    resid : float32 (N, S, S)
        ``p - plane`` everywhere in the patch.
    sigma : float64 (N,)
        Standard deviation of the residual over the finally used pixels.
    n_used : float64 (N,)
        Number of pixels used in the final fit.
    coef : float32 (N, 3)
        Coefficients of ``1, x, y``.
    """
    n, s, _ = p.shape
    terms = MONO[:3]
    pairs = np.asarray([[MONO_INDEX[(a[0] + b[0], a[1] + b[1])] for b in terms] for a in terms])
    pf = p.reshape(n, s * s)
    bk = mono[:, :3]
    w = mask.reshape(n, s * s).astype(np.float32)
    resid = pf
    sigma = np.zeros(n)
    s0 = np.zeros(n)
    c = np.zeros((n, 3), np.float32)
    for it in range(iters + 1):
        m = dot_rows(w, mono[:, :6]).astype(np.float64)              # sums of w * (1, x, y, xx, xy, yy)
        s0 = m[:, 0]
        A = m[:, pairs]                                       # (N, 3, 3)
        A[:, [0, 1, 2], [0, 1, 2]] += 1e-6 * np.maximum(A[:, [0, 1, 2], [0, 1, 2]], 1e-6) + 1e-9
        rhs = dot_rows(w * pf, bk).astype(np.float64)
        c = np.linalg.solve(A, rhs[..., None])[..., 0].astype(np.float32)
        resid = pf - (c[:, 0:1] * bk[:, 0] + c[:, 1:2] * bk[:, 1] + c[:, 2:3] * bk[:, 2])  # c @ bk.T, no BLAS
        e2 = np.einsum("ij,ij->i", w * resid, resid, dtype=np.float64)
        sigma = np.sqrt(e2 / np.maximum(s0 - 3, 1.0))
        if it < iters:
            lim = (2.5 * np.maximum(sigma, 0.3)).astype(np.float32)[:, None]
            w = w * (np.abs(resid) < lim)
    # Clipping at 2.5 sigma shrinks a Gaussian's std by ~0.94: undo that.
    scale = 0.94 if iters > 0 else 1.0
    return resid.reshape(n, s, s), sigma / scale, s0, c


def _prefer_informative(mask: np.ndarray, dead: np.ndarray, min_count: int = 20) -> np.ndarray:
    """``mask & ~dead`` for patches where that leaves at least ``min_count`` pixels and a third
    of ``mask`` (a face next to a black background), else ``mask`` (a dot on a clipped card)."""
    info = mask & ~dead
    n_info = info.reshape(len(mask), -1).sum(axis=1)
    enough = (n_info >= min_count) & (3 * n_info >= mask.reshape(len(mask), -1).sum(axis=1))
    return np.where(enough[:, None, None], info, mask)


def _flood(level: np.ndarray, pky: np.ndarray, pkx: np.ndarray, iters: int, floor: int) -> np.ndarray:
    """Flood levels ``L`` (uint8 (N, S, S)) of each patch from its peak pixel, at least ``floor``.

    ``L(p)`` is the largest ``t >= floor`` such that ``p`` is 8-connected to the peak through
    pixels of ``level >= t`` (morphological reconstruction by dilation of the peak under
    ``level``), computed by up to ``iters`` rounds of 3x3 dilation clipped by ``level``: exact
    for pixels reached by such a path within ``iters`` steps, an under-estimate beyond. Only
    the region above ``floor`` has to be flooded, and a patch leaves the rounds as soon as a
    round of :data:`_FLOOD_ROUND` steps changes nothing in it (it has converged: exact).
    """
    n, s, _ = level.shape
    b = s + SEP
    lv = cv2.max(mosaic(level, floor), floor).reshape(n, b, s)
    marker = np.full((n, s, s), floor, np.uint8)
    marker[np.arange(n), pky, pkx] = np.maximum(level[np.arange(n), pky, pkx], floor)
    mk = mosaic(marker, floor).reshape(n, b, s)
    # Rounds of a few steps on the patches still changing (a patch that did not change during
    # a whole round has converged).
    act = np.arange(n)
    done = 0
    while len(act) and done < iters:
        steps = min(_FLOOD_ROUND, iters - done)
        whole = len(act) == n
        m0 = mk if whole else mk[act]
        lim = (lv if whole else lv[act]).reshape(-1, s)
        m = m0.reshape(-1, s)
        for _ in range(steps):
            m = cv2.min(cv2.dilate(m, K3), lim)
        m = m.reshape(len(act), b, s)
        changed = (m != m0).reshape(len(act), -1).any(axis=1)
        mk[act] = m
        act = act[changed]
        done += steps
    return mk[:, :s]


def _thresholds() -> np.ndarray:
    """The searched levels (:data:`LEVELS`) in the fixed point of the flood levels, int16 (K,)."""
    return np.rint(np.asarray(LEVELS) * _FP).astype(np.int16)


def _moments(q: np.ndarray, mono: np.ndarray) -> tuple:
    """Centroid ``mx, my``, second central moments ``cxx, cxy, cyy`` and mass ``m0`` (N,) of
    soft regions ``q (N, S, S)`` (offsets from the patch centre)."""
    n = q.shape[0]
    mom = dot_rows(q.reshape(n, -1), mono[:, :6]).astype(np.float64)
    m0 = mom[:, 0]
    m0s = np.maximum(m0, 1e-9)
    mx, my = mom[:, 1] / m0s, mom[:, 2] / m0s
    cxx = np.maximum(mom[:, 3] / m0s - mx * mx, 1e-6)
    cxy = mom[:, 4] / m0s - mx * my
    cyy = np.maximum(mom[:, 5] / m0s - my * my, 1e-6)
    return mx, my, cxx, cxy, cyy, m0


def fit_patches(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, radius: np.ndarray, half: int, *,
                polarity: int, max_radius: float, pixel_noise: float, bad: np.ndarray | None, saturated: tuple[int, int] | None,
                min_core: float = 0.0) -> PatchFit:
    """Fit blobs around candidate pixels of one pyramid level image.

    Parameters
    ----------
    img : uint8 (H, W)
        Signed image at the level (blobs bright).
    cx, cy : int arrays (N,)
        Candidate pixels (level px).
    radius : float64 (N,)
        Candidate radius estimates (level px).
    half : int
        Patch half size; patches are ``(2 half + 1)`` square.
    polarity : int
        +1 (white blobs: ``img`` is the image) or -1 (black: ``img`` is ``255 - image``).
    max_radius : float
        Largest allowed blob radius (level px): bigger cores are not blobs.
    pixel_noise : float
        Pixel noise of ``img`` (grey levels).
    bad : bool (H, W) or None
        Pixels to ignore (user mask). A blob touching them is rejected.
    saturated : (lo, hi) or None
        Pixels of ``img`` with values in ``lo..hi`` are saturated pixels of the original
        image (give it for white blobs). They are left out of the background and may only be
        inside the blob itself (an over-exposed white dot); a blob next to a saturated region
        is rejected. Black blobs do not need it: a black dot on a clipped white card is fine.
    min_core : float
        Lowest level (fraction of the peak, one of :data:`LEVELS`) allowed for the core: an
        alternative, tighter outline for a dot that merges with a dark band at the level the
        search picks (the detector fits both and keeps the more probable).

    Returns
    -------
    PatchFit
        Centres in level pixels.
    """
    n = len(cx)
    pat = extract_patches(img, cx, cy, half, bad=bad, saturated=saturated)
    st = search_levels(pat, radius, max_radius=np.full(n, float(max_radius)),
                       pixel_noise=np.full(n, float(pixel_noise)))
    from .blob_outline import fit_outlines

    res = fit_outlines(st, np.arange(n), polarity=polarity, min_core=np.full(n, float(min_core)))
    res.x += cx
    res.y += cy
    return res


@dataclass
class LevelSearch:
    """Steps 1-2 of the fit for a stack of patches (:func:`search_levels`), kept so that
    outlines at several core levels (:func:`fit_outlines`) share them. Arrays are over the
    ``alive`` patches (those with a peak) unless noted."""

    n: int                   # patches in the stack
    half: int
    alive: np.ndarray        # int (A,): patches with a peak above the ring noise
    pu: np.ndarray           # uint8 (A, S, S)
    bad: np.ndarray          # bool (A, S, S)
    sat: np.ndarray          # bool (A, S, S)
    d0: np.ndarray           # float32 (A, S, S): patch minus ring plane
    sig0: np.ndarray         # (A,) ring residual std
    c0: np.ndarray           # float32 (A, 3) ring plane
    L: np.ndarray            # uint8 (A, S, S) flood levels
    lvl: np.ndarray          # uint8 (A, S, S) smoothed signal in fixed point
    area: np.ndarray         # (A, K) area of the peak's component per level
    k_found: np.ndarray      # int (A,) core level index found by the search
    has: np.ndarray          # bool (A,) an isolated core exists
    peak: np.ndarray         # (A,) peak of the 3x3 mean over the ring plane (grey levels)
    fill: np.ndarray         # (A,) core area over its moment ellipse's, at the found level
    # int: stack indices of the patches with a peak that the pre-gate rejected (not alive)
    pregated: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def p(self) -> np.ndarray:
        """float32 (A, S, S): the patches' values."""
        return self.pu.astype(np.float32)

    @property
    def dead(self) -> np.ndarray:
        """bool (A, S, S): black or clipped pixels (a dark background beyond the face's
        silhouette, a clipped card carry no shading information: left out of backgrounds
        when enough others remain)."""
        return (self.pu <= _FLAT_LO) | (self.pu >= _FLAT_HI)

    def rows(self, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For patch indices ``sel`` (into the stack), the positions in ``sel`` of those
        alive and their rows in the alive arrays."""
        pos = np.full(self.n, -1)
        pos[self.alive] = np.arange(len(self.alive))
        r = pos[sel]
        keep = np.flatnonzero(r >= 0)
        return keep, r[keep]


@dataclass
class RingSearch:
    """Step 1 of the fit for a stack of patches (:func:`ring_search`): arrays over all ``N``
    patches of the stack."""

    pat: Patches
    d0: np.ndarray           # float32 (N, S, S): patch minus ring plane
    sig0: np.ndarray         # (N,) ring residual std
    c0: np.ndarray           # float32 (N, 3) ring plane
    pk: np.ndarray           # int64 (N,): flat index of the peak
    peak: np.ndarray         # (N,) peak of the 3x3 mean over the ring plane (grey levels)
    alive: np.ndarray        # int (A,): patches with a peak above the ring noise


def ring_search(pat: Patches, radius: np.ndarray) -> RingSearch:
    """Step 1 (ring background, peak) of the fit for the patch stack ``pat`` with radius
    estimates ``radius`` (N,) (level px): one compiled call (:func:`blob_kernels.ring_step`);
    ``alive`` lists the patches whose peak stands above the ring noise."""
    d0, sig0, n0, c0, pk, peak = blob_kernels.ring_step(pat.pu, pat.bad, pat.sat, np.asarray(radius, np.float32),
                                                       pat.half)
    alive = np.flatnonzero((peak > 1.0 * sig0) & (peak > 0.5) & (n0 >= 8))
    return RingSearch(pat, d0, sig0, c0, pk, peak, alive)


def level_search(ring: RingSearch, go: np.ndarray | None = None, *, max_radius: np.ndarray,
                 pixel_noise: np.ndarray) -> LevelSearch:
    """Step 2 (flood levels, core level) of the fit on the patches of ``ring`` with a peak;
    ``go`` (bool (A,) over ``ring.alive``, optional: the pre-gate's verdict) says which of them
    are searched, the others are listed in the result's ``pregated``. ``max_radius`` and
    ``pixel_noise`` are per patch of the stack (N,) (level px / grey levels of the level each
    patch came from). One compiled call (:func:`blob_kernels.level_step`)."""
    pat = ring.pat
    half = pat.half
    S = 2 * half + 1
    alive = ring.alive
    pregated = np.zeros(0, np.int64)
    if go is not None:
        pregated, alive = alive[~go], alive[go]
    # Flood levels in fixed point (the peak is _FP).
    n = len(alive)
    pu, badp, satp, d0 = pat.pu[alive], pat.bad[alive], pat.sat[alive], ring.d0[alive]
    pk, peak, sig0, c0 = ring.pk[alive], ring.peak[alive], ring.sig0[alive], ring.c0[alive]
    max_radius, pixel_noise = np.asarray(max_radius, float)[alive], np.asarray(pixel_noise, float)[alive]
    K = len(LEVELS)
    if n == 0:
        z = np.zeros((0, S, S), np.uint8)
        return LevelSearch(len(pat), half, alive, pu, badp, satp, d0, sig0, c0, z, z, np.zeros((0, K)),
                           np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0), np.zeros(0), pregated)
    lvl, L, area, fill, edge_max, valid, k_found, has = blob_kernels.level_step(d0, peak, pk, half, max_radius,
                                                                              pixel_noise)
    if DEBUG is not None:
        DEBUG.update(dict(alive=alive, L=L, area=area, fill=fill, edge_max=edge_max, valid=valid, kc=k_found, lvl=lvl,
                          p=pu, peak=peak, pky=pk // S, pkx=pk % S, sig0=sig0, half=half))
    return LevelSearch(len(pat), half, alive, pu, badp, satp, d0, sig0, c0, L, lvl, area,
                       k_found, has, peak, fill[np.arange(n), k_found], pregated)


def search_levels(pat: Patches, radius: np.ndarray, *, max_radius: np.ndarray,
                  pixel_noise: np.ndarray) -> LevelSearch:
    """Steps 1 (ring background, peak: :func:`ring_search`) and 2 (flood levels, core level:
    :func:`level_search`) of the fit, without a pre-gate.

    ``radius``, ``max_radius`` and ``pixel_noise`` are per patch (N,) (level px / grey levels
    of the level each patch came from). The detector runs the two steps apart
    (:func:`carapost.core.blobs._fit`: the pre-gate between them, over all its stacks at once).
    """
    return level_search(ring_search(pat, radius), max_radius=max_radius, pixel_noise=pixel_noise)
