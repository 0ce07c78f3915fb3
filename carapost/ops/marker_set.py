"""Marker-set templates and swaps on a take: Save Template, Label From Template, Find / Repair Swaps."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from carapost.core.swaps import Relabel, SwapReport, detect_swaps
from carapost.core.template import MarkerTemplate, TemplateFit, label_from_template as fit_template
from carapost.core.template import template_from_frame
from carapost.io.marker_template import read_marker_template, write_marker_template
from carapost.model.take import POINT_ARRAYS, Take

from .change import ArrayPatch, AttributeChange, Change, Composite

__all__ = ["save_template", "label_from_template", "find_swaps", "repair_swaps"]


def save_template(take: Take, frame: int, path: str | os.PathLike) -> MarkerTemplate:
    """Save the labelled face points of ``frame`` (names, positions, sticks) as a marker-set template."""
    cols = np.array([c for c in take.face_points() if take.points.labels[c]], dtype=np.int64)
    if len(cols) < 3:
        raise ValueError("Save Template: label at least three face points first")
    ids = take.points.ids[cols]
    index = {int(i): k for k, i in enumerate(ids)}
    sticks = np.array([[index[a], index[b]] for a, b in take.sticks.tolist() if a in index and b in index],
                      np.int64).reshape(-1, 2)
    tpl = template_from_frame(take.xyz[frame, cols], [take.points.labels[c] for c in cols], sticks,
                              source=take.name or "take")
    write_marker_template(tpl, path)
    return tpl


def label_from_template(take: Take, frame: int, template: MarkerTemplate | str | os.PathLike, *,
                        scale: bool = True) -> tuple[Composite, TemplateFit]:
    """"Label From Template": name every face point with 3D data in ``frame``.

    A rigid (+ scale) and non-rigid fit of the template to the points, then an optimal
    assignment; the template's sticks join the take. The fit's report lists the points it could
    not label and the template markers not found.
    """
    tpl = template if isinstance(template, MarkerTemplate) else read_marker_template(template)
    cols = take.face_points()
    fit = fit_template(take.xyz[frame, cols], tpl, scale=scale)
    labels = list(take.points.labels)
    names = set(tpl.names)
    for c in cols:  # template names move to the points the fit gives them
        if labels[c] in names:
            labels[c] = ""
    for j, m in enumerate(fit.labels):
        if m >= 0:
            labels[cols[j]] = tpl.names[m]
    pts = take.points.copy()
    pts.labels = labels
    changes: list[Change] = [AttributeChange.capture(take, "points", pts)]
    new_labels = [n for n in tpl.names if n not in take.labels]
    if new_labels:
        changes.append(AttributeChange.capture(take, "labels", take.labels + new_labels))
    col_of = {tpl.names[m]: int(cols[j]) for j, m in enumerate(fit.labels) if m >= 0}
    new_sticks = []
    existing = {tuple(sorted(s)) for s in take.sticks.tolist()}
    for a, b in np.asarray(tpl.sticks).tolist():
        na, nb = tpl.names[a], tpl.names[b]
        if na in col_of and nb in col_of:
            pair = tuple(sorted((int(take.points.ids[col_of[na]]), int(take.points.ids[col_of[nb]]))))
            if pair not in existing:
                new_sticks.append(pair)
                existing.add(pair)
    if new_sticks:
        changes.append(AttributeChange.capture(take, "sticks", np.vstack([take.sticks, np.array(new_sticks)])))
        changes.append(AttributeChange.capture(take, "stick_colours", np.vstack(
            [take.stick_colours, np.tile(np.array([[200, 200, 200]], np.uint8), (len(new_sticks), 1))])))
    n = int((fit.labels >= 0).sum())
    return Composite(changes, f"Label From Template: {n} labelled, {len(fit.unlabelled)} not labelled, "
                              f"{len(fit.missing)} template markers missing"), fit


def find_swaps(take: Take, *, points: Sequence[int] | None = None, threshold: float = 8.0) -> SwapReport:
    """Swap detection: frames where a marker jumps inconsistently with its neighbours, worst first."""
    cols = take.face_points() if points is None else np.asarray(points, np.int64)
    return detect_swaps(take.xyz[:, cols], threshold=threshold)


def repair_swaps(take: Take, relabels: Sequence[Relabel], *, points: Sequence[int] | None = None) -> Composite:
    """Apply swap repairs: within each relabel's frames, point ``m`` takes the data (3D, 2D
    observations, reconstruction type) of point ``perm[m]``."""
    cols = take.face_points() if points is None else np.asarray(points, np.int64)
    if not relabels:
        return Composite([], "Repair Swaps: nothing to repair")
    lo = min(r.start for r in relabels)
    hi = max(r.end for r in relabels)
    frames = np.arange(lo, hi)
    idx = (frames[:, None], cols[None, :])
    changes: list[Change] = []
    for name in POINT_ARRAYS:
        arr = getattr(take, name)[idx].copy()
        for r in relabels:
            sl = slice(r.start - lo, r.end - lo)
            arr[sl] = arr[sl][:, np.asarray(r.perm)]
        changes.append(ArrayPatch.capture(take, name, idx, arr))
    moved = sorted({cols[m] for r in relabels for m in r.markers})
    return Composite(changes, f"Repair Swaps: {len(relabels)} range(s), points "
                              f"{', '.join(take.points.name(c) for c in moved[:8])}{' ...' if len(moved) > 8 else ''}")
