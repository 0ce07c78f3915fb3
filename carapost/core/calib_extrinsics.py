"""Extrinsic calibration: every camera of a rig in one world frame, from shots of a flat target.

A *shot* is one moment at which one or more cameras see the target. Each view gives the
target's pose in that camera (:func:`target_pose`); cameras are placed one after the other
along a maximum spanning tree of shared shots, then all camera poses and all target poses are
refined together (the target stays rigid), minimising the raw-pixel reprojection error through
:func:`carapost.core.camera.project`. Intrinsics are held fixed (from
:func:`carapost.core.calibrate.calibrate_intrinsics` or an ``.xcp``).

Conventions are those of :mod:`carapost.core.camera`: raw pixels, mm, ``X_cam = R X + t``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from .calib_targets import TargetSpec, target_points
from .camera import Intrinsics, project, rodrigues, undistort

__all__ = ["ExtrinsicsResult", "calibrate_extrinsics", "target_pose"]

_BIG = 1e3  # residual (px) standing in for a point that cannot be projected


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) of a rotation matrix (3, 3)."""
    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def _mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal mean (3, 3) of rotations ``(K, 3, 3)``."""
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def target_pose(obj: np.ndarray, raw: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Target-to-camera pose from one view, with the camera's intrinsics known.

    The raw pixels are corrected (:func:`carapost.core.camera.undistort`, exact) and
    OpenCV's PnP solves the pinhole problem (IPPE for a flat target).

    Parameters
    ----------
    obj : array (N, 3)
        Target points, mm.
    raw : array (N, 2)
        Their raw pixels; rows with NaN are skipped (at least 4 must remain).
    intr : Intrinsics

    Returns
    -------
    R : array (3, 3)
    t : array (3,)
        ``X_cam = R X + t``, mm.

    Raises
    ------
    ValueError
        If fewer than 4 points are finite or PnP fails.
    """
    ok = np.isfinite(raw).all(axis=1)
    if ok.sum() < 4:
        raise ValueError(f"a target pose needs at least 4 points, got {int(ok.sum())}")
    pc = undistort(raw[ok], intr)
    flag = cv2.SOLVEPNP_IPPE if np.ptp(obj[ok, 2]) == 0 else cv2.SOLVEPNP_ITERATIVE
    good, rvec, tvec = cv2.solvePnP(obj[ok].astype(np.float64), pc.astype(np.float64), intr.K, None, flags=flag)
    if not good:
        raise ValueError("the target pose could not be estimated from a view")
    return cv2.Rodrigues(rvec)[0], tvec.ravel()


# --------------------------------------------------------------------------------------
# Extrinsics
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExtrinsicsResult:
    """Result of :func:`calibrate_extrinsics`.

    Attributes
    ----------
    R, t : arrays (C, 3, 3), (C, 3)
        World-to-camera pose of every camera, mm.
    target_R, target_t : arrays (S, 3, 3), (S, 3)
        Target-to-world pose in each shot (NaN for shots no camera saw).
    residuals : array (S, N, C)
        Reprojection error of each observation after the refinement, raw px (NaN where
        unobserved).
    rms : float
        Over all observations, px.
    rms_per_camera : array (C,)
    shared_shots : array (C, C) int
        Number of shots seen by both cameras of each pair.
    chain : list of (int, int)
        ``(parent, camera)`` edges through which the cameras were first placed.
    world : str
        ``"camera"`` (the reference camera's frame) or ``"target"``.
    """

    R: np.ndarray
    t: np.ndarray
    target_R: np.ndarray
    target_t: np.ndarray
    residuals: np.ndarray
    rms: float
    rms_per_camera: np.ndarray
    shared_shots: np.ndarray
    chain: list[tuple[int, int]]
    world: str


def _observation_array(observations: Any, C: int, n: int) -> np.ndarray:
    """``(S, N, C, 2)`` from an array of that shape or ``observations[c][s]`` lists."""
    if isinstance(observations, np.ndarray):
        obs = np.asarray(observations, dtype=float)
        if obs.ndim != 4 or obs.shape[1:] != (n, C, 2):
            raise ValueError(f"observations must have shape (S, {n}, {C}, 2), got {obs.shape}")
        return obs
    if len(observations) != C:
        raise ValueError(f"observations for {len(observations)} cameras, intrinsics for {C}")
    S = max((len(o) for o in observations), default=0)
    obs = np.full((S, n, C, 2), np.nan)
    for c, per_cam in enumerate(observations):
        for s, v in enumerate(per_cam):
            if v is None:
                continue
            a = np.asarray(v, dtype=float)
            if a.shape != (n, 2):
                raise ValueError(f"camera {c} shot {s}: expected ({n}, 2) target points, got shape {a.shape}")
            obs[s, :, c] = a
    return obs


