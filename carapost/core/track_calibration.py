"""Refine static cameras' extrinsics from markers moving through the room (wand-style).

Wand calibration (seed 001) finds the cameras' poses from an object that moves through the
volume seen by all cameras. Here the moving object is whatever markers the footage holds: a
person's body markers, say. Correspondences are not known and the starting poses (a
calibration file) may be off by tens of pixels, too far for per-frame epipolar matching, so
whole 2D *tracks* are matched instead of single detections:

1. :func:`link_tracks`: in each camera, detections are linked from frame to frame into 2D
   tracks (constant-velocity prediction, one-to-one assignment within a small gate, a link
   refused when a second detection is almost as close);
2. :func:`track_pair_table`: for every pair of moving tracks of two cameras with enough common
   frames, the signed symmetric epipolar distance under the current poses, frame by frame. A
   true pair (the same marker) has a distance that is biased by the pose error but smooth and
   bounded over time; a coincidental pair is close in a few frames and far in the others;
3. :func:`match_tracks`: track pairs whose distance stays within a tolerance and varies
   smoothly are accepted one-to-one (mutual best), joined across cameras into marker
   trajectories, and a trajectory whose tracks of one camera overlap in time is refused;
4. :func:`refine_extrinsics`: one robust bundle over all the frames of the accepted
   trajectories (one pose per camera, a point per trajectory and frame, the first camera
   fixed, the scale kept from the starting poses' baselines), then matching again with the
   refined poses and a tighter tolerance, a few rounds.

The result is only as good as the correspondences *and* the geometry they span: check it on
something the fit did not use (static landmarks, a null control with one camera's tracks
shifted in time). On the Pose2Sim demo the matched track pairs are real (a camera shifted by
20-30 frames keeps none) but too few, on markers within about a metre, to determine the back
cameras' poses: the bundle fits them to 0.2-0.8 px while static landmarks get no better; see
``benchmarks/bench_pose2sim.py --tracks`` and ``docs/initialize-3d.md``. On a synthetic rig
with markers moving through the room (``tests/core/test_track_calibration.py``) poses off by
0.8 degree and 50 mm are recovered to < 0.15 degree and < 25 mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from .camera import Intrinsics, camera_centre, fundamental_matrix, project, rodrigues, undistort
from .scene_refine import pose_change
from .triangulate import triangulate

__all__ = ["link_tracks", "moving_tracks", "signed_epipolar_distance", "track_pair_table", "TrackPairs",
           "match_tracks", "trajectory_observations", "TrackCalibration", "refine_extrinsics", "bundle_poses"]


# --------------------------------------------------------------------------------------
# 1. 2D tracks
# --------------------------------------------------------------------------------------


def link_tracks(frames: Sequence[np.ndarray], *, gate_px: float = 6.0, ratio: float = 1.5) -> np.ndarray:
    """Link one camera's detections from frame to frame into 2D tracks.

    Each track's next position is predicted from its last two (constant velocity); predictions
    and the next frame's detections are assigned one-to-one (Hungarian) within ``gate_px``. A
    link is refused (the track ends, the detection starts a new one) when another detection or
    another track's prediction lies within ``ratio`` times the link's distance: nearby
    markers are not guessed. Tracks do not bridge gaps.

    Parameters
    ----------
    frames : sequence of F arrays (n_f, 2)
        Raw-pixel detections per frame.
    gate_px : float
        Largest distance between a prediction and the detection it takes, px.
    ratio : float
        Ambiguity ratio (> 1).

    Returns
    -------
    array (T, F, 2)
        Tracks, NaN where a track has no detection.

    Raises
    ------
    ValueError
        A frame is not an (n, 2) array, or ``gate_px`` / ``ratio`` make no sense.
    """
    if gate_px <= 0 or ratio < 1:
        raise ValueError(f"link_tracks: gate_px must be > 0 and ratio >= 1, got {gate_px}, {ratio}")
    xy = []
    for f, d in enumerate(frames):
        d = np.asarray(d, float)
        if d.ndim != 2 or d.shape[1] != 2:
            raise ValueError(f"link_tracks: frame {f} holds an array of shape {d.shape}, expected (n, 2)")
        xy.append(d[np.isfinite(d).all(1)])
    F = len(xy)
    rows: list[list[tuple[int, int]]] = []  # per track: (frame, detection)
    active: list[int] = []  # tracks continued into the current frame
    for f in range(F):
        cur = xy[f]
        taken = np.zeros(len(cur), bool)
        nxt: list[int] = []
        if active and len(cur):
            pred = np.empty((len(active), 2))
            for k, tr in enumerate(active):
                (f1, i1) = rows[tr][-1]
                p = xy[f1][i1]
                if len(rows[tr]) >= 2 and rows[tr][-2][0] == f1 - 1:
                    p = 2 * p - xy[f1 - 1][rows[tr][-2][1]]
                pred[k] = p
            D = np.linalg.norm(pred[:, None] - cur[None], axis=-1)
            big = 1e9
            r, c = linear_sum_assignment(np.where(D <= gate_px, D, big))
            for k, i in zip(r, c):
                d = D[k, i]
                if d > gate_px:
                    continue
                others_det = np.delete(D[k], i)
                others_trk = np.delete(D[:, i], k)
                lim = max(ratio * d, 1.0)
                if (others_det < lim).any() or (others_trk < lim).any():
                    continue
                rows[active[k]].append((f, int(i)))
                taken[i] = True
                nxt.append(active[k])
        for i in np.flatnonzero(~taken):
            rows.append([(f, int(i))])
            nxt.append(len(rows) - 1)
        active = nxt
    out = np.full((len(rows), F, 2), np.nan)
    for k, row in enumerate(rows):
        for f, i in row:
            out[k, f] = xy[f][i]
    return out


def moving_tracks(tracks: np.ndarray, *, min_frames: int = 15, min_motion_px: float = 15.0) -> np.ndarray:
    """bool (T,): tracks with at least ``min_frames`` detections whose positions span at least
    ``min_motion_px`` (the diagonal of their bounding box). Static tracks (clutter, the room)
    cannot be told apart by their motion, so they are not matched."""
    n = np.isfinite(tracks[..., 0]).sum(1)
    with np.errstate(invalid="ignore"):
        span = np.hypot(*(np.nanmax(tracks, axis=1) - np.nanmin(tracks, axis=1)).T) if len(tracks) else np.zeros(0)
    return (n >= min_frames) & (np.nan_to_num(span) >= min_motion_px)


# --------------------------------------------------------------------------------------
# 2. Track pairs
# --------------------------------------------------------------------------------------


def signed_epipolar_distance(xy1: np.ndarray, xy2: np.ndarray, intr1: Intrinsics, R1: np.ndarray, t1: np.ndarray,
                             intr2: Intrinsics, R2: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Signed symmetric epipolar distance (corrected px) between raw pixels ``xy1 (..., 2)``
    and ``xy2 (..., 2)`` (broadcast): the sign of ``x2^T F x1``, the size of
    :func:`~carapost.core.camera.symmetric_epipolar_distance`."""
    Fm = fundamental_matrix(intr1, R1, t1, intr2, R2, t2)
    p1 = undistort(xy1, intr1)
    p2 = undistort(xy2, intr2)
    h1 = np.concatenate([p1, np.ones(p1.shape[:-1] + (1,))], axis=-1)
    h2 = np.concatenate([p2, np.ones(p2.shape[:-1] + (1,))], axis=-1)
    l2 = h1 @ Fm.T
    l1 = h2 @ Fm
    num = np.sum(h2 * l2, axis=-1)
    return 0.5 * num * (1.0 / np.hypot(l2[..., 0], l2[..., 1]) + 1.0 / np.hypot(l1[..., 0], l1[..., 1]))


