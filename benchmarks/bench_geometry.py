"""Projection and triangulation speed.

Targets (issue 2): >= 1 million projected points/s; triangulation of 160 points x 4 views for
10,000 frames in under 2 s. Prints one JSON line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, emit  # noqa: E402

from carapost.core.camera import Intrinsics, project  # noqa: E402
from carapost.core.triangulate import triangulate  # noqa: E402


def rig():
    intr, Rs, ts = [], [], []
    for ang in (-0.55, -0.25, 0.25, 0.55):
        C = np.array([200 * np.sin(ang), -30.0, 200 * np.cos(ang)])
        z = -C / np.linalg.norm(C)
        x = np.cross([0, 1, 0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        intr.append(Intrinsics(1100.0, (640.0, 360.0), (1280, 720), radial=(2e-8, -1e-14, 0.0)))
        Rs.append(R)
        ts.append(-R @ C)
    return intr, np.array(Rs), np.array(ts)


def main() -> None:
    intr, R, t = rig()
    rng = np.random.default_rng(0)
    n = 1_000_000
    X = np.c_[rng.uniform(-60, 60, n), rng.uniform(-80, 80, n), rng.uniform(-10, 30, n)]
    t_proj = best_time(lambda: project(X, intr[0], R[0], t[0]))

    F, P = 10_000, 160
    Xf = np.c_[rng.uniform(-60, 60, F * P), rng.uniform(-80, 80, F * P), rng.uniform(-10, 30, F * P)].reshape(F, P, 3)
    xy = np.stack([project(Xf, intr[v], R[v], t[v]) for v in range(4)], axis=2)
    xy += rng.normal(scale=0.2, size=xy.shape)
    xy[rng.random(xy.shape[:3]) < 0.1] = np.nan
    t_tri = best_time(lambda: triangulate(xy, intr, R, t), repeat=2)
    res = triangulate(xy, intr, R, t)
    err = np.linalg.norm(res.xyz - Xf, axis=-1)
    emit("geometry",
         projected_points_per_s=n / t_proj,
         triangulate_160x4x10000_s=t_tri,
         triangulate_median_err_mm=float(np.nanmedian(err)),
         targets_met=bool(n / t_proj >= 1e6 and t_tri < 2.0))


if __name__ == "__main__":
    main()
