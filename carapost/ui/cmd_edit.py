"""Edit menu commands that need more than one operation call (dialogs, selections, sequences)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from carapost.ops import detect as detect_ops
from carapost.ops import labels as label_ops
from carapost.ops import points as point_ops
from carapost.ops import settings as settings_ops

if TYPE_CHECKING:  # pragma: no cover
    from .main_window import MainWindow

log = logging.getLogger("carapost")


def _one_point(w: "MainWindow", what: str) -> int:
    cols = w.doc.selected_columns()
    if len(cols) != 1:
        raise ValueError(f"{what}: select exactly one point")
    return cols[0]


def _cameras(w: "MainWindow", what: str) -> list[int]:
    cams = w.doc.target_cameras()
    if not cams:
        raise ValueError(f"{what}: click in a camera view or select cameras in the Selection pane")
    return cams


def clear_history(w: "MainWindow") -> None:
    w.doc.clear_history()
    log.info("History cleared")


def create_points(w: "MainWindow") -> None:
    doc = w.doc
    first = doc.take.next_point_id
    if w.apply(point_ops.create_points_from_detections(doc.take, doc.sel_detections)):
        doc.select(range(first, doc.take.next_point_id))


def delete_selected(w: "MainWindow") -> None:
    """Delete Selected (Ctrl+D): selected detections first, then the selected points."""
    doc = w.doc
    if not doc.sel_points and not doc.sel_detections:
        raise ValueError("Delete Selected: nothing is selected")
    steps = []
    if doc.sel_detections:
        dets = list(doc.sel_detections)
        steps.append(lambda: point_ops.delete_detections(doc.take, dets))
    if doc.sel_points:
        ids = list(doc.sel_points)
        steps.append(lambda: point_ops.delete_points(doc.take, _columns_of(doc.take, ids)))
    w.apply_sequence("Delete Selected", steps)
    doc.clear_selection()


def _columns_of(take, ids):  # type: ignore[no-untyped-def]
    return [int(np.flatnonzero(take.points.ids == i)[0]) for i in ids if np.any(take.points.ids == i)]


def split(w: "MainWindow") -> None:
    col = _one_point(w, "Split Selected Point")
    w.apply(point_ops.split_point(w.doc.take, col, w.doc.frame))


def merge(w: "MainWindow") -> None:
    """Merge (M): selected points and/or detections become one point (then selected)."""
    doc = w.doc
    cols = doc.selected_columns()
    first = doc.take.next_point_id
    target = int(doc.take.points.ids[cols[0]]) if cols else None
    if w.apply(point_ops.merge(doc.take, cols, doc.sel_detections, frame=doc.frame)):
        doc.select([target] if target is not None else range(first, doc.take.next_point_id))


def clear_frame(w: "MainWindow") -> None:
    doc = w.doc
    w.apply(point_ops.clear_points(doc.take, doc.selected_columns(), [doc.frame],
                                   text="Clear Selected [Current Frame]"))


def clear_range(w: "MainWindow") -> None:
    doc = w.doc
    a, b = doc.take.active_range
    w.apply(point_ops.clear_points(doc.take, doc.selected_columns(), np.arange(a, b + 1),
                                   text="Clear Selected [Active Range]"))


def detach_frame(w: "MainWindow") -> None:
    doc = w.doc
    what = "Detach Detections [Current Frame]"
    w.apply(point_ops.clear_points(doc.take, doc.selected_columns(), [doc.frame], cameras=_cameras(w, what), text=what))


def detach_range(w: "MainWindow") -> None:
    doc = w.doc
    what = "Detach Detections [Active Range]"
    a, b = doc.take.active_range
    w.apply(point_ops.clear_points(doc.take, doc.selected_columns(), np.arange(a, b + 1), cameras=_cameras(w, what),
                                   text=what))


def relocate_files(w: "MainWindow") -> None:
    from .dialogs import RelocateFilesDialog

    RelocateFilesDialog(w).exec()


def increment_offset(w: "MainWindow") -> None:
    cams = _cameras(w, "Increment Image Sequence Offset")
    w.apply(settings_ops.increment_image_sequence_offset(w.doc.take, cams))


def add_target_track(w: "MainWindow") -> None:
    w.set_point_edit_mode("Add Target Track")


def edit_target_track(w: "MainWindow") -> None:
    _one_point(w, "Edit Target Track")
    w.set_point_edit_mode("Edit Target Track")


def stop_point_edit(w: "MainWindow") -> None:
    w.set_point_edit_mode("")


def remove_unused(w: "MainWindow") -> None:
    w.apply(detect_ops.remove_unused_detections(w.doc.take))


def remove_interpolated(w: "MainWindow") -> None:
    w.apply(point_ops.remove_interpolated(w.doc.take, w.doc.selected_columns()))


def rename(w: "MainWindow") -> None:
    """Rename Point (Ctrl+R)."""
    col = _one_point(w, "Rename Point")
    take = w.doc.take
    label = w.prompts.get_text("Rename Point", f"Label of {take.points.name(col)}:", take.points.labels[col])
    if label is not None:
        w.apply(label_ops.assign_label(take, col, label.strip()))


def clear_labels(w: "MainWindow") -> None:
    w.apply(label_ops.clear_all_labels(w.doc.take))


def delete_labels(w: "MainWindow") -> None:
    names = w.selected_labels()
    if not names:
        raise ValueError("Delete Selected Labels: select labels in the Labelling pane")
    w.apply(label_ops.delete_labels(w.doc.take, names))


def unlabel(w: "MainWindow") -> None:
    cols = w.doc.selected_columns()
    if not cols:
        raise ValueError("Unlabel Selected Points: select points first")
    w.apply(label_ops.unlabel_points(w.doc.take, cols))


def create_stick(w: "MainWindow") -> None:
    cols = w.doc.selected_columns()
    if len(cols) != 2:
        raise ValueError("Create Stick: select exactly two points")
    w.apply(label_ops.create_stick(w.doc.take, cols[0], cols[1]))


def stick_mesh(w: "MainWindow") -> None:
    w.apply(label_ops.create_stick_mesh(w.doc.take, w.doc.frame))


def selected_sticks(w: "MainWindow") -> list[int]:
    """Sticks of the selection: those joining two selected points, or (one point selected)
    every stick touching it."""
    take = w.doc.take
    ids = np.asarray(w.doc.sel_points, np.int64)
    if len(take.sticks) == 0 or len(ids) == 0:
        return []
    inside = np.isin(take.sticks, ids)
    rows = inside.all(1) if len(ids) > 1 else inside.any(1)
    return np.flatnonzero(rows).tolist()


def stick_colour(w: "MainWindow") -> None:
    rows = selected_sticks(w)
    if not rows:
        raise ValueError("Edit Stick Color: select the points at both ends of the sticks")
    take = w.doc.take
    colour = w.prompts.get_colour("Edit Stick Color", tuple(int(v) for v in take.stick_colours[rows[0]]))
    if colour is not None:
        w.apply(label_ops.edit_stick_colour(take, rows, colour))


def read_blob_parameters(w: "MainWindow") -> None:
    session = w.doc.session
    meta = next((s.meta for s in session.sources if s is not None), None) if session else None
    w.apply(detect_ops.read_blob_parameters_from_pico(w.doc.take, meta.blob_parameters if meta else None))
