"""Blob detection: black and/or white painted dots in an 8-bit grayscale image.

The reference guide's four steps (classifier -> probability of a blob centre -> boundary ->
ellipse):

1. A dense, multi-scale centre-surround response normalised by the image's own clutter
   (:mod:`carapost.core.blob_candidates`) proposes candidate centres; a ring test (contrast
   against a ring of pixels around each) removes edges and faint texture.
2. Candidates that climb to the same peak (one blob seen at several scales) are fitted once
   (:mod:`carapost.core.blob_groups`).
   Each fit (:mod:`carapost.core.blob_fit`) searches the levels of its peak for the blob's
   core, models its local background, and measures the ellipse, sub-pixel centre and shape.
   Candidates whose core was found low (a dot merging with an eyebrow or a lip line) are
   fitted again with tighter outlines (:data:`ALT_CORE_LEVELS`); the more probable is kept.
3. A small neural-network classifier (:mod:`carapost.core.blob_score`), calibrated on rendered dots and
   synthetic faces with exact ground truth, turns the fit's features into the probability
   that it is a (well-located) blob centre; the Blob Parameters threshold is applied to it.
4. Duplicates and nested detections are resolved, keeping the most probable.

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
from .blob_candidates import (
    detection_scales,
    find_candidates,
    pixel_noise,
    pyramid,
    refine_level,
    responses,
    ring_test,
    signed_image,
)
from .blob_context import context_ring
from .blob_fit import LEVELS, LevelSearch, level_search, patch_half_size, ring_search
from .blob_groups import representatives
from .blob_kernels_outline import OUTPUT_FIELDS
from .blob_outline import outline_tables
from .blob_patches import Patches, extract_patches
from .blob_select import unique_detections

__all__ = ["detect_blobs", "analyse_blobs", "BlobAnalysis", "empty_table", "check_image",
           "CANDIDATE_MIN_SNR"]

#: Dense-stage threshold on the normalised response: deliberately low (recall).
CANDIDATE_MIN_SNR = 4.0
#: Dense-stage threshold on the rough Weber contrast (response over surround level).
CANDIDATE_MIN_WEBER = 0.05
#: Ring test: the candidate's centre must exceed the ring's upper quartile by this many pixel
#: noise sigmas (an edge has half its ring as bright as its centre) ...
RING_MIN_CNR = 6.0
#: ... and the ring's median by this fraction of the background grey level (paint is a large
#: relative change, skin texture a small one).
RING_MIN_WEBER = 0.12
#: Core levels of the alternative outlines fitted for candidates whose core was found lower
#: (see :func:`analyse_blobs`).
ALT_CORE_LEVELS: tuple[float, ...] = (0.75, 0.9)
#: ... only for candidates whose first outline has a lower probability than this.
_ALT_BELOW = 0.9
#: ... and only for strong candidates (dense SNR and ring-test Weber contrast): the dots these
#: outlines recover all stand far above both (SNR > 50, Weber > 0.3 on the benchmark's
#: synthetic takes), texture and shading candidates do not, and are not refitted.
_ALT_MIN_SNR = 30.0
_ALT_MIN_WEBER = 0.2


@dataclass
class BlobAnalysis:
    """Every fitted candidate of one polarity with its probability (full-resolution pixels).

    Attributes
    ----------
    x, y, major, minor, angle : float64 (N,)
        Fitted ellipse (px, radians).
    score : float64 (N,)
        Probability of a blob centre (0 for rejected candidates).
    ok : bool (N,)
        Passed the hard checks (core found, radius in range, not masked or saturated, not a
        duplicate of a more probable candidate).
    features : float64 (N, F)
        Classifier features (:data:`carapost.core.blob_score.FEATURES`).
    measures : dict of str to float64 (N,)
        Raw fit measurements (contrast, background, noise, shape, ...), for diagnostics.
    cand_x, cand_y : float64 (N,)
        The peak pixel the fit started from (full-resolution px).
    snr : float64 (N,)
        The candidate's normalised dense response.
    cand_weber : float64 (N,)
        The candidate's ring contrast over its background grey level.
    polarity : int
        +1 white, -1 black.
    levels : list
        The dense responses (:class:`carapost.core.blob_candidates.ResponseLevel`).
    n_candidates : int
        Dense candidates before the ring test.
    gate_features : float64 (N, G)
        Gate features of each candidate's latest level search
        (:data:`carapost.core.blob_score.GATE_FEATURES`; 0 where it had no peak).
    gated : bool (N,)
        Rejected by the gate (not fitted beyond the level search).
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
    n_candidates: int = 0
    gate_features: np.ndarray | None = None
    gated: np.ndarray | None = None

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


