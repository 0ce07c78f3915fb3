"""Automatic 3D initialization: find points without hand-matched seeds.

With a calibration good enough for epipolar matching, detections are matched across all
cameras at once:

1. for every camera pair, the candidate pairs within Max Allowed Symmetric Epipolar Distance
   are triangulated (:func:`~carapost.core.epipolar_match.pair_candidates`);
2. each candidate is verified in the other cameras: a real point reprojects onto a detection
   there, and the joint triangulation stays within ``max_reprojection_px``
   (:func:`~carapost.core.epipolar_match.consistent_views`); views that break the joint
   triangulation are dropped, worst first;
3. the hypotheses seen in at least ``min_views`` cameras are ranked by their number of views,
   then by RMS reprojection error, and accepted greedily, each detection used once; a
   hypothesis that shares a detection with a *different* hypothesis having as many views is
   ambiguous and is not accepted (it may become unambiguous once its rival loses a detection
   to a better point);
4. the accepted points then serve as seeds for :func:`~carapost.core.init3d.initialize_3d`
   (growing two-view points within the caddies, merging, attaching, bundling), or are only
   consolidated when ``grow`` is off;
5. the camera poses stay bundled only when the points determine them
   (:func:`pose_redundancy`): with a handful of two- and three-view points and no brim, a
   bundle fits the poses to the points' own errors and its residuals (near zero) say nothing;
   the result is then recomputed with the input poses and ``report["auto"]["poses_bundled"]``
   is False.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.stats import chi2

from ..model.params import Initialize3DParameters
from .camera import Intrinsics
from .epipolar_match import (DetectionArrays, consistent_views, detection_arrays, pair_candidates,
                             triangulate_points)
from .init3d import (DEFAULT_CADDIES, Init3DResult, brim_observations, brim_region_mask, check_cameras, exclusions,
                     initialize_3d)
from .init3d_steps import CHI2_ADD_VIEW, NOISE_FLOOR_PX

__all__ = ["auto_initialize", "multi_view_hypotheses", "pose_redundancy", "select_hypotheses"]


def multi_view_hypotheses(dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics], R: np.ndarray,
                          t: np.ndarray, usable: Sequence[np.ndarray], *, max_epipolar: float, tol: float,
                          min_views: int, max_increase: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Point hypotheses seen consistently in at least ``min_views`` cameras.

    Parameters
    ----------
    dets : C DetectionArrays
    intrinsics, R, t
        Cameras (``R (C, 3, 3)``, ``t (C, 3)``).
    usable : C bool arrays (n_c,)
        Detections that may be matched.
    max_epipolar : float
        px, for the camera-pair candidates.
    tol : float
        Largest reprojection error of any view, px.
    min_views : int
    max_increase : float
        Chi-square bound on the squared error a verifying view may add, px^2 (see
        :func:`~carapost.core.epipolar_match.consistent_views`).

    Returns
    -------
    det : int array (H, C)
        Distinct hypotheses (detection per camera, -1 none).
    rms : array (H,)
        RMS reprojection error of each, px.
    """
    C = len(dets)
    rows = []
    for a in range(C):
        for b in range(a + 1, C):
            cand = pair_candidates(a, b, dets, intrinsics, R, t, max_epipolar=max_epipolar, usable=usable)
            if len(cand) == 0:
                continue
            det = np.full((len(cand), C), -1, np.int64)
            det[:, a] = cand.ia
            det[:, b] = cand.ib
            others = [c for c in range(C) if c not in (a, b)]
            if others:
                extra = consistent_views(det, cand.xyz, dets, intrinsics, R, t, usable, others, search=3 * tol, tol=tol,
                                         max_increase=max_increase)
                det = np.where(extra >= 0, extra, det)
            rows.append(det)
    if not rows:
        return np.zeros((0, C), np.int64), np.zeros(0)
    det = np.concatenate(rows)
    det = det[(det >= 0).sum(axis=1) >= min_views]
    # views that together break the triangulation: drop the worst until consistent
    for _ in range(C):
        if len(det) == 0:
            break
        _, res = triangulate_points(det, dets, intrinsics, R, t)
        r = np.where(np.isfinite(res), res, -1.0)
        worst = np.argmax(r, axis=1)
        bad = r[np.arange(len(r)), worst] > tol
        if not bad.any():
            break
        det[np.flatnonzero(bad), worst[bad]] = -1
        det = det[(det >= 0).sum(axis=1) >= min_views]
    det = np.unique(det, axis=0)
    if len(det) == 0:
        return det, np.zeros(0)
    X, res = triangulate_points(det, dets, intrinsics, R, t)
    ok = np.isfinite(X).all(1) & ~(np.nan_to_num(res, nan=0.0) > tol).any(axis=1)
    det, res = det[ok], res[ok]
    rms = np.sqrt(np.nanmean(np.where(np.isfinite(res), res, np.nan) ** 2, axis=1)) if len(det) else np.zeros(0)
    return det, rms


