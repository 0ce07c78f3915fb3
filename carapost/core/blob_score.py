"""The blob classifier: shape measurements of fitted candidates, features, and the probability
that a candidate is a blob centre.

Shape measurements (computed by :mod:`carapost.core.blob_fit` with the functions below):

``shape_residual``
    mismatch between the soft half-contrast region and its moment ellipse (0 for a perfect
    ellipse; merged blobs and dots cut by an occluding edge score high).
``asymmetry``
    mismatch between the region and its point reflection about the centre (an ellipse is
    centrally symmetric; a dot cut by an occluding edge, or merged with a different one, is
    not).
``profile_rms``
    residual of the blob signal around its own elliptical radial profile (a blurred ellipse is
    a function of its elliptical radius; a merged or cut blob is not).

Features of the classifier (:data:`FEATURES`):

``log_snr``
    the candidate's normalised dense response (signal-to-clutter ratio).
``log_cnr_pix``
    contrast over the image's pixel noise: how clearly it stands out of the noise.
``log_cnr``
    contrast over the residual of its local background (noise, texture, structure around it).
``log_weber``
    contrast over the background grey level (for white blobs over the smaller of that and the
    headroom to 255): paint is a large *relative* change of reflectance, skin texture a small
    one, whatever the lighting.
``rise``
    how far the local background stands above the wider ring around it, over the contrast (a
    dot on an eyebrow or a lip line stands on a band; a texture spot on a band rarely has the
    contrast of paint).
``core_level``
    the level of the peak at which the blob separates from its surround.
``shape``, ``asymmetry``, ``log_profile_chi2``
    departures from a blurred ellipse (profile residual over pixel noise^2 + (2% C)^2).
``aspect``
    minor / major semi-axis.
``open``
    the dot's contrast against its surround in its weakest direction, over its full contrast
    (near 0 where it merges with something as dark: a neighbouring dot, a shadow, the lips).
``kept``
    the fraction of the half-contrast region inside its own ellipse (trimmed moments).
``area_ratio``
    the area of the peak's component one level above the core over the core's area (a flat
    paint top keeps its area; a soft texture bump shrinks).
``paint``
    the dot's extreme grey level over a bright reference level of the image (white blobs),
    or one minus that (black blobs): paint has a fixed reflectance, so black ink is among the
    darkest things in view and white paint among the brightest, whatever the exposure (teeth
    in an open mouth, eye corners and nostrils are not).
``saturated``
    the fraction of a white blob's surround that is clipped at 255.

``log_major``
    the fitted major semi-axis (px).
``log_cnr_ring``
    contrast over the residual of the wider ring background.
``log_ring_weber``
    the candidate's ring contrast over its background grey level (before the fit).
``level``
    the pyramid level the blob was fitted on.
``polarity``
    +1 white, -1 black.
``background``
    the local background grey level over 255.
``ctx_max``, ``ctx_mean``, ``ctx_line``
    context at about twice the blob's size: the signal over the contrast on a ring at twice
    the fitted ellipse + 1.5 px — its largest value (an eye or nostril beside an eye corner),
    its mean, and the larger of two opposite points' minimum (a line or band through it).
``ctx_inner``
    the mean of the same on a ring at 1.3x the ellipse + 1.5 px (a pupil inside its iris).
``forced``
    how far an alternative outline's core level was forced above the level its search
    found (0 for the first outline; see :data:`carapost.core.blobs.ALT_CORE_LEVELS`).

Squares of ``log_cnr_pix`` and ``log_weber`` and a few products are kept from the earlier
logistic model. Every feature is clipped to a physical range, so nothing extrapolates.

**The classifier** is a small neural network: the standardised features feed one hidden layer
of ``tanh`` units whose weighted sum is passed through the logistic function; three such
networks fitted from different random starts are averaged (their mean logit). Trained with the
log-loss (the negative log-likelihood of the labels), its output is a probability; its
calibration is checked on held-out images (``docs/blobs.md``). The weights live in
``carapost/resources/blob_classifier.json``, written by ``benchmarks/fit_blob_score.py``,
together with the per-pixel (dense) logistic model used by the preview.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

__all__ = ["FEATURES", "GATE_FEATURES", "PRE_GATE_FEATURES", "PROFILE_MODEL_ERROR", "features", "probability",
           "dense_probability", "gate_features", "gate_probability", "gate_threshold", "gate_min_threshold",
           "pre_gate_probability", "pre_gate_threshold",
           "load_model", "save_model", "network_probability", "shape_residual", "asymmetry", "profile_rms",
           "MODEL_PATH"]

FEATURES: tuple[str, ...] = ("bias", "log_snr", "log_cnr_pix", "log_cnr", "log_weber", "rise", "core_level",
                             "shape", "asymmetry", "log_profile_chi2", "aspect", "log_cnr_pix^2",
                             "log_weber^2", "asymmetry*log_cnr_pix", "log_profile_chi2*log_cnr_pix",
                             "shape*log_cnr_pix", "open", "kept", "area_ratio", "open^2", "open*log_weber",
                             "paint", "paint^2", "saturated", "log_major", "log_cnr_ring", "log_ring_weber",
                             "level", "polarity", "background", "ctx_max", "ctx_mean", "ctx_line", "ctx_inner",
                             "forced")

_SNR_CAP = 100.0
#: Smallest background grey level used for the Weber contrast (below it the skin is in deep
#: shadow or beyond the silhouette, and noise dominates any ratio).
_MIN_BACKGROUND = 15.0
_CNR_CAP = 300.0

#: Relative error allowed to the elliptical-profile model of a blob (fraction of its contrast).
PROFILE_MODEL_ERROR = 0.02

#: The classifier's weights (JSON, see :func:`load_model`).
MODEL_PATH = Path(__file__).resolve().parents[1] / "resources" / "blob_classifier.json"


def features(snr: np.ndarray, m: dict[str, np.ndarray]) -> np.ndarray:
    """Feature matrix ``(N, len(FEATURES))`` (float64) from per-candidate measurements.

    Parameters
    ----------
    snr : (N,)
        Dense normalised response of each candidate.
    m : dict of str to (N,) arrays
        ``contrast``, ``background`` (original grey levels), ``noise`` (local background
        residual std), ``pixel_noise`` (grey levels), ``polarity`` (+1 white / -1 black),
        ``rise``, ``core_level``, ``shape``, ``asymmetry``, ``profile_rms``, ``open``, ``kept``,
        ``area_ratio``, ``paint``, ``saturated``, ``major``, ``minor`` (px), ``ring_noise``
        (ring background residual std), ``ring_weber``, ``level``, ``ctx_max``, ``ctx_mean``,
        ``ctx_line``, ``ctx_inner`` (context rings, see :func:`carapost.core.blobs._context_ring`),
        ``found_level`` (core level found by the search; ``forced`` = ``core_level`` minus it,
        > 0 for an alternative outline).

    The columns are assembled in one ``(F, N)`` block: the raw values, one clip with the
    per-feature bounds (:data:`_FEATURE_BOUNDS`), one log of the logged rows, the products.
    """
    def col(name: str) -> np.ndarray:
        return np.asarray(m[name], float)

    snr = np.asarray(snr, float)
    X = np.empty((len(FEATURES), len(snr)))
    contrast = col("contrast")
    pix = np.maximum(col("pixel_noise"), 0.5)
    bg = col("background")
    # A white dot cannot rise above 255: its room is the smaller of the background level
    # (paint multiplies the light) and the headroom to saturation.
    room = np.where(np.asarray(m["polarity"]) > 0, np.minimum(bg, 255.0 - bg), bg)
    X[0] = 1.0
    X[1] = snr
    X[2] = contrast / pix
    X[3] = contrast / np.maximum(col("noise"), 0.5)
    X[4] = contrast / np.maximum(room, _MIN_BACKGROUND)
    X[5] = col("rise")
    X[6] = col("core_level")
    X[7] = col("shape")
    X[8] = col("asymmetry")
    X[9] = col("profile_rms") ** 2 / (pix ** 2 + (PROFILE_MODEL_ERROR * contrast) ** 2)
    X[10] = col("minor") / np.maximum(col("major"), 1e-6)
    X[16] = col("open")
    X[17] = col("kept")
    X[18] = col("area_ratio")
    X[21] = col("paint")
    X[23] = col("saturated")
    X[24] = col("major")
    X[25] = contrast / np.maximum(col("ring_noise"), 0.5)
    X[26] = col("ring_weber")
    X[27] = col("level")
    X[28] = col("polarity")
    X[29] = bg
    for i, name in enumerate(("ctx_max", "ctx_mean", "ctx_line", "ctx_inner")):
        X[30 + i] = col(name)
    X[34] = X[6] - col("found_level")
    np.clip(X, _FEATURE_BOUNDS[0][:, None], _FEATURE_BOUNDS[1][:, None], out=X)
    X[_FEATURE_LOGS] = np.log(X[_FEATURE_LOGS])
    X[29] /= 255.0
    lp, lw = X[2], X[4]
    X[11], X[12], X[13], X[14], X[15] = lp * lp, lw * lw, X[8] * lp, X[9] * lp, X[7] * lp
    X[19], X[20], X[22] = X[16] * X[16], X[16] * lw, X[21] * X[21]
    return np.ascontiguousarray(X.T)


def _bounds(spec: dict[str, tuple[float, float]], names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper clip bounds ``(F,)`` of the features ``names`` (unbounded where not in
    ``spec``)."""
    lo = np.array([spec.get(f, (-np.inf, np.inf))[0] for f in names])
    hi = np.array([spec.get(f, (-np.inf, np.inf))[1] for f in names])
    return lo, hi


