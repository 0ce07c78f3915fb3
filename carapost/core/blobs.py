"""Blob detection: black and/or white painted dots in an 8-bit grayscale image.

The reference guide's four steps (classifier -> probability of a blob centre -> boundary ->
ellipse):

1. A dense, multi-scale centre-surround response normalised by the image's own clutter
   (:mod:`carapost.core.blob_candidates`) proposes candidate centres.
2. Each candidate is refined on a patch (:mod:`carapost.core.blob_fit`): local plane
   background, half-contrast boundary, moment ellipse, sub-pixel centroid, shape check.
3. A logistic classifier (:mod:`carapost.core.blob_score`), calibrated on rendered dots with
   exact ground truth, turns the candidate's features into the probability that it is a
   (well-located) blob centre; the Blob Parameters threshold is applied to it.
4. Duplicates (one blob found at two scales) are merged, keeping the most probable.

Saturated pixels (255) never produce blobs; pixels where ``mask`` is True are ignored, and a
blob touching them is dropped. See ``docs/blobs.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..model.detections import BLACK, DETECTION_FIELDS, WHITE
from ..model.params import BlobParameters
from . import blob_score
from .blob_candidates import find_candidates, level_range, pixel_noise, pyramid, responses, signed_image
from .blob_fit import fit_patches, patch_half_size

__all__ = ["detect_blobs", "blob_probability", "analyse_blobs", "BlobAnalysis", "empty_table",
           "CANDIDATE_MIN_SNR"]

#: Dense-stage threshold on the normalised response: deliberately low (recall); the classifier
#: decides.
CANDIDATE_MIN_SNR = 4.0
#: Dense-stage threshold on the rough Weber contrast (response over surround level): skin
#: texture and shading ripples are far below it, paint far above (see docs/blobs.md).
CANDIDATE_MIN_WEBER = 0.05
#: Largest blob radius refined at full resolution; bigger blobs are refined on a pyramid level
#: where their radius is at most this many pixels.
_MAX_REFINE_RADIUS = 8.0
#: A fitted blob with at least this probability hides smaller, weaker-contrast detections
#: inside its ellipse (rim maxima and interior texture of big blobs).
_CONTAINER_SCORE = 0.3
#: A deferred candidate inside a blob found with at least ``_CONTAINER_SCORE`` is not fitted
#: when that blob is at most this many times its scale (the same blob at another scale).
_SAME_BLOB_RATIO = 2.5
#: ... and it is never fitted inside a blob found with at least this probability.
_CONFIDENT_SCORE = 0.8


@dataclass
class BlobAnalysis:
    """Every candidate of one polarity with its fit and probability (full-resolution pixels).

    Attributes
    ----------
    x, y, major, minor, angle : float64 (N,)
        Fitted ellipse (px, radians).
    score : float64 (N,)
        Probability of a blob centre (0 for rejected candidates).
    ok : bool (N,)
        Passed the hard checks (boundary found, radius in range, not masked or saturated,
        not a duplicate of a more probable candidate).
    features : float64 (N, F)
        Classifier features (:data:`carapost.core.blob_score.FEATURES`).
    measures : dict of str to float64 (N,)
        Raw fit measurements (contrast, background, noise, shape, offset, ...), for diagnostics.
    cand_x, cand_y : float64 (N,)
        The candidate pixel the fit started from (full-resolution px).
    snr : float64 (N,)
        The candidate's normalised dense response.
    cand_weber : float64 (N,)
        The candidate's rough Weber contrast (dense stage).
    polarity : int
        +1 white, -1 black.
    levels : list
        The dense responses (:class:`carapost.core.blob_candidates.ResponseLevel`).
    """

    x: np.ndarray
    y: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    angle: np.ndarray
    score: np.ndarray
    ok: np.ndarray
    features: np.ndarray
    measures: dict
    cand_x: np.ndarray
    cand_y: np.ndarray
    snr: np.ndarray
    cand_weber: np.ndarray
    polarity: int
    levels: list

    def table(self, threshold: float) -> dict[str, np.ndarray]:
        """Detections with ``score > threshold`` as a table of :data:`DETECTION_FIELDS`."""
        keep = self.ok & (self.score > threshold)
        order = np.lexsort((self.x[keep], self.y[keep]))
        sel = np.flatnonzero(keep)[order]
        return {
            "x": self.x[sel].astype(np.float32),
            "y": self.y[sel].astype(np.float32),
            "major": self.major[sel].astype(np.float32),
            "minor": self.minor[sel].astype(np.float32),
            "angle": self.angle[sel].astype(np.float32),
            "polarity": np.full(len(sel), self.polarity, np.int8),
            "score": self.score[sel].astype(np.float32),
        }


def empty_table() -> dict[str, np.ndarray]:
    """A detection table with no rows."""
    return {k: np.zeros(0, dt) for k, dt in DETECTION_FIELDS.items()}


def _check_image(image: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"blob detection needs a grayscale image (H, W), got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"blob detection needs an 8-bit image (uint8), got {image.dtype}")
    if min(image.shape) < 8:
        raise ValueError(f"image of shape {image.shape} is too small for blob detection")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != image.shape:
            raise ValueError(f"mask shape {mask.shape} does not match image shape {image.shape}")
        mask = mask.astype(bool, copy=False)
        if not mask.any():
            mask = None
    return np.ascontiguousarray(image), mask


def _level_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A bool mask reduced to a pyramid level's ``shape``: True if any covered pixel is True."""
    if mask.shape == shape:
        return mask
    m = cv2.resize(mask.astype(np.uint8) * 255, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return m > 0


def _saturation(level: int) -> tuple[int, int]:
    """Value range of saturated pixels (255) in a pyramid level of the image (white blobs)."""
    tol = 0 if level == 0 else 2
    return (255 - tol, 255)


def analyse_blobs(image: np.ndarray, polarity: int, *, min_radius: float, max_radius: float,
                  adaptive: bool = False, mask: np.ndarray | None = None) -> BlobAnalysis:
    """Find, fit and score every blob candidate of one polarity.

    Parameters
    ----------
    image : uint8 (H, W)
    polarity : int
        ``WHITE`` (+1) or ``BLACK`` (-1).
    min_radius, max_radius : float
        Range of the major semi-axis (px).
    adaptive : bool
        Normalise the dense response by a local (per-tile) clutter estimate.
    mask : bool (H, W), optional
        True where pixels must be ignored.

    Returns
    -------
    BlobAnalysis
        All candidates (use :meth:`BlobAnalysis.table` to threshold).

    Raises
    ------
    ValueError
        Bad image or mask.
    """
    image, mask = _check_image(image, mask)
    if polarity not in (WHITE, BLACK):
        raise ValueError(f"polarity must be {WHITE} (white) or {BLACK} (black), got {polarity}")
    signed = signed_image(image, polarity)
    lv_range = level_range(min_radius, max_radius)
    pyr = pyramid(signed, lv_range.stop)
    levels = [responses(pyr[k], k, adaptive=adaptive) for k in lv_range if k < len(pyr)]
    cand = find_candidates(levels, min_snr=CANDIDATE_MIN_SNR, min_radius=min_radius,
                           max_radius=max_radius, polarity=polarity, min_weber=CANDIDATE_MIN_WEBER)
    if mask is not None and len(cand):
        keep = np.ones(len(cand), bool)
        for k in np.unique(cand.level):
            sel = np.flatnonzero(cand.level == k)
            keep[sel] = ~_level_mask(mask, pyr[k].shape)[cand.y[sel], cand.x[sel]]
        cand = cand.subset(keep)

    n = len(cand)
    out = {k: np.zeros(n) for k in ("x", "y", "major", "minor", "angle", "contrast", "background",
                                   "noise", "shape", "offset", "asymmetry", "profile_rms",
                                   "pixel_noise")}
    ok = np.zeros(n, bool)
    if n:
        # Pass 1: candidates not close to a stronger one. Pass 2: the others (rim maxima of a
        # big blob, a second scale) unless inside a blob already found at their scale, together
        # with pass 1's blobs that reached their patch border, again with a patch twice the
        # size. Pass 3: pass 2's border blobs.
        lm_cache: dict = {}
        shadow = _shadowed(cand)
        radius = cand.radius.copy()
        sel = np.flatnonzero(~shadow)
        border = _fit_groups(pyr, cand, sel, radius[sel], out, ok, polarity, mask, lm_cache)
        retry = sel[border & (radius[sel] * 2 <= max_radius * 1.6)]
        radius[retry] *= 2.0
        second = np.flatnonzero(shadow)
        if len(second):
            sc1 = _score(cand, out, ok, min_radius, max_radius, image.shape, polarity)[0]
            px = cand.x[second] * 2.0 ** cand.level[second]
            py = cand.y[second] * 2.0 ** cand.level[second]
            # Inside a blob found at the candidate's scale (the same blob), or inside a clean,
            # confident blob (a rim maximum): not fitted.
            skip = _inside(px, py, out, ok & (sc1 >= _CONTAINER_SCORE), radius=cand.radius[second])
            skip |= _inside(px, py, out, ok & (sc1 >= _CONFIDENT_SCORE))
            second = second[~skip]
        for _ in range(2):
            sel = np.concatenate([retry, second])
            if len(sel) == 0:
                break
            border = _fit_groups(pyr, cand, sel, radius[sel], out, ok, polarity, mask, lm_cache)
            retry = sel[border & (radius[sel] * 2 <= max_radius * 1.6)]
            radius[retry] *= 2.0
            second = second[:0]
    score, ok, feat = _score(cand, out, ok, min_radius, max_radius, image.shape, polarity)
    ok &= _unique(out, score, ok)
    return BlobAnalysis(x=out["x"], y=out["y"], major=out["major"], minor=out["minor"],
                        angle=out["angle"], score=score, ok=ok, features=feat, measures=out,
                        cand_x=(cand.x * 2.0 ** cand.level).astype(float),
                        cand_y=(cand.y * 2.0 ** cand.level).astype(float), snr=cand.snr,
                        cand_weber=cand.weber,
                        polarity=polarity, levels=levels)


def _shadowed(cand) -> np.ndarray:
    """Candidates within 1.5 radii of a candidate with a higher SNR, (N,) bool."""
    from scipy.spatial import cKDTree

    n = len(cand)
    out = np.zeros(n, bool)
    if n < 2:
        return out
    s = 2.0 ** cand.level
    pts = np.stack([cand.x * s, cand.y * s], axis=1)
    pairs = cKDTree(pts).query_pairs(r=float(1.5 * cand.radius.max()), output_type="ndarray")
    if len(pairs) == 0:
        return out
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    d = np.linalg.norm(pts[i] - pts[j], axis=1)
    hit = (d < 1.5 * cand.radius[i]) & (cand.snr[i] > cand.snr[j])
    out[j[hit]] = True
    return out


def _score(cand, out: dict[str, np.ndarray], ok: np.ndarray, min_radius: float, max_radius: float,
           shape: tuple[int, int], polarity: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radius and image-bounds checks, features and probabilities of fitted candidates.

    Returns ``score (N,)`` (0 where not ok), ``ok (N,)`` and the features ``(N, F)``.
    """
    H, W = shape
    ok = ok & (out["major"] >= min_radius) & (out["major"] <= max_radius)
    ok &= (out["x"] >= -0.5) & (out["x"] <= W - 0.5) & (out["y"] >= -0.5) & (out["y"] <= H - 0.5)
    feat = blob_score.features(cand.snr, {**out, "polarity": np.full(len(cand), polarity)})
    score = np.where(ok, blob_score.probability(feat), 0.0)
    return score, ok, feat


def _inside(px: np.ndarray, py: np.ndarray, out: dict[str, np.ndarray], found: np.ndarray,
            margin: float = 1.0, radius: np.ndarray | None = None) -> np.ndarray:
    """Which points ``(px, py)`` lie inside (``margin`` px grown) a fitted ellipse ``found``.

    With ``radius`` (the points' scale, px), only ellipses at most ``_SAME_BLOB_RATIO`` times
    bigger count: a much smaller candidate inside a big blob may be a dot on a dark band.
    """
    from scipy.spatial import cKDTree

    res = np.zeros(len(px), bool)
    idx = np.flatnonzero(found)
    if len(idx) == 0 or len(px) == 0:
        return res
    cen = np.stack([out["x"][idx], out["y"][idx]], axis=1)
    big = float(out["major"][idx].max()) + margin
    lists = cKDTree(np.stack([px, py], axis=1)).query_ball_point(cen, r=big)
    jj = np.repeat(idx, [len(v) for v in lists])
    if len(jj) == 0:
        return res
    ii = np.concatenate([np.asarray(v, int) for v in lists])
    hit = _in_ellipse(px[ii], py[ii], out, jj, margin)
    if radius is not None:
        hit &= out["major"][jj] <= _SAME_BLOB_RATIO * radius[ii]
    res[ii[hit]] = True
    return res


def _in_ellipse(px: np.ndarray, py: np.ndarray, out: dict[str, np.ndarray], j: np.ndarray,
                margin: float) -> np.ndarray:
    """Whether each point lies inside ellipse ``j`` grown by ``margin`` px."""
    dx = px - out["x"][j]
    dy = py - out["y"][j]
    c, s = np.cos(out["angle"][j]), np.sin(out["angle"][j])
    u = (dx * c + dy * s) / (out["major"][j] + margin)
    v = (-dx * s + dy * c) / (out["minor"][j] + margin)
    return u * u + v * v <= 1.0


def _fit_groups(pyr: list[np.ndarray], cand, sel_all: np.ndarray, radius: np.ndarray,
                out: dict[str, np.ndarray], ok: np.ndarray, polarity: int,
                mask: np.ndarray | None, lm_cache: dict) -> np.ndarray:
    """Fit candidates ``sel_all`` (radius estimates ``radius``, full-res px) in groups of equal
    refinement level and patch size, writing into ``out``/``ok``. Returns ``border (len(sel_all),)``."""
    border = np.zeros(len(sel_all), bool)
    level = cand.level[sel_all]
    # Refinement level: where the blob's radius is at most _MAX_REFINE_RADIUS px, never coarser
    # than the candidate's own level.
    ref = np.clip(np.ceil(np.log2(np.maximum(radius, 1e-6) / _MAX_REFINE_RADIUS)), 0, None).astype(int)
    ref = np.minimum(ref, len(pyr) - 1)
    r_ref = radius / 2.0 ** ref
    half = patch_half_size(r_ref)
    # Candidate pixel at the refinement level.
    sh = level - ref
    px = np.where(sh >= 0, cand.x[sel_all] << np.maximum(sh, 0), cand.x[sel_all] >> np.maximum(-sh, 0))
    py = np.where(sh >= 0, cand.y[sel_all] << np.maximum(sh, 0), cand.y[sel_all] >> np.maximum(-sh, 0))
    group = ref * 10000 + half
    for g in np.unique(group):
        loc = np.flatnonzero(group == g)
        sel = sel_all[loc]
        k, h = int(g // 10000), int(g % 10000)
        img_k = pyr[k]
        if mask is not None and k not in lm_cache:
            lm_cache[k] = _level_mask(mask, img_k.shape)
        fit = fit_patches(img_k, px[loc], py[loc], r_ref[loc], h,
                          bad=None if mask is None else lm_cache[k],
                          saturated=_saturation(k) if polarity > 0 else None)
        s = 2.0 ** k
        out["x"][sel] = fit.x * s
        out["y"][sel] = fit.y * s
        out["major"][sel] = fit.major * s
        out["minor"][sel] = fit.minor * s
        out["angle"][sel] = fit.angle
        out["contrast"][sel] = fit.contrast
        # Background level in the original image's grey levels (the level image is signed).
        out["background"][sel] = fit.background if polarity > 0 else 255.0 - fit.background
        out["noise"][sel] = fit.noise
        out["shape"][sel] = fit.shape_residual
        out["offset"][sel] = fit.offset
        out["asymmetry"][sel] = fit.asymmetry
        if ("noise", k) not in lm_cache:
            lm_cache[("noise", k)] = pixel_noise(img_k)
        out["profile_rms"][sel] = fit.profile_rms
        out["pixel_noise"][sel] = lm_cache[("noise", k)]
        ok[sel] = fit.ok
        border[loc] = fit.border
    return border


def _unique(out: dict[str, np.ndarray], score: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Mask of fitted candidates kept after removing duplicates and nested detections.

    Two detections closer than ``max(1, minor/2)`` px are one blob: the more probable stays.
    A detection whose centre lies inside a bigger one's ellipse (grown by 0.5 px) is either a
    dot on a darker band (it has at least half the bigger one's contrast and is more probable:
    the bigger one is dropped) or a rim maximum / interior texture of the bigger blob (it is
    dropped when the bigger one is plausible, probability >= ``_CONTAINER_SCORE``). The result does not depend on the user's
    threshold, so raising the threshold only ever removes detections.
    """
    from scipy.spatial import cKDTree

    keep = ok.copy()
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        return keep
    x, y, major, minor = out["x"], out["y"], out["major"], out["minor"]
    pts = np.stack([x[idx], y[idx]], axis=1)
    pairs = cKDTree(pts).query_pairs(r=float(major[idx].max()) + 0.5, output_type="ndarray")
    if len(pairs) == 0:
        return keep
    a, b = idx[pairs[:, 0]], idx[pairs[:, 1]]
    d = np.hypot(x[a] - x[b], y[a] - y[b])
    # Near-duplicates: the lower score loses.
    dup = d < np.maximum(1.0, 0.5 * np.minimum(minor[a], minor[b]))
    better_a = (score[a] > score[b]) | ((score[a] == score[b]) & (a < b))
    lose = np.where(better_a, b, a)[dup]
    # Nested: a smaller blob inside a bigger one. If it stands out from the bigger one (at
    # least half its contrast) and is more probable, it is a dot on a darker band (eyebrow,
    # lip line) and the band goes; otherwise it is a ripple of the bigger blob and goes.
    big_a = major[a] >= major[b]
    big, small = np.where(big_a, a, b), np.where(big_a, b, a)
    inside = ~dup & _in_ellipse(x[small], y[small], out, big, 0.5)
    contrast = out["contrast"]
    dot_on_band = inside & (contrast[small] >= 0.5 * contrast[big]) & (score[small] > score[big])
    ripple = inside & ~dot_on_band & (score[big] >= _CONTAINER_SCORE)
    keep[big[dot_on_band]] = False
    keep[lose] = False
    keep[small[ripple]] = False
    return keep


def _polarities(params: BlobParameters) -> list[tuple[int, float, float, float]]:
    out = []
    if params.find_black_blobs:
        out.append((BLACK, params.black_min_radius, params.black_max_radius, params.black_threshold))
    if params.find_white_blobs:
        out.append((WHITE, params.white_min_radius, params.white_max_radius, params.white_threshold))
    return out


def detect_blobs(image: np.ndarray, params: BlobParameters, *,
                 mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Detect blobs in one image.

    Parameters
    ----------
    image : uint8 (H, W)
        Grayscale frame.
    params : BlobParameters
        Which polarities, radius range (longest semi-axis, px) and probability threshold.
    mask : bool (H, W), optional
        True where pixels must be ignored (per-camera invalid regions).

    Returns
    -------
    dict of str to array
        The fields of :data:`carapost.model.detections.DETECTION_FIELDS`, one row per blob:
        centre ``x, y`` (raw px, sub-pixel), semi-axes ``major, minor`` (px), ``angle``
        (radians), ``polarity`` (+1 white, -1 black) and ``score`` (probability 0..1).

    Raises
    ------
    ValueError
        If the image is not a 2-D uint8 array or the mask does not match it.
    """
    image, mask = _check_image(image, mask)
    tables = []
    for pol, rmin, rmax, thr in _polarities(params):
        an = analyse_blobs(image, pol, min_radius=rmin, max_radius=rmax,
                           adaptive=params.adaptive_background, mask=mask)
        tables.append(an.table(thr))
    if not tables:
        return empty_table()
    return {k: np.concatenate([t[k] for t in tables]).astype(dt, copy=False) for k, dt in DETECTION_FIELDS.items()}


def blob_probability(image: np.ndarray, params: BlobParameters, polarity: int, *,
                     mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel probability that a pixel is a blob centre, for the blob preview.

    The dense model (normalised response only) gives every pixel a probability; around each
    candidate that was fitted, the map is capped by the candidate's final probability (0 for a
    rejected candidate), and the core of each detection (half its minor axis) carries its
    score. So the map agrees with :func:`detect_blobs`: a detection's centre pixel carries its
    score, and no pixel exceeds the threshold without a detection nearby.

    Parameters
    ----------
    image : uint8 (H, W)
    params : BlobParameters
        Radius range and adaptive flag of the ``polarity`` are used.
    polarity : int
        ``WHITE`` (+1) or ``BLACK`` (-1).
    mask : bool (H, W), optional

    Returns
    -------
    float32 (H, W)
        Probabilities in 0..1 (0 in masked pixels).
    """
    image, mask = _check_image(image, mask)
    if polarity == WHITE:
        rmin, rmax = params.white_min_radius, params.white_max_radius
    elif polarity == BLACK:
        rmin, rmax = params.black_min_radius, params.black_max_radius
    else:
        raise ValueError(f"polarity must be {WHITE} (white) or {BLACK} (black), got {polarity}")
    an = analyse_blobs(image, polarity, min_radius=rmin, max_radius=rmax,
                       adaptive=params.adaptive_background, mask=mask)
    H, W = image.shape
    prob = np.zeros((H, W), np.float32)
    for lv in an.levels:
        p = blob_score.dense_probability(lv.snr)
        if p.shape != (H, W):
            p = cv2.resize(p, (W, H), interpolation=cv2.INTER_LINEAR)
        np.maximum(prob, p, out=prob)
    # Around every fitted candidate the map is capped by its final score (0 if rejected); the
    # core of each detection (half its minor axis) carries its score.
    if len(an.x):
        fin = np.isfinite(an.x) & np.isfinite(an.y)
        cap = np.where(an.ok, an.score, 0.0)
        rad = np.clip(np.where(an.ok, an.major, np.maximum(an.major, 2.0)), 1.0, 64.0)
        _paint_discs(prob, an.x[fin], an.y[fin], rad[fin], cap[fin], np.minimum)
        det = an.ok & fin
        core = np.clip(0.5 * an.minor[det], 1.0, 64.0)
        _paint_discs(prob, an.x[det], an.y[det], core, an.score[det], np.maximum)
    if mask is not None:
        prob[mask] = 0.0
    return prob


def _paint_discs(prob: np.ndarray, x: np.ndarray, y: np.ndarray, r: np.ndarray, value: np.ndarray,
                 op: np.ufunc) -> None:
    """``prob = op(prob, value_i)`` inside the disc of radius ``r_i`` around each ``(x_i, y_i)``."""
    H, W = prob.shape
    rc = np.ceil(r).astype(int)
    for R in np.unique(rc):
        sel = rc == R
        off = np.arange(-R, R + 1)
        oy, ox = np.meshgrid(off, off, indexing="ij")
        disc = (ox * ox + oy * oy) <= R * R
        oy, ox = oy[disc], ox[disc]
        rows = np.rint(y[sel]).astype(int)[:, None] + oy[None]
        cols = np.rint(x[sel]).astype(int)[:, None] + ox[None]
        inside = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
        vals = np.broadcast_to(value[sel, None], rows.shape).astype(np.float32)
        op.at(prob, (rows[inside], cols[inside]), vals[inside])
