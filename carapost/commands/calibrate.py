"""``carapost calibrate``: camera calibration from target images, written as ``.xcp``."""

from __future__ import annotations

import argparse
import glob
from pathlib import Path
from typing import Any

from .common import check_outputs
from .progress import progress_bar

__all__ = ["cmd_calibrate", "add_parsers"]


def _expand(pattern: str) -> list[str]:
    p = Path(pattern)
    if p.is_dir():
        files = sorted(str(f) for f in p.iterdir() if f.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp"))
    else:
        files = sorted(glob.glob(pattern))
    if not files:
        raise ValueError(f"{pattern}: no images found")
    return files


def cmd_calibrate(args: argparse.Namespace) -> dict[str, Any]:
    from carapost.ops.calibrate import calibrate_cameras_to_file, parse_target

    spec = parse_target(args.target)
    check_outputs(args.out)
    sets = [_expand(p) for p in args.camera]
    with progress_bar("calibrate", unit="image") as prog:
        calib, rig = calibrate_cameras_to_file(sets, spec, args.out, extrinsics=not args.no_extrinsics, progress=prog)
    cams = []
    for c, cam in enumerate(calib.cameras):
        res = rig.intrinsic_results[c]
        i = cam.intrinsics
        cams.append({"name": cam.name, "images": len(sets[c]), "views_used": int(len(res.views)),
                     "focal_length_px": i.focal_length, "principal_point": list(i.principal_point),
                     "radial": list(i.radial), "rms_px": float(res.rms)})
        print(f"  {cam.name}: f={i.focal_length:.2f} px  pp=({i.principal_point[0]:.1f}, {i.principal_point[1]:.1f})"
              f"  rms {res.rms:.3f} px  ({len(res.views)} of {len(sets[c])} images)")
    if rig.extrinsics is not None:
        print(f"  extrinsics: rms {rig.extrinsics.rms:.3f} px")
    print(f"carapost calibrate: wrote {args.out}")
    return {"cameras": cams, "output": str(args.out),
            "extrinsics_rms_px": float(rig.extrinsics.rms) if rig.extrinsics is not None else None}


def add_parsers(sub: Any) -> dict[str, Any]:
    p = sub.add_parser("calibrate", help="calibrate cameras from checkerboard / dot-grid images (writes .xcp)",
                       description="Intrinsics per camera from its target images; extrinsics from synchronised "
                                   "shots (image k of every camera taken at the same moment).")
    p.add_argument("--target", required=True, help="kind:COLSxROWS:spacing_mm, e.g. checkerboard:4x7:60 "
                                                   "(inner corners), circles:4x11:20, asymmetric_circles:4x11:20")
    p.add_argument("--camera", action="append", required=True,
                   help="images of one camera (folder or glob); repeat once per camera in channel order")
    p.add_argument("--out", required=True, type=Path, help="output .xcp or .toml")
    p.add_argument("--no-extrinsics", action="store_true", help="intrinsics only (images not synchronised)")
    return {"calibrate": cmd_calibrate}
