"""``carapost label``: label the markers of a C3D or CSV file (either labelling method).

:func:`label_file` reads the input (C3D via :mod:`carapost.io.c3d`, or seed 002's CSV layout
via :mod:`carapost.io.marker_csv`), decides the marker set and what is known (hints: the
labelled reference frame, or a template fitted to it; seed 002's frame mappings, fallback
frames, fully labelled and ignored markers), runs
:func:`~carapost.core.label_assign.label_assignment` (default) or
:func:`~carapost.core.label_nn.label_nearest`, writes the labelled trajectories (C3D or CSV by
the output's extension) and, optionally, seed 002's inspection plots every N frames.

The input's own labels are trusted only where said so: in the reference frame (unless a
template is given), in fallback frames and for fully labelled / ignored markers. Everywhere
else the points are relabelled, so swapped labels in the input are repaired; the report lists
where the output's labels differ from the input's.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from carapost import __version__
from carapost.core.label_hands import hand_model, hand_skeleton
from carapost.core.labelling import skeleton_from_sticks, trajectories_from_labels
from carapost.core.label_plot import render_markers
from carapost.core.template import MarkerTemplate, label_from_template
from carapost.io import c3d_binary as cb
from carapost.io.atomic import atomic_write_bytes
from carapost.io.c3d import read_c3d
from carapost.io.marker_csv import read_marker_csv, write_marker_csv
from carapost.io.marker_template import read_marker_template

__all__ = ["label_file", "MarkerData", "read_markers", "write_markers", "UNLABELLED_NAME"]

#: Names taken for unlabelled points (not markers) when ``marker_names`` is not given: seed 002
#: skips names starting with "Marker"; Vicon writes "*12", OptiTrack "Unlabeled 1036".
UNLABELLED_NAME = re.compile(r"^\s*(marker|unlabeled|unlabelled|\*)", re.IGNORECASE)
_RESIDUAL_SCALE = -0.01


@dataclass
class MarkerData:
    """Trajectories read from a C3D or CSV file (what :func:`label_file` needs of them)."""

    names: list[str]
    xyz: np.ndarray
    frame_rate: float
    frames: np.ndarray
    residual: np.ndarray | None = None
    first_line: str | None = None
    first_frame: int = 1


def read_markers(path: str | os.PathLike, *, units: str | None = None) -> MarkerData:
    """Read marker trajectories from ``.c3d`` or ``.csv`` (mm).

    Raises
    ------
    ValueError
        Unknown extension or unreadable file (the readers' errors, which name the file).
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".c3d":
        d = read_c3d(p)
        mi = d.marker_indices()
        return MarkerData([d.labels[i] for i in mi], d.xyz[:, mi], d.frame_rate,
                          np.arange(d.n_frames) + d.first_frame, d.residual[:, mi], None, d.first_frame)
    if ext == ".csv":
        c = read_marker_csv(p, units=units)
        return MarkerData(c.names, c.xyz, c.frame_rate, c.frames, None, c.first_line,
                          int(c.frames[0]) if len(c.frames) else 0)
    raise ValueError(f"{p}: unknown marker file type {ext!r} (expected .c3d or .csv)")


def write_markers(path: str | os.PathLike, names: Sequence[str], xyz: np.ndarray, *, frame_rate: float,
                  frames: np.ndarray | None = None, residual: np.ndarray | None = None,
                  first_line: str | None = None) -> None:
    """Write trajectories (mm) to ``.c3d`` (Intel float, residual unit 0.01 mm; a sample without
    a known residual is written with the smallest non-zero one) or ``.csv``, atomically."""
    p = Path(path)
    x = np.asarray(xyz, np.float64)
    ext = p.suffix.lower()
    if ext == ".csv":
        write_marker_csv(p, names, x, frame_rate=frame_rate, frames=frames, first_line=first_line)
        return
    if ext != ".c3d":
        raise ValueError(f"{p}: unknown marker file type {ext!r} (expected .c3d or .csv)")
    if not p.parent.is_dir():
        raise cb.C3DError(f"{p}: cannot write, the folder {p.parent} does not exist")
    valid = np.isfinite(x).all(-1)
    res = np.ones(valid.shape) if residual is None else np.where(np.isfinite(residual), residual, 0.01)
    code = np.clip(np.round(res / abs(_RESIDUAL_SCALE)), 1, 255)
    fourth = np.where(valid, code, -1).astype(np.float32)
    xyz32 = np.where(valid[..., None], x, 0.0).astype(np.float32)
    labels = [n.strip() or f"M{i + 1}" for i, n in enumerate(names)]
    params: list[tuple[str, object, str]] = []
    for k, s in enumerate(range(0, max(len(labels), 1), 255)):
        params.append(("LABELS" if k == 0 else f"LABELS{k + 1}", labels[s:s + 255], "Point labels"))
        params.append(("DESCRIPTIONS" if k == 0 else f"DESCRIPTIONS{k + 1}", [""] * len(labels[s:s + 255]),
                       "Point descriptions"))
    params.append(("UNITS", "mm", "Units of the point coordinates"))
    first = int(frames[0]) if frames is not None and len(frames) else 1
    data = cb.encode_c3d(xyz=xyz32, fourth=fourth, frame_rate=float(frame_rate), first_frame=max(first, 1),
                         scale=_RESIDUAL_SCALE, point_groups={"POINT": params},
                         extra_groups=[("MANUFACTURER", "Writer", [("COMPANY", "CaraPost for Python", ""),
                                                                   ("SOFTWARE", "carapost label", ""),
                                                                   ("VERSION_LABEL", str(__version__), "")])])
    atomic_write_bytes(p, data)


def _marker_set(names: list[str], marker_names: Sequence[str] | None, template: MarkerTemplate | None,
                ignore: Sequence[str]) -> list[str]:
    if template is not None:
        out = list(template.names)
    elif marker_names:
        out = list(dict.fromkeys(marker_names))
    else:
        out = list(dict.fromkeys(n for n in names if n and not UNLABELLED_NAME.match(n)))
    out += [n for n in ignore if n not in out]
    if not out:
        raise ValueError("no marker names: the input has only unlabelled points; give marker_names or a template")
    return out


def label_file(in_path: str | os.PathLike, out_path: str | os.PathLike, *, method: str = "assignment",
               template: str | os.PathLike | MarkerTemplate | None = None,
               progress: Callable[[int, int], object] | None = None,
               marker_names: Sequence[str] | None = None, reference_frame: int | None = None,
               frame_mappings: Mapping[int, Mapping[str, str]] | None = None, fallback_frames: Sequence[int] = (),
               labeled_markers: Sequence[str] = (), ignore_markers: Sequence[str] = (),
               sticks: Sequence[tuple[str, str]] | None = None, use_skeleton: bool = True,
               hand_heuristics: bool = False, plot_every: int = 0, plot_dir: str | os.PathLike | None = None,
               keep_unlabelled: bool = True, units: str | None = None,
               options: Mapping[str, object] | None = None) -> dict:
    """Label the markers of a C3D or CSV file and write the result.

    Parameters
    ----------
    in_path, out_path : path-like
        ``.c3d`` or ``.csv`` (seed 002's layout) each; the output is replaced atomically.
    method : {"assignment", "nearest"}
        The default global-assignment labeller or seed 002's nearest-neighbour method.
    template : path or MarkerTemplate, optional
        A marker-set template (``.json``): the marker names come from it and the reference
        frame is labelled by fitting it (the input's labels are then not needed at all).
    progress : callable, optional
        ``progress(done, total)``; returning False stops early (what is labelled is written).
    marker_names : sequence of str, optional
        The markers to label (seed 002's ``marker_names``); default: the input's names that do
        not look unlabelled (see :data:`UNLABELLED_NAME`).
    reference_frame : int, optional
        0-based frame whose input labels are trusted (default: the first frame where every
        marker is present, else the one with the most).
    frame_mappings : {frame: {input name: marker name}}, optional
        Seed 002's ``frame_marker_names``: in that frame the point the input calls
        ``input name`` is ``marker name``.
    fallback_frames : sequence of int
        Frames whose input labels are all right.
    labeled_markers : sequence of str
        Markers whose input labels are right throughout.
    ignore_markers : sequence of str
        Markers left as they are in the input (reference or device markers).
    sticks : sequence of (str, str), optional
        Marker-name pairs: the nearest method's skeleton (parent, child). Default: the
        template's sticks, or the hand scheme's finger chains when the names follow it.
    use_skeleton : bool
        Nearest method: extrapolate missing markers with the skeleton.
    hand_heuristics : bool
        Nearest method: seed 002's hand heuristics (hand naming scheme only).
    plot_every : int
        Save an inspection plot every this many frames (and of the last frame); 0 for none.
    plot_dir : path-like, optional
        Where the plots go (default ``<output folder>/<output stem>_plots``).
    keep_unlabelled : bool
        Also write the points left unlabelled, packed into ``Unlabeled_<k>`` columns.
    units : str, optional
        CSV input: coordinate unit when line 1 does not say.
    options : mapping, optional
        Further keyword arguments of the labelling function (thresholds, parameters).

    Returns
    -------
    dict
        JSON-serialisable report: input, output, method, frames, markers, reference frame,
        labelled / unlabelled samples, the input-vs-output relabelling (``relabelled_samples``
        and up to 200 ``relabel_runs``: marker, input name, first and last frame), the
        labeller's own report, plot files and the time taken.

    Raises
    ------
    ValueError
        Unreadable input, unknown names in the options, nothing to label, a bad frame.
    """
    t_start = time.perf_counter()
    src = read_markers(in_path, units=units)
    F, P = src.xyz.shape[:2]
    if F == 0 or P == 0:
        raise ValueError(f"{in_path}: no marker data to label")
    tpl = read_marker_template(template) if isinstance(template, (str, os.PathLike)) else template
    names = _marker_set(src.names, marker_names, tpl, ignore_markers)
    index = {n: i for i, n in enumerate(names)}
    M = len(names)
    col_marker = np.array([index.get(n, -1) for n in src.names], np.int64)
    # a name used by several columns: only the first is that marker
    seen: set[int] = set()
    for j, m in enumerate(col_marker):
        if m >= 0 and m in seen:
            col_marker[j] = -1
        seen.add(int(m))
    pts = src.xyz
    valid = np.isfinite(pts).all(-1)
    named_valid = valid & (col_marker >= 0)[None]
    if reference_frame is None:
        counts = named_valid.sum(1) if tpl is None else valid.sum(1)
        full = np.flatnonzero(counts == counts.max())
        reference_frame = int(full[0])
    if not 0 <= reference_frame < F:
        raise ValueError(f"reference frame {reference_frame} is outside 0..{F - 1}")
    hints = np.full((F, P), -1, np.int32)
    ref_note = "input labels"
    if tpl is not None:
        fit = label_from_template(pts[reference_frame], tpl)
        hints[reference_frame] = np.where(valid[reference_frame], fit.labels, -1)
        ref_note = f"template ({len(fit.missing)} markers missing, {len(fit.unlabelled)} points unlabelled)"
    else:
        hints[reference_frame] = np.where(named_valid[reference_frame], col_marker, -1)
    for f in fallback_frames:
        if not 0 <= int(f) < F:
            raise ValueError(f"fallback frame {f} is outside 0..{F - 1}")
        hints[int(f)] = np.where(named_valid[int(f)], col_marker, -1)
    for f, mapping in (frame_mappings or {}).items():
        if not 0 <= int(f) < F:
            raise ValueError(f"frame mapping for frame {f} is outside 0..{F - 1}")
        for src_name, dst in mapping.items():
            if src_name not in src.names:
                raise ValueError(f"frame {f}: no input column named {src_name!r}")
            if dst not in index:
                raise ValueError(f"frame {f}: {dst!r} is not a marker name")
            j = src.names.index(src_name)
            if valid[int(f), j]:
                hints[int(f)][hints[int(f)] == index[dst]] = -1
                hints[int(f), j] = index[dst]
    fixed = list(labeled_markers) + list(ignore_markers)
    for n in fixed:
        if n not in index:
            raise ValueError(f"{n!r} is not a marker name")
        j = np.flatnonzero(col_marker == index[n])
        if j.size:
            col = valid[:, j[0]]
            hints[(hints == index[n]) & col[:, None]] = -1
            hints[:, j[0]] = np.where(col, index[n], hints[:, j[0]])
    ignore_idx = [index[n] for n in ignore_markers]
    opts = dict(options or {})
    if method == "assignment":
        from carapost.core.label_assign import label_assignment
        tpl_xyz = None
        if tpl is not None:
            tpl_xyz = np.full((M, 3), np.nan)
            tpl_xyz[:len(tpl)] = tpl.xyz
        res = label_assignment(pts, hints, M, template=tpl_xyz, ignore=ignore_idx,
                               progress=progress, **opts)  # type: ignore[arg-type]
    elif method == "nearest":
        from carapost.core.label_nn import label_nearest
        skel = None
        if use_skeleton:
            if sticks is not None:
                skel = skeleton_from_sticks(np.array([[index[a], index[b]] for a, b in sticks], np.int64), M)
            elif tpl is not None and len(tpl.sticks):
                skel = skeleton_from_sticks(tpl.sticks, M)
            elif hand_model(names) is not None:
                skel = hand_skeleton(names)
        res = label_nearest(pts, hints, M, names=names, skeleton=skel, ignore=ignore_idx,
                            hand_heuristics=hand_heuristics, progress=progress, **opts)  # type: ignore[arg-type]
    else:
        raise ValueError(f"unknown labelling method {method!r} (expected 'assignment' or 'nearest')")
    labels = res.labels
    out_xyz = trajectories_from_labels(pts, labels, M)
    out_res = None
    if src.residual is not None:
        out_res = np.full((F, M), np.nan)
        f_i, j_i = np.nonzero(labels >= 0)
        out_res[f_i, labels[f_i, j_i]] = src.residual[f_i, j_i]
    out_names = list(names)
    if keep_unlabelled:
        extra, extra_res = _pack_unlabelled(pts, labels, src.residual)
        if extra.shape[1]:
            out_xyz = np.concatenate([out_xyz, extra], axis=1)
            out_names += [f"Unlabeled_{k + 1}" for k in range(extra.shape[1])]
            if out_res is not None:
                out_res = np.concatenate([out_res, extra_res], axis=1)
    write_markers(out_path, out_names, out_xyz, frame_rate=src.frame_rate, frames=src.frames, residual=out_res,
                  first_line=src.first_line)

    # where the output differs from the input's labels
    lab_v = labels >= 0
    differs = lab_v & (col_marker[None, :] != labels)
    runs = _relabel_runs(differs, labels, src.names, names)
    report = {
        "input": str(in_path), "output": str(out_path), "method": method, "frames": F, "markers": M,
        "reference_frame": int(reference_frame), "reference": ref_note,
        "labelled_samples": int(lab_v.sum()), "unlabelled_points": int((valid & ~lab_v).sum()),
        "relabelled_samples": int(differs.sum()), "relabel_runs": runs[:200], "labeller": res.report,
    }
    if plot_every and plot_every > 0:
        report["plots"] = _save_plots(out_xyz[:, :M], names, labels, pts, col_marker, src.names, out_path, plot_dir,
                                      int(plot_every), None if tpl is None else tpl.sticks)
    report["seconds"] = round(time.perf_counter() - t_start, 3)
    return report


def _pack_unlabelled(pts: np.ndarray, labels: np.ndarray,
                     residual: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Unlabelled valid points of each frame packed into columns (F, K, 3) (+ residuals)."""
    F = pts.shape[0]
    un = np.isfinite(pts).all(-1) & (labels < 0)
    K = int(un.sum(1).max(initial=0))
    out = np.full((F, K, 3), np.nan)
    res = np.full((F, K), np.nan)
    if K:
        rank = np.cumsum(un, axis=1) - 1
        f, j = np.nonzero(un)
        out[f, rank[f, j]] = pts[f, j]
        if residual is not None:
            res[f, rank[f, j]] = residual[f, j]
    return out, res


def _relabel_runs(differs: np.ndarray, labels: np.ndarray, in_names: list[str], names: list[str]) -> list[dict]:
    """Runs of consecutive frames where a marker's point came from another input column."""
    f, j = np.nonzero(differs)
    if f.size == 0:
        return []
    m = labels[f, j]
    order = np.lexsort((f, j, m))
    f, j, m = f[order], j[order], m[order]
    brk = np.ones(len(f), bool)
    brk[1:] = (m[1:] != m[:-1]) | (j[1:] != j[:-1]) | (f[1:] != f[:-1] + 1)
    starts = np.flatnonzero(brk)
    ends = np.concatenate([starts[1:], [len(f)]]) - 1
    runs = [{"marker": names[int(m[a])], "input": in_names[int(j[a])], "first": int(f[a]), "last": int(f[b])}
            for a, b in zip(starts, ends)]
    runs.sort(key=lambda r: (-(r["last"] - r["first"]), r["first"]))
    return runs


def _save_plots(xyz: np.ndarray, names: list[str], labels: np.ndarray, pts: np.ndarray, col_marker: np.ndarray,
                in_names: list[str], out_path: str | os.PathLike, plot_dir: str | os.PathLike | None, every: int,
                sticks: np.ndarray | None) -> list[str]:
    out = Path(out_path)
    folder = Path(plot_dir) if plot_dir is not None else out.parent / f"{out.stem}_plots"
    folder.mkdir(parents=True, exist_ok=True)
    F = xyz.shape[0]
    ok = np.isfinite(xyz).all(-1)
    allp = xyz[ok]
    if allp.size:
        lo, hi = np.percentile(allp, 0.5, axis=0), np.percentile(allp, 99.5, axis=0)
        pad = 0.1 * np.maximum(hi - lo, 1.0)
        limits = np.stack([lo - pad, hi + pad], 1)
    else:
        limits = None
    frames = sorted(set(range(0, F, every)) | {F - 1})
    files = []
    for f in frames:
        hl = np.zeros(len(names), bool)
        notes = []
        for j in np.flatnonzero(labels[f] >= 0):
            m = int(labels[f, j])
            if col_marker[j] != m:
                hl[m] = True
                notes.append(f"{names[m]} <- {in_names[j]}")
        img = render_markers(xyz[f], names, sticks=sticks, highlight=hl, notes=notes, title=f"Frame: {f}",
                             limits=limits)
        path = folder / f"{out.stem}_{f}.png"
        if not cv2.imwrite(str(path), img):
            raise ValueError(f"{path}: cannot write the inspection plot")
        files.append(str(path))
    return files