def _place_cameras(seen: np.ndarray, Rcs: np.ndarray, tcs: np.ndarray,
                   reference: int) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]], np.ndarray]:
    """Initial world (= reference camera) poses by a maximum spanning tree of shared shots."""
    S, C = seen.shape
    shared = (seen[:, :, None] & seen[:, None, :]).sum(axis=0)
    R = np.full((C, 3, 3), np.nan)
    t = np.full((C, 3), np.nan)
    R[reference], t[reference] = np.eye(3), np.zeros(3)
    placed = {reference}
    chain: list[tuple[int, int]] = []
    while len(placed) < C:
        best = (0, -1, -1)
        for p in placed:
            for c in range(C):
                if c not in placed and shared[p, c] > best[0]:
                    best = (int(shared[p, c]), p, c)
        if best[0] == 0:
            missing = sorted(set(range(C)) - placed)
            raise ValueError(f"camera(s) {missing} share no shot of the target with camera {reference} "
                             "(directly or through other cameras); film the target where they overlap")
        _, p, c = best
        shots = np.flatnonzero(seen[:, p] & seen[:, c])
        R_rel = Rcs[shots, c] @ np.transpose(Rcs[shots, p], (0, 2, 1))  # camera p -> camera c
        t_rel = tcs[shots, c] - np.einsum("sij,sj->si", R_rel, tcs[shots, p])
        Rm = _mean_rotation(R_rel)
        R[c] = Rm @ R[p]
        t[c] = Rm @ t[p] + np.median(t_rel, axis=0)
        placed.add(c)
        chain.append((p, c))
    return R, t, chain, shared


class _ExtrinsicsProblem:
    """Joint refinement of camera poses (all but the reference) and target poses per shot."""

    def __init__(self, obj: np.ndarray, obs: np.ndarray, intr: Sequence[Intrinsics], reference: int,
                 R0: np.ndarray, t0: np.ndarray, TR0: np.ndarray, Tt0: np.ndarray, shots: np.ndarray):
        self.obj, self.obs, self.intr = obj, obs, list(intr)
        self.C = obs.shape[2]
        self.free = np.array([c for c in range(self.C) if c != reference], dtype=np.int64)
        self.shots = shots  # shots seen by at least one camera
        self.R0, self.t0, self.TR0, self.Tt0 = R0, t0, TR0, Tt0
        self.mask = np.isfinite(obs[shots]).all(-1)  # (S', N, C)

    @property
    def n_params(self) -> int:
        return 6 * (len(self.free) + len(self.shots))

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        nc = len(self.free)
        cam = x[:6 * nc].reshape(nc, 6)
        sh = x[6 * nc:].reshape(-1, 6)
        R, t = self.R0.copy(), self.t0.copy()
        if nc:
            R[self.free] = rodrigues(cam[:, :3]) @ self.R0[self.free]
            t[self.free] = self.t0[self.free] + cam[:, 3:]
        TR = rodrigues(sh[:, :3]) @ self.TR0[self.shots]
        Tt = self.Tt0[self.shots] + sh[:, 3:]
        return R, t, TR, Tt

    def errors(self, x: np.ndarray) -> np.ndarray:
        """Observed minus projected ``(S', N, C, 2)``."""
        R, t, TR, Tt = self.unpack(x)
        Xw = np.einsum("sij,nj->sni", TR, self.obj) + Tt[:, None, :]
        out = np.empty(self.obs[self.shots].shape)
        for c in range(self.C):
            out[:, :, c] = self.obs[self.shots][:, :, c] - project(Xw, self.intr[c], R[c], t[c])
        return out

    def residuals(self, x: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):  # a wild trial step may overflow; it is then penalised
            e = self.errors(x)[self.mask]
        return np.where(np.isfinite(e), e, _BIG).ravel()

    def sparsity(self) -> Any:
        s_idx, _, c_idx = np.nonzero(self.mask)
        s_idx, c_idx = np.repeat(s_idx, 2), np.repeat(c_idx, 2)
        rows = np.arange(len(s_idx))
        col_of_cam = np.full(self.C, -1)
        col_of_cam[self.free] = np.arange(len(self.free))
        S = lil_matrix((len(rows), self.n_params), dtype=int)
        nc = len(self.free)
        for k in range(6):
            S[rows, 6 * nc + 6 * s_idx + k] = 1
            has = col_of_cam[c_idx] >= 0
            S[rows[has], 6 * col_of_cam[c_idx[has]] + k] = 1
        return S.tocsr()