@dataclass(frozen=True)
class TrackPairs:
    """Result of :func:`track_pair_table` for cameras ``a`` and ``b``.

    Attributes
    ----------
    common : int array (Ta, Tb)
        Frames in which both tracks have a detection.
    bias : array (Ta, Tb)
        Mean signed epipolar distance over those frames, px (NaN: none).
    spread : array (Ta, Tb)
        Its standard deviation, px: small for a true pair, whatever the bias.
    sweep : array (Ta, Tb)
        The spread the pair would have if camera b's track stood still at its mean position
        while camera a's moved, and the converse (the larger): how much the tracks move across
        each other's epipolar lines, i.e. how much a small ``spread`` says.
    """

    common: np.ndarray
    bias: np.ndarray
    spread: np.ndarray
    sweep: np.ndarray


def track_pair_table(tracks_a: np.ndarray, tracks_b: np.ndarray, intr_a: Intrinsics, R_a: np.ndarray,
                     t_a: np.ndarray, intr_b: Intrinsics, R_b: np.ndarray, t_b: np.ndarray) -> TrackPairs:
    """Epipolar agreement over time of every track of camera a with every track of camera b
    (``tracks_* (T, F, 2)`` raw px, same frames; poses world-to-camera, mm)."""
    Ta, Tb = len(tracks_a), len(tracks_b)
    if Ta == 0 or Tb == 0:
        z = np.zeros((Ta, Tb))
        return TrackPairs(z.astype(int), z + np.nan, z + np.nan, z + np.nan)
    S = signed_epipolar_distance(tracks_a[:, None], tracks_b[None], intr_a, R_a, t_a, intr_b, R_b, t_b)
    ok = np.isfinite(S)
    n = ok.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        Sz = np.where(ok, S, 0.0)
        mean = Sz.sum(-1) / n
        spread = np.sqrt(np.maximum(0.0, (Sz * Sz).sum(-1) / n - mean * mean))
        # tracks frozen at their mean positions over the common frames
        wa = np.where(ok[..., None], tracks_a[:, None], 0.0).sum(2) / n[..., None]
        wb = np.where(ok[..., None], tracks_b[None], 0.0).sum(2) / n[..., None]
        sweeps = []
        for xy_a, xy_b in ((tracks_a[:, None], wb[:, :, None]), (wa[:, :, None], tracks_b[None])):
            Sm = signed_epipolar_distance(xy_a, xy_b, intr_a, R_a, t_a, intr_b, R_b, t_b)
            Sm = np.where(ok, Sm, 0.0)
            m = Sm.sum(-1) / n
            sweeps.append(np.sqrt(np.maximum(0.0, (Sm * Sm).sum(-1) / n - m * m)))
        sweep = np.maximum(*sweeps)
    return TrackPairs(n, np.where(n > 0, mean, np.nan), np.where(n > 0, spread, np.nan),
                      np.where(n > 0, sweep, np.nan))