def select_hypotheses(det: np.ndarray, rms: np.ndarray, n_dets: Sequence[int]) -> np.ndarray:
    """Greedy, unambiguous choice among point hypotheses; each detection used once.

    Parameters
    ----------
    det : int array (H, C)
        Hypotheses (distinct rows).
    rms : array (H,)
        Their RMS reprojection errors, px.
    n_dets : C ints
        Detections per camera.

    Returns
    -------
    bool array (H,)
        The accepted hypotheses. In each round, a hypothesis is accepted when none of its
        detections is used, it ranks first (most views, then smallest RMS) for every one of
        its detections, and no other live hypothesis with as many views shares a detection.
    """
    H, C = det.shape
    accepted = np.zeros(H, bool)
    if H == 0:
        return accepted
    offset = np.concatenate([[0], np.cumsum(n_dets)])
    nv = (det >= 0).sum(axis=1)
    order = np.lexsort((rms, -nv))
    rank = np.empty(H, np.int64)
    rank[order] = np.arange(H)
    h, c = np.nonzero(det >= 0)
    key = offset[c] + det[h, c]            # global detection id of each (hypothesis, view)
    n_keys = int(offset[-1])
    used = np.zeros(n_keys, bool)
    while True:
        dead = np.zeros(H, bool)
        np.logical_or.at(dead, h, used[key])
        live = ~dead & ~accepted
        if not live.any():
            break
        lv = live[h]
        best = np.full(n_keys, H, np.int64)
        np.minimum.at(best, key[lv], rank[h[lv]])
        top_views = np.zeros(n_keys, np.int64)
        np.maximum.at(top_views, key[lv], nv[h[lv]])
        n_top = np.zeros(n_keys, np.int64)
        at_top = lv & (nv[h] == top_views[key])
        np.add.at(n_top, key[at_top], 1)
        lose = np.zeros(H, bool)
        np.logical_or.at(lose, h[lv], (rank[h[lv]] != best[key[lv]]) | (n_top[key[lv]] > 1))
        acc = live & ~lose
        if not acc.any():
            break
        accepted |= acc
        used[key[acc[h]]] = True
    return accepted


