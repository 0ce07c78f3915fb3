"""Calibrate cameras without CaraLive: intrinsics and extrinsics from views of a flat target.

For users without a Vicon ``.xcp``: film a checkerboard or dot grid
(:class:`~carapost.core.calib_targets.TargetSpec`) with every camera, then

* :func:`calibrate_intrinsics` fits one camera's focal length, principal point and radial
  correction **directly in the XCP model** of :mod:`carapost.core.camera` (raw to corrected
  pixels, ``s = 1 + k1 r^2 + k2 r^4 + k3 r^6`` with ``r`` in pixels): OpenCV's
  ``calibrateCamera`` gives the starting point (its Brown model converted with
  :func:`carapost.core.lens_models.fit_radial_correction`), then the raw-pixel
  reprojection error through :func:`carapost.core.camera.project` (which inverts the
  correction) is minimised over the intrinsics and every view's target pose;
* :func:`calibrate_extrinsics` puts all cameras in one world frame from *shots* in which two
  or more cameras see the target at the same moment (directly, or through a chain of
  cameras sharing shots), refining every camera pose and every target pose together;
* :func:`calibrate_cameras` does both from images and returns a :class:`RigCalibration`,
  whose :meth:`RigCalibration.camera_records` build an ``.xcp``-ready
  ``carapost.io.calibration.Calibration``.

Conventions are those of :mod:`carapost.core.camera`: raw pixels, mm, ``X_cam = R X + t``.
See ``docs/calibrate-cameras.md`` for the workflow and the accuracy measured on real images.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from .calib_extrinsics import _BIG, ExtrinsicsResult, _rotvec, calibrate_extrinsics, target_pose
from .calib_targets import TargetSpec, detect_target, target_points
from .camera import Intrinsics, project, rodrigues
from .lens_models import brown_undistort, fit_radial_correction, monotonic_radius

__all__ = [
    "RADIAL_MODELS",
    "IntrinsicsResult",
    "ExtrinsicsResult",
    "RigCalibration",
    "calibrate_intrinsics",
    "calibrate_extrinsics",
    "calibrate_cameras",
    "reprojection_check",
]

#: Radial models: name -> number of radial terms fitted (``xcp2`` is ``VICON_RADIAL``).
RADIAL_MODELS = {"none": 0, "xcp1": 1, "xcp2": 2, "xcp3": 3}


# --------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------


def _view_array(views: Sequence[np.ndarray | None], n: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Stack the non-empty views: ``(V, n, 2)`` and their input indices ``(V,)``."""
    keep, arrs = [], []
    for i, v in enumerate(views):
        if v is None:
            continue
        a = np.asarray(v, dtype=float)
        if a.shape != (n, 2):
            raise ValueError(f"{what} {i}: expected ({n}, 2) target points, got shape {a.shape}")
        if np.isfinite(a).all(axis=1).sum() < 4:
            continue
        keep.append(i)
        arrs.append(a)
    out = np.stack(arrs) if arrs else np.empty((0, n, 2))
    return out, np.asarray(keep, dtype=np.int64)


# --------------------------------------------------------------------------------------
# Intrinsics
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class IntrinsicsResult:
    """Result of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    intrinsics : Intrinsics
        The fitted camera, XCP model (``sensor_size`` is the image size).
    R, t : arrays (V, 3, 3), (V, 3)
        Target-to-camera pose of each view used.
    views : array (V,) int
        Index of each used view in the input list (``None`` and rejected views left out).
    rejected : array (K,) int
        Input indices of views dropped as outliers.
    residuals : array (V, N, 2)
        Observed minus projected raw pixels (NaN where a point was not observed).
    rms : float
        RMS reprojection error over all points of the used views, raw px (the final error
        in our model).
    per_view_rms : array (V,)
        RMS per used view, px.
    std : dict
        One-sigma uncertainty of ``focal_length``, ``principal_point_x``,
        ``principal_point_y`` (px) and ``k1``.. (same units as ``radial``) from the
        Gauss-Newton covariance.
    valid_radius_px : float
        Raw radius up to which the fitted correction is monotonic
        (:func:`carapost.core.lens_models.monotonic_radius`).
    corner_radius_px : float
        Distance from the distortion centre to the farthest image corner; the model is
        usable over the whole image when ``valid_radius_px`` exceeds it.
    opencv_rms : float
        RMS of OpenCV's own fit (Brown model, used as the starting point), px.
    model : str
        The radial model fitted (``model``, or fewer terms when it folded inside the image).
    notes : tuple of str
        What was done besides the plain fit (rejected views, a model reduced).
    """

    intrinsics: Intrinsics
    R: np.ndarray
    t: np.ndarray
    views: np.ndarray
    rejected: np.ndarray
    residuals: np.ndarray
    rms: float
    per_view_rms: np.ndarray
    std: dict[str, float]
    valid_radius_px: float
    corner_radius_px: float
    opencv_rms: float
    model: str = "xcp3"
    notes: tuple[str, ...] = ()


