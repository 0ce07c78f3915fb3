"""Speed and size of the ``.cara`` project file.

Builds a realistic tracked take (default 10,000 frames, 160 points, 4 cameras, ~170 detections
per frame per camera: smooth noisy trajectories with ~5 % gaps, 2D observations and detections
per camera, per-frame camera poses, stabilized data), then measures

* ``save_s`` / ``load_s``: best wall time of :func:`carapost.io.cara.save_take` / ``load_take``;
* ``file_mb``: size of the written file;
* ``zlib1_mb``: the sum over all the take's arrays of ``len(zlib.compress(arr.tobytes(), 1))``
  (the reference size), and ``size_ratio = file_mb / zlib1_mb`` (target <= 1.5);
* ``raw_mb``: the arrays' uncompressed size.

Targets: save < 2 s, load < 2 s, size_ratio <= 1.5. Prints one JSON line.
Usage: ``python benchmarks/bench_cara.py [--frames N] [--repeat K]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit  # noqa: E402

from carapost.core.camera import Intrinsics  # noqa: E402
from carapost.io.cara import load_take, save_take  # noqa: E402
from carapost.model.detections import BLACK, DETECTION_FIELDS, Detections  # noqa: E402
from carapost.model.take import POINT_ARRAYS, CameraInfo, ObsSource, PointKind, Recon, Take  # noqa: E402


def _rig(C: int) -> tuple[list[Intrinsics], np.ndarray, np.ndarray]:
    intr, Rs, ts = [], [], []
    for ang in np.linspace(-0.55, 0.55, C):
        centre = np.array([200 * np.sin(ang), -30.0, 200 * np.cos(ang)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0, 1, 0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        intr.append(Intrinsics(1100.0, (640.0, 360.0), (1280, 720), radial=(2e-8, -1e-14, 0.0)))
        Rs.append(R)
        ts.append(-R @ centre)
    return intr, np.array(Rs), np.array(ts)


def make_tracked_take(F: int = 10_000, P: int = 160, C: int = 4, *, n_brim: int = 20,
                      det_per_frame: int = 170, seed: int = 0) -> Take:
    """A take with realistic tracked content (see the module docstring)."""
    rng = np.random.default_rng(seed)
    intr, R0, t0 = _rig(C)
    cams = [CameraInfo(f"cam_{c}", c, intr[c], image_size=(1280, 720)) for c in range(C)]
    # The rig flexes slightly: per-frame poses = static + small smooth perturbation + noise.
    tt = np.arange(F) / 60.0
    R = np.broadcast_to(R0, (F, C, 3, 3)) + 1e-4 * rng.standard_normal((F, C, 3, 3))
    t = (np.broadcast_to(t0, (F, C, 3)) + 0.3 * np.sin(tt)[:, None, None]
         + 0.01 * rng.standard_normal((F, C, 3)))
    R[rng.random(F) < 0.01] = np.nan  # a few frames where the brim solve failed
    take = Take.new(cams, F, 60.0, R=R, t=t, name="bench")
    take.add_points(P - n_brim, labels=[f"face_{i}" for i in range(P - n_brim)])
    take.add_points(n_brim, kind=PointKind.BRIM, brim_index=np.arange(n_brim))

    base = np.c_[rng.uniform(-60, 60, P), rng.uniform(-80, 80, P), rng.uniform(-10, 30, P)]
    freq = rng.uniform(0.1, 2.0, (P, 3))
    phase = rng.uniform(0, 2 * np.pi, (P, 3))
    amp = rng.uniform(0.5, 8.0, (P, 3))
    head = np.c_[3 * np.sin(0.3 * tt), 2 * np.sin(0.21 * tt + 1), np.zeros(F)]
    xyz = (base + amp * np.sin(freq * tt[:, None, None] * 2 * np.pi + phase) + head[:, None, :]
           + 0.05 * rng.standard_normal((F, P, 3)))
    # ~5 % gaps in runs of 5..60 frames
    gap = np.zeros((F, P), bool)
    n_runs = int(0.05 * F * P / 32)
    starts = rng.integers(0, F, n_runs)
    lens = rng.integers(5, 60, n_runs)
    pts = rng.integers(0, P, n_runs)
    for s, n, p in zip(starts, lens, pts):  # benchmark set-up only, not a hot path
        gap[s:s + n, p] = True
    xyz[gap] = np.nan
    take.xyz = xyz
    recon = np.full((F, P), int(Recon.MULTI_VIEW), np.uint8)
    recon[rng.random((F, P)) < 0.03] = int(Recon.SINGLE_SENSOR)
    recon[rng.random((F, P)) < 0.02] = int(Recon.INTERPOLATED)
    recon[gap] = int(Recon.NONE)
    take.recon = recon
    stab = xyz - head[:, None, :]
    take.xyz_stabilized = stab

    # 2D observations: pinhole projection + noise; each camera misses ~20 % of points.
    Xc = np.einsum("fcij,fpj->fpci", np.nan_to_num(R, nan=0.0), np.nan_to_num(xyz)) + t[:, None]
    uv = Xc[..., :2] / Xc[..., 2:3] * 1100.0 + np.array([640.0, 360.0])
    obs_xy = (uv + 0.2 * rng.standard_normal(uv.shape)).astype(np.float32)
    seen = ~gap[:, :, None] & (rng.random((1, P, C)) > 0.2) & (rng.random((F, P, C)) > 0.02)
    seen &= np.isfinite(R[:, None, :, 0, 0])
    obs_xy[~seen] = np.nan
    take.obs_xy = obs_xy
    obs_src = np.where(seen, int(ObsSource.BLOB), int(ObsSource.NONE)).astype(np.uint8)
    patch = seen & (rng.random((F, P, C)) < 0.03)
    obs_src[patch] = int(ObsSource.PATCH)
    take.obs_src = obs_src
    obs_q = np.full((F, P, C), np.nan, np.float32)
    obs_q[patch] = rng.uniform(0.8, 1.0, int(patch.sum())).astype(np.float32)
    take.obs_q = obs_q

    # Detections: the seen points (in a shuffled order) plus spurious blobs up to ~det_per_frame.
    obs_det = np.full((F, P, C), -1, np.int32)
    dets = []
    for c in range(C):
        n_seen = seen[:, :, c].sum(1)
        counts = np.maximum(det_per_frame + rng.integers(-10, 11, F), n_seen)
        ptr = np.zeros(F + 1, np.int64)
        np.cumsum(counts, out=ptr[1:])
        N = int(ptr[-1])
        x = rng.uniform(0, 1280, N).astype(np.float32)
        y = rng.uniform(0, 720, N).astype(np.float32)
        # place the seen points at random slots of their frame
        order = np.argsort(rng.random(N) + np.repeat(np.arange(F), counts))  # a shuffle within frames
        within = order - np.repeat(ptr[:-1], counts)
        fr, pt = np.nonzero(seen[:, :, c])
        rank = np.arange(len(fr)) - np.repeat(np.r_[0, np.cumsum(n_seen)[:-1]], n_seen)
        slot = within[ptr[fr] + rank]
        obs_det[fr, pt, c] = slot
        x[ptr[fr] + slot] = obs_xy[fr, pt, c, 0]
        y[ptr[fr] + slot] = obs_xy[fr, pt, c, 1]
        major = rng.uniform(4, 9, N).astype(np.float32)
        minor = (major * rng.uniform(0.6, 1.0, N)).astype(np.float32)
        arrays = dict(x=x, y=y, major=major, minor=minor,
                      angle=rng.uniform(-np.pi / 2, np.pi / 2, N).astype(np.float32),
                      polarity=np.full(N, BLACK, np.int8),
                      score=rng.uniform(0.4, 1.0, N).astype(np.float32))
        dets.append(Detections(frame_ptr=ptr, detected=np.ones(F, bool), **arrays))
    take.detections = dets
    take.obs_det = obs_det
    take.sticks = np.array([[i, i + 1] for i in range(0, 40, 2)], np.int64)
    take.stick_colours = np.full((len(take.sticks), 3), 200, np.uint8)
    take.labels = list(take.points.labels)
    take.check()
    return take


def take_arrays(take: Take) -> list[np.ndarray]:
    """Every array of the take that the file stores (the reference for the size target)."""
    arrays = [take.R, take.t] + [getattr(take, name) for name in POINT_ARRAYS]
    for det in take.detections:
        arrays += [det.frame_ptr, det.detected] + [getattr(det, k) for k in DETECTION_FIELDS]
    pts = take.points
    arrays += [pts.ids, pts.kind, pts.brim_index, pts.colour, take.sticks, take.stick_colours]
    return arrays


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--points", type=int, default=160)
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    take = make_tracked_take(args.frames, args.points, args.cameras)
    arrays = take_arrays(take)
    raw = sum(a.nbytes for a in arrays)
    t0 = time.perf_counter()
    ref = sum(len(zlib.compress(np.ascontiguousarray(a).tobytes(), 1)) for a in arrays)
    t_zlib = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.cara"
        save_s, load_s = float("inf"), float("inf")
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            save_take(take, path)
            save_s = min(save_s, time.perf_counter() - t0)
        size = os.path.getsize(path)
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            res = load_take(path)
            load_s = min(load_s, time.perf_counter() - t0)
        back = res.take
        same = all(np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
                   for a, b in zip(take_arrays(take), take_arrays(back)))
    emit("cara", frames=args.frames, points=args.points, cameras=args.cameras,
         detections=int(sum(len(d) for d in take.detections)),
         save_s=round(save_s, 3), load_s=round(load_s, 3),
         raw_mb=round(raw / 1e6, 1), zlib1_mb=round(ref / 1e6, 1), file_mb=round(size / 1e6, 1),
         size_ratio=round(size / ref, 3), zlib1_single_thread_s=round(t_zlib, 2), round_trip_exact=same,
         targets={"save_s": 2.0, "load_s": 2.0, "size_ratio": 1.5})


if __name__ == "__main__":
    main()
