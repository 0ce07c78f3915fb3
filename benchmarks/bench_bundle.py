"""Bundle adjustment speed: ours against the common approach.

Ours: analytic Jacobian + Schur-complement Levenberg-Marquardt (the default). The common
approach: ``scipy.optimize.least_squares`` with finite differences on the sparse Jacobian
pattern. Also printed: scipy with our analytic Jacobian (isolates the solver's share).
Targets (issue 3): ours >= 5x faster to an equal or lower final cost; a 300-frame, 80-point
sequence bundle (per-frame camera poses, brim pinned) in seconds. Prints one JSON line.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "core"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit  # noqa: E402
from test_bundle import perturb, scene  # noqa: E402

from carapost.core.bundle import bundle_adjust  # noqa: E402


def run(F: int, P: int, solver: str, jac: str = "analytic", seed: int = 0) -> tuple[float, object, np.ndarray, np.ndarray]:
    intr, R, t, X, obs, fixed, rng = scene(F=F, P=P, seed=seed, flex=0.3)
    obs = obs + rng.normal(scale=0.2, size=obs.shape)
    obs[rng.random(obs.shape[:3]) < 0.1] = np.nan
    R0, t0 = perturb(R, t, rng, rot=0.005, trans=1.0)
    X0 = X.copy()
    X0[:, ~fixed] += rng.normal(scale=0.5, size=X0[:, ~fixed].shape)
    t_start = time.perf_counter()
    res = bundle_adjust(obs, intr, R0, t0, X0, fixed_points=fixed, solver=solver, jac=jac,
                        max_iterations=None if solver == "scipy" else 50)
    return time.perf_counter() - t_start, res, X, fixed


def main() -> None:
    F_cmp = 100
    t_lm, r_lm, _, _ = run(F_cmp, 80, "lm")
    t_an, r_an, _, _ = run(F_cmp, 80, "scipy", "analytic")
    t_fd, r_fd, _, _ = run(F_cmp, 80, "scipy", "2-point")
    t_seq, r_seq, Xs, fixed_s = run(300, 80, "lm", seed=1)
    err = np.linalg.norm(r_seq.xyz - Xs, axis=-1)[:, ~fixed_s]
    emit("bundle",
         compare_frames=F_cmp, points=80, cameras=4,
         ours_lm_s=t_lm, scipy_analytic_s=t_an, scipy_finite_diff_s=t_fd,
         speedup_vs_finite_diff=t_fd / t_lm,
         ours_cost=r_lm.final_cost, scipy_analytic_cost=r_an.final_cost, finite_diff_cost=r_fd.final_cost,
         sequence_300x80_s=t_seq, sequence_median_err_mm=float(np.nanmedian(err)),
         sequence_iterations=r_seq.nfev,
         targets_met=bool(t_fd / t_lm >= 5 and r_lm.final_cost <= r_fd.final_cost * (1 + 1e-6) and t_seq < 10))


if __name__ == "__main__":
    main()