def calibrate_extrinsics(observations: Any, intrinsics: Sequence[Intrinsics], spec: TargetSpec, *,
                         reference: int = 0, world: str = "camera", world_shot: int | None = None,
                         loss: str = "linear", f_scale: float = 1.0) -> ExtrinsicsResult:
    """Place every camera in one world frame from shots of the target seen by several cameras.

    Each view gives the target's pose in that camera (PnP in the camera's XCP model); cameras
    are placed one by one along a maximum spanning tree of shared shots starting at
    ``reference`` (relative poses averaged over the shared shots), then every camera pose
    and every target pose are refined together, minimising the raw-pixel reprojection error
    through :func:`carapost.core.camera.project`; the target's points stay rigid.

    Parameters
    ----------
    observations : array (S, N, C, 2), or ``observations[c][s]`` arrays (N, 2) or None
        Target points per shot and camera, raw px; NaN / ``None`` where a camera did not
        see the target. A shot is one moment seen by the cameras at once.
    intrinsics : sequence of C Intrinsics
        Fixed intrinsics (e.g. from :func:`calibrate_intrinsics`).
    spec : TargetSpec
        Its points must be numbered the same way in every camera; a layout with
        ``spec.orientation_unique`` False is safe only if all cameras see it upright.
    reference : int
        The camera placed first.
    world : {"camera", "target"}
        World frame: the reference camera's own frame, or the target's frame in shot
        ``world_shot`` (default: the first shot the reference camera sees).
    loss, f_scale : str, float
        Robust loss of ``scipy.optimize.least_squares`` and its scale (px).

    Returns
    -------
    ExtrinsicsResult

    Raises
    ------
    ValueError
        Mismatched shapes, a bad ``reference`` / ``world`` / ``world_shot``, or a camera
        with no chain of shared shots to the reference camera.
    """
    C = len(intrinsics)
    if not 0 <= reference < C:
        raise ValueError(f"reference camera {reference} out of range 0..{C - 1}")
    if world not in ("camera", "target"):
        raise ValueError(f"world must be 'camera' or 'target', got {world!r}")
    n = spec.n_points
    obj = target_points(spec)
    obs = _observation_array(observations, C, n)
    S = obs.shape[0]
    seen = np.isfinite(obs).all(-1).sum(axis=1) >= 4  # (S, C)
    if not seen[:, reference].any():
        raise ValueError(f"camera {reference} (the reference) sees the target in no shot")
    s0 = int(np.flatnonzero(seen[:, reference])[0]) if world_shot is None else int(world_shot)
    if world == "target" and not (0 <= s0 < S and seen[s0].any()):
        raise ValueError(f"world_shot {world_shot}: no camera sees the target in that shot")
    Rcs = np.full((S, C, 3, 3), np.nan)
    tcs = np.full((S, C, 3), np.nan)
    for s, c in zip(*np.nonzero(seen)):
        Rcs[s, c], tcs[s, c] = target_pose(obj, obs[s, :, c], intrinsics[c])
    R0, t0, chain, shared = _place_cameras(seen, Rcs, tcs, reference)
    # Target poses in the world: averaged over the cameras that see each shot.
    TR0 = np.full((S, 3, 3), np.nan)
    Tt0 = np.full((S, 3), np.nan)
    shots = np.flatnonzero(seen.any(axis=1))
    for s in shots:
        cs = np.flatnonzero(seen[s])
        Rw = np.transpose(R0[cs], (0, 2, 1)) @ Rcs[s, cs]
        tw = np.einsum("cji,cj->ci", R0[cs], tcs[s, cs] - t0[cs])
        TR0[s], Tt0[s] = _mean_rotation(Rw), tw.mean(axis=0)
    prob = _ExtrinsicsProblem(obj, obs, intrinsics, reference, R0, t0, TR0, Tt0, shots)
    x0 = np.zeros(prob.n_params)
    sol = least_squares(prob.residuals, x0, jac_sparsity=prob.sparsity(), method="trf", x_scale="jac",
                        loss=loss, f_scale=f_scale, ftol=1e-8, xtol=1e-8, gtol=1e-8, max_nfev=200)
    R, t, TRs, Tts = prob.unpack(sol.x)
    TR = np.full((S, 3, 3), np.nan)
    Tt = np.full((S, 3), np.nan)
    TR[shots], Tt[shots] = TRs, Tts
    res = np.full((S, n, C), np.nan)
    res[shots] = np.linalg.norm(prob.errors(sol.x), axis=-1)
    if world == "target":
        A, b = TR[s0].copy(), Tt[s0].copy()  # target(s0) -> old world
        t = np.einsum("cij,j->ci", R, b) + t
        R = R @ A
        Tt = np.einsum("ji,sj->si", A, Tt - b)
        TR = A.T @ TR
    with np.errstate(invalid="ignore"):
        sq = np.where(np.isfinite(res), res ** 2, 0.0)
        cnt = np.isfinite(res).sum(axis=(0, 1))
        per_cam = np.where(cnt > 0, np.sqrt(sq.sum(axis=(0, 1)) / np.maximum(cnt, 1)), np.nan)
        rms = float(np.sqrt(sq.sum() / max(cnt.sum(), 1)))
    return ExtrinsicsResult(R=R, t=t, target_R=TR, target_t=Tt, residuals=res, rms=rms,
                            rms_per_camera=per_cam, shared_shots=shared, chain=chain, world=world)