# --------------------------------------------------------------------------------------
# 3. Matching tracks across cameras
# --------------------------------------------------------------------------------------


def match_tracks(tracks: Sequence[np.ndarray], intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, *,
                 max_bias_px: float = 30.0, max_spread_px: float = 1.0, min_sweep_px: float = 3.0,
                 min_sweep_ratio: float = 3.0, min_common: int = 20
                 ) -> tuple[list[np.ndarray], list[tuple[int, int, int, int, float]]]:
    """Join tracks of all cameras into marker trajectories.

    A pair of tracks of two cameras is a candidate when it has ``min_common`` common frames,
    its mean signed epipolar distance is within ``max_bias_px``, its spread within
    ``max_spread_px`` and its sweep at least ``min_sweep_px`` and ``min_sweep_ratio`` times the
    spread (:class:`TrackPairs`: the pair agrees much better than its motion across the
    epipolar lines would let a coincidence). Candidates are taken in order of
    ``spread / max_spread_px + |bias| / max_bias_px`` (Kruskal-like):
    each joins two trajectories unless the result would hold two tracks of one camera that
    share a frame.

    Parameters
    ----------
    tracks : C arrays (T_c, F, 2)
        Each camera's tracks (:func:`link_tracks`, usually only :func:`moving_tracks`).
    intrinsics, R, t
        Cameras, ``R (C, 3, 3)``, ``t (C, 3)`` world-to-camera, mm.

    Returns
    -------
    label : list of C int arrays (T_c,)
        Trajectory of each track (-1: none; trajectories numbered 0..G-1).
    edges : list of (a, i, b, j, cost)
        The accepted track pairs.
    """
    C = len(tracks)
    cand = []
    for a in range(C):
        for b in range(a + 1, C):
            tp = track_pair_table(tracks[a], tracks[b], intrinsics[a], R[a], t[a], intrinsics[b], R[b], t[b])
            with np.errstate(invalid="ignore"):
                ok = ((tp.common >= min_common) & (np.abs(tp.bias) <= max_bias_px) & (tp.spread <= max_spread_px)
                      & (tp.sweep >= min_sweep_px) & (tp.sweep >= min_sweep_ratio * tp.spread))
            for i, j in zip(*np.nonzero(ok)):
                cand.append((tp.spread[i, j] / max_spread_px + abs(tp.bias[i, j]) / max_bias_px, a, int(i), b, int(j)))
    cand.sort()
    offs = np.cumsum([0] + [len(tr) for tr in tracks])
    parent = list(range(int(offs[-1])))
    present = [np.isfinite(tr[..., 0]) for tr in tracks]
    F = tracks[0].shape[1] if C else 0
    # per component: (C, F) frame occupancy
    occ = {}

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    def occupancy(node: int) -> np.ndarray:
        if node not in occ:
            c = int(np.searchsorted(offs, node, side="right") - 1)
            o = np.zeros((C, F), bool)
            o[c] = present[c][node - offs[c]]
            occ[node] = o
        return occ[node]

    edges = []
    for cost, a, i, b, j in cand:
        ra, rb = find(offs[a] + i), find(offs[b] + j)
        if ra == rb:
            continue
        oa, ob = occupancy(ra), occupancy(rb)
        if (oa & ob).any():
            continue
        parent[rb] = ra
        occ[ra] = oa | ob
        occ.pop(rb, None)
        edges.append((a, i, b, j, float(cost)))
    roots = {}
    label = []
    joined = {find(offs[a] + i) for a, i, *_ in edges}
    for c in range(C):
        lab = np.full(len(tracks[c]), -1)
        for k in range(len(tracks[c])):
            r = find(offs[c] + k)
            if r in joined:
                lab[k] = roots.setdefault(r, len(roots))
        label.append(lab)
    return label, edges