class _IntrinsicsProblem:
    """Parameter packing for the XCP-model refinement."""

    def __init__(self, obj: np.ndarray, obs: np.ndarray, size: tuple[int, int], n_terms: int,
                 fix_aspect: bool, f0: float):
        self.obj, self.obs, self.size = obj, obs, size
        self.n_terms, self.fix_aspect, self.f0 = n_terms, fix_aspect, f0
        self.n_intr = 3 + (0 if fix_aspect else 1) + n_terms
        self.V = obs.shape[0]
        self.mask = np.isfinite(obs).all(axis=-1)

    def pack(self, intr: Intrinsics, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        head = [intr.focal_length, *intr.principal_point]
        if not self.fix_aspect:
            head.append(intr.aspect)
        head += [intr.radial[j] * self.f0 ** (2 * (j + 1)) for j in range(self.n_terms)]
        poses = np.concatenate([np.stack([_rotvec(r) for r in R]), t], axis=1)
        return np.concatenate([np.asarray(head, dtype=float), poses.ravel()])

    def intrinsics(self, x: np.ndarray) -> Intrinsics:
        i = 3
        aspect = 1.0
        if not self.fix_aspect:
            aspect = float(x[3])
            i = 4
        k = [0.0, 0.0, 0.0]
        for j in range(self.n_terms):
            k[j] = float(x[i + j]) / self.f0 ** (2 * (j + 1))
        return Intrinsics(focal_length=float(abs(x[0])) or 1e-9, principal_point=(float(x[1]), float(x[2])),
                          sensor_size=self.size, aspect=abs(aspect) or 1e-9, radial=(k[0], k[1], k[2]))

    def poses(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = x[self.n_intr:].reshape(self.V, 6)
        return rodrigues(p[:, :3]), p[:, 3:].copy()

    def errors(self, x: np.ndarray) -> np.ndarray:
        """Observed minus projected ``(V, N, 2)``."""
        R, t = self.poses(x)
        proj = project(self.obj[None], self.intrinsics(x), R[:, None], t[:, None])
        return self.obs - proj

    def residuals(self, x: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):  # a wild trial step may overflow; it is then penalised
            e = self.errors(x)[self.mask]
        return np.where(np.isfinite(e), e, _BIG).ravel()

    def sparsity(self) -> Any:
        view_of_row = np.repeat(np.nonzero(self.mask)[0], 2)
        S = lil_matrix((len(view_of_row), self.n_intr + 6 * self.V), dtype=int)
        S[:, :self.n_intr] = 1
        for k in range(6):
            S[np.arange(len(view_of_row)), self.n_intr + 6 * view_of_row + k] = 1
        return S.tocsr()


def _opencv_start(obj: np.ndarray, obs: np.ndarray, size: tuple[int, int],
                  fix_aspect: bool) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray], float]:
    """``cv2.calibrateCamera`` with ``k1, k2`` only: ``K, dist, rvecs, tvecs, rms``."""
    objs, imgs = [], []
    for v in range(obs.shape[0]):
        ok = np.isfinite(obs[v]).all(axis=1)
        objs.append(obj[ok].astype(np.float32))
        imgs.append(obs[v, ok].astype(np.float32).reshape(-1, 1, 2))
    w, h = size
    K0 = np.array([[1.0, 0, (w - 1) / 2], [0, 1.0, (h - 1) / 2], [0, 0, 1]])
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    if fix_aspect:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, (int(w), int(h)), K0, None, flags=flags)
    except cv2.error as e:
        raise ValueError(f"OpenCV could not start the calibration ({str(e).strip().splitlines()[-1]})") from None
    return K, dist.ravel(), list(rvecs), list(tvecs), float(rms)