def auto_initialize(detections: Sequence[Any], intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                    params: Initialize3DParameters | None = None, *, min_views: int = 3,
                    max_reprojection_px: float = 2.0, caddies: Sequence[Sequence[int]] = DEFAULT_CADDIES,
                    exclude: Sequence[np.ndarray] | None = None, brim_xyz: np.ndarray | None = None,
                    grow: bool = True, bundle: bool = True, brim_margin_px: float = 15.0) -> Init3DResult:
    """Initialize 3D without seeds.

    Parameters
    ----------
    detections : C per-camera detections
        Tables with ``"x"``, ``"y"`` (optionally ``"polarity"``) or arrays (n_c, 2), raw px.
    intrinsics : C Intrinsics
    R, t : arrays (C, 3, 3), (C, 3)
        World-to-camera poses, mm.
    params : Initialize3DParameters, optional
        Max Allowed Symmetric Epipolar Distance bounds the camera-pair candidates; the others
        apply to growing (see :func:`~carapost.core.init3d.initialize_3d`).
    min_views : int
        Fewest cameras a point must be verified in (2..C). 3 (the default) makes a wrong point
        need two coincidences; 2 accepts epipolar pairs that nothing else confirms.
    max_reprojection_px : float
        Largest reprojection error of a view of a hypothesis, px.
    caddies : sequence of camera pairs
        For growing two-view points (ignored with ``grow=False``).
    exclude : C bool arrays (n_c,), optional
        Detections never to match.
    brim_xyz : array (B, 3), optional
        Brim dots: excluded with their image region and held fixed when bundling.
    grow : bool
        Use the points found as seeds of :func:`initialize_3d` (growing within the caddies,
        merging, attaching, bundling). Off: the points found are returned as they are (bundled
        if ``bundle``).
    bundle : bool
        Bundle-adjust poses and points. The poses stay bundled only when the points leave at
        least :data:`MIN_POSE_REDUNDANCY` degrees of freedom per pose parameter
        (:func:`pose_redundancy`); otherwise the result is recomputed with the input poses.

    Returns
    -------
    Init3DResult
        ``from_seed`` is False for every point; ``report["auto"]`` holds the hypothesis counts
        and ``poses_bundled`` (with ``bundle_dof`` and ``pose_parameters`` when bundling was
        asked for).

    Raises
    ------
    ValueError
        Bad shapes, ``min_views`` out of range, non-positive ``max_reprojection_px``.
    """
    params = Initialize3DParameters() if params is None else params
    params.validate()
    C = len(detections)
    dets = [detection_arrays(d, c) for c, d in enumerate(detections)]
    R, t = check_cameras(intrinsics, R, t, C)
    if not 2 <= min_views <= max(C, 2) or C < 2:
        raise ValueError(f"min_views must be within 2..{C} (and at least two cameras are needed), got {min_views}")
    if not max_reprojection_px > 0:
        raise ValueError(f"max_reprojection_px must be positive, got {max_reprojection_px}")
    n = [len(d) for d in dets]
    usable = [~e for e in exclusions(dets, exclude)]
    if brim_xyz is not None:
        brim = np.asarray(brim_xyz, float).reshape(-1, 3)
        bd = brim_observations(brim, dets, intrinsics, R, t, radius=max_reprojection_px)
        for c in range(C):
            usable[c][bd[bd[:, c] >= 0, c]] = False
            usable[c] &= ~brim_region_mask(brim, dets[c].xy, intrinsics[c], R[c], t[c], margin=brim_margin_px)

    # A: points verified in every camera (at most four): two coincidences would make a wrong one
    strict = min(C, max(min_views, 4))
    det, rms = multi_view_hypotheses(dets, intrinsics, R, t, usable,
                                     max_epipolar=params.max_allowed_symmetric_epipolar_distance,
                                     tol=max_reprojection_px, min_views=strict)
    found = det[select_hypotheses(det, rms, n)]
    auto: dict[str, Any] = {"strict_views": strict, "strict_hypotheses": int(len(det)), "strict_points": int(len(found))}
    kw = dict(caddies=caddies if grow else (), exclude=exclude, brim_xyz=brim_xyz, bundle=bundle, relaxed=grow,
              attach_px=max_reprojection_px, brim_margin_px=brim_margin_px, trust_seeds=False)
    res = initialize_3d(detections, intrinsics, R, t, _as_seeds(found), params, **kw)  # type: ignore[arg-type]
    # with the refined poses, drop the points whose errors are improbable for the measured noise
    # (a symmetric face and rig can pair mirror-image markers into a consistent phantom point)
    ok = _plausible_errors(found, dets, intrinsics, res.R, res.t)
    auto["strict_rejected"] = int((~ok).sum())
    if not ok.all():
        found = found[ok]
        res = initialize_3d(detections, intrinsics, R, t, _as_seeds(found), params, **kw)  # type: ignore[arg-type]
    # B: points in fewer cameras, verified with the tolerances measured on A (and its refined poses)
    if min_views < strict:
        if res.n_points >= MIN_MEASURED:  # tolerances measured on the points of A
            tol = res.report["tolerances"]
            epi, view = float(tol["epipolar_px"]), float(tol["view_px"])
            max_inc = CHI2_ADD_VIEW * float(tol["noise_px"]) ** 2
        else:  # nothing to measure on: the user's limits
            epi, view, max_inc = params.max_allowed_symmetric_epipolar_distance, max_reprojection_px, np.inf
        used = [np.zeros(k, bool) for k in n]
        for c in range(C):
            d = res.det_index[:, c]
            used[c][d[d >= 0]] = True
        free = [usable[c] & ~used[c] for c in range(C)]
        det_b, rms_b = multi_view_hypotheses(dets, intrinsics, res.R, res.t, free, max_epipolar=epi, tol=view,
                                             min_views=min_views, max_increase=max_inc)
        more = det_b[select_hypotheses(det_b, rms_b, n)]
        auto.update(hypotheses=int(len(det_b)), points=int(len(more)))
        if len(more):
            seeds = np.concatenate([res.det_index, more])
            res = initialize_3d(detections, intrinsics, res.R, res.t, _as_seeds(seeds), params,
                                **kw)  # type: ignore[arg-type]
    # the poses: bundled only when the points determine them (else the residuals are fitted away)
    auto["poses_bundled"] = False
    if bundle and res.n_points:
        dof, n_pose = pose_redundancy(res.det_index, res.brim_det_index)
        auto["bundle_dof"], auto["pose_parameters"] = dof, n_pose
        if dof >= MIN_POSE_REDUNDANCY * n_pose:
            auto["poses_bundled"] = True
        else:
            kw_fixed = {**kw, "bundle": False}
            res = initialize_3d(detections, intrinsics, R, t, _as_seeds(res.det_index), params,
                                **kw_fixed)  # type: ignore[arg-type]
    res.report["auto"] = auto
    return Init3DResult(xyz=res.xyz, det_index=res.det_index, xy=res.xy, from_seed=np.zeros(res.n_points, bool),
                        caddy=res.caddy, pair=res.pair, residuals=res.residuals, R=res.R, t=res.t,
                        brim_det_index=res.brim_det_index, report=res.report)