def check_image(image: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
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


_MEASURES = ("x", "y", "major", "minor", "angle", "contrast", "background", "rise", "noise", "ring_noise",
             "core_level", "found_level", "area_ratio", "shape", "asymmetry", "profile_rms", "area", "pixel_noise", "level",
             "border", "open", "kept", "saturated")


class _Context:
    """Per-image state shared by the fitting passes."""

    def __init__(self, pyr: list[np.ndarray], mask: np.ndarray | None, polarity: int, max_radius: float):
        self.pyr = pyr
        self.mask = mask
        self.polarity = polarity
        self.max_radius = max_radius
        self.noise: dict[int, float] = {}
        self.masks: dict[int, np.ndarray] = {}
        # The level search of each candidate's latest fit, reused by the alternative outlines:
        # ``searches[state[i]]`` row ``row[i]`` (-1: not fitted), at pixel ``px, py`` of ``level``.
        self.searches: list[LevelSearch] = []
        self.state = np.zeros(0, np.int64)
        self.row = np.zeros(0, np.int64)
        self.px = np.zeros(0, np.int64)
        self.py = np.zeros(0, np.int64)
        self.level = np.zeros(0, np.int64)

    def start(self, n: int, snr: np.ndarray, weber: np.ndarray, ref_level: float, gate: float,
              pre_gate: float = 0.0) -> None:
        """Prepare the per-candidate records for ``n`` candidates (dense SNR, ring Weber
        contrast), the image's reference grey level and the gate and pre-gate thresholds (0:
        none)."""
        self.snr, self.weber, self.ref_level, self.gate, self.pre_gate = snr, weber, ref_level, gate, pre_gate
        self.gate_feat = np.zeros((n, len(blob_score.GATE_FEATURES)))
        self.gated = np.zeros(n, bool)
        self.state = np.full(n, -1, np.int64)
        self.row = np.full(n, -1, np.int64)
        self.px = np.zeros(n, np.int64)
        self.py = np.zeros(n, np.int64)
        self.level = np.zeros(n, np.int64)

    def level_noise(self, k: int) -> float:
        if k not in self.noise:
            self.noise[k] = pixel_noise(self.pyr[k])
        return self.noise[k]

    def noise_of(self, k: np.ndarray) -> np.ndarray:
        """Pixel noise (grey levels) of pyramid levels ``k`` (int (N,)) -> float64 (N,)."""
        k = np.asarray(k, np.int64)
        if len(k) == 0:
            return np.zeros(0)
        per_level = np.zeros(int(k.max()) + 1)
        for v in np.flatnonzero(np.bincount(k)):
            per_level[v] = self.level_noise(int(v))
        return per_level[k]

    def level_mask(self, k: int) -> np.ndarray | None:
        if self.mask is None:
            return None
        if k not in self.masks:
            self.masks[k] = _level_mask(self.mask, self.pyr[k].shape)
        return self.masks[k]


def analyse_blobs(image: np.ndarray, polarity: int, *, min_radius: float, max_radius: float,
                  adaptive: bool = False, mask: np.ndarray | None = None, gate: bool = True) -> BlobAnalysis:
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
    gate : bool
        Apply the classifier's gate (candidates whose pre-score after the level search is too
        low are not fitted further; :func:`carapost.core.blob_score.gate_probability`).
        ``False`` fits every candidate (for calibration).

    Returns
    -------
    BlobAnalysis
        All fitted candidates (use :meth:`BlobAnalysis.table` to threshold).

    Raises
    ------
    ValueError
        Bad image or mask.
    """
    image, mask = check_image(image, mask)
    if polarity not in (WHITE, BLACK):
        raise ValueError(f"polarity must be {WHITE} (white) or {BLACK} (black), got {polarity}")
    signed = signed_image(image, polarity)
    scales = detection_scales(min_radius, max_radius)
    n_levels = max(max(scales), int(refine_level(max_radius * 2.0))) + 1
    pyr = pyramid(signed, n_levels)
    levels = [responses(pyr[k], k, sides, adaptive=adaptive) for k, sides in scales.items() if k < len(pyr)]
    cand = find_candidates(levels, min_snr=CANDIDATE_MIN_SNR, polarity=polarity, min_weber=CANDIDATE_MIN_WEBER)
    ctx = _Context(pyr, mask, polarity, max_radius)
    n_cand = len(cand)
    if mask is not None and len(cand):
        keep = np.ones(len(cand), bool)
        for k in np.unique(cand.level):
            sel = np.flatnonzero(cand.level == k)
            keep[sel] = ~ctx.level_mask(int(k))[cand.y[sel], cand.x[sel]]
        cand = cand.subset(keep)
    rt = ring_test(pyr, levels, cand, ctx.noise, polarity)
    c75 = rt.contrast(0.75)
    weber = rt.contrast(0.5) / np.maximum(rt.background(), 1.0)
    ring_ok = (c75 >= RING_MIN_CNR * rt.noise) & (weber >= RING_MIN_WEBER)
    cand, c75, weber = cand.subset(ring_ok), c75[ring_ok], weber[ring_ok]
    rep, px, py, ref, rep_radius = representatives(pyr, ctx.noise_of, cand, c75)
    cand, weber = cand.subset(rep), weber[rep]

    n = len(cand)
    ref_level = _reference_level(image)
    ctx.start(n, cand.snr, weber, ref_level, blob_score.gate_threshold() if gate else 0.0,
              blob_score.pre_gate_threshold() if gate else 0.0)
    block = np.zeros((len(_MEASURES), n))             # the measures' rows, written by _store at once
    out = dict(zip(_MEASURES, block))
    out["ring_weber"] = weber.astype(float)
    ok = np.zeros(n, bool)
    if n:
        radius = rep_radius.copy()
        level = ref.copy()
        sel = np.arange(n)
        refit = np.zeros(0, np.int64)
        # Rounds: candidates whose fit ran into its patch border are retried with twice the
        # radius; blobs fitted on a coarse level that turn out small enough for a finer one
        # are refitted there, in the next round's batches (each only once).
        for _ in range(3):
            if len(sel) == 0 and len(refit) == 0:
                break
            both = np.concatenate([sel, refit])
            border = _fit(ctx, both, px[both], py[both], level[both], radius[both], block, ok)[:len(sel)]
            retry = sel[border & (radius[sel] * 2 <= max_radius * 1.6)]
            refit = _finer(out, ok, sel[~border], level, px, py, radius)
            radius[retry] *= 2.0
            new_level = np.minimum(refine_level(radius[retry]), len(pyr) - 1)
            sh = new_level - level[retry]
            px[retry] >>= np.maximum(sh, 0)
            py[retry] >>= np.maximum(sh, 0)
            level[retry] = new_level
            sel = retry
        if len(refit):
            _fit(ctx, refit, px[refit], py[refit], level[refit], radius[refit], block, ok)
    ctx_img = cv2.blur(signed, (3, 3))
    score, ok_s, feat = _score(cand, out, ok, min_radius, max_radius, ctx_img, polarity, ref_level)
    if n and ALT_CORE_LEVELS:
        # Alternative, tighter outlines for dots whose core was taken at a low level (a dot
        # on an eyebrow, a lip line, next to the mouth): the classifier picks the more
        # probable outline of each candidate. All levels are fitted in one pass from the
        # candidates' level searches, then taken in order (each level sees the outline the
        # previous one chose).
        strong = (score < _ALT_BELOW) & (cand.snr >= _ALT_MIN_SNR) & (weber >= _ALT_MIN_WEBER) & ~ctx.gated
        reqs = [np.flatnonzero(strong & (out["core_level"] < lv - 1e-9)) for lv in ALT_CORE_LEVELS]
        rows = np.concatenate(reqs)
        if len(rows):
            mc = np.concatenate([np.full(len(r), lv) for r, lv in zip(reqs, ALT_CORE_LEVELS)])
            block2 = block[:, rows]
            out2 = dict(zip(_MEASURES, block2))
            out2.update((k, v[rows]) for k, v in out.items() if k not in out2)
            ok2 = np.zeros(len(rows), bool)
            _fit_alternatives(ctx, rows, mc, block2, ok2)
            score2, ok2_s, feat2 = _score(cand.subset(rows), out2, ok2, min_radius, max_radius, ctx_img, polarity,
                                          ref_level)
            off = 0
            for lv_alt, alt in zip(ALT_CORE_LEVELS, reqs):
                j = np.arange(off, off + len(alt))
                off += len(alt)
                take = ((out["core_level"][alt] < lv_alt - 1e-9) & (score[alt] < _ALT_BELOW)
                        & ok2_s[j] & (score2[j] > score[alt]))
                better, j = alt[take], j[take]
                block[:, better] = block2[:, j]
                for k in out:
                    if k not in _MEASURE_ROW:
                        out[k][better] = out2[k][j]
                ok[better], ok_s[better], score[better], feat[better] = ok2[j], True, score2[j], feat2[j]
    ok = ok_s
    ok &= unique_detections(out, score, ok)
    cx, cy = cand.full_xy()
    return BlobAnalysis(x=out["x"], y=out["y"], major=out["major"], minor=out["minor"],
                        angle=out["angle"], score=score, ok=ok, features=feat, measures=out,
                        cand_x=cx, cand_y=cy, snr=cand.snr, cand_weber=weber,
                        polarity=polarity, levels=levels, n_candidates=n_cand,
                        gate_features=ctx.gate_feat, gated=ctx.gated)


def _finer(out: dict[str, np.ndarray], ok: np.ndarray, sel: np.ndarray, level: np.ndarray, px: np.ndarray,
           py: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Of the fitted candidates ``sel``, those fitted on a coarser pyramid level than their
    size needs; their pixel, level and radius are set for the refit (in place). Returns them."""
    fine = np.minimum(refine_level(out["major"][sel]), level[sel])
    take = ok[sel] & (fine < level[sel])
    again, k = sel[take], fine[take]
    s = 2.0 ** k
    px[again] = np.rint(out["x"][again] / s).astype(np.int64)
    py[again] = np.rint(out["y"][again] / s).astype(np.int64)
    level[again] = k
    radius[again] = np.maximum(out["major"][again], 1.0)
    return again