def trajectory_observations(tracks: Sequence[np.ndarray], label: Sequence[np.ndarray]) -> np.ndarray:
    """Observations ``(F, G, C, 2)`` raw px of the trajectories of :func:`match_tracks` (NaN:
    not seen; a trajectory-frame seen by fewer than two cameras is left out)."""
    C = len(tracks)
    G = max([int(lab.max()) + 1 if len(lab) else 0 for lab in label] + [0])
    F = tracks[0].shape[1] if C else 0
    O = np.full((F, G, C, 2), np.nan)
    for c in range(C):
        for k in np.flatnonzero(label[c] >= 0):
            seen = np.isfinite(tracks[c][k, :, 0])
            O[seen, label[c][k], c] = tracks[c][k, seen]
    few = np.isfinite(O[..., 0]).sum(-1) < 2
    O[few] = np.nan
    return O


# --------------------------------------------------------------------------------------
# 4. Extrinsics
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrackCalibration:
    """Result of :func:`refine_extrinsics`.

    Attributes
    ----------
    R, t : arrays (C, 3, 3), (C, 3)
        Refined world-to-camera poses, mm (camera ``fixed`` unchanged; the mean distance of the
        other cameras' centres from it kept from the starting poses).
    observations : array (F, G, C, 2)
        The last round's trajectories, raw px.
    residuals : array (F, G, C)
        Their reprojection errors with the refined poses, px.
    rounds : list of dict
        Per round: tolerances, accepted track pairs and trajectories, observations, median
        residual after the bundle.
    turned_deg, moved_mm : arrays (C,)
        Change from the starting poses.
    """

    R: np.ndarray
    t: np.ndarray
    observations: np.ndarray
    residuals: np.ndarray
    rounds: list = field(default_factory=list)
    turned_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    moved_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))