def _fit_intrinsics(obj: np.ndarray, obs: np.ndarray, size: tuple[int, int], n_terms: int, fix_aspect: bool,
                    loss: str) -> tuple[_IntrinsicsProblem, Any, float]:
    K, dist, rvecs, tvecs, cv_rms = _opencv_start(obj, obs, size, fix_aspect)
    linear = Intrinsics(focal_length=float(K[0, 0]), principal_point=(float(K[0, 2]), float(K[1, 2])),
                        sensor_size=size, aspect=1.0 if fix_aspect else float(K[0, 0] / K[1, 1]))
    start = linear
    if n_terms > 0 and np.any(dist[:2] != 0):
        try:
            start, _ = fit_radial_correction(linear, lambda xy: brown_undistort(xy, dist[:5]), n_terms=n_terms)
        except ValueError:
            start = linear
    R0 = np.stack([cv2.Rodrigues(r)[0] for r in rvecs])
    t0 = np.stack([np.asarray(tv, dtype=float).ravel() for tv in tvecs])
    prob = _IntrinsicsProblem(obj, obs, size, n_terms, fix_aspect, float(K[0, 0]))
    x0 = prob.pack(start, R0, t0)
    sol = least_squares(prob.residuals, x0, jac_sparsity=prob.sparsity(), method="trf", x_scale="jac",
                        loss=loss, ftol=1e-8, xtol=1e-8, gtol=1e-8, max_nfev=200)
    return prob, sol, cv_rms


def _std(prob: _IntrinsicsProblem, sol: Any) -> dict[str, float]:
    """One-sigma uncertainty of the intrinsic parameters (Gauss-Newton covariance)."""
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    r = prob.residuals(sol.x)
    s2 = float(r @ r) / max(r.size - sol.x.size, 1)
    n_i = prob.n_intr
    sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J))[:n_i] * s2, 0, None))
    names = ["focal_length", "principal_point_x", "principal_point_y"] + ([] if prob.fix_aspect else ["aspect"])
    out = {n: float(v) for n, v in zip(names, sd)}
    for j in range(prob.n_terms):
        out[f"k{j + 1}"] = float(sd[len(names) + j]) / prob.f0 ** (2 * (j + 1))
    return out


