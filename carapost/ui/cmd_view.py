"""View menu commands: navigation, selection helpers, ranges, display toggles."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from carapost.model.take import PointKind
from carapost.ops import settings as settings_ops

from . import queries
from .adapters import ops

if TYPE_CHECKING:  # pragma: no cover
    from .main_window import MainWindow

log = logging.getLogger("carapost")


def _valid(w: "MainWindow") -> np.ndarray:
    take = w.doc.take
    xyz = take.xyz_stabilized if w.doc.show_stabilized else take.xyz
    return np.isfinite(xyz).all(-1)


def floating_workspace(w: "MainWindow") -> None:
    w.new_floating_workspace()


def show_brim_svg(w: "MainWindow") -> None:
    from carapost.io.brim import brim_svg_text

    brim = w.doc.take.brim
    if brim is None:
        raise ValueError("Show Calibration Brim SVG: no calibration brim (import one or initialize a default brim)")
    w.show_svg(brim.svg or brim_svg_text(brim), f"Calibration Brim {brim.name}")


def full_screen(w: "MainWindow") -> None:
    w.toggle_full_screen()


def toggle_docks(w: "MainWindow") -> None:
    w.toggle_docks()


def blob_preview(w: "MainWindow") -> None:
    w.doc.set_display("blob_preview", not w.doc.blob_preview)


def show_stabilized(w: "MainWindow") -> None:
    w.doc.set_display("show_stabilized", not w.doc.show_stabilized)


def lock_to_point(w: "MainWindow") -> None:
    w.doc.set_display("lock_to_point", not w.doc.lock_to_point)


def go_to_frame(w: "MainWindow") -> None:
    doc = w.doc
    f = w.prompts.get_int("Go To Frame", "Frame:", doc.frame, 0, doc.take.n_frames - 1)
    if f is not None:
        doc.set_frame(f)


def start_frame(w: "MainWindow") -> None:
    w.doc.set_frame(0)


def end_frame(w: "MainWindow") -> None:
    w.doc.set_frame(w.doc.take.n_frames - 1)


def play(w: "MainWindow") -> None:
    w.timebar.toggle_play()


def next_frame(w: "MainWindow") -> None:
    w.doc.set_frame(w.doc.frame + 1)


def prev_frame(w: "MainWindow") -> None:
    w.doc.set_frame(w.doc.frame - 1)


def _key_step(w: "MainWindow", forward: bool) -> None:
    doc = w.doc
    target = ops("target")
    fn = target.next_keyframe if forward else target.prev_keyframe
    doc.set_frame(fn(doc.take, doc.selected_columns(), doc.frame))


def next_key(w: "MainWindow") -> None:
    _key_step(w, True)


def prev_key(w: "MainWindow") -> None:
    _key_step(w, False)


def select_point(w: "MainWindow") -> None:
    """Select Point (Ctrl+P): by id, label or displayed name."""
    take = w.doc.take
    text = w.prompts.get_text("Select Point", "Point id or label:")
    if not text:
        return
    text = text.strip()
    names = take.points.names()
    if text.lstrip("-").isdigit() and np.any(take.points.ids == int(text)):
        w.doc.select([int(text)])
    elif text in names or text in take.points.labels:
        col = names.index(text) if text in names else take.points.labels.index(text)
        w.doc.select([int(take.points.ids[col])])
    else:
        raise ValueError(f"Select Point: no point with id or label {text!r}")


def point_information(w: "MainWindow") -> None:
    cols = w.doc.selected_columns()
    if len(cols) != 1:
        raise ValueError("Get Point Information: select exactly one point")
    info = settings_ops.point_information(w.doc.take, cols[0], w.doc.frame)
    lines = [f"{k}: {v}" for k, v in info.items()]
    for line in lines:
        log.info("Point information: %s", line)
    w.prompts.info("Point Information", "\n".join(lines))


def _cams(w: "MainWindow", what: str) -> list[int]:
    cams = w.doc.target_cameras()
    if not cams:
        raise ValueError(f"{what}: Shift+click a camera view or select cameras in the Selection pane")
    return cams


def rotate_cw(w: "MainWindow") -> None:
    w.apply(settings_ops.rotate_sensors(w.doc.take, _cams(w, "Rotate Selected Sensors"), clockwise=True))


def rotate_ccw(w: "MainWindow") -> None:
    w.apply(settings_ops.rotate_sensors(w.doc.take, _cams(w, "Rotate Selected Sensors"), clockwise=False))


def fewest_gaps(w: "MainWindow") -> None:
    take = w.doc.take
    col = queries.point_with_fewest_gaps(_valid(w), np.flatnonzero(take.points.kind == PointKind.FACE))
    if col < 0:
        log.info("Select Point With Fewest Gaps: no point has a gap")
        return
    runs, frames = queries.gap_counts(_valid(w)[:, [col]])
    w.doc.select([int(take.points.ids[col])])
    log.info("Selected %s: %d gap(s), %d frame(s) missing", take.points.name(col), runs[0], frames[0])


def next_gap(w: "MainWindow") -> None:
    cols = w.doc.selected_columns()
    if len(cols) != 1:
        raise ValueError("Go To Next Gap of Selected Point: select exactly one point")
    f = queries.next_gap_frame(_valid(w)[:, cols[0]], w.doc.frame)
    if f < 0:
        log.info("%s has no gaps", w.doc.take.points.name(cols[0]))
    else:
        w.doc.set_frame(f)


def distance(w: "MainWindow") -> None:
    cols = w.doc.selected_columns()
    if len(cols) != 2:
        raise ValueError("Distance Between Two Points: select exactly two points")
    take = w.doc.take
    d = settings_ops.distance_between_points(take, cols[0], cols[1], w.doc.frame)
    log.info("Distance %s - %s in frame %d: %.3f mm", take.points.name(cols[0]), take.points.name(cols[1]),
             w.doc.frame, d)


def range_start(w: "MainWindow") -> None:
    take, f = w.doc.take, w.doc.frame
    w.apply(settings_ops.set_active_range(take, f, max(f, take.active_range[1])))


def range_end(w: "MainWindow") -> None:
    take, f = w.doc.take, w.doc.frame
    w.apply(settings_ops.set_active_range(take, min(f, take.active_range[0]), f))


def range_reset(w: "MainWindow") -> None:
    take = w.doc.take
    w.apply(settings_ops.set_active_range(take, 0, take.n_frames - 1))


def view_range(w: "MainWindow") -> None:
    take = w.doc.take
    w.apply(settings_ops.set_view_range(take, *take.active_range))


def view_range_reset(w: "MainWindow") -> None:
    take = w.doc.take
    w.apply(settings_ops.set_view_range(take, 0, take.n_frames - 1))


def center_selection(w: "MainWindow") -> None:
    for v in w.camera_views():
        v.center_selection()


def frame_selection(w: "MainWindow") -> None:
    for v in w.camera_views():
        v.frame_selection()


def layout_1(w: "MainWindow") -> None:
    w.workspace.set_layout(1)


def layout_2(w: "MainWindow") -> None:
    w.workspace.set_layout(2)


def layout_4(w: "MainWindow") -> None:
    w.workspace.set_layout(4)