#: Clip bounds of the raw feature values (before their log where the name says ``log_``);
#: products of features are computed after the clip.
_FEATURE_BOUNDS = _bounds({
    "log_snr": (1.0, _SNR_CAP), "log_cnr_pix": (1.0, _CNR_CAP), "log_cnr": (1.0, _CNR_CAP),
    "log_weber": (0.02, 3.0), "rise": (-1.0, 4.0), "shape": (0.0, 1.0), "asymmetry": (0.0, 1.0),
    "log_profile_chi2": (0.1, 1e3), "open": (0.0, 1.0), "kept": (0.0, 1.0), "area_ratio": (0.0, 1.0),
    "paint": (0.0, 2.0), "saturated": (0.0, 1.0), "log_major": (1.0, 30.0), "log_cnr_ring": (1.0, _CNR_CAP),
    "log_ring_weber": (0.01, 3.0), "level": (0.0, 3.0), "background": (0.0, 255.0), "ctx_max": (-1.0, 2.0),
    "ctx_mean": (-1.0, 2.0), "ctx_line": (-1.0, 2.0), "ctx_inner": (-1.0, 2.0), "forced": (0.0, 1.0)}, FEATURES)
_FEATURE_LOGS = np.array([i for i, f in enumerate(FEATURES) if f.startswith("log_") and "^" not in f and "*" not in f])


