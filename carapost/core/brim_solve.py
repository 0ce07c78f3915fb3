"""Solve Calibration Brim [Manual]: camera poses from a few hand-matched brim dots.

The reference guide's three steps ("Solve calibration brim algorithm"):

1. **Initial poses.** Each camera with at least four of the user's brim correspondences is
   posed by PnP with its known intrinsics (:mod:`.pose`: raw pixels corrected with the XCP
   model; IPPE for a planar brim, IPPE on the best-fit plane then refinement for a curved
   one, plus SQPNP). With more than four, every 4-subset proposes poses and the pose most
   correspondences agree with wins, so one wrong click is left out; four that do not agree
   are reported ("camera 2: the 4 brim correspondences are
   inconsistent (reprojection 23.4 px)"). A camera with fewer (or inconsistent) ones is posed
   from a solved camera, preferably its caddy partner, through the relative pose of the
   initial extrinsics (``initial_R``, ``initial_t``, e.g. from the XCP file).
2. **Find the other brim dots** (:mod:`.brim_match`). All dots are projected and each
   attached to the nearest unambiguous detection within ``match_radius_px``: the dot and the
   detection must be each other's nearest, and the second-nearest detection must be clearly
   farther (ratio test). The pose is re-estimated robustly (least trimmed squares) from every
   attachment, attachments far above the noise are dropped, and the loop repeats until
   nothing changes. Every PnP solution of the clicks is tried (a planar brim seen face-on
   has two); the one that finds most dots wins. With exactly four clicks, which fit a wrong
   pose loosely more often than one would like, a pose that finds few dots is checked by
   leaving each click out in turn (P3P on the other three): if three clicks find clearly
   more of the brim without the fourth, the fourth is a wrong click and the camera is refused.
3. **Refine** every pose with :func:`carapost.core.bundle.bundle_adjust` on all attached
   dots (brim points fixed: they define the world frame) and report the RMS per camera.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from carapost.model.take import BrimModel

from .brim_match import Attachment, attach_dots, match_projections
from .bundle import bundle_adjust
from .camera import Intrinsics, camera_centre, normalized_rays, project
from .pose import compose_relative, is_degenerate, is_planar, p3p_candidates, reprojection_px, robust_pnp

__all__ = ["BrimSolveResult", "BrimSolveError", "solve_brim", "match_projections"]

class BrimSolveError(ValueError):
    """No camera could be posed from the brim; the message says why, camera by camera."""


@dataclass
class BrimSolveResult:
    """Result of :func:`solve_brim` for ``B`` brim dots and ``C`` cameras.

    Attributes
    ----------
    R : array (C, 3, 3)
    t : array (C, 3)
        World (= brim frame) to camera poses, mm; NaN for a camera that could not be solved.
    det_index : int array (B, C)
        Detection index (within the frame) attached to each brim dot per camera; -1 if none.
    xy : array (B, C, 2)
        The attached detection centres, raw px (NaN if none).
    rms_px : array (C,)
        RMS reprojection error of the attached dots per camera, px (NaN if unsolved).
    n_dots : int array (C,)
        Number of attached dots per camera.
    messages : list of str
        What happened, camera by camera (rejected clicks, cameras posed from a partner, ...).
    rejected : list of (int, int, int)
        User correspondences ``(brim dot, camera, detection)`` that were left out.
    """

    R: np.ndarray
    t: np.ndarray
    det_index: np.ndarray
    xy: np.ndarray
    rms_px: np.ndarray
    n_dots: np.ndarray
    messages: list[str] = field(default_factory=list)
    rejected: list[tuple[int, int, int]] = field(default_factory=list)

    @property
    def solved(self) -> np.ndarray:
        """bool (C,): cameras with a pose."""
        return np.isfinite(self.R).all(axis=(1, 2)) & np.isfinite(self.t).all(axis=1)


@dataclass
class _Cam:
    """Working state of one camera."""

    R: np.ndarray
    t: np.ndarray
    att: np.ndarray          # (B,) detection per dot, -1 none
    source: str              # "own" or "camera k"


def solve_brim(brim: BrimModel, intrinsics: Sequence[Intrinsics], detections_xy: Sequence[np.ndarray],
               correspondences: Mapping[int, Mapping[int, int]], *, match_radius_px: float = 6.0,
               refine: bool = True, initial_R: np.ndarray | None = None, initial_t: np.ndarray | None = None,
               caddies: Sequence[Sequence[int]] = ((0, 1), (2, 3)), ratio: float = 0.6,
               max_initial_error_px: float = 5.0, min_outlier_px: float = 1.0,
               max_iterations: int = 12) -> BrimSolveResult:
    """Solve the camera poses of one frame from the brim (Process > Solve Calibration Brim [Manual]).

    Parameters
    ----------
    brim : BrimModel
        Dot centres ``xyz (B, 3)`` mm in the brim frame (planar or curved).
    intrinsics : sequence of C Intrinsics
        Known camera intrinsics (XCP).
    detections_xy : sequence of C arrays (n_c, 2)
        Detection centres of the frame per camera, raw px (NaN rows are ignored).
    correspondences : mapping ``{brim_dot: {camera: detection_index}}``
        The user's matches: four or more per camera to pose it from its own view
        (a detection index of -1 or None means no match in that camera).
    match_radius_px : float
        Largest distance between a projected dot and the detection attached to it.
    refine : bool
        Bundle-adjust all poses on every attached dot at the end (step 3).
    initial_R, initial_t : arrays (C, 3, 3), (C, 3), optional
        Initial extrinsics in any world frame (e.g. the XCP's); only the poses *relative*
        to each other are used, to pose a camera with fewer than four correspondences from
        a solved one. NaN for unknown cameras.
    caddies : sequence of camera groups
        Cameras on the same arm; a camera is posed from its caddy partner first.
    ratio : float
        Ratio test: the nearest detection must be closer than ``ratio`` times the second.
    max_initial_error_px : float
        Largest reprojection error of a user correspondence for it to agree with a pose.
    min_outlier_px : float
        Attached dots whose error exceeds ``max(min_outlier_px, 4.5 sigma)`` (at most
        ``match_radius_px / 2``) are dropped; ``sigma`` is the robust noise level of the
        camera's attachments. A user correspondence is only overruled beyond three times that.
    max_iterations : int
        Match / re-estimate rounds per camera.

    Returns
    -------
    BrimSolveResult

    Raises
    ------
    ValueError
        On malformed input (shapes, indices out of range, a detection matched to two dots).
    BrimSolveError
        If no camera at all could be posed (the message gives the reason per camera).
    """
    xyz = np.asarray(brim.xyz, dtype=float)
    B = len(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or B == 0 or not np.all(np.isfinite(xyz)):
        raise ValueError(f"brim {brim.name!r}: xyz must be finite (B, 3), got shape {xyz.shape}")
    C = len(intrinsics)
    if C == 0 or len(detections_xy) != C:
        raise ValueError(f"need one detection array per camera: {C} intrinsics, {len(detections_xy)} arrays")
    dets = []
    for c, d in enumerate(detections_xy):
        d = np.asarray(d, dtype=float)
        if d.size == 0:
            d = d.reshape(0, 2)
        if d.ndim != 2 or d.shape[1] != 2:
            raise ValueError(f"camera {c}: detections must have shape (n, 2), got {d.shape}")
        dets.append(d)
    if not match_radius_px > 0 or not 0 < ratio <= 1:
        raise ValueError(f"match_radius_px must be > 0 and ratio within (0, 1], got {match_radius_px}, {ratio}")
    user = _check_correspondences(correspondences, B, dets)
    R0, t0 = _check_initial(initial_R, initial_t, C)

    messages: list[str] = []
    rejected: list[tuple[int, int, int]] = []
    cams: list[_Cam | None] = [None] * C
    failures: dict[int, str] = {}
    opts = dict(radius=match_radius_px, ratio=ratio, min_outlier_px=min_outlier_px, max_iterations=max_iterations)

    # Steps 1 and 2 for cameras with their own >= 4 correspondences.
    for c in range(C):
        corr = user[c]
        if len(corr) < 4:
            continue
        cams[c] = _pose_own(c, corr, xyz, dets[c], intrinsics[c], max_initial_error_px, opts,
                            messages, rejected, failures)

    # Cameras with fewer (or inconsistent) correspondences: from a solved camera.
    for c in range(C):
        if cams[c] is not None:
            continue
        p = _partner(c, cams, R0, t0, caddies)
        if p is None:
            n = len(user[c])
            if c not in failures:
                failures[c] = (f"camera {c}: not solved: it needs at least 4 brim correspondences (has {n})"
                               + (" or a known pose relative to a solved camera (initial_R, initial_t)"
                                  if R0 is None else ", and no solved camera has a known relative pose to it"))
            continue
        cams[c] = _pose_from(c, p, cams[p], user[c], xyz, dets[c], intrinsics[c], R0, t0, opts,
                             messages, rejected)

    messages[:0] = [failures[c] for c in sorted(failures)]
    if all(cam is None for cam in cams):
        raise BrimSolveError("cannot solve the calibration brim: " + "; ".join(failures[c] for c in sorted(failures)))

    # Step 3: joint refinement, brim fixed.
    R = np.full((C, 3, 3), np.nan)
    t = np.full((C, 3), np.nan)
    det_index = np.full((B, C), -1, np.int64)
    for c, cam in enumerate(cams):
        if cam is not None:
            R[c], t[c], det_index[:, c] = cam.R, cam.t, cam.att
    xy = np.full((B, C, 2), np.nan)
    for c in range(C):
        m = det_index[:, c] >= 0
        xy[m, c] = dets[c][det_index[m, c]]
    solved = np.isfinite(R).all(axis=(1, 2))
    if refine and np.any(solved & (det_index >= 0).any(axis=0)):
        Rb = np.where(solved[:, None, None], R, np.eye(3))
        tb = np.where(solved[:, None], t, 0.0)
        ba = bundle_adjust(xy[None], intrinsics, Rb[None], tb[None], xyz[None], fixed_points=np.ones(B, bool),
                           fix_cameras=~solved)
        R = np.where(solved[:, None, None], ba.R[0], np.nan)
        t = np.where(solved[:, None], ba.t[0], np.nan)
    rms = np.full(C, np.nan)
    for c in np.flatnonzero(solved):
        m = det_index[:, c] >= 0
        if np.any(m):
            e = reprojection_px(xyz[m], xy[m, c], intrinsics[c], R[c], t[c])
            rms[c] = float(np.sqrt(np.mean(e * e)))
    n_dots = (det_index >= 0).sum(axis=0)
    for c in np.flatnonzero(solved):
        cam = cams[c]
        assert cam is not None
        how = "" if cam.source == "own" else f" (posed from {cam.source})"
        messages.append(f"camera {c}: {n_dots[c]} brim dots attached, RMS {rms[c]:.3f} px{how}")
        if is_planar(xyz) and np.allclose(xyz[:, 2], xyz[0, 2]):
            z = camera_centre(R[c], t[c])[2] - xyz[0, 2]
            if z < 0:
                messages.append(f"camera {c}: the camera is behind the brim card (Z = {z:.1f} mm): is the brim "
                                "model mirrored?")
    return BrimSolveResult(R, t, det_index, xy, rms, n_dots, messages, rejected)


# ------------------------------------------------------------------------------ checks
def _check_correspondences(correspondences: Mapping[int, Mapping[int, int]], B: int,
                           dets: list[np.ndarray]) -> list[dict[int, int]]:
    """Per camera ``{dot: detection}``, validated."""
    C = len(dets)
    user: list[dict[int, int]] = [{} for _ in range(C)]
    for b, per_cam in correspondences.items():
        b = int(b)
        if not 0 <= b < B:
            raise ValueError(f"brim dot {b} does not exist (the brim has {B} dots)")
        for c, d in per_cam.items():
            if d is None or int(d) == -1:
                continue
            c, d = int(c), int(d)
            if not 0 <= c < C:
                raise ValueError(f"brim dot {b}: camera {c} does not exist ({C} cameras)")
            if not 0 <= d < len(dets[c]):
                raise ValueError(f"brim dot {b}: camera {c} has no detection {d} ({len(dets[c])} detections)")
            if not np.all(np.isfinite(dets[c][d])):
                raise ValueError(f"brim dot {b}: detection {d} of camera {c} has no position")
            for b2, d2 in user[c].items():
                if d2 == d:
                    raise ValueError(f"camera {c}: detection {d} is matched to brim dots {b2} and {b}")
            user[c][b] = d
    return user


def _check_initial(R0: np.ndarray | None, t0: np.ndarray | None, C: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    if R0 is None and t0 is None:
        return None, None
    if R0 is None or t0 is None:
        raise ValueError("give both initial_R and initial_t, or neither")
    R0 = np.asarray(R0, dtype=float)
    t0 = np.asarray(t0, dtype=float)
    if R0.shape != (C, 3, 3) or t0.shape != (C, 3):
        raise ValueError(f"initial_R/initial_t must have shapes ({C}, 3, 3), ({C}, 3); got {R0.shape}, {t0.shape}")
    return R0, t0


# ------------------------------------------------------------------------------ step 1
def _pose_own(c: int, corr: dict[int, int], xyz: np.ndarray, det: np.ndarray, intr: Intrinsics,
              max_err: float, opts: dict, messages: list[str], rejected: list[tuple[int, int, int]],
              failures: dict[int, str]) -> _Cam | None:
    """Pose a camera from its own correspondences (step 1), then attach dots (step 2)."""
    bs = np.array(sorted(corr))
    ds = np.array([corr[b] for b in bs])
    k = len(bs)
    if is_degenerate(xyz[bs]):
        failures[c] = (f"camera {c}: the {k} brim correspondences (dots {', '.join(map(str, bs))}) are nearly "
                       "collinear; match dots from at least two rows of the brim")
        return None
    fits = robust_pnp(xyz[bs], det[ds], intr, threshold_px=max_err)
    if not fits:
        failures[c] = (f"camera {c}: the {k} brim correspondences are inconsistent: no camera pose puts all the "
                       "matched dots in front of the camera")
        return None
    best = fits[0]
    n_in = int(best.inliers.sum())
    if n_in < 4 or (k > 4 and 2 * n_in <= k):
        worst = min(float(np.sort(f.errors)[min(3, k - 1)] if k > 4 else f.errors.max()) for f in fits)
        what = "" if k == 4 else ": no 4 of them agree on one pose"
        failures[c] = f"camera {c}: the {k} brim correspondences are inconsistent{what} (reprojection {worst:.1f} px)"
        return None
    ties = [f for f in fits if int(f.inliers.sum()) == n_in]
    rivals = [f for f in ties if not np.array_equal(f.inliers, best.inliers)]
    if any(f.rms < 3 * best.rms + 0.5 for f in rivals):
        failures[c] = (f"camera {c}: the {k} brim correspondences are ambiguous: different subsets of {n_in} agree "
                       "on different poses; check the matches")
        return None
    forced = {int(b): int(d) for b, d, ok in zip(bs, ds, best.inliers) if ok}
    for b, d, ok, e in zip(bs, ds, best.inliers, best.errors):
        if not ok:
            rejected.append((int(b), c, int(d)))
            messages.append(f"camera {c}: brim dot {b} -> detection {d} rejected: it disagrees with the other "
                            f"matches (reprojection {e:.1f} px)")
    # Step 2 for every candidate pose (the planar flip ambiguity); keep the one finding most dots.
    results = [attach_dots(xyz, det, intr, f.R, f.t, forced, **opts) for f in ties
               if np.array_equal(f.inliers, best.inliers)]
    results.sort(key=lambda r: (-r.n, r.rms))
    R, t, att, _, dropped = results[0]
    if k == 4 and dropped:
        b, d, e = dropped[0]
        failures[c] = (f"camera {c}: the 4 brim correspondences are inconsistent (reprojection {e:.1f} px): "
                       f"brim dot {b} -> detection {d} disagrees with the brim dots the other three find")
        return None
    if len(forced) == 4:
        # Four clicks fit several poses loosely: check that no three of them find a better brim.
        why, better = _leave_one_out(c, forced, att, xyz, det, intr, R, t, opts)
        if why is not None:
            failures[c] = why
            return None
        if better is not None:
            R, t, att, _, dropped = better
    _report_dropped(c, dropped, messages, rejected)
    return _Cam(R, t, att, "own")


def _n_expected(xyz: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray, det: np.ndarray,
                margin: float) -> int:
    """Brim dots projecting inside the image (the sensor, or the detections' bounding box)."""
    p = project(xyz, intr, R, t)
    w, h = intr.sensor_size
    if w > 0 and h > 0:
        lo, hi = np.array([-0.5, -0.5]), np.array([w - 0.5, h - 0.5])
    else:
        good = det[np.isfinite(det).all(axis=1)]
        if len(good) == 0:
            return 0
        lo, hi = good.min(axis=0) - margin, good.max(axis=0) + margin
    with np.errstate(invalid="ignore"):
        inside = np.all((p >= lo) & (p <= hi), axis=1)
    return int(inside.sum())


def _leave_one_out(c: int, forced: dict[int, int], att: np.ndarray, xyz: np.ndarray, det: np.ndarray,
                   intr: Intrinsics, R: np.ndarray, t: np.ndarray,
                   opts: dict) -> tuple[str | None, Attachment | None]:
    """Pose the camera from every three of the four user correspondences (P3P) and attach dots.

    Returns ``(message, None)`` if three of them find clearly more brim dots without the
    fourth (a wrong click), ``(None, result)`` if such a pose keeps all four (the four-point
    pose had fallen into a wrong minimum), else ``(None, None)``.
    Skipped when enough other dots already agree with the four clicks.
    """
    n_att = int((att >= 0).sum())
    n_exp = _n_expected(xyz, intr, R, t, det, opts["radius"])
    if n_att - 4 >= max(4, 0.6 * (n_exp - 4)):
        return None, None
    m = att >= 0
    rms_all = float(np.sqrt(np.mean(reprojection_px(xyz[m], det[att[m]], intr, R, t) ** 2)))
    max_rms = max(1.5 * rms_all, opts["min_outlier_px"])  # a rival must fit about as well
    uv = normalized_rays(det, intr)[:, :2]
    wrong: tuple[int, int, int, float] | None = None
    better: Attachment | None = None
    items = sorted(forced.items())
    for i, (b_out, d_out) in enumerate(items):
        three = dict(items[:i] + items[i + 1:])
        bs = np.array(list(three))
        ds = np.array([three[b] for b in bs])
        for R3, t3 in p3p_candidates(xyz[bs], uv[ds]):
            res = attach_dots(xyz, det, intr, R3, t3, three, **opts)
            n3 = res.n
            if n3 < n_att + 3 or res.rms > max_rms:
                continue
            if res.att[b_out] == d_out:
                if better is None or n3 > better.n:
                    better = res
                continue
            e = float(reprojection_px(xyz[[b_out]], det[[d_out]], intr, res.R, res.t)[0])
            if wrong is None or n3 > wrong[2]:
                wrong = (b_out, d_out, n3, e)
    if wrong is not None and (better is None or wrong[2] > better.n):
        b, d, n3, e = wrong
        return (f"camera {c}: the 4 brim correspondences are inconsistent (reprojection {e:.1f} px): brim dot {b} "
                f"-> detection {d} disagrees with the other three, which find {n3 - 3} more brim dots without it"), None
    return None, better


# ------------------------------------------------------------------------------ partners
def _partner(c: int, cams: list[_Cam | None], R0: np.ndarray | None, t0: np.ndarray | None,
             caddies: Sequence[Sequence[int]]) -> int | None:
    """A solved camera with a known initial pose relative to camera ``c`` (caddy partner first)."""
    if R0 is None or t0 is None:
        return None

    def known(k: int) -> bool:
        return bool(np.all(np.isfinite(R0[k])) and np.all(np.isfinite(t0[k])))

    if not known(c):
        return None
    ok = [k for k, cam in enumerate(cams) if cam is not None and cam.source == "own" and known(k) and k != c]
    if not ok:
        return None
    same = [k for grp in caddies if c in grp for k in grp if k in ok]
    if same:
        return same[0]
    cc = camera_centre(R0[c], t0[c])
    return min(ok, key=lambda k: float(np.linalg.norm(camera_centre(R0[k], t0[k]) - cc)))


def _pose_from(c: int, p: int, cam_p: _Cam | None, corr: dict[int, int], xyz: np.ndarray, det: np.ndarray,
               intr: Intrinsics, R0: np.ndarray | None, t0: np.ndarray | None, opts: dict, messages: list[str],
               rejected: list[tuple[int, int, int]]) -> _Cam:
    """Pose camera ``c`` from solved camera ``p`` through their initial relative pose, then attach dots."""
    assert cam_p is not None and R0 is not None and t0 is not None
    R_rel = R0[c] @ R0[p].T
    t_rel = t0[c] - R_rel @ t0[p]
    R, t = compose_relative(cam_p.R, cam_p.t, R_rel, t_rel)
    forced: dict[int, int] = {}
    if corr:
        bs = np.array(sorted(corr))
        ds = np.array([corr[b] for b in bs])
        err = reprojection_px(xyz[bs], det[ds], intr, R, t)
        for b, d, e in zip(bs, ds, err):
            if e <= opts["radius"]:
                forced[int(b)] = int(d)
            else:
                rejected.append((int(b), c, int(d)))
                messages.append(f"camera {c}: brim dot {b} -> detection {d} rejected: it is {e:.1f} px from the "
                                f"dot's projection with the pose from camera {p}")
    R, t, att, _, dropped = attach_dots(xyz, det, intr, R, t, forced, **opts)
    _report_dropped(c, dropped, messages, rejected)
    n = int((att >= 0).sum())
    messages.append(f"camera {c}: posed from camera {p} through the initial relative pose"
                    + ("" if n >= 4 else f"; only {n} brim dots found, so the relative pose was kept"))
    return _Cam(R, t, att, f"camera {p}")


def _report_dropped(c: int, dropped: list[tuple[int, int, float]], messages: list[str],
                    rejected: list[tuple[int, int, int]]) -> None:
    for b, d, e in dropped:
        rejected.append((b, c, d))
        messages.append(f"camera {c}: brim dot {b} -> detection {d} rejected: {e:.1f} px from the solved dot")
