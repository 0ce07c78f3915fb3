"""Labels and sticks: the Labelling pane and the label/stick commands of the Edit menu."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from scipy.spatial import Delaunay

from carapost.io.labels import merge_labels, read_label_file
from carapost.model.take import Take

from .change import AttributeChange, Change, Composite

__all__ = [
    "import_labels_from_text",
    "import_labels_from_cara",
    "assign_label",
    "unlabel_points",
    "clear_all_labels",
    "delete_labels",
    "rename_label",
    "create_stick",
    "create_stick_mesh",
    "edit_stick_colour",
    "delete_sticks",
]

DEFAULT_STICK_COLOUR = (200, 200, 200)


def _labels_change(take: Take, labels: list[str], text: str) -> AttributeChange:
    return AttributeChange.capture(take, "labels", labels, text)


def import_labels_from_text(take: Take, path: str | os.PathLike) -> AttributeChange:
    """"Import Labels From Text File": adds to the existing labels (duplicates get " - Copy")."""
    new = read_label_file(path)
    return _labels_change(take, merge_labels(take.labels, new), f"Import {len(new)} labels from {os.path.basename(path)}")


def import_labels_from_cara(take: Take, path: str | os.PathLike) -> AttributeChange:
    """"Import Labels From Cara File": the label list of another project (same marker set)."""
    from carapost.io.cara import load_take

    other = load_take(path).take
    names = list(other.labels) or [lab for lab in other.points.labels if lab]
    return _labels_change(take, merge_labels(take.labels, names),
                          f"Import {len(names)} labels from {os.path.basename(path)}")


def _points_change(take: Take, labels: list[str], text: str) -> AttributeChange:
    pts = take.points.copy()
    pts.labels = labels
    return AttributeChange.capture(take, "points", pts, text)


def assign_label(take: Take, point: int, label: str) -> Composite:
    """Give a point a label ("Rename Point (Ctrl+R)" or assigning from the Labelling pane).

    A label names one point: another point holding it loses it. The label joins the label
    list if it is new. An empty label unlabels the point.

    Raises
    ------
    ValueError
        For a missing point or a label containing whitespace.
    """
    if not 0 <= point < take.n_points:
        raise ValueError(f"point {point} does not exist")
    label = label.strip()
    if any(ch.isspace() for ch in label):
        raise ValueError(f"label {label!r} must not contain spaces")
    labels = list(take.points.labels)
    if label:
        labels = ["" if lab == label else lab for lab in labels]
    labels[point] = label
    changes: list[Change] = [_points_change(take, labels, f"Label {take.points.name(point)} as {label or '(none)'}")]
    if label and label not in take.labels:
        changes.append(_labels_change(take, take.labels + [label], ""))
    return Composite(changes, changes[0].text)


def unlabel_points(take: Take, points: Sequence[int]) -> AttributeChange:
    """"Unlabel Selected Points (Ctrl+U)"."""
    labels = list(take.points.labels)
    for p in points:
        labels[int(p)] = ""
    return _points_change(take, labels, f"Unlabel {len(points)} point(s)")


def clear_all_labels(take: Take) -> Composite:
    """"Clear All Labels": empty the label list and detach every label from its point."""
    return Composite([_labels_change(take, [], "Clear All Labels"),
                      _points_change(take, [""] * take.n_points, "")], "Clear All Labels")


def delete_labels(take: Take, names: Sequence[str]) -> Composite:
    """"Delete Selected Labels": remove labels from the list and from the points holding them."""
    gone = set(names)
    return Composite([_labels_change(take, [lab for lab in take.labels if lab not in gone], ""),
                      _points_change(take, ["" if lab in gone else lab for lab in take.points.labels], "")],
                     f"Delete {len(gone)} label(s)")


def rename_label(take: Take, old: str, new: str) -> Composite:
    """Rename a label of the Labelling pane's list (and on the point holding it).

    Raises
    ------
    ValueError
        If ``old`` is not a label, ``new`` is empty, contains white space or already exists.
    """
    new = new.strip()
    if old not in take.labels:
        raise ValueError(f"Rename label: there is no label {old!r}")
    if not new or any(ch.isspace() for ch in new):
        raise ValueError(f"Rename label: {new!r} is not a valid label (no spaces, not empty)")
    if new in take.labels:
        raise ValueError(f"Rename label: {new!r} already exists")
    labels = [new if lab == old else lab for lab in take.labels]
    pts = take.points.copy()
    pts.labels = [new if lab == old else lab for lab in pts.labels]
    return Composite([AttributeChange.capture(take, "labels", labels), AttributeChange.capture(take, "points", pts)],
                     f"Rename label {old} to {new}")


def _sticks_change(take: Take, sticks: np.ndarray, colours: np.ndarray, text: str) -> Composite:
    return Composite([AttributeChange.capture(take, "sticks", np.asarray(sticks, np.int64).reshape(-1, 2), text),
                      AttributeChange.capture(take, "stick_colours", np.asarray(colours, np.uint8).reshape(-1, 3), "")],
                     text)


def create_stick(take: Take, p1: int, p2: int, colour: Sequence[int] = DEFAULT_STICK_COLOUR) -> Composite:
    """"Create Stick from Selected Point (S)": a stick between two points (by column)."""
    if p1 == p2 or not (0 <= p1 < take.n_points and 0 <= p2 < take.n_points):
        raise ValueError("Create Stick: select exactly two different points")
    ids = sorted((int(take.points.ids[p1]), int(take.points.ids[p2])))
    existing = {tuple(sorted(s)) for s in take.sticks.tolist()}
    if tuple(ids) in existing:
        raise ValueError("Create Stick: these points are already joined")
    return _sticks_change(take, np.vstack([take.sticks, [ids]]), np.vstack([take.stick_colours, [colour]]),
                          f"Create stick {take.points.name(p1)} - {take.points.name(p2)}")


def create_stick_mesh(take: Take, frame: int, colour: Sequence[int] = DEFAULT_STICK_COLOUR,
                      max_edge_mm: float | None = None) -> Composite:
    """"Create Stick Mesh": a triangle mesh over the face points with 3D data in ``frame``.

    The points are projected onto their best-fit plane and Delaunay-triangulated; edges longer
    than ``max_edge_mm`` (default: 3x the median edge) are dropped so the mesh follows the face.
    """
    cols = take.face_points()
    cols = cols[np.isfinite(take.xyz[frame, cols]).all(-1)]
    if len(cols) < 3:
        raise ValueError("Create Stick Mesh: needs at least 3 face points with 3D data in the current frame")
    X = take.xyz[frame, cols]
    c = X - X.mean(0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    uv = c @ vt[:2].T
    tri = Delaunay(uv)
    e = np.concatenate([tri.simplices[:, [0, 1]], tri.simplices[:, [1, 2]], tri.simplices[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    length = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    limit = 3 * np.median(length) if max_edge_mm is None else max_edge_mm
    e = e[length <= limit]
    ids = take.points.ids[cols][e]
    existing = {tuple(sorted(s)) for s in take.sticks.tolist()}
    new = np.array([s for s in np.sort(ids, axis=1).tolist() if tuple(s) not in existing], np.int64).reshape(-1, 2)
    colours = np.tile(np.asarray(colour, np.uint8), (len(new), 1))
    return _sticks_change(take, np.vstack([take.sticks, new]), np.vstack([take.stick_colours, colours]),
                          f"Create Stick Mesh: {len(new)} sticks")


def edit_stick_colour(take: Take, sticks: Sequence[int], colour: Sequence[int]) -> Composite:
    """"Edit Stick Color" of the selected sticks (by row)."""
    colours = take.stick_colours.copy()
    colours[list(sticks)] = colour
    return _sticks_change(take, take.sticks, colours, f"Colour {len(sticks)} stick(s)")


def delete_sticks(take: Take, sticks: Sequence[int]) -> Composite:
    keep = np.ones(len(take.sticks), bool)
    keep[list(sticks)] = False
    return _sticks_change(take, take.sticks[keep], take.stick_colours[keep], f"Delete {len(sticks)} stick(s)")