#: Features of the gate: the cheap pre-score computed after the level search (steps 1-2 of
#: the fit), before the outline (steps 3-6), from which candidates that cannot become
#: probable detections are not fitted further (:func:`gate_probability`).
GATE_FEATURES: tuple[str, ...] = ("bias", "log_snr", "log_ring_weber", "log_peak_pix", "log_peak_ring", "found_level",
                                  "log_area", "fill", "log_radius", "level", "peak_weber", "paint", "polarity",
                                  "background")


def gate_features(snr: np.ndarray, m: dict[str, np.ndarray]) -> np.ndarray:
    """Gate feature matrix ``(N, len(GATE_FEATURES))`` (float64).

    ``m`` holds per candidate: ``ring_weber``; from the level search ``peak`` (grey levels
    above the ring plane), ``ring_noise`` (its residual std), ``pixel_noise``, ``found_level``,
    ``core_area`` (full-resolution px^2), ``fill``; the candidate's ``radius`` (px) and
    ``level``; ``background`` (the ring plane at the centre, original grey levels), ``paint``
    (as for :func:`features`, from the peak) and ``polarity``. Assembled like
    :func:`features` (one clip, one log).
    """
    def col(name: str) -> np.ndarray:
        return np.asarray(m[name], float)

    snr = np.asarray(snr, float)
    G = np.empty((len(GATE_FEATURES), len(snr)))
    peak = col("peak")
    bg = col("background")
    pol = col("polarity")
    room = np.where(pol > 0, np.minimum(bg, 255.0 - bg), bg)
    G[0] = 1.0
    G[1] = snr
    G[2] = col("ring_weber")
    G[3] = peak / np.maximum(col("pixel_noise"), 0.5)
    G[4] = peak / np.maximum(col("ring_noise"), 0.5)
    G[5] = col("found_level")
    G[6] = col("core_area")
    G[7] = col("fill")
    G[8] = col("radius")
    G[9] = col("level")
    G[10] = peak / np.maximum(room, _MIN_BACKGROUND)
    G[11] = col("paint")
    G[12] = pol
    G[13] = bg
    np.clip(G, _GATE_BOUNDS[0][:, None], _GATE_BOUNDS[1][:, None], out=G)
    G[_GATE_LOGS] = np.log(G[_GATE_LOGS])
    G[13] /= 255.0
    return np.ascontiguousarray(G.T)