#: Default rounds of :func:`refine_extrinsics`: (max_bias_px, max_spread_px) per round.
DEFAULT_ROUNDS = ((30.0, 3.0), (15.0, 2.0), (6.0, 1.5), (4.0, 1.0))


def _fixed_set(fixed: int | Sequence[int], C: int) -> set[int]:
    out = {int(fixed)} if np.isscalar(fixed) else {int(c) for c in fixed}
    if not out or not all(0 <= c < C for c in out):
        raise ValueError(f"fixed cameras {sorted(out)} are not among the {C} cameras")
    return out


def _keep_scale(R: np.ndarray, t: np.ndarray, R0: np.ndarray, t0: np.ndarray, fixed: int | Sequence[int]) -> np.ndarray:
    """Translations of poses ``R, t`` scaled about the (first) fixed camera's centre so that the
    mean distance of the other centres from it equals the starting poses' (reprojection
    unchanged). With two or more fixed cameras their baseline pins the scale: ``t`` as it is."""
    if not np.isscalar(fixed):
        if len(fixed) > 1:
            return t.copy()
        fixed = int(fixed[0])
    c0, c = camera_centre(R0, t0), camera_centre(R, t)
    others = np.arange(len(R)) != fixed
    s = (np.linalg.norm(c0[others] - c0[fixed], axis=1).mean()
         / max(np.linalg.norm(c[others] - c[fixed], axis=1).mean(), 1e-12))
    cn = c[fixed] + s * (c - c[fixed])
    return -np.einsum("cij,cj->ci", R, cn)


def refine_extrinsics(tracks: Sequence[np.ndarray], intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray,
                      *, fixed: int | Sequence[int] = 0, rounds: Sequence[tuple[float, float]] = DEFAULT_ROUNDS,
                      min_sweep_px: float = 3.0, min_sweep_ratio: float = 3.0, min_common: int = 20,
                      loss: str = "cauchy",
                      f_scale_px: float = 2.0, rotation_sigma_deg: float = 2.0, centre_sigma_mm: float = 200.0,
                      max_points: int = 3000) -> TrackCalibration:
    """Refine static cameras' poses from 2D tracks, matching and bundling in rounds.

    Each round matches the tracks with the current poses (:func:`match_tracks`, that round's
    ``(max_bias_px, max_spread_px)``), then bundles all frames of the trajectories (one pose
    per camera, camera ``fixed`` kept, robust ``loss`` at ``f_scale_px``), and restores the
    scale (:func:`_keep_scale`: a bundle without a known length leaves it free).

    Parameters
    ----------
    tracks : C arrays (T_c, F, 2)
        Moving tracks of each camera, raw px, over the same F frames.
    intrinsics : C Intrinsics
        Kept as they are.
    R, t : arrays (C, 3, 3), (C, 3)
        Starting world-to-camera poses, mm (the prior pulls towards them in every round).
    fixed : int or sequence of int
        Camera(s) kept; with one, the scale is kept from the starting baselines.
    rounds : sequence of (max_bias_px, max_spread_px)
        Matching tolerances per round (:data:`DEFAULT_ROUNDS`).
    min_sweep_px, min_sweep_ratio, min_common
        Track pair criteria of :func:`match_tracks`.
    loss, f_scale_px, rotation_sigma_deg, centre_sigma_mm
        Robust loss and pose prior of :func:`bundle_poses`.
    max_points : int
        At most this many trajectory points (evenly chosen) per bundle.

    Returns
    -------
    TrackCalibration

    Raises
    ------
    ValueError
        Mismatched shapes, or a round finds no trajectory seen by two cameras.
    """
    R0 = np.asarray(R, float)
    t0 = np.asarray(t, float)
    C = len(tracks)
    if R0.shape != (C, 3, 3) or t0.shape != (C, 3) or len(intrinsics) != C:
        raise ValueError(f"refine_extrinsics: {C} track sets, R {R0.shape}, t {t0.shape}, "
                         f"{len(intrinsics)} intrinsics")
    if len({tr.shape[1] for tr in tracks}) > 1:
        raise ValueError("refine_extrinsics: the cameras' tracks do not cover the same frames")
    _fixed_set(fixed, C)
    Rc, tc = R0.copy(), t0.copy()
    log = []
    O = np.zeros((0, 0, C, 2))
    for max_bias, max_spread in rounds:
        label, edges = match_tracks(tracks, intrinsics, Rc, tc, max_bias_px=max_bias, max_spread_px=max_spread,
                                    min_sweep_px=min_sweep_px, min_sweep_ratio=min_sweep_ratio,
                                    min_common=min_common)
        O = trajectory_observations(tracks, label)
        seen = np.isfinite(O[..., 0])
        if not seen.any():
            raise ValueError(f"refine_extrinsics: no trajectory seen by two cameras at {max_bias} px")
        xy = O.reshape(-1, C, 2)
        xy = xy[np.isfinite(xy[..., 0]).sum(1) >= 2]
        if len(xy) > max_points:  # evenly over the trajectories' frames
            xy = xy[np.linspace(0, len(xy) - 1, max_points).round().astype(int)]
        Rc, tb, res = bundle_poses(xy, intrinsics, Rc, tc, fixed=fixed, rotation_sigma_deg=rotation_sigma_deg,
                                   centre_sigma_mm=centre_sigma_mm, loss=loss, f_scale_px=f_scale_px,
                                   anchor=(R0, t0))
        tc = _keep_scale(Rc, tb, R0, t0, fixed)
        res = res[np.isfinite(res)]
        log.append({"max_bias_px": max_bias, "max_spread_px": max_spread, "track_pairs": len(edges),
                    "pairs_per_camera_pair": _pair_counts(edges, C), "trajectories": int(O.shape[1]),
                    "observations": int(seen.sum()), "median_residual_px": float(np.median(res)),
                    "within_2px": float(np.mean(res < 2.0))})
    X = triangulate(O, intrinsics, Rc[None, None], tc[None, None]).xyz
    resid = np.full(O.shape[:3], np.nan)
    for c in range(C):
        resid[..., c] = np.linalg.norm(project(X, intrinsics[c], Rc[c], tc[c]) - O[..., c, :], axis=-1)
    turned, moved = pose_change(R0, t0, Rc, tc)
    return TrackCalibration(R=Rc, t=tc, observations=O, residuals=resid, rounds=log, turned_deg=turned,
                            moved_mm=moved)