def _reference_level(image: np.ndarray) -> float:
    """95th percentile of the informative pixels (neither black nor clipped) of every fourth
    row and column: the grey level of brightly lit skin or card."""
    sub = np.ascontiguousarray(image[::4, ::4])
    hist = cv2.calcHist([sub], [0], None, [256], [0, 256]).ravel()[5:251].astype(np.int64)   # exact counts
    n = int(hist.sum())
    if n < 64:
        return 255.0
    # numpy's linear percentile (np.percentile(info, 95)) of the sorted values, from their
    # histogram: the order statistics around (n - 1) 0.95 and numpy's interpolation.
    vi = (n - 1) * 0.95
    lo = int(np.floor(vi))
    g = vi - lo
    cum = np.cumsum(hist)
    a = float(np.searchsorted(cum, lo + 1) + 5)
    b = float(np.searchsorted(cum, min(lo + 2, n)) + 5)
    v = b - (b - a) * (1.0 - g) if g >= 0.5 else a + (b - a) * g
    return max(v, 8.0)


def _fit(ctx: _Context, sel: np.ndarray, px: np.ndarray, py: np.ndarray, level: np.ndarray,
         radius: np.ndarray, block: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Fit blobs ``sel`` centred on pixels ``px, py`` of pyramid ``level`` with full-resolution
    radius estimates ``radius``, writing into ``block`` (the measures' rows, see
    :func:`_store`)/``ok``. One patch stack per patch size
    (whatever their level), each step over all stacks before the next: the ring step of
    every stack, one pre-gate, the level step of every stack, one gate, the outlines
    (:func:`~carapost.core.blob_outline.outline_tables`), one store. The level searches are
    kept in ``ctx`` for the alternative outlines (:func:`_fit_alternatives`). Returns
    ``border (len(sel),)``."""
    r_lv = radius / 2.0 ** level
    half = patch_half_size(r_lv)
    noise = ctx.noise_of(level)
    # 1. Ring background and peak, per stack.
    stacks = []                                       # (positions in sel, RingSearch)
    for h in np.unique(half):
        h = int(h)
        groups = [np.flatnonzero((half == h) & (level == k)) for k in np.unique(level[half == h])]
        loc = np.concatenate(groups)
        pat = Patches.concat([extract_patches(ctx.pyr[int(level[g[0]])], px[g], py[g], h,
                                              bad=ctx.level_mask(int(level[g[0]])),
                                              saturated=_saturation(int(level[g[0]])) if ctx.polarity > 0 else None)
                              for g in groups])
        stacks.append((loc, ring_search(pat, r_lv[loc])))
    # The pre-gate (before step 2), over the patches with a peak of all stacks at once:
    # candidates whose pre-score is too low for the outline to make them probable are not
    # fitted further (rejected).
    gos: list = [None] * len(stacks)
    if ctx.gate > 0 and ctx.pre_gate > 0:
        pos = np.concatenate([loc[rs.alive] for loc, rs in stacks])
        if len(pos):
            gf = _gate_features(ctx, sel[pos], level[pos], noise[pos], r_lv[pos],
                                np.concatenate([rs.peak[rs.alive] for _, rs in stacks]),
                                np.concatenate([rs.sig0[rs.alive] for _, rs in stacks]),
                                np.concatenate([rs.c0[rs.alive, 0] for _, rs in stacks]))
            go = blob_score.pre_gate_probability(gf) >= ctx.pre_gate
            gos = np.split(go, np.cumsum([len(rs.alive) for _, rs in stacks])[:-1])
    # 2. Level search, per stack.
    searches = []                                     # (positions in sel, LevelSearch)
    for (loc, rs), go in zip(stacks, gos):
        k = level[loc]
        st = level_search(rs, go, max_radius=ctx.max_radius / 2.0 ** k, pixel_noise=noise[loc])
        ctx.gated[sel[loc[st.pregated]]] = True
        searches.append((loc, st))
    # The gate (after step 2), over all stacks at once.
    pos = np.concatenate([loc[st.alive] for loc, st in searches])
    has = np.concatenate([st.has for _, st in searches])
    gf = _gate_features(ctx, sel[pos], level[pos], noise[pos], r_lv[pos],
                        np.concatenate([st.peak for _, st in searches]),
                        np.concatenate([st.sig0 for _, st in searches]),
                        np.concatenate([st.c0[:, 0] for _, st in searches]),
                        np.asarray(LEVELS)[np.concatenate([st.k_found for _, st in searches])],
                        np.concatenate([st.area[np.arange(len(st.alive)), st.k_found] for _, st in searches])
                        * 4.0 ** level[pos],
                        np.concatenate([st.fill for _, st in searches]))
    ctx.gate_feat[sel[pos]] = gf
    go = has
    if ctx.gate > 0 and has.any():
        pg = blob_score.gate_probability(gf[has])
        go = has.copy()
        go[has] = pg >= ctx.gate
        ctx.gated[sel[pos[has]]] = pg < ctx.gate
    # 3-6. Outlines of the candidates that passed, then one store.
    ends = np.cumsum([len(st.alive) for _, st in searches])[:-1]
    gos = [st.alive[g] for (_, st), g in zip(searches, np.split(go, ends))]
    tables = outline_tables([(st, g, np.zeros(len(g))) for (_, st), g in zip(searches, gos)], polarity=ctx.polarity)
    fit = _Table(len(sel))
    for (loc, st), g, (keep, tab, ok_go, _) in zip(searches, gos, tables):
        fit.put(loc[g[keep]], tab, ok_go)
        fit.border[loc[st.alive]] = ~st.has
        ctx.state[sel[loc]] = len(ctx.searches)
        ctx.row[sel[loc]] = np.arange(len(loc))
        ctx.searches.append(st)
    _store(block, ok, sel, fit, px, py, level, noise, ctx.polarity)
    ctx.px[sel], ctx.py[sel], ctx.level[sel] = px, py, level
    return fit.border


def _gate_features(ctx: _Context, idx: np.ndarray, k: np.ndarray, noise: np.ndarray, r_lv: np.ndarray,
                   peak: np.ndarray, ring_noise: np.ndarray, bg_signed: np.ndarray,
                   found_level: np.ndarray | None = None, core_area: np.ndarray | None = None,
                   fill: np.ndarray | None = None) -> np.ndarray:
    """Gate features (:data:`carapost.core.blob_score.GATE_FEATURES`) of candidates ``idx`` on
    levels ``k`` with level pixel noise ``noise`` and radius estimates ``r_lv`` (level px), from
    their level search: the peak over the ring plane, the ring residual std and the ring plane
    at the centre (signed grey levels), and after step 2 the found core level, the core's area
    (full-resolution px^2) and fill (None before step 2, for the pre-gate: those columns are 0)."""
    n = len(idx)
    top = bg_signed + peak
    bg = bg_signed if ctx.polarity > 0 else 255.0 - bg_signed
    top_grey = top if ctx.polarity > 0 else 255.0 - top
    paint = top_grey / ctx.ref_level if ctx.polarity > 0 else 1.0 - top_grey / ctx.ref_level
    zero = np.zeros(n)
    m = {"ring_weber": ctx.weber[idx], "peak": peak, "ring_noise": ring_noise, "pixel_noise": noise,
         "found_level": zero if found_level is None else found_level,
         "core_area": zero if core_area is None else core_area, "fill": zero if fill is None else fill,
         "radius": r_lv * 2.0 ** k, "level": k, "background": bg, "paint": paint,
         "polarity": np.full(n, ctx.polarity)}
    return blob_score.gate_features(ctx.snr[idx], m)


class _Table:
    """The outline kernel's outputs for ``n`` patches (zero where not fitted): ``cols``
    float64 (len(OUTPUT_FIELDS), n) in the order of
    :data:`~carapost.core.blob_kernels_outline.OUTPUT_FIELDS`, ``ok`` and ``border`` bool (n,)."""

    def __init__(self, n: int):
        self.cols = np.zeros((len(OUTPUT_FIELDS), n))
        self.ok = np.zeros(n, bool)
        self.border = np.zeros(n, bool)

    def put(self, rows: np.ndarray, tab: np.ndarray, ok: np.ndarray) -> None:
        """Rows ``rows`` from a kernel table ``tab (M, F)`` and its ``ok (M,)``."""
        self.cols[:, rows] = tab.T
        self.ok[rows] = ok


_MEASURE_ROW = {name: i for i, name in enumerate(_MEASURES)}
#: The measures are the outline outputs in their order (``shape`` is ``shape_residual``) with
#: ``pixel_noise``, ``level`` and ``border`` inserted before ``open, kept, saturated``.
_N_HEAD = _MEASURES.index("pixel_noise")
assert (_MEASURES[:_N_HEAD] == tuple("shape" if f == "shape_residual" else f for f in OUTPUT_FIELDS[:_N_HEAD])
        and _MEASURES[_N_HEAD:_N_HEAD + 3] == ("pixel_noise", "level", "border")
        and _MEASURES[_N_HEAD + 3:] == OUTPUT_FIELDS[_N_HEAD:])
_X, _Y, _MINOR, _BACKGROUND, _AREA = (_MEASURE_ROW[k] for k in ("x", "y", "minor", "background", "area"))
assert _MEASURES[_X:_MINOR + 1] == ("x", "y", "major", "minor")


def _store(block: np.ndarray, ok: np.ndarray, idx: np.ndarray, fit: "_Table", px: np.ndarray,
           py: np.ndarray, k: np.ndarray, noise: np.ndarray, polarity: int) -> None:
    """Write the outlines ``fit`` (centres relative to patch centres ``px, py`` of levels
    ``k``) into columns ``idx`` of ``block`` float64 (len(_MEASURES), N) (the rows of the
    measures :data:`_MEASURES`) and ``ok`` (N,), in full-resolution px: one assignment of a
    ``(len(_MEASURES), len(idx))`` block."""
    s = 2.0 ** k
    h = _N_HEAD
    v = np.empty((len(_MEASURES), len(idx)))
    v[:h] = fit.cols[:h]
    v[h] = noise
    v[h + 1] = k
    v[h + 2] = fit.border
    v[h + 3:] = fit.cols[h:]
    v[_X] += px
    v[_Y] += py
    v[_X:_MINOR + 1] *= s                             # x, y, major, minor
    # Background level in the original image's grey levels (the level image is signed).
    if polarity <= 0:
        np.subtract(255.0, v[_BACKGROUND], out=v[_BACKGROUND])
    v[_AREA] *= s                                     # area: (area s) s
    v[_AREA] *= s
    block[:, idx] = v
    ok[idx] = fit.ok


def _fit_alternatives(ctx: _Context, cands: np.ndarray, min_core: np.ndarray, block: np.ndarray,
                      ok: np.ndarray) -> None:
    """Outlines of candidates ``cands`` (repeats allowed) with their core forced to at least
    ``min_core``, from their latest level search (no refitting of steps 1-2), into rows
    ``0..len(cands)-1`` of ``block`` (the measures' rows, see :func:`_store`)/``ok``."""
    st_id = ctx.state[cands]
    parts, order = [], []
    for sid in np.unique(st_id[st_id >= 0]):
        m = np.flatnonzero(st_id == sid)
        parts.append((ctx.searches[int(sid)], ctx.row[cands[m]], min_core[m]))
        order.append(m)
    for m, (keep, tab, ok_m, border) in zip(order, outline_tables(parts, polarity=ctx.polarity)):
        fit = _Table(len(m))
        fit.put(keep, tab, ok_m)
        fit.border[keep] = border
        c = cands[m]
        k = ctx.level[c]
        _store(block, ok, m, fit, ctx.px[c], ctx.py[c], k, ctx.noise_of(k), ctx.polarity)


def _score(cand, out: dict[str, np.ndarray], ok: np.ndarray, min_radius: float, max_radius: float,
           ctx_img: np.ndarray, polarity: int, ref_level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radius and image-bounds checks, features and probabilities of fitted candidates.

    ``ctx_img`` is the 3x3 mean of the signed full-resolution image (blobs bright), from
    which the context ring is sampled (:func:`~carapost.core.blob_context.context_ring`).

    Sets ``out["paint"]``: the dot's extreme grey level over ``ref_level``, a bright reference
    level of the image (paint has a fixed reflectance: black ink is among the darkest things
    in view, white paint among the brightest, whatever the exposure).

    Returns ``score (N,)`` (0 where not ok), ``ok (N,)`` and the features ``(N, F)``.
    """
    top = out["background"] + polarity * out["contrast"]
    out["paint"] = top / ref_level if polarity > 0 else 1.0 - top / ref_level
    context_ring(ctx_img, out, polarity)
    H, W = ctx_img.shape
    ok = ok & (out["major"] >= min_radius) & (out["major"] <= max_radius)
    ok &= (out["x"] >= -0.5) & (out["x"] <= W - 0.5) & (out["y"] >= -0.5) & (out["y"] <= H - 0.5)
    feat = blob_score.features(cand.snr, {**out, "polarity": np.full(len(cand), polarity)})
    score = np.zeros(len(ok))
    score[ok] = blob_score.probability(feat[ok])
    return score, ok, feat


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
    image, mask = check_image(image, mask)
    tables = []
    for pol, rmin, rmax, thr in _polarities(params):
        an = analyse_blobs(image, pol, min_radius=rmin, max_radius=rmax,
                           adaptive=params.adaptive_background, mask=mask,
                           gate=thr >= blob_score.gate_min_threshold())
        tables.append(an.table(thr))
    if not tables:
        return empty_table()
    return {k: np.concatenate([t[k] for t in tables]).astype(dt, copy=False) for k, dt in DETECTION_FIELDS.items()}