_GATE_BOUNDS = _bounds({
    "log_snr": (1.0, _SNR_CAP), "log_ring_weber": (0.01, 3.0), "log_peak_pix": (0.1, _CNR_CAP),
    "log_peak_ring": (0.1, _CNR_CAP), "log_area": (1.0, 2000.0), "fill": (0.0, 2.0), "log_radius": (0.5, 30.0),
    "level": (0.0, 3.0), "peak_weber": (0.01, 3.0), "paint": (0.0, 2.0), "background": (0.0, 255.0)}, GATE_FEATURES)
_GATE_LOGS = np.array([i for i, f in enumerate(GATE_FEATURES) if f.startswith("log_") or f == "peak_weber"])


#: The gate features known before the flood (step 1 of the level search: ring background and
#: peak): the **pre-gate**, a second small network on these alone, rejects the clearest
#: non-dots before their flood and level search (:func:`pre_gate_probability`).
PRE_GATE_FEATURES: tuple[str, ...] = tuple(f for f in GATE_FEATURES if f not in ("found_level", "log_area", "fill"))
#: Columns of :data:`GATE_FEATURES` that are :data:`PRE_GATE_FEATURES`.
PRE_GATE_COLUMNS = np.array([GATE_FEATURES.index(f) for f in PRE_GATE_FEATURES])


def pre_gate_probability(gf: np.ndarray, model: dict | None = None) -> np.ndarray | None:
    """The pre-gate's output ``(N,)`` on gate features ``gf (N, len(GATE_FEATURES))`` (only
    the :data:`PRE_GATE_COLUMNS` are read; a network stored as ``gate_pre_*`` arrays), or None
    when the model has no pre-gate."""
    sub = _default_part("gate_pre_") if model is None else _part(model, "gate_pre_")
    if sub is None:
        return None
    g = np.asarray(gf, float)[:, PRE_GATE_COLUMNS]
    return network_probability(g, sub)


def pre_gate_threshold(model: dict | None = None) -> float:
    """Candidates whose pre-gate output is below this are rejected before their flood (0: no
    pre-gate). Used with the gate (:func:`gate_min_threshold`)."""
    model = load_model() if model is None else model
    return float(model["gate_pre_threshold"]) if "gate_pre_threshold" in model else 0.0


def gate_probability(gf: np.ndarray, model: dict | None = None) -> np.ndarray | None:
    """The gate's output ``(N,)`` on gate features ``gf`` (a one-hidden-layer network like the
    classifier, stored as ``gate_*`` arrays), or None when the model has no gate."""
    sub = _default_part("gate_") if model is None else _part(model, "gate_")
    if sub is None:
        return None
    return network_probability(gf, sub)


def _part(model: dict, prefix: str) -> dict | None:
    """The network stored in ``model`` as ``prefix`` + ``mean``, ``std``, ``W1``, ``b1``, ``w2``,
    ``b2`` (None if absent)."""
    if prefix + "W1" not in model:
        return None
    return {k: model[prefix + k] for k in ("mean", "std", "W1", "b1", "w2", "b2")}


@lru_cache(maxsize=4)
def _default_part(prefix: str) -> dict | None:
    """:func:`_part` of the default classifier (kept: the gates run a few times per batch)."""
    return _part(load_model(), prefix)


def gate_threshold(model: dict | None = None) -> float:
    """Candidates whose gate output is below this are not fitted further (0: no gate)."""
    model = load_model() if model is None else model
    return float(model["gate_threshold"]) if "gate_threshold" in model else 0.0


def gate_min_threshold(model: dict | None = None) -> float:
    """The lowest detection threshold at which the gate is used: it was set to drop at most
    a tenth of a percent of the candidates more probable than this (below it, every
    candidate is fitted, so that a low threshold shows everything the classifier sees)."""
    model = load_model() if model is None else model
    return float(model["gate_keep"]) if "gate_keep" in model else float("inf")


def _logistic(z: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * z))