#: Fewest points of stage A to measure the tolerances of stage B on.
MIN_MEASURED = 5
#: The poses are bundled only when the residuals leave at least this many degrees of freedom
#: per pose parameter (:func:`pose_redundancy`). The synthetic takes (35-156 markers in four
#: views, 18 brim dots) have 8-18; the Pose2Sim demo's frame 0 (about ten two- and three-view
#: points, no brim) has less than 1, and a bundle there drives its residuals to ~0 px.
MIN_POSE_REDUNDANCY = 2.0


def pose_redundancy(det_index: np.ndarray, brim_det_index: np.ndarray | None = None) -> tuple[int, int]:
    """Degrees of freedom a bundle of poses and points leaves, and its number of pose parameters.

    Parameters
    ----------
    det_index : int array (P, C)
        The points' views (-1 none); each view is two residuals, each point three unknowns.
    brim_det_index : int array (B, C), optional
        Views of the brim dots: fixed points, two residuals per view and no unknowns; with
        them the world frame is pinned, without them seven parameters (a similarity) are free.

    Returns
    -------
    dof : int
        Residuals minus unknowns (the gauge removed).
    n_pose : int
        Six per camera with at least one view.
    """
    det_index = np.asarray(det_index)
    seen = (det_index >= 0).any(axis=0)
    n_res = 2 * int((det_index >= 0).sum())
    pinned = brim_det_index is not None and bool((np.asarray(brim_det_index) >= 0).any())
    if pinned:
        brim = np.asarray(brim_det_index) >= 0
        n_res += 2 * int(brim.sum())
        seen |= brim.any(axis=0)
    n_pose = 6 * int(seen.sum())
    gauge = 0 if pinned else 7
    return n_res - 3 * len(det_index) - n_pose + gauge, n_pose
#: Significance of the chi-square test on a point's reprojection errors.
ERROR_TEST_P = 0.999


def _plausible_errors(det: np.ndarray, dets: Sequence[DetectionArrays], intrinsics: Sequence[Intrinsics],
                      R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points whose sum of squared reprojection errors passes a chi-square test, bool (P,).

    The noise is estimated robustly from all the points (median of each point's error sum
    over the median of its chi-square distribution), so a few wrong points do not inflate it.
    """
    if len(det) == 0:
        return np.zeros(0, bool)
    X, res = triangulate_points(det, dets, intrinsics, R, t)
    nv = (det >= 0).sum(axis=1)
    dof = 2 * nv - 3
    ssr = np.nansum(res ** 2, axis=1)
    good = np.isfinite(X).all(1) & (dof > 0)
    if good.sum() < 3:
        return good
    sigma2 = float(np.median(ssr[good] / chi2.median(dof[good])))
    sigma2 = max(sigma2, NOISE_FLOOR_PX ** 2 / 4)
    return good & (ssr <= chi2.ppf(ERROR_TEST_P, np.maximum(dof, 1)) * sigma2)


def _as_seeds(det: np.ndarray) -> list[dict[int, int]]:
    """Rows of views as :func:`initialize_3d` seeds."""
    return [{int(c): int(det[p, c]) for c in np.flatnonzero(det[p] >= 0)} for p in range(len(det))]