def calibrate_intrinsics(views: Sequence[np.ndarray | None], spec: TargetSpec, image_size: tuple[int, int], *,
                         model: str = "xcp3", fix_aspect: bool = True, loss: str = "linear",
                         reject_factor: float | None = 4.0, reject_min_px: float = 1.0,
                         allow_fold: bool = False, uncertainty: bool = True) -> IntrinsicsResult:
    """Fit one camera's intrinsics in the XCP model from views of a flat target.

    Parameters
    ----------
    views : sequence of arrays (N, 2) or None
        Target points detected in each image (:func:`~carapost.core.calib_targets.detect_target`),
        raw px, ``N = spec.n_points``; ``None`` (target not found) and views with fewer than 4
        finite points are skipped. At least 3 views are needed; 6 or more, tilted in
        different directions and covering the image, give a good calibration.
    spec : TargetSpec
    image_size : (width, height)
        Pixels.
    model : {"xcp3", "xcp2", "xcp1", "none"}
        Radial terms fitted: ``k1, k2, k3`` (``VICON_RADIAL2``), ``k1, k2``
        (``VICON_RADIAL``), ``k1``, or none. The distortion centre is the principal point.
    fix_aspect : bool
        Keep the pixel aspect ratio at 1 (square pixels; every real XCP we have seen).
    loss : str
        Robust loss of ``scipy.optimize.least_squares`` (1 px scale).
    reject_factor, reject_min_px : float
        After a first fit, views whose RMS exceeds both ``reject_factor`` times the median
        view RMS and ``reject_min_px`` are dropped (a mis-detected target) and the fit is
        repeated. ``reject_factor=None`` keeps every view.
    allow_fold : bool
        Keep a fit whose correction folds back inside the image (see
        :func:`carapost.core.lens_models.monotonic_radius`). By default such a fit is
        repeated with one radial term fewer: a polynomial that folds inside the image maps two
        raw radii to one ray, and happens when the views leave the image corners uncovered.
    uncertainty : bool
        Compute :attr:`IntrinsicsResult.std`.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    ValueError
        Fewer than 3 usable views, a view of the wrong shape, an unknown model, a
        non-positive image size, or a calibration OpenCV cannot start.
    """
    if model not in RADIAL_MODELS:
        raise ValueError(f"model must be one of {', '.join(RADIAL_MODELS)}, got {model!r}")
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image size must be positive (width, height), got {image_size}")
    obj = target_points(spec)
    obs, used = _view_array(views, spec.n_points, "view")
    if len(used) < 3:
        raise ValueError(f"at least 3 views of the target are needed to calibrate a camera, got {len(used)}")
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    n_terms = RADIAL_MODELS[model]
    names = {v: k for k, v in RADIAL_MODELS.items()}
    notes: list[str] = []
    while True:
        prob, sol, cv_rms = _fit_intrinsics(obj, obs, (w, h), n_terms, fix_aspect, loss)
        rejected = np.zeros(0, dtype=np.int64)
        if reject_factor is not None:
            e = prob.errors(sol.x)
            vr = np.sqrt(np.nanmean(np.sum(e * e, axis=-1), axis=1))
            bad = (vr > reject_factor * np.median(vr)) & (vr > reject_min_px)
            if bad.any() and (~bad).sum() >= 3:
                rejected = used[bad]
                notes.append(f"views {rejected.tolist()} rejected (RMS {np.round(vr[bad], 2).tolist()} px "
                             f"against a median of {np.median(vr):.2f} px)")
                obs, used = obs[~bad], used[~bad]
                prob, sol, cv_rms = _fit_intrinsics(obj, obs, (w, h), n_terms, fix_aspect, loss)
        intr = prob.intrinsics(sol.x)
        c = intr.centre
        corner_r = float(np.max(np.hypot(corners[:, 0] - c[0], intr.aspect * (corners[:, 1] - c[1]))))
        valid_r = monotonic_radius(intr.radial)
        if valid_r >= corner_r or n_terms <= 1 or allow_fold:
            break
        notes.append(f"{names[n_terms]} folds at {valid_r:.0f} px, inside the image (corner at "
                     f"{corner_r:.0f} px): refitted with {names[n_terms - 1]}")
        n_terms -= 1
    x = sol.x
    R, t = prob.poses(x)
    err = prob.errors(x)
    sq = np.sum(err * err, axis=-1)
    per_view = np.sqrt(np.nanmean(sq, axis=1))
    rms = float(np.sqrt(np.nanmean(sq)))
    return IntrinsicsResult(intrinsics=intr, R=R, t=t, views=used, rejected=rejected, residuals=err, rms=rms,
                            per_view_rms=per_view, std=_std(prob, sol) if uncertainty else {},
                            valid_radius_px=valid_r, corner_radius_px=corner_r, opencv_rms=cv_rms,
                            model=names[n_terms], notes=tuple(notes))


def reprojection_check(views: Sequence[np.ndarray | None], spec: TargetSpec,
                       intr: Intrinsics) -> tuple[float, np.ndarray]:
    """How well given intrinsics explain views of a target (e.g. a calibration from elsewhere).

    Each view's target pose is fitted (PnP, then least squares on the raw-pixel error through
    :func:`carapost.core.camera.project`) with the intrinsics held fixed.

    Parameters
    ----------
    views : sequence of arrays (N, 2) or None
        As for :func:`calibrate_intrinsics`.
    spec : TargetSpec
    intr : Intrinsics

    Returns
    -------
    rms : float
        Over all points of all views, px.
    per_view_rms : array (V,)
        For the non-empty views, in order.
    """
    obj = target_points(spec)
    obs, _ = _view_array(views, spec.n_points, "view")
    per_view = np.empty(len(obs))
    sq_all = []
    for v, o in enumerate(obs):
        R, t = target_pose(obj, o, intr)
        ok = np.isfinite(o).all(axis=1)

        def res(x: np.ndarray, o: np.ndarray = o, ok: np.ndarray = ok) -> np.ndarray:
            e = (project(obj[ok], intr, rodrigues(x[:3]), x[3:]) - o[ok]).ravel()
            return np.where(np.isfinite(e), e, _BIG)

        sol = least_squares(res, np.concatenate([_rotvec(R), t]), method="lm", xtol=1e-10, ftol=1e-10)
        sq = np.sum(sol.fun.reshape(-1, 2) ** 2, axis=1)
        per_view[v] = np.sqrt(sq.mean())
        sq_all.append(sq)
    rms = float(np.sqrt(np.mean(np.concatenate(sq_all)))) if sq_all else float("nan")
    return rms, per_view


