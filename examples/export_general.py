#!/usr/bin/env python3
"""Query a ``.cara`` file for point data, and plot the 2D track data.

Prints a table of the take's points (name, label, face or brim, frames with 3D data by
reconstruction type, 2D observations per camera) and draws every point's 2D track in every
camera into one PNG image: one panel per camera, over the camera's first frame when its
``.pico`` file can be found, a track line per point in the point's colour (broken where the
point is not tracked), its name at the first tracked position.

(The original script used PyLab; this one draws with OpenCV, which CaraPost already uses.)

Example::

    python export_general.py Example.cara -o Example_tracks.png
    python export_general.py Example.cara --cameras 0,1 --points Nose_Tip,Forehead_L
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

import carapost.api as cp


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cara", type=Path, help=".cara project")
    p.add_argument("-o", "--output", type=Path, help="output PNG (default NAME_tracks.png next to the .cara)")
    p.add_argument("--cameras", help="comma-separated cameras to plot (default all)")
    p.add_argument("--points", help="comma-separated point names to plot (default all)")
    p.add_argument("--width", type=int, default=640, help="width of one camera panel in pixels (default 640)")
    p.add_argument("--no-image", action="store_true", help="plot on a grey background, not the first frame")
    return p.parse_args(argv)


def print_points(exp: cp.CaraExport) -> None:
    recon = exp.reconstruction                                   # (F, P)
    seen = np.isfinite(exp.observations[..., 0]).any(0)          # (P, C) ever observed
    obs = np.isfinite(exp.observations[..., 0]).sum(0)           # (P, C) frames observed
    print(f"{exp.name}: {exp.n_points} points, {exp.n_frames} frames, {exp.n_cameras} cameras, {exp.frame_rate:g} Hz")
    print(f"{'point':<16s} {'label':<14s} {'kind':<5s} {'multi':>6s} {'single':>6s} {'interp':>6s}  2D frames per camera")
    for info in exp.points():
        r = recon[:, info.index]
        counts = [int((r == k).sum()) for k in (cp.Recon.MULTI_VIEW, cp.Recon.SINGLE_SENSOR, cp.Recon.INTERPOLATED)]
        per_cam = " ".join(str(int(n)) if s else "-" for n, s in zip(obs[info.index], seen[info.index]))
        print(f"{info.name:<16s} {info.label or '-':<14s} {info.kind:<5s} {counts[0]:>6d} {counts[1]:>6d} "
              f"{counts[2]:>6d}  {per_cam}")


def background(exp: cp.CaraExport, camera: int, size: tuple[int, int], use_image: bool) -> np.ndarray:
    """The camera's first frame (dimmed, BGR) at the panel size, or a grey panel."""
    w, h = size
    path = exp.source_path(camera) if use_image else None
    if path is not None and path.suffix.lower() == ".pico":
        try:
            with cp.Pico(path) as pico:
                img = pico.frame(min(exp.cameras[camera].frame_offset, pico.n_frames - 1) if pico.n_frames else 0)
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            return cv2.cvtColor((img * 0.6).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        except (ValueError, IndexError):
            pass
    return np.full((h, w, 3), 60, np.uint8)


def draw_camera(exp: cp.CaraExport, camera: int, points: list[int], width: int, use_image: bool) -> np.ndarray:
    sw, sh = exp.cameras[camera].image_size
    if not (sw and sh):
        sw, sh = exp.intrinsics(camera).sensor_size
    scale = width / sw
    panel = background(exp, camera, (width, max(1, round(sh * scale))), use_image)
    tracks = exp.tracks_2d(camera)                                    # (F, P, 2) raw px
    colours = exp.point_colours[:, ::-1]                              # RGB -> BGR
    names = exp.point_names
    for p in points:
        xy = tracks[:, p].astype(float) * scale
        ok = np.isfinite(xy).all(-1)
        if not ok.any():
            continue
        # Split the track into runs of consecutive tracked frames (a gap breaks the line).
        breaks = np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1
        runs = [seg for seg, good in zip(np.split(xy, breaks), np.split(ok, breaks)) if good[0]]
        colour = tuple(int(v) for v in colours[p])
        pts = [np.round(r * 16).astype(np.int32).reshape(-1, 1, 2) for r in runs]   # 4 fractional bits
        cv2.polylines(panel, pts, False, colour, 1, cv2.LINE_AA, shift=4)
        x0, y0 = xy[np.argmax(ok)]
        cv2.circle(panel, (int(round(x0)), int(round(y0))), 2, colour, -1, cv2.LINE_AA)
        cv2.putText(panel, names[p], (int(x0) + 3, int(y0) - 3), cv2.FONT_HERSHEY_PLAIN, 0.7, colour, 1, cv2.LINE_AA)
    cv2.putText(panel, f"camera {camera}: {exp.cameras[camera].name}", (6, 16), cv2.FONT_HERSHEY_PLAIN, 1.0,
                (255, 255, 255), 1, cv2.LINE_AA)
    return panel


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        exp = cp.CaraExport(args.cara)
        if exp.n_cameras == 0:
            raise ValueError(f"{args.cara}: the take has no cameras (no 2D data)")
        cams = list(range(exp.n_cameras))
        if args.cameras:
            cams = [int(c) for c in args.cameras.split(",") if c.strip()]
            bad = [c for c in cams if not 0 <= c < exp.n_cameras]
            if bad:
                raise ValueError(f"camera(s) {bad} do not exist (the take has {exp.n_cameras})")
        points = list(range(exp.n_points))
        if args.points:
            try:
                points = [exp.point_index(n.strip()) for n in args.points.split(",") if n.strip()]
            except KeyError as exc:
                raise ValueError(f"{args.cara}: {exc.args[0]}") from None
        if args.width < 16:
            raise ValueError(f"--width must be at least 16 pixels, got {args.width}")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print_points(exp)
    panels = [draw_camera(exp, c, points, args.width, not args.no_image) for c in cams]
    h = max(p.shape[0] for p in panels)
    panels = [np.pad(p, ((0, h - p.shape[0]), (0, 0), (0, 0))) for p in panels]
    cols = 2 if len(panels) > 1 else 1
    panels += [np.zeros_like(panels[0])] * (-len(panels) % cols)
    grid = np.vstack([np.hstack(panels[i:i + cols]) for i in range(0, len(panels), cols)])
    out = args.output or args.cara.with_name(f"{args.cara.stem}_tracks.png")
    ok, buf = cv2.imencode(".png", grid)
    try:
        if not ok:
            raise OSError("PNG encoding failed")
        out.write_bytes(buf.tobytes())
    except OSError as exc:
        print(f"error: {out}: cannot write ({exc})", file=sys.stderr)
        return 1
    print(f"wrote {out} ({grid.shape[1]}x{grid.shape[0]}, {len(points)} points, cameras {cams})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