def network_probability(feat: np.ndarray, model: dict) -> np.ndarray:
    """Output ``(N,)`` of the one-hidden-layer network (or ensemble of networks) ``model`` on
    features ``(N, F)``.

    ``model`` holds ``mean``, ``std`` (F-1,) for the standardisation of every feature but the
    bias, ``W1`` (F-1, H), ``b1`` (H,), ``w2`` (H,), ``b2`` (scalar):
    ``p = logistic(tanh(((x - mean) / std) W1 + b1) w2 + b2)``. An ensemble of ``M`` networks
    fitted from different random starts stacks them: ``W1`` (M, F-1, H), ``b1``, ``w2`` (M, H),
    ``b2`` (M,); its output is the logistic of the members' mean logit.
    """
    x = (np.asarray(feat, float)[:, 1:] - model["mean"]) / model["std"]
    W1 = np.asarray(model["W1"], float)
    if W1.ndim == 2:
        h = np.tanh(x @ W1 + model["b1"])
        z = h @ model["w2"] + model["b2"]
    else:
        h = np.tanh(np.matmul(x, W1) + np.asarray(model["b1"])[:, None, :])           # (M, N, H)
        z = (np.matmul(h, np.asarray(model["w2"])[:, :, None])[:, :, 0]
             + np.asarray(model["b2"])[:, None]).mean(axis=0)
    return _logistic(np.clip(z, -60.0, 60.0))


def save_model(path: Path, model: dict, info: dict | None = None) -> None:
    """Write a classifier (network arrays and ``dense_coef``) as JSON, with ``info`` (how it
    was fitted)."""
    out = {"features": list(FEATURES), "info": info or {}}
    for k, v in model.items():
        out[k] = np.asarray(v, float).tolist()
    Path(path).write_text(json.dumps(out, separators=(",", ":")).replace('],"', '],\n"') + "\n")


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> dict:
    """The classifier stored at ``path`` (default :data:`MODEL_PATH`) as arrays.

    Raises
    ------
    ValueError
        If the file's feature list does not match :data:`FEATURES`.
    """
    p = Path(path) if path else MODEL_PATH
    raw = json.loads(p.read_text())
    if tuple(raw.get("features", ())) != FEATURES:
        raise ValueError(f"{p}: blob classifier was fitted on other features; rerun benchmarks/fit_blob_score.py")
    return {k: np.asarray(v, float) for k, v in raw.items() if k not in ("features", "info")}


def probability(feat: np.ndarray, model: dict | None = None) -> np.ndarray:
    """Probability ``(N,)`` float64 that each candidate is a well-located blob centre."""
    return network_probability(feat, load_model() if model is None else model)