# --------------------------------------------------------------------------------------
# The whole rig from images
# --------------------------------------------------------------------------------------


@dataclass
class RigCalibration:
    """Result of :func:`calibrate_cameras`.

    Attributes
    ----------
    names : list of str
    intrinsics : list of Intrinsics
    R, t : arrays (C, 3, 3), (C, 3)
        World-to-camera poses, mm (identity where ``extrinsics`` is None: poses unknown).
    image_sizes : list of (width, height)
    intrinsic_results : list of IntrinsicsResult
    extrinsics : ExtrinsicsResult or None
        None when calibrated with ``extrinsics=False``.
    detections : list of list of (N, 2) arrays or None
        ``detections[c][s]``: the target points found in camera ``c``'s image ``s``.
    """

    names: list[str]
    intrinsics: list[Intrinsics]
    R: np.ndarray
    t: np.ndarray
    image_sizes: list[tuple[int, int]]
    intrinsic_results: list[IntrinsicsResult]
    extrinsics: ExtrinsicsResult | None
    detections: list[list[np.ndarray | None]] = field(default_factory=list)

    def camera_records(self) -> list[dict[str, Any]]:
        """Keyword arguments of ``carapost.io.calibration.CameraCalibration``, one per camera.

        ``Calibration([CameraCalibration(**r) for r in rig.camera_records()])`` can then be
        saved as ``.xcp`` with ``save_calibration``. ``IMAGE_ERROR`` is the intrinsic RMS (px);
        ``extra["calibrate"]`` keeps the fit report.
        """
        out = []
        for c, name in enumerate(self.names):
            ir = self.intrinsic_results[c]
            rep: dict[str, Any] = {
                "rms_px": ir.rms, "opencv_rms_px": ir.opencv_rms, "n_views": int(len(ir.views)),
                "rejected_views": [int(v) for v in ir.rejected], "std": dict(ir.std),
                "valid_radius_px": ir.valid_radius_px, "corner_radius_px": ir.corner_radius_px,
                "extrinsics": "none" if self.extrinsics is None else self.extrinsics.world,
            }
            if self.extrinsics is not None:
                rep["extrinsic_rms_px"] = float(self.extrinsics.rms_per_camera[c])
            out.append({"name": name, "device_id": "", "user_id": str(c + 1), "intrinsics": self.intrinsics[c],
                        "frames": np.array([0]), "R": self.R[c][None].copy(), "t": self.t[c][None].copy(),
                        "image_error": np.array([ir.rms]), "world_error": np.array([np.nan]),
                        "extra": {"calibrate": rep}})
        return out


