"""Camera calibration from checkerboards: accuracy on real images and on synthetic renders.

Real: the Pose2Sim demo's checkerboard images (4 portrait cameras, 1088 x 1920, 7 images
each, 4 x 7 inner corners, 60 mm squares) calibrated with ``calibrate_intrinsics`` and
compared with the Qualisys calibration shipped with them (``Calib.qca.txt``, read and
converted to our model by ``carapost.io.qca``). Per camera: focal length and principal point,
ours and Qualisys's, the differences (% of the focal length, % of the image width / height),
our RMS, the RMS of Qualisys's intrinsics on the same detections (poses re-fitted), the
leave-one-view-out spread of our principal point, and our one-sigma uncertainties.

Synthetic: 10 rendered views of a 9 x 6 board through a known distorting XCP camera (the
scene of ``tests/core/test_calibrate.py``): recovered focal length, principal point, k1 and
the worst ray error over the image.

Prints one JSON line. Needs the real data (``CARAPOST_REAL_DATA`` or ``shared/data/real``).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "core"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit  # noqa: E402
from conftest import real_data_dir  # noqa: E402
from test_calibrate import BOARD, CAM, ray_error_px, views_of_target  # noqa: E402

from carapost.core.calib_targets import TargetSpec, detect_target, render_target, target_points  # noqa: E402
from carapost.core.calibrate import calibrate_intrinsics, reprojection_check  # noqa: E402
from carapost.core.camera import project  # noqa: E402
from carapost.io.calibration import load_calibration  # noqa: E402


def real_cameras(root: Path) -> tuple[list[dict], float]:
    qualisys = load_calibration(root / "Calib.qca.txt")
    spec = TargetSpec("checkerboard", 4, 7, 60.0)
    out, det_times = [], []
    for c in range(4):
        files = sorted((root / "intrinsics" / f"int_cam0{c + 1}_img").glob("*.jpg"))
        views = []
        for f in files:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            t0 = time.perf_counter()
            views.append(detect_target(img, spec))
            det_times.append(time.perf_counter() - t0)
        w, h = img.shape[1], img.shape[0]
        t0 = time.perf_counter()
        res = calibrate_intrinsics(views, spec, (w, h))
        t_cal = time.perf_counter() - t0
        ours, q = res.intrinsics, qualisys.cameras[c].intrinsics
        used = [views[i] for i in res.views]
        q_rms, _ = reprojection_check(used, spec, q)
        loo = []
        for k in range(len(used)):
            r = calibrate_intrinsics([v for i, v in enumerate(used) if i != k], spec, (w, h),
                                     model=res.model, reject_factor=None, uncertainty=False)
            loo.append(r.intrinsics.principal_point)
        loo = np.array(loo)
        out.append({
            "camera": qualisys.cameras[c].name,
            "images": len(files),
            "found": int(sum(v is not None for v in views)),
            "used": int(len(res.views)),
            "rejected": [int(v) for v in res.rejected],
            "model": res.model,
            "f_ours": round(ours.focal_length, 2),
            "f_qualisys": round(q.focal_length, 2),
            "f_diff_pct": round(100 * (ours.focal_length / q.focal_length - 1), 3),
            "pp_ours": [round(v, 2) for v in ours.principal_point],
            "pp_qualisys": [round(v, 2) for v in q.principal_point],
            "pp_diff_pct_of_size": [round(100 * (ours.principal_point[0] - q.principal_point[0]) / w, 3),
                                    round(100 * (ours.principal_point[1] - q.principal_point[1]) / h, 3)],
            "radial_ours": [float(f"{k:.4g}") for k in ours.radial],
            "rms_ours_px": round(res.rms, 4),
            "rms_opencv_brown_px": round(res.opencv_rms, 4),
            "rms_qualisys_intrinsics_px": round(q_rms, 4),
            "pp_leave_one_out_range_px": [round(float(np.ptp(loo[:, 0])), 2), round(float(np.ptp(loo[:, 1])), 2)],
            "std_px": {k: round(v, 3) for k, v in res.std.items() if not k.startswith("k")},
            "calibrate_s": round(t_cal, 3),
        })
    return out, float(np.mean(det_times))


def synthetic() -> dict:
    poses = views_of_target(CAM, BOARD, 10, seed=1)
    views = [detect_target(render_target(BOARD, CAM, R, t, noise=2.0, seed=i), BOARD)
             for i, (R, t) in enumerate(poses)]
    X = target_points(BOARD)
    det = np.concatenate([np.linalg.norm(v - project(X, CAM, R, t), axis=1) for v, (R, t) in zip(views, poses)])
    res = calibrate_intrinsics(views, BOARD, CAM.sensor_size)
    fit = res.intrinsics
    gx, gy = np.meshgrid(np.linspace(0, CAM.sensor_size[0] - 1, 25), np.linspace(0, CAM.sensor_size[1] - 1, 25))
    return {
        "detection_rms_px": round(float(np.sqrt(np.mean(det ** 2))), 4),
        "f_err_pct": round(100 * (fit.focal_length / CAM.focal_length - 1), 4),
        "pp_err_px": [round(a - b, 3) for a, b in zip(fit.principal_point, CAM.principal_point)],
        "k1_err_pct": round(100 * (fit.radial[0] / CAM.radial[0] - 1), 3),
        "max_ray_err_px_over_image": round(float(ray_error_px(fit, CAM, np.c_[gx.ravel(), gy.ravel()]).max()), 3),
        "rms_px": round(res.rms, 4),
    }


def main() -> None:
    root = real_data_dir()
    real, det_s = ([], float("nan"))
    if root is not None:
        real, det_s = real_cameras(root / "pose2sim-demo" / "calibration")
    ok_f = all(abs(r["f_diff_pct"]) < 1 for r in real)
    ok_pp = all(abs(d) < 1 for r in real for d in r["pp_diff_pct_of_size"])
    emit("calibrate", real=real, detect_s_per_image=round(det_s, 3), focal_within_1pct=ok_f,
         principal_point_within_1pct=ok_pp, synthetic=synthetic())


if __name__ == "__main__":
    main()