def bundle_poses(xy: np.ndarray, intrinsics: Sequence[Intrinsics], R: np.ndarray, t: np.ndarray, *,
                 fixed: int | Sequence[int] = 0, rotation_sigma_deg: float = 2.0, centre_sigma_mm: float = 200.0,
                 loss: str = "cauchy", f_scale_px: float = 2.0, max_nfev: int = 100,
                 anchor: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bundle static cameras' poses and points, with a prior on each pose change.

    Parameters are each free camera's rotation change (rotation vector) and centre change, and
    the points; residuals are the reprojection errors (robust ``loss`` at ``f_scale_px``) and
    the prior (a change of ``rotation_sigma_deg`` or ``centre_sigma_mm`` costs as much as a
    1 px residual), which keeps poses that the points leave weakly determined near their start.
    The Jacobian is sparse (finite differences grouped by scipy).

    Parameters
    ----------
    xy : array (P, C, 2)
        Observations, raw px, NaN where unseen; every point seen by two or more cameras.
    intrinsics, R, t
        Cameras; ``R (C, 3, 3)``, ``t (C, 3)`` starting world-to-camera poses, mm.
    fixed : int or sequence of int
        Camera(s) kept as they are.
    anchor : (R, t), optional
        Poses the prior pulls towards (default: the starting poses), e.g. the calibration file's
        when bundling in rounds.

    Returns
    -------
    R, t : arrays (C, 3, 3), (C, 3)
        Bundled poses (camera ``fixed`` unchanged).
    residuals : array (P, C)
        Reprojection errors, px (NaN: unseen).
    """
    xy = np.asarray(xy, float)
    P, C = xy.shape[:2]
    seen = np.isfinite(xy[..., 0])
    if P == 0 or (seen.sum(1) < 2).any():
        raise ValueError("bundle_poses: every point needs two or more views")
    fixed_set = _fixed_set(fixed, C)
    free = [c for c in range(C) if c not in fixed_set]
    centres0 = camera_centre(R, t)
    X0 = triangulate(xy, intrinsics, R, t).xyz
    bad = ~np.isfinite(X0).all(1)
    X0[bad] = np.nanmean(X0[~bad], axis=0) if (~bad).any() else 0.0
    obs_p, obs_c = np.nonzero(seen)
    target = xy[obs_p, obs_c]
    n_obs, n_pose = len(obs_p), 6 * len(free)
    sig_r = np.radians(rotation_sigma_deg)
    offset = np.zeros(n_pose)  # the start's change from the anchor (rotation vectors add for small angles)
    if anchor is not None:
        Ra, ta = np.asarray(anchor[0], float), np.asarray(anchor[1], float)
        ca = camera_centre(Ra, ta)
        for k, c in enumerate(free):
            offset[6 * k:6 * k + 3] = Rotation.from_matrix(R[c] @ Ra[c].T).as_rotvec()
            offset[6 * k + 3:6 * k + 6] = centres0[c] - ca[c]

    def unpack(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Rn, tn = R.copy(), t.copy()
        for k, c in enumerate(free):
            Rn[c] = rodrigues(v[6 * k:6 * k + 3]) @ R[c]
            tn[c] = -Rn[c] @ (centres0[c] + v[6 * k + 3:6 * k + 6])
        return Rn, tn, v[n_pose:].reshape(P, 3)

    def fun(v: np.ndarray) -> np.ndarray:
        Rn, tn, X = unpack(v)
        r = np.empty((n_obs, 2))
        for c in range(C):
            sel = obs_c == c
            r[sel] = project(X[obs_p[sel]], intrinsics[c], Rn[c], tn[c]) - target[sel]
        r = np.nan_to_num(r, nan=1e3).ravel() / f_scale_px
        if loss == "cauchy":
            r = np.sign(r) * np.sqrt(np.log1p(r * r))
        elif loss == "soft_l1":
            r = np.sign(r) * np.sqrt(2.0 * (np.sqrt(1.0 + r * r) - 1.0))
        elif loss != "linear":
            raise ValueError(f"bundle_poses: loss must be linear, soft_l1 or cauchy, got {loss!r}")
        w = v[:n_pose] + offset
        prior = np.concatenate([np.r_[w[6 * k:6 * k + 3] / sig_r, w[6 * k + 3:6 * k + 6] / centre_sigma_mm]
                                for k in range(len(free))]) if free else np.zeros(0)
        return np.concatenate([r * f_scale_px, prior])

    J = lil_matrix((2 * n_obs + n_pose, n_pose + 3 * P), dtype=int)
    rows = np.arange(n_obs)
    for k, c in enumerate(free):
        sel = rows[obs_c == c]
        for d in range(2):
            for q in range(6):
                J[2 * sel + d, 6 * k + q] = 1
    for d in range(2):
        for q in range(3):
            J[2 * rows + d, n_pose + 3 * obs_p + q] = 1
    for q in range(n_pose):
        J[2 * n_obs + q, q] = 1
    v0 = np.concatenate([np.zeros(n_pose), X0.ravel()])
    sol = least_squares(fun, v0, jac_sparsity=J.tocsr(), method="trf", x_scale="jac", max_nfev=max_nfev)
    Rn, tn, X = unpack(sol.x)
    res = np.full((P, C), np.nan)
    for c in range(C):
        res[:, c] = np.linalg.norm(project(X, intrinsics[c], Rn[c], tn[c]) - xy[:, c], axis=-1)
    return Rn, tn, res


def _pair_counts(edges: list, C: int) -> dict:
    out: dict = {}
    for a, _, b, _, _ in edges:
        out[f"{a + 1}-{b + 1}"] = out.get(f"{a + 1}-{b + 1}", 0) + 1
    return out