def calibrate_cameras(image_sets: Sequence[Sequence[Any]], spec: TargetSpec, *,
                      load_image: Callable[[Any], np.ndarray] | None = None, names: Sequence[str] | None = None,
                      model: str = "xcp3", fix_aspect: bool = True, extrinsics: bool = True,
                      reference: int = 0, world: str = "camera",
                      progress: Callable[[int, int], None] | None = None) -> RigCalibration:
    """Calibrate a rig of cameras from images of a flat target.

    Parameters
    ----------
    image_sets : sequence of C sequences
        ``image_sets[c][s]``: camera ``c``'s image of shot ``s`` (an array, or anything
        ``load_image`` reads, e.g. a path; ``None`` if the camera has no image of that
        shot). Every image of a camera is used for its intrinsics; with ``extrinsics``, shots
        in which two or more cameras see the target place the cameras.
    spec : TargetSpec
    load_image : callable, optional
        Turns a non-array item into a grey image array (the caller's file reading:
        this module reads no files). It should raise ``ValueError`` naming the file.
    names : sequence of str, optional
        Camera names (default ``cam1``, ``cam2``, ...).
    model, fix_aspect :
        See :func:`calibrate_intrinsics`.
    extrinsics : bool
        ``True``: the images ``image_sets[c][s]`` of every camera show the same moment
        (synchronised shots); the cameras are placed in one world frame
        (:func:`calibrate_extrinsics`). ``False``: intrinsics only, e.g. from separate,
        unsynchronised films per camera (poses left at identity).
    reference, world :
        See :func:`calibrate_extrinsics`.
    progress : callable(done, total), optional
        Called after each image is searched.

    Returns
    -------
    RigCalibration

    Raises
    ------
    ValueError
        Images of different sizes within a camera, an unreadable item, a camera whose
        target was found in fewer than 3 images, or (``extrinsics=True``) a camera that
        cannot be placed, or shots that disagree (reprojection RMS above 2 px and 5 times the
        worst intrinsic RMS: the images of a shot were not taken at the same moment, or the
        target is numbered differently in two cameras).
    """
    C = len(image_sets)
    if C == 0:
        raise ValueError("no cameras given")
    if not isinstance(extrinsics, (bool, np.bool_)):
        raise ValueError(f"extrinsics must be True or False, got {extrinsics!r}")
    names = [f"cam{c + 1}" for c in range(C)] if names is None else [str(n) for n in names]
    if len(names) != C:
        raise ValueError(f"{len(names)} names for {C} cameras")
    total = sum(len(s) for s in image_sets)
    done = 0
    detections: list[list[np.ndarray | None]] = []
    sizes: list[tuple[int, int]] = []
    for c, items in enumerate(image_sets):
        found: list[np.ndarray | None] = []
        size: tuple[int, int] | None = None
        for s, item in enumerate(items):
            if item is None:
                found.append(None)
            else:
                if isinstance(item, np.ndarray):
                    img = item
                elif load_image is not None:
                    img = load_image(item)
                    if not isinstance(img, np.ndarray) or img.ndim not in (2, 3):
                        raise ValueError(f"camera {c} ({names[c]}) image {s} ({item}): could not be read as an image")
                else:
                    raise ValueError(f"camera {c} ({names[c]}) image {s}: got {type(item).__name__} {item!r}; "
                                     "pass load_image to read it")
                hw = (int(img.shape[1]), int(img.shape[0]))
                if size is None:
                    size = hw
                elif hw != size:
                    raise ValueError(f"camera {c} ({names[c]}) image {s} ({item if not isinstance(item, np.ndarray) else 'array'}): "
                                     f"size {hw[0]} x {hw[1]} differs from the camera's first image, {size[0]} x {size[1]}")
                found.append(detect_target(img, spec))
            done += 1
            if progress is not None:
                progress(done, total)
        n_found = sum(v is not None for v in found)
        if size is None or n_found < 3:
            raise ValueError(f"camera {c} ({names[c]}): the target was found in {n_found} of {len(items)} images; "
                             "at least 3 are needed")
        detections.append(found)
        sizes.append(size)
    results = [calibrate_intrinsics(detections[c], spec, sizes[c], model=model, fix_aspect=fix_aspect)
               for c in range(C)]
    intr = [r.intrinsics for r in results]
    R = np.broadcast_to(np.eye(3), (C, 3, 3)).copy()
    t = np.zeros((C, 3))
    ext = None
    if extrinsics:
        ext = calibrate_extrinsics(detections, intr, spec, reference=reference, world=world)
        limit = max(2.0, 5 * max(r.rms for r in results))
        if ext.rms > limit:
            raise ValueError(f"the cameras' views of the shared shots disagree (reprojection RMS {ext.rms:.2f} px, "
                             f"intrinsics {max(r.rms for r in results):.2f} px): are the images of each shot taken "
                             "at the same moment, and is the target numbered the same way in every camera "
                             f"(orientation unique: {spec.orientation_unique})? Use extrinsics=False for "
                             "intrinsics only")
        R, t = ext.R, ext.t
    return RigCalibration(names=names, intrinsics=intr, R=R, t=t, image_sizes=sizes, intrinsic_results=results,
                          extrinsics=ext, detections=detections)
