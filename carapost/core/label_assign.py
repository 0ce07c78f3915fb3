"""The default labeller: tracklets + global assignment against motion and shape predictions.

1. :func:`~carapost.core.label_tracks.link_frames` links points of consecutive frames where
   the link is unambiguous (mutual nearest neighbours after a constant-velocity prediction,
   ratio test both ways, no newly appearing point close by); chains of links are *tracklets*.
   On clean data nearly every point of nearly every frame is linked, so this vectorised step
   does most of the work.
2. Tracklets containing hinted points (the labelled reference frame, fallback frames, user
   mappings, fully labelled markers) take those labels.
3. Every other tracklet is an *event* where it starts (going forwards from the reference
   frame; where it ends, going backwards). All tracklets starting in a frame are assigned
   together by a global optimal assignment (Hungarian, :func:`scipy.optimize.linear_sum_assignment`)
   to the markers that are unoccupied in that frame (:class:`~carapost.core.label_engine.AssignmentEngine`).
   The cost is the -2 log-likelihood of the best of each marker's predictions:

   * a marker seen in the adjacent frame and the one before: constant velocity;
   * a marker missing for a while, or seen in one adjacent frame only: the rigid motion of its
     most rigidly attached labelled neighbours (Kabsch fit) since it was last seen carries its
     last position (neighbourhood-shape consistency); the neighbours' fit residual and the
     spread of their distances widen the uncertainty;
   * a marker never seen: the template (if given) fitted to the labelled markers around it.

   A tracklet farther than ``gate`` sigmas from every prediction, or (a ghost) nearer to an
   occupied marker than half a missing marker's spacing, stays unlabelled.
4. Optionally (default) :func:`~carapost.core.swaps.detect_swaps` checks the result, trusting
   the reference frame, and its repairs are applied.
5. Optionally (default) the rigid-group check (:mod:`carapost.core.label_rigid`) names
   returning rigid clusters as a whole, from the mutual distances of their points.
6. Optionally (default) the shape check (:mod:`carapost.core.label_shape`) re-identifies
   markers against the rigid shape around the reference frame: it undoes confusions that
   continuity alone never undoes (fast motion, a source's own inconsistent labels).
7. Optionally (default) the isolated check (:mod:`carapost.core.label_isolated`) unnames
   pieces no neighbourhood allows, names the one marker never labelled by elimination, and
   renames (or unnames) pieces no partner checks that ride rigidly on another body.
8. Optionally (default) the take check (:mod:`carapost.core.label_ranges`) names pieces by
   the marker set learnt over the whole take (rigid groups of the take fitted in every
   frame, every pair's distance and spread), where a marker is long absent or a check
   before repaired something: segments that vanished for good leave their names free, and
   the reference frame's shape cannot name what comes back.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from .label_engine import AssignmentEngine, AssignmentParams, kabsch, motion_scales
from .label_tracks import Tracklets, build_tracklets, link_frames
from .labelling import LabelResult, ProgressFn, check_hints, check_points

if TYPE_CHECKING:
    from .label_rigid import RigidGroups
    from .label_shape import ShapeModel

__all__ = ["AssignmentParams", "AssignmentEngine", "label_assignment", "kabsch", "motion_scales"]


# ---------------------------------------------------------------------------- labeller
def label_assignment(points: np.ndarray, hints: np.ndarray | None, n_markers: int, *,
                     template: np.ndarray | None = None, ignore: Sequence[int] = (),
                     params: AssignmentParams | None = None, ratio: float = 0.5, passes: int = 2,
                     repair_swaps: bool = True, rigid_check: bool = True, shape_check: bool = True,
                     isolated_check: bool = True, take_check: bool = True, shape_tolerance: float = 0.5,
                     path_switch: float | None = 300.0, progress: ProgressFn | None = None) -> LabelResult:
    """Label unlabelled point clouds (the default method).

    Parameters
    ----------
    points : float (F, N, 3)
        Point clouds, mm, any order within a frame, NaN rows empty.
    hints : int (F, N) or None
        Known labels (-1 unknown): a labelled reference frame, fallback frames, frame
        mappings, fully labelled markers. Hinted points always keep their hint.
    n_markers : int
    template : float (M, 3), optional
        Neutral positions of the markers (NaN rows unknown). Without hints, the frame with the
        most points is labelled from it (:func:`~carapost.core.template.label_from_template`);
        it also predicts markers not yet seen.
    ignore : sequence of int
        Markers to leave alone: their hinted points keep their hints and take no part in the
        labelling; the markers are never assigned to other points.
    params : AssignmentParams, optional
    ratio, passes : float, int
        Linking (see :func:`~carapost.core.label_tracks.link_frames`).
    repair_swaps : bool
        Run :func:`~carapost.core.swaps.detect_swaps` on the result and apply its repairs.
    rigid_check : bool
        Then rename pieces of tracklets that rigid fits of the marker set's rigid groups
        clearly name otherwise (:func:`~carapost.core.label_rigid.rigid_relabel`): rigid
        clusters that vanished and came back under other names.
    shape_check : bool
        Then re-identify markers against the shape around the reference frame
        (:func:`~carapost.core.label_shape.shape_relabels`) and apply its repairs; where it
        repaired something (and ``repair_swaps``), run the swap repair again, keeping the
        repairs that lower the shape cost or raise it by at most ``shape_tolerance`` per frame
        and marker moved, and then, if that changed anything, the shape check once more.
        No repair is kept that the pairs rigid over the whole take contradict.
    path_switch : float or None
        Where the shape check repaired something, the groups of 2-5 markers its repairs
        permuted together are first decided over the whole take at once
        (:func:`~carapost.core.label_perm.permutation_path`, a change of permutation costing
        ``path_switch``), and the shape check runs again from there. None: off.
    isolated_check : bool
        Then unname pieces of tracklets whose label's neighbourhood rules them out
        (:func:`~carapost.core.label_isolated.impossible_pieces`), and give the one marker
        never labelled the isolated unlabelled tracklets
        (:func:`~carapost.core.label_isolated.name_unseen`); then rename or unname the
        pieces no partner of their label anchors that are attached to another body
        (:func:`~carapost.core.label_isolated.attached_pieces`).
    take_check : bool
        Finally name pieces by the marker set learnt over the take
        (:mod:`carapost.core.label_ranges`): rigid groups of the whole take fitted in every
        frame (a near-symmetric cluster told apart by the distances learnt over the take),
        then unnamed and badly fitting pieces named by those distances. Only where a marker
        is absent for a long run (120 frames, or 2 % of the take) or the checks before
        repaired something.
    progress : callable, optional
        ``progress(done, total)`` over the events; returning False stops early (the labels
        found so far are returned).

    Returns
    -------
    LabelResult
        ``report``: ``reference_frame``, ``tracklets``, ``events``, ``unlabelled_points``,
        ``link_residual_mm`` (median, p90), ``swaps_repaired``, ``rigid_renamed``,
        ``shape_repairs``, ``impossible_unnamed`` (points), ``unseen_named`` (tracklets),
        ``attached_relabelled`` (pieces), ``take_renamed``, ``range_named``, ``range_unnamed``
        (pieces), ``conflicts``.

    Raises
    ------
    ValueError
        Bad shapes or hints, or neither hints nor a template to start from.
    """
    pts, valid = check_points(points)
    F, N, _ = pts.shape
    if n_markers < 1:
        raise ValueError("n_markers must be at least 1")
    h = check_hints(hints, (F, N), n_markers, valid)
    p = params or AssignmentParams()
    ign = np.zeros(n_markers, bool)
    for m in ignore:
        if not 0 <= int(m) < n_markers:
            raise ValueError(f"ignored marker {m} is outside 0..{n_markers - 1}")
        ign[int(m)] = True
    keep_h = h.copy()
    ign_pts = (h >= 0) & ign[np.maximum(h, 0)]
    work = pts.copy()
    work[ign_pts] = np.nan
    h = np.where(ign_pts, -1, h)
    wvalid = valid & ~ign_pts
    tp = None if template is None else np.asarray(template, np.float64)
    if tp is not None and tp.shape != (n_markers, 3):
        raise ValueError(f"template must have shape ({n_markers}, 3), got {tp.shape}")
    if not (h >= 0).any():
        if tp is None:
            raise ValueError("labelling needs hints (a labelled frame) or a template")
        from .template import label_from_template
        ref = int(np.argmax(wvalid.sum(1)))
        fit = label_from_template(work[ref][wvalid[ref]], tp)
        h[ref, np.flatnonzero(wvalid[ref])] = np.where(ign[np.maximum(fit.labels, 0)], -1, fit.labels)
    t0 = int(np.flatnonzero((h >= 0).any(1))[0])

    links, stats = link_frames(work, hints=h, ratio=ratio, passes=passes)
    tracks = build_tracklets(work, links)
    tracks = _split_conflicting_hints(work, links, tracks, h)
    sig = p.motion_sigma if p.motion_sigma is not None else max(stats.p90, p.min_sigma)
    rel, fastest = motion_scales(np.where(wvalid[..., None], work, 0.0), links)
    eng = AssignmentEngine(tracks, n_markers, p, sig, template=tp, relative_sigma=rel, max_step=fastest)
    eng.template = None if tp is None else np.where(ign[:, None], np.nan, tp)
    # seeds
    sf, sj = np.nonzero(h >= 0)
    st = tracks.tid[sf, sj]
    seeds: dict[int, int] = {}
    for t, L in zip(st.tolist(), h[sf, sj].tolist()):
        seeds.setdefault(t, L)
    order = sorted(seeds, key=lambda t: (abs(int(tracks.start[t]) - t0), t))
    for t in order:
        eng.assign(t, seeds[t])
    eng.allowed = ~ign
    hinted = np.flatnonzero((h >= 0).any(1))
    eng.set_reference_spacing(hinted[np.linspace(0, hinted.size - 1, min(hinted.size, 20)).astype(int)])
    eng.run(t0, progress)

    labels = np.where(tracks.tid >= 0, eng.label[np.maximum(tracks.tid, 0)], -1).astype(np.int32)
    labels[ign_pts] = keep_h[ign_pts]
    report = {"method": "assignment", "reference_frame": t0, "tracklets": len(tracks), "events": eng.events,
              "link_residual_mm": [round(stats.median, 4), round(stats.p90, 4)],
              "motion_sigma_mm": round(float(eng.sig_cv), 4),
              "relative_sigma_mm": round(float(eng.sig_rel), 4), "conflicts": eng.conflicts, "swaps_repaired": 0}
    if repair_swaps:
        from .swaps import detect_swaps, relabel_points
        xyz, _ = _trajectories(pts, labels, n_markers)
        rep = detect_swaps(xyz, fixed=np.flatnonzero(ign), reference_frame=t0)
        # a repair never overrides a hint: drop those that would move a hinted point
        hinted_frames = np.flatnonzero((h >= 0).any(1))
        keep = []
        for r in rep.relabels:
            fr = hinted_frames[(hinted_frames >= r.start) & (hinted_frames < r.end)]
            if not np.isin(h[fr], r.markers).any():
                keep.append(r)
        if keep:
            labels = relabel_points(labels, keep)
            report["swaps_repaired"] = len(keep)
    groups = None
    model = None
    if rigid_check:
        labels, groups, rrep = _rigid_check(pts, labels, tracks, h, n_markers, t0, ign)
        report["rigid_renamed"] = rrep["pieces_renamed"]
    if shape_check:
        labels, n_shape, model = _shape_check(pts, labels, tracks, h, n_markers, t0, ign,
                                              shape_tolerance if repair_swaps else None, groups,
                                              path_switch=path_switch)
        report["shape_repairs"] = n_shape
    if isolated_check:
        labels, report["impossible_unnamed"], report["unseen_named"], report["attached_relabelled"] = \
            _isolated_check(pts, labels, tracks, h, n_markers, t0, ign, model, groups)
    if take_check and (_long_gaps(labels, n_markers) or any(report.get(k, 0) for k in _TROUBLE)):
        labels, trep = _take_check(pts, labels, tracks, h, n_markers, ign)
        report.update(trep)
    report["unlabelled_points"] = int((valid & (labels < 0)).sum())
    return LabelResult(labels, report)


def _trajectories(pts: np.ndarray, labels: np.ndarray, n_markers: int,
                  tid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Labelled trajectories (F, M, 3) of the points (F, N, 3) and, with ``tid`` (F, N), the
    tracklet carrying each marker's sample (F, M) (-1 none). Flat indices: a scatter of
    (frame, label) pairs costs twice as much."""
    F, N = labels.shape
    src = np.flatnonzero(labels.ravel() >= 0)
    dst = (src // N) * n_markers + labels.ravel()[src]
    xyz = np.full((F * n_markers, 3), np.nan)
    xyz[dst] = np.take(np.asarray(pts).reshape(-1, 3), src, axis=0)
    if tid is None:
        return xyz.reshape(F, n_markers, 3), None
    pieces = np.full(F * n_markers, -1, np.int64)
    pieces[dst] = np.asarray(tid).ravel()[src]
    return xyz.reshape(F, n_markers, 3), pieces.reshape(F, n_markers)


def _rigid_check(pts: np.ndarray, labels: np.ndarray, tracks: Tracklets, hints: np.ndarray, n_markers: int,
                 t0: int, ign: np.ndarray) -> tuple[np.ndarray, RigidGroups, dict]:
    """Rename returning rigid clusters (:func:`~carapost.core.label_rigid.rigid_relabel`) with
    the rigid groups (of 3 or more markers) of the trusted frames around ``t0``; hinted points
    keep their labels. Returns the labels, the rigid groups (the shape check's veto) and the
    report."""
    from .label_rigid import rigid_groups, rigid_relabel
    F = pts.shape[0]
    xyz, fr, trusted = _trusted_frames(pts, labels, tracks, n_markers, t0, ign)
    whole = np.unique(np.linspace(0, F - 1, min(F, 100)).astype(int))
    groups = rigid_groups(xyz, fr, trusted=trusted, check_frames=whole)
    labels, rep = rigid_relabel(pts, labels, tracks.tid, groups, protected=hints >= 0)
    return labels, groups, rep


def _trusted_frames(pts: np.ndarray, labels: np.ndarray, tracks: Tracklets, n_markers: int, t0: int,
                    ign: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labelled trajectories (F, M, 3), up to 91 frames around ``t0`` and which of their
    samples are trusted (between the nearest tracklet changes, see
    :func:`~carapost.core.label_shape.reference_model`)."""
    from .label_shape import _trusted_spans
    xyz, pieces = _trajectories(pts, labels, n_markers, tracks.tid)
    xyz[:, ign] = np.nan
    lo, hi = _trusted_spans(xyz, pieces, t0, 100)
    a, b = int(lo.min()), int(hi.max()) + 1
    # every frame near t0 (where most markers' trusted spans are), a sample of the rest
    near = np.arange(max(a, t0 - 25), min(b, t0 + 26))
    fr = np.unique(np.concatenate([near, np.linspace(a, b - 1, min(b - a, 40)).astype(int)]))
    return xyz, fr, (fr[:, None] >= lo[None]) & (fr[:, None] <= hi[None])


def _shape_check(pts: np.ndarray, labels: np.ndarray, tracks: Tracklets, hints: np.ndarray, n_markers: int,
                 t0: int, ign: np.ndarray, tolerance: float | None,
                 groups: RigidGroups | None = None,
                 take_veto: float = 1.0, path_switch: float | None = 300.0) -> tuple[np.ndarray, int, ShapeModel]:
    """Re-identify against the shape around frame ``t0``, then repair swaps by continuity again.

    :func:`~carapost.core.label_shape.shape_relabels` repairs the labels that contradict the
    rigid shape around the reference frame; :func:`~carapost.core.swaps.detect_swaps` then
    repairs, by motion continuity, the short confusions left between them (during fast motion
    the shape says little), keeping only repairs that do not break the shape (shape gain at
    least ``-tolerance`` per frame and marker; ``None``: no second swap repair); if it
    repaired something, the shape check runs once more; then once with runs of single frames
    (short confusions during fast motion). No repair moves a hinted point, nor
    (with the rigid ``groups``) permutes markers of one rigid group that its other members
    cannot check (:func:`~carapost.core.label_rigid.keeps_rigid_groups`), nor one that the
    pairs rigid over the whole take contradict: among 12 candidate partners of each marker,
    the (up to 6) pairs that keep their distance in at least half of the take along the
    reference frame's own tracklets (:func:`~carapost.core.label_shape.rigid_over_take`; a
    label-free measure) must not lose more than ``take_veto`` of shape gain per frame and
    marker moved (near the reference frame a resting arm makes an upper-arm and a forearm
    marker look rigid). Where the first shape check repaired something and ``path_switch`` is
    not None, the groups of markers its repairs permuted together are decided over the whole
    take first (:func:`_permutation_paths`) and the shape check is redone from there. Returns
    the labels, the number of repairs applied and the shape model (6 partners per marker,
    from the labels before the repairs).
    """
    from .label_shape import reference_model, relabel_gain, rigid_over_take, shape_relabels
    from .swaps import apply_relabel, detect_swaps, relabel_points
    xyz, pieces = _trajectories(pts, labels, n_markers, tracks.tid)
    fixed = np.flatnonzero(ign)
    wide = reference_model(xyz, t0, pieces=pieces, k=12)
    model = _first_partners(wide, 6)  # the same as reference_model(..., k=6)
    # the pairs rigid over the whole take, measured along the reference frame's own tracklets
    # (label-free): a repair they contradict is refused; measured once, and only when a
    # repair is to be judged
    take_cache: list[ShapeModel] = []

    def take_model() -> ShapeModel:
        if not take_cache:
            on_ref = (pieces == pieces[t0][None]) & (pieces >= 0)
            take_cache.append(rigid_over_take(wide, np.where(on_ref[..., None], xyz, np.nan), k=6))
        return take_cache[0]
    hinted_frames = np.flatnonzero((hints >= 0).any(1))

    def moves_hint(r) -> bool:
        fr = hinted_frames[(hinted_frames >= r.start) & (hinted_frames < r.end)]
        return bool(np.isin(hints[fr], r.markers).any())

    from .label_rigid import keeps_rigid_groups

    def rigid_ok(x: np.ndarray, r, gain: float) -> bool:
        if groups is not None and len(groups) and not keeps_rigid_groups(x, r, groups):
            return False
        return relabel_gain(x, take_model(), r) >= -take_veto

    accept = rigid_ok

    keep = [r for r in shape_relabels(xyz, t0, pieces=pieces, fixed=fixed, model=model, accept=accept,
                                      propagate=True) if not moves_hint(r)]
    if not keep:
        return labels, 0, model
    if path_switch is not None:
        # the markers those repairs permuted together are decided again over the whole take
        # at once (a confusion carried over many segments, judged on all of them), and the
        # shape check runs again from there
        path = _permutation_paths(xyz, pieces, keep, model, t0, fixed, hints, accept, path_switch)
        if path:
            x1, p1 = apply_relabel(xyz, path), apply_relabel(pieces, path)
            keep = path + [r for r in shape_relabels(x1, t0, pieces=p1, fixed=fixed, model=model, accept=accept,
                                                     propagate=True) if not moves_hint(r)]
    if tolerance is None:
        return relabel_points(labels, keep), len(keep), model
    xyz = apply_relabel(xyz, keep)
    n0 = len(keep)
    for r in detect_swaps(xyz, fixed=fixed, reference_frame=t0).relabels:
        if moves_hint(r):
            continue
        g = relabel_gain(xyz, model, r)
        if g >= -tolerance and (accept is None or accept(xyz, r, g)):
            xyz = apply_relabel(xyz, [r])
            keep.append(r)
    if len(keep) > n0:
        more = shape_relabels(xyz, t0, pieces=apply_relabel(pieces, keep), fixed=fixed, model=model, accept=accept,
                              propagate=True)
        more = [r for r in more if not moves_hint(r)]
        xyz = apply_relabel(xyz, more)
        keep += more
    # where there were confusions, look for short ones (1-3 frames, during fast motion) too:
    # frame-exact runs, every frame, the same gain test, two rounds
    short = shape_relabels(xyz, t0, fixed=fixed, model=model, accept=accept, stride=1, min_run=1, iterations=2)
    keep += [r for r in short if not moves_hint(r)]
    return relabel_points(labels, keep), len(keep), model


def _permutation_paths(xyz: np.ndarray, pieces: np.ndarray, repairs: list, model: ShapeModel, t0: int,
                       fixed: np.ndarray, hints: np.ndarray, accept, switch_cost: float) -> list:
    """Whole-take permutation paths (:func:`~carapost.core.label_perm.permutation_path`) of
    the groups of 2-5 markers that the shape ``repairs`` permuted together (not ``fixed``
    ones), on the labels before those repairs; each run must pass ``accept``. Returns the
    runs kept, to apply in order."""
    from .label_perm import confusable_groups, permutation_path
    from .label_shape import relabel_gain
    from .swaps import apply_relabel
    out: list = []
    x = xyz
    for g in confusable_groups(repairs):
        if np.isin(g, fixed).any():
            continue
        locked = np.isin(hints, g).any(1)
        for r in permutation_path(x, pieces, g, model, t0, switch_cost=switch_cost, locked=locked):
            if accept is None or accept(x, r, relabel_gain(x, model, r)):
                x = apply_relabel(x, [r])
                pieces = apply_relabel(pieces, [r])
                out.append(r)
    return out


def _first_partners(model: ShapeModel, k: int) -> ShapeModel:
    """The model with each marker's ``k`` most rigid partners only."""
    from .label_shape import ShapeModel
    return ShapeModel(model.partners[:, :k], model.dist[:, :k], model.spread[:, :k])


def _isolated_check(pts: np.ndarray, labels: np.ndarray, tracks: Tracklets, hints: np.ndarray, n_markers: int,
                    t0: int, ign: np.ndarray, model: ShapeModel | None = None,
                    groups: RigidGroups | None = None) -> tuple[np.ndarray, int, int, int]:
    """Unname pieces their label's shape rules out (the shape ``model`` around ``t0``, by
    default made here), then give the one marker never labelled the isolated unlabelled
    tracklets, then rename (or unname) the pieces no partner checks that ride rigidly on
    another body (:mod:`carapost.core.label_isolated`). Returns the labels, the points
    unnamed, the tracklets named and the pieces renamed or unnamed as attached."""
    from .label_isolated import attached_pieces, impossible_pieces, name_unseen
    from .label_shape import reference_model
    if model is None:
        xyz, pieces = _trajectories(pts, labels, n_markers, tracks.tid)
        xyz[:, ign] = np.nan
        model = reference_model(xyz, t0, pieces=pieces)
    bad = impossible_pieces(pts, labels, tracks.tid, model, protected=hints >= 0)
    bad &= ~ign[np.maximum(labels, 0)]
    labels = np.where(bad, -1, labels).astype(np.int32)
    labels, n = name_unseen(pts, labels, tracks.tid, n_markers, t0, ignore=ign)
    prot = (hints >= 0) | ign[np.maximum(labels, 0)]
    labels, ren, unn = attached_pieces(pts, labels, tracks.tid, model,
                                       None if groups is None else groups.members, protected=prot)
    return labels, int(bad.sum()), n, ren + unn


_TROUBLE = ("rigid_renamed", "shape_repairs", "impossible_unnamed", "unseen_named", "attached_relabelled")


def _long_gaps(labels: np.ndarray, n_markers: int, frames: int = 120, share: float = 0.02) -> bool:
    """Whether some labelled marker is absent for a run of at least ``max(frames, share x F)``
    frames (it vanished and came back, or vanished for good): where the take check can help."""
    F = labels.shape[0]
    run = max(frames, int(share * F))
    if F <= run:
        return False
    f, j = np.nonzero(labels >= 0)
    pres = np.zeros((F, n_markers), bool)
    pres[f, labels[f, j]] = True
    seen = pres.any(0)
    # a window of ``run`` frames without the marker: a rolling count of its samples
    c = np.vstack([np.zeros((1, n_markers), np.int64), np.cumsum(pres, 0)])
    empty = (c[run:] - c[:-run]) == 0
    return bool((empty.any(0) & seen).any())


def _take_check(pts: np.ndarray, labels: np.ndarray, tracks: Tracklets, hints: np.ndarray, n_markers: int,
                ign: np.ndarray, rounds: int = 3) -> tuple[np.ndarray, dict]:
    """Name pieces by the marker set learnt over the take (:mod:`carapost.core.label_ranges`):
    the rigid groups of the whole take are fitted in every frame where one is incompletely
    confirmed (:func:`~carapost.core.label_rigid.rigid_relabel`, one vote enough, coverage
    over the frames a fit could judge, ties of near-symmetric clusters broken by the learnt
    distances to confirmed and ungrouped markers), then ``rounds`` passes of
    :func:`~carapost.core.label_ranges.range_relabel`, then the short pieces named by the
    motion they continue (:func:`~carapost.core.label_motion.motion_bridge`). Returns the
    labels and the report."""
    from .label_motion import fitting_samples, motion_bridge
    from .label_ranges import learn_ranges, range_relabel, range_tiebreak, take_groups
    from .label_rigid import rigid_relabel
    rep = {"take_renamed": 0, "range_named": 0, "range_unnamed": 0}
    xyz, pieces = _trajectories(pts, labels, n_markers, tracks.tid)
    xyz[:, ign] = np.nan
    groups = take_groups(xyz, pieces)
    model = learn_ranges(xyz, pieces)
    prot = (hints >= 0) | ign[np.maximum(labels, 0)] & (labels >= 0)
    if len(groups):
        labels, rr = rigid_relabel(pts, labels, tracks.tid, groups, protected=prot, stride=1, min_votes=1,
                                   judged=True, exchange=True, partial=True,
                                   tiebreak=range_tiebreak(model, groups=groups))
        rep["take_renamed"] = rr["pieces_renamed"]
    for _ in range(rounds):
        labels, nn, nu, _m = range_relabel(pts, labels, tracks.tid, n_markers, model=model, protected=prot,
                                           ignore=ign)
        rep["range_named"] += nn
        rep["range_unnamed"] += nu
        if nn + nu == 0:
            break
    short = (tracks.end - tracks.start < 3)[np.maximum(tracks.tid, 0)] & (tracks.tid >= 0)
    anchors = fitting_samples(pts, labels, short, model.dist, model.spread)
    labels, rep["motion_bridged"] = motion_bridge(pts, labels, tracks.tid, n_markers, protected=prot,
                                                  anchors=anchors)
    return labels, rep


def _split_conflicting_hints(points: np.ndarray, links: np.ndarray, tracks: Tracklets,
                             hints: np.ndarray) -> Tracklets:
    """Cut tracklets whose hinted samples disagree (at the first sample of each new hint)."""
    hs = hints[tracks.frames, tracks.index]
    tid = np.repeat(np.arange(len(tracks)), np.diff(tracks.offsets))
    k = np.flatnonzero(hs >= 0)
    if k.size < 2:
        return tracks
    same_t = tid[k[1:]] == tid[k[:-1]]
    change = same_t & (hs[k[1:]] != hs[k[:-1]])
    if not change.any():
        return tracks
    lk = links.copy()
    cut = k[1:][change]
    lk[tracks.frames[cut], tracks.index[cut]] = -1
    return build_tracklets(points, lk)