def dense_probability(snr: np.ndarray, coef: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel probability (float32, shape of ``snr``) from the normalised response alone
    (logistic in ``log snr`` with coefficients ``coef`` = (bias, slope))."""
    c = load_model()["dense_coef"] if coef is None else np.asarray(coef, float)
    z = c[0] + c[1] * np.log(np.clip(snr, 1e-3, None))
    return _logistic(z).astype(np.float32)


# -- shape measurements ----------------------------------------------------------------------

def ellipse_distance(mx: np.ndarray, my: np.ndarray, cov: tuple, dxf: np.ndarray,
                     dyf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Approximate signed distance (px, negative inside) of every patch pixel ``(N, S, S)`` from
    the ellipse of centre ``mx, my`` whose uniform-disc covariance is ``cov = (cxx, cxy, cyy)``,
    and the squared normalised elliptical radius of every pixel (1 on the ellipse)."""
    cxx, cxy, cyy = cov
    det = np.maximum(cxx * cyy - cxy * cxy, 1e-9)
    ia = (cyy / (4 * det)).astype(np.float32)[:, None, None]
    ib = (-cxy / (4 * det)).astype(np.float32)[:, None, None]
    ic = (cxx / (4 * det)).astype(np.float32)[:, None, None]
    ux = dxf[None] - mx.astype(np.float32)[:, None, None]
    uy = dyf[None] - my.astype(np.float32)[:, None, None]
    r2 = ux * ux + uy * uy
    rho2 = np.maximum(ia * ux * ux + 2 * ib * ux * uy + ic * uy * uy, 1e-12)
    return np.sqrt(r2) - np.sqrt(r2 / rho2), rho2       # = |u| (1 - 1/rho): negative inside


def shape_residual(q: np.ndarray, mx: np.ndarray, my: np.ndarray, cov: tuple, dxf: np.ndarray,
                   dyf: np.ndarray, win: np.ndarray, m0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mismatch between soft regions ``q (N, S, S)`` and their moment ellipses.

    ``cov = (cxx, cxy, cyy)`` are the regions' second central moments (a uniform ellipse's
    boundary matrix is ``4 Sigma``); ``mx, my`` the centroids (offsets from the patch
    centre); ``win`` the pixels compared; ``m0`` the regions' areas. Returns ``sum |q -
    ellipse| / m0`` (N,) and the squared normalised elliptical radius ``(N, S, S)`` of every
    pixel (1 on the ellipse).
    """
    n = q.shape[0]
    dist, rho_e2 = ellipse_distance(mx, my, cov, dxf, dyf)
    q_ell = np.clip(0.5 - dist, 0.0, 1.0)
    shape = np.einsum("ij,ij->i", np.abs(q - q_ell).reshape(n, -1), win.reshape(n, -1),
                      dtype=np.float64) / m0
    return shape, rho_e2


_PROFILE_BIN = 0.35
_PROFILE_MARGIN = 2.5


def profile_rms(d: np.ndarray, rho2: np.ndarray, radius: np.ndarray, win: np.ndarray) -> np.ndarray:
    """RMS of ``d (N, S, S)`` around its mean profile over the elliptical radius
    ``sqrt(rho2) * radius`` (0.35 px bins, out to 2.5 px beyond the boundary, within ``win``)."""
    n = d.shape[0]
    if n == 0:
        return np.zeros(0)
    patch, pix = np.divmod(np.flatnonzero(win.ravel()), d.shape[1] * d.shape[2])
    rad = radius.astype(np.float32)[patch]
    t = np.sqrt(rho2.reshape(n, -1)[patch, pix]) * rad
    inside = t <= rad + _PROFILE_MARGIN
    patch, pix, t = patch[inside], pix[inside], t[inside]
    nb = int(np.ceil((float(radius.max()) + _PROFILE_MARGIN) / _PROFILE_BIN)) + 1
    key = patch * nb + np.minimum(t * (1.0 / _PROFILE_BIN), nb - 1).astype(np.int64)
    df = d.reshape(n, -1)[patch, pix].astype(np.float64)
    cnt = np.bincount(key, minlength=n * nb)
    prof = np.bincount(key, weights=df, minlength=n * nb) / np.maximum(cnt, 1)
    r = df - prof[key]
    rss = np.bincount(patch, weights=r * r, minlength=n)
    npix = np.bincount(patch, minlength=n)
    nbins = (cnt.reshape(n, nb) > 0).sum(axis=1)
    return np.sqrt(rss / np.maximum(npix - nbins, 1))


def asymmetry(q: np.ndarray, mx: np.ndarray, my: np.ndarray, half: int) -> np.ndarray:
    """``sum |q'(p) - q'(2c - p)| / (2 sum q)`` per patch, ``c = (mx, my)`` (offsets from the
    patch centre).

    ``2c = k + f`` with integer ``k``; ``q'`` is ``q`` shifted by ``f/2`` (bilinear), whose
    reflection about ``c - f/2 = k/2`` is an exact index flip, so both sides of the comparison
    carry the same interpolation blur and a centrally symmetric blob scores ~0.
    """
    n, s, _ = q.shape
    if n == 0:
        return np.zeros(0)
    pad = 2
    sp = s + 2 * pad
    qp = np.zeros((n, sp, sp), np.float32)
    qp[:, pad:pad + s, pad:pad + s] = q
    ty2, tx2 = 2.0 * my, 2.0 * mx
    ky, kx = np.floor(ty2).astype(np.int64), np.floor(tx2).astype(np.int64)
    ty = ((ty2 - ky) / 2.0).astype(np.float32)[:, None, None]
    tx = ((tx2 - kx) / 2.0).astype(np.float32)[:, None, None]
    # q'(p) = q(p + t): bilinear with offsets 0/1 (same integer offsets for all patches).
    q1 = ((1 - ty) * (1 - tx) * qp[:, 1:-1, 1:-1] + (1 - ty) * tx * qp[:, 1:-1, 2:]
          + ty * (1 - tx) * qp[:, 2:, 1:-1] + ty * tx * qp[:, 2:, 2:])      # (n, s+2, s+2), offset -1
    # Reflection about k/2: q'(k - o); q1 index of offset o is o + half + 1.
    s1 = s + 2
    off = np.arange(-half, half + 1)
    iy = np.clip(ky[:, None] - off[None] + half + 1, 0, s1 - 1)
    ix = np.clip(kx[:, None] - off[None] + half + 1, 0, s1 - 1)
    flat = q1.reshape(-1)
    base = (np.arange(n) * s1 * s1)[:, None, None]
    qr = flat[base + iy[:, :, None] * s1 + ix[:, None, :]]
    num = np.abs(q1[:, 1:-1, 1:-1] - qr).reshape(n, -1).sum(axis=1, dtype=np.float64)
    return num / np.maximum(2.0 * q.reshape(n, -1).sum(axis=1, dtype=np.float64), 1e-9)
