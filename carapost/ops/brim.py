"""Calibration brim operations: Initialize Default Calibration Brim [v1.0/v1.1/v2.0], Import
Calibration Brim [svg], Solve Calibration Brim [Manual]."""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from carapost.core.brim_solve import BrimSolveResult, solve_brim
from carapost.io.brim import load_default_brim
from carapost.io.brim_svg import read_brim_svg
from carapost.model.take import BrimModel, ObsSource, PointKind, Recon, Take

from .change import ArrayPatch, AttributeChange, Change, Composite, PointsAdded, PointsRemoved
from .points import PointBlock

__all__ = ["set_brim", "initialize_default_brim", "import_brim_svg", "solve_brim_manual"]


def set_brim(take: Take, brim: BrimModel, text: str) -> Composite:
    """Replace the take's brim model and its brim points (one point per dot, at the model's
    position in every frame: the brim frame is the world frame)."""
    changes: list[Change] = []
    old = take.brim_points()
    if len(old):
        changes.append(PointsRemoved(old))
    n = len(brim)
    F = take.n_frames
    C = take.n_cameras
    arrays = {
        "xyz": np.broadcast_to(brim.xyz[None], (F, n, 3)).astype(np.float64).copy(),
        "recon": np.zeros((F, n), np.uint8),
        "obs_xy": np.full((F, n, C, 2), np.nan, np.float32),
        "obs_det": np.full((F, n, C), -1, np.int32),
        "obs_src": np.zeros((F, n, C), np.uint8),
    }
    changes.append(AttributeChange.capture(take, "brim", brim, ""))
    changes.append(PointsAdded(n, int(PointKind.BRIM), [""] * n, np.arange(n, dtype=np.int32), arrays))
    return Composite(changes, text)


def initialize_default_brim(take: Take, version: str = "v2.0") -> Composite:
    """"Initialize Default Calibration Brim [version]"."""
    return set_brim(take, load_default_brim(version), f"Initialize Default Calibration Brim [{version}]")


def import_brim_svg(take: Take, path: str | os.PathLike) -> Composite:
    """"Import Calibration Brim [svg]": a custom planar brim."""
    return set_brim(take, read_brim_svg(path), f"Import Calibration Brim [svg]: {os.path.basename(path)}")


def solve_brim_manual(take: Take, frame: int, correspondences: Mapping[int, Mapping[int, int]], *,
                      all_frames: bool = True, match_radius_px: float = 6.0) -> tuple[Composite, BrimSolveResult]:
    """"Solve Calibration Brim [Manual]": camera poses of ``frame`` from >= 4 brim dots per camera.

    The brim dots found are attached to their detections in ``frame``; the solved poses become
    the cameras' poses in ``frame`` and, with ``all_frames``, the starting poses of every frame
    that has none yet (tracking refines them frame by frame).

    Raises
    ------
    ValueError
        No brim initialized, or no camera could be solved (the message says why per camera).
    """
    if take.brim is None:
        raise ValueError("Solve Calibration Brim: initialize or import a calibration brim first")
    cols = take.brim_points()
    dot_col = {int(take.points.brim_index[c]): int(c) for c in cols}
    dets = [take.detections[c].xy(frame) for c in range(take.n_cameras)]
    R0 = take.R[frame] if np.isfinite(take.R[frame]).all() else None
    t0 = take.t[frame] if np.isfinite(take.t[frame]).all() else None
    res = solve_brim(take.brim, take.intrinsics(), dets, correspondences, match_radius_px=match_radius_px,
                     initial_R=R0, initial_t=t0, caddies=take.caddies)
    solved = res.solved
    changes: list[Change] = []
    frames = np.arange(take.n_frames) if all_frames else np.array([frame])
    Rn = take.R[frames].copy()
    tn = take.t[frames].copy()
    unsolved_before = ~np.isfinite(Rn).all(axis=(-1, -2))
    for c in np.flatnonzero(solved):
        sel = unsolved_before[:, c] | (frames == frame)
        Rn[sel, c] = res.R[c]
        tn[sel, c] = res.t[c]
    changes.append(ArrayPatch.capture(take, "R", (frames,), Rn))
    changes.append(ArrayPatch.capture(take, "t", (frames,), tn))
    # Attach the matched detections to the brim points in the frame.
    blk = PointBlock(take, [frame], cols)
    blk.detach(np.ones(blk.arrays["obs_det"].shape, bool))
    for b in range(len(take.brim)):
        if b not in dot_col:
            continue
        j = int(np.flatnonzero(blk.cols == dot_col[b])[0])
        for c in range(take.n_cameras):
            i = int(res.det_index[b, c])
            if i >= 0:
                blk.attach(0, j, c, i, res.xy[b, c])
    a = blk.arrays
    n_views = (a["obs_det"] >= 0).sum(-1)
    a["xyz"][0] = take.brim.xyz[take.points.brim_index[cols]]
    a["recon"][0] = np.where(n_views >= 2, Recon.MULTI_VIEW, np.where(n_views == 1, Recon.SINGLE_SENSOR, Recon.NONE))
    a["obs_src"][0] = np.where(a["obs_det"][0] >= 0, ObsSource.BLOB, ObsSource.NONE)
    changes += blk.patches()
    n = int(res.n_dots.sum())
    text = f"Solve Calibration Brim [Manual]: {int(solved.sum())} of {take.n_cameras} cameras, {n} dot observations"
    return Composite(changes, text), res
