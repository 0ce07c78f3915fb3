"""The blob classifier: features of a fitted candidate -> probability that it is a blob centre.

A logistic model on a handful of features of each candidate (see ``docs/blobs.md``):

``log_snr``
    log of the candidate's normalised centre-surround response (signal-to-clutter ratio of
    the dense stage, :mod:`carapost.core.blob_candidates`).
``log_cnr_pix``
    log of the blob's contrast over the image's pixel noise (how clearly it stands out of the
    noise).
``log_cnr``
    log of the contrast over the standard deviation of the blob's background residual (noise,
    texture and structure around it).
``shape``
    mismatch between the half-contrast region and its moment ellipse (0 for a perfect
    ellipse; merged blobs and dots cut by an occluding edge score high).
``aspect``
    minor / major semi-axis.
``log_weber``
    log of the Weber contrast: blob contrast over the background level (in the original
    image's grey levels; for white blobs over the smaller of that and the headroom to 255).
    Paint is a large *relative* change of reflectance, skin texture a small one, whatever
    the lighting.
``asymmetry``
    mismatch between the half-contrast region and its point reflection about the centre (an
    ellipse is centrally symmetric; a dot cut by an occluding edge, or merged with another
    one, is not).
``log_profile_chi2``
    log of the blob's residual variance around its own elliptical profile over the expected
    variance (pixel noise^2 + (2% of the contrast)^2): a blurred ellipse is a function of
    its elliptical radius, a merged or cut blob is not.

Squares (``log_snr``, ``log_cnr_pix``, ``log_weber``) let the logistic curve bend;
``asymmetry`` times ``log_cnr_pix`` and ``log_profile_chi2`` times ``log_cnr`` make a departure
from an ellipse count more on a high-contrast blob than on a noisy one. Every feature is
clipped to a physical range, so the quadratic terms never extrapolate.

The coefficients are fitted by ``benchmarks/fit_blob_score.py`` on rendered frames with exact
ground truth (positives: candidates whose refined centre is within 0.5 px of a fully visible
dot; negatives: everything else, including merged and partly occluded dots). The dense map
model (``DENSE_COEF``) is the same fit on ``log_snr`` alone and drives the blob preview.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FEATURES", "PROFILE_MODEL_ERROR", "COEF", "DENSE_COEF", "features", "probability", "dense_probability"]

FEATURES: tuple[str, ...] = ("bias", "log_snr", "log_cnr_pix", "log_cnr", "shape", "aspect",
                             "log_snr^2", "log_cnr_pix^2", "log_weber", "log_weber^2", "asymmetry",
                             "log_profile_chi2", "asymmetry*log_cnr_pix", "log_profile_chi2*log_cnr")

_SNR_CAP = 100.0
_CNR_CAP = 300.0

#: Relative error allowed to the elliptical-profile model of a blob (fraction of its contrast).
PROFILE_MODEL_ERROR = 0.02

#: Logistic coefficients, in the order of ``FEATURES``. Fitted by benchmarks/fit_blob_score.py.
COEF: np.ndarray = np.array([-6.1041, 0.2322, 1.2397, 2.8765, -2.3340, 1.8193, -0.1152, -0.0090, 0.8495,
                            -1.3743, -0.8680, 0.3723, -2.3849, -0.7977])

#: Logistic coefficients (bias, log_snr) of the dense (per-pixel) model.
DENSE_COEF: np.ndarray = np.array([-3.6444, 0.4417])


def features(snr: np.ndarray, m: dict[str, np.ndarray]) -> np.ndarray:
    """Feature matrix ``(N, len(FEATURES))`` (float64) from per-candidate measurements.

    Parameters
    ----------
    snr : (N,)
        Dense normalised response of each candidate.
    m : dict of str to (N,) arrays
        ``contrast``, ``background`` (original grey levels), ``noise`` (background residual
        std), ``pixel_noise`` (grey levels), ``polarity`` (optional, +1 white / -1 black), ``shape``, ``asymmetry``, ``profile_rms``
        (:class:`carapost.core.blob_fit.PatchFit`), ``major``, ``minor`` (px).
    """
    def log(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
        return np.log(np.clip(np.asarray(x, float), lo, hi))

    snr = np.asarray(snr, float)
    contrast = np.asarray(m["contrast"], float)
    pix = np.maximum(np.asarray(m["pixel_noise"], float), 0.5)
    ls = log(snr, 1e-3, _SNR_CAP)
    lp = log(contrast / pix, 1e-3, _CNR_CAP)
    lc = log(contrast / np.maximum(np.asarray(m["noise"], float), 0.5), 1e-3, _CNR_CAP)
    bg = np.asarray(m["background"], float)
    if "polarity" in m:
        # A white dot cannot rise above 255: its room is the smaller of the background level
        # (paint multiplies the light) and the headroom to saturation.
        bg = np.where(np.asarray(m["polarity"]) > 0, np.minimum(bg, 255.0 - bg), bg)
    lw = log(contrast / np.maximum(bg, 1.0), 1e-3, 3.0)
    asym = np.asarray(m["asymmetry"], float)
    expected = pix ** 2 + (PROFILE_MODEL_ERROR * contrast) ** 2
    chi = log(np.asarray(m["profile_rms"], float) ** 2 / expected, 0.1, 1e3)
    aspect = np.asarray(m["minor"], float) / np.maximum(np.asarray(m["major"], float), 1e-6)
    return np.stack([
        np.ones_like(snr), ls, lp, lc, np.asarray(m["shape"], float), aspect,
        ls * ls, lp * lp, lw, lw * lw, asym, chi, asym * lp, chi * lc,
    ], axis=1)


def _logistic(z: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * z))


def probability(feat: np.ndarray, coef: np.ndarray | None = None) -> np.ndarray:
    """Probability ``(N,)`` float64 that each candidate is a well-located blob centre."""
    c = COEF if coef is None else np.asarray(coef, float)
    return _logistic(np.clip(np.asarray(feat, float) @ c, -60.0, 60.0))


def dense_probability(snr: np.ndarray, coef: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel probability (float32, shape of ``snr``) from the normalised response alone."""
    c = DENSE_COEF if coef is None else np.asarray(coef, float)
    z = c[0] + c[1] * np.log(np.clip(snr, 1e-3, None))
    return _logistic(z).astype(np.float32)
