"""Labelling accuracy and speed: the default (assignment) method beside seed 002's method.

Targets (issue 7): on synthetic face- and body-like data (60-240 Hz) with dropouts, noise,
spurious points and swapped pairs, and on the real C3D files with their labels hidden and
shuffled, the default method labels >= 99.9 % of the samples correctly and repairs every
injected swap; >= 5,000 frames/s for 100 markers on one core.

Protocol
--------
* Synthetic: :mod:`carapost.synth.mocap` trajectories corrupted by
  :func:`~carapost.synth.mocap.corrupt` (noise 0.1 mm face / 0.3 mm body, gaps starting with
  probability 0.002 per marker and frame, 0.1 isolated spurious points per frame, ghost
  tracks). Points are shuffled in every frame; only frame 0's labels are given.
* Real: every C3D below, markers only (no model outputs), shuffled per frame; the labels of
  the first frame where all markers are present (else the fullest frame) are given. Accuracy
  is against the file's own labels, which are wrong in places (a few files swap labels
  themselves; the "file swaps" column counts what :func:`detect_swaps` finds in the original);
  markers whose trajectories coincide within 1 mm (duplicated virtual markers) count as one,
  and so do columns with the same name (a label is a name). Columns the file leaves unlabelled
  (names like ``*39``, ``Unlabeled1``: :data:`~carapost.ops.label_file.UNLABELLED_NAME`) are
  extra points, not markers: right when left unlabelled ("spurious_labelled" counts those
  given a marker's name). Gaps in the file are not samples. The file's labels are not always
  right: "disputed" counts our wrong samples where the file's label breaks the file's own
  rigid shape around the reference frame and ours keeps it (see :func:`_disputed`);
  "accuracy_undisputed" leaves them out. "disputed_take" adds the wrong samples where the
  file's label breaks the distances learnt from the file's own labels over the whole take and
  ours keeps them, or where the file renames a point that did not move and we keep the first
  name; "accuracy_undisputed_take" leaves all of those out. The headline accuracy counts them
  as wrong.
  "worst_markers" lists the three markers with most samples not given their name.
* Swaps: pairs of neighbouring markers exchanged over 5-200 frames (synthetic) or 60 frames
  (real), repaired by :func:`~carapost.core.swaps.detect_swaps`; "false relabels" are repairs
  proposed on the same data without injected swaps.
* Speed: CPU time (best of 3) of the whole default labeller on a 100-marker face at 60 Hz,
  one BLAS thread.

Usage: ``python benchmarks/bench_labelling.py [--quick] [--synth-take]`` (``--synth-take`` adds
a face from :func:`carapost.synth.generate_take`'s ground truth; slow to generate).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit  # noqa: E402

from carapost.core.label_assign import label_assignment  # noqa: E402
from carapost.core.label_nn import label_nearest  # noqa: E402
from carapost.core.label_shape import shape_costs, shape_model  # noqa: E402
from carapost.core.labelling import (points_from_trajectories, skeleton_from_sticks,  # noqa: E402
                                     trajectories_from_labels)
from carapost.core.swaps import apply_relabel, detect_swaps  # noqa: E402
from carapost.ops.label_file import UNLABELLED_NAME  # noqa: E402
from carapost.synth.mocap import body_motion, corrupt, face_motion  # noqa: E402

REAL = ["ezc3d/Vicon.c3d", "ezc3d/Qualisys.c3d", "c3d.org-samples/sample_29/Facial-Sing.c3d",
        "opensim-core/walking2.c3d", "kineticstoolkit/kinematics_tennis_serve.c3d",
        "kineticstoolkit/kinematics_racing_static.c3d", "c3d.org-samples/sample_01/Eb015pi.c3d",
        "c3d.org-samples/sample_00/Motion_Analysis_Corporation/Walk1.c3d",
        "c3d.org-samples/sample_32/vicon_zerowire.c3d", "kineticstoolkit/kinematics_basket_sprint.c3d",
        "c3d.org-samples/sample_33/bigparlove.c3d"]


def _equivalence(xyz: np.ndarray, names: list[str] | None = None, tol: float = 1.0) -> np.ndarray:
    """Group id per marker; markers within ``tol`` mm of each other wherever both exist share one,
    and so do markers with the same name (a label is a name: Walk1 has two "VRTO" columns)."""
    M = xyz.shape[1]
    group = np.arange(M)
    if names is not None:
        first: dict[str, int] = {}
        for m, n in enumerate(names):
            group[m] = first.setdefault(n.strip(), m)
    idx = np.unique(np.linspace(0, len(xyz) - 1, min(len(xyz), 200)).astype(int))
    X = xyz[idx]
    d = np.linalg.norm(X[:, :, None] - X[:, None], axis=-1)
    both = np.isfinite(d)
    close = np.where(both, d <= tol, True).all(0) & both.any(0)
    for a in range(M):
        for b in np.flatnonzero(close[a]):
            if b > a:
                group[group == group[b]] = group[a]
    return group


def _score(labels: np.ndarray, truth: np.ndarray, group: np.ndarray | None = None) -> dict:
    is_m = truth >= 0
    if group is not None:
        same = is_m & (labels >= 0) & (group[np.maximum(labels, 0)] == group[np.maximum(truth, 0)])
    else:
        same = is_m & (labels == truth)
    n = int(is_m.sum())
    return {"accuracy": round(same.sum() / max(n, 1), 6), "wrong": int((is_m & (labels >= 0) & ~same).sum()),
            "missed": int((is_m & (labels < 0)).sum()), "spurious_labelled": int((~is_m & (labels >= 0)).sum())}


def _timed(fn):
    t0 = time.process_time()
    out = fn()
    return out, time.process_time() - t0


def _disputed(pts, labels, truth, group, M, reference: int, tau: float = 3.0, far: float = 2.5,
              lower: float = 1.0, still: float = 5.0, apart: float = 50.0, window: int = 3,
              jump: float = 3.0, tight_mm: float = 3.0, tight_rel: float = 0.03, own_z: float = 5.0,
              samples: bool = False) -> dict:
    """Wrong samples where the file's label breaks the file's own shape and ours keeps it: the
    file, not the labeller, is likely wrong there.

    *Near the reference frame*: the shape model (:func:`~carapost.core.label_shape.shape_model`)
    is made from the file's labels within 100 frames of the reference frame. A wrong sample
    (file says marker ``m``, we say ``L``) is disputed when the file's cost of ``m`` there is
    anomalous (mean squared z-score of its partner distances above 2) and our cost of ``L``
    at the same point is lower by at least 1.

    *Over the take*: every pair's distance and spread learnt from the file's own labels over
    the whole take (:func:`~carapost.core.label_ranges.learn_ranges`, runs of presence of at
    least 20 frames); a wrong sample is disputed when the mean of ``2 ln(1 + z^2)`` (the take
    check's Cauchy term, ``z`` the deviation from the file's learnt distance in spreads) over
    the *agreed* points of the frame (those both labellings name alike, so that neither side's
    disputed points are evidence) is above ``far`` under the file's label and at least
    ``lower`` below that under ours. This catches what the reference frame cannot: the file's
    ForearmL Marker1/Marker4 of ``kinematics_basket_sprint`` exchanged at 2382-2458 (their
    distances to the upper arm's markers off the file's own).

    *Renamed points*: a wrong sample (file ``m``, ours ``L``) where the file's run of ``m``
    begins within ``still`` mm of where the file's ``L`` was in the frame before (or ends
    within ``still`` mm of where its ``L`` is in the frame after), and ``m`` and ``L`` are
    markers at least ``apart`` mm apart (median over the take, so two markers that touch at
    times - Facial-Sing's section4-1/4-2, 1.5 mm apart at 1078 - are no evidence): the file
    gave one point another name, and we kept the first. ``kinematics_basket_sprint`` at
    3202-3246: the file's ArmL Marker2/Marker3 become ForearmL Marker4/Marker3 and back five
    times on points that move 0.1-3.6 mm between those frames (the two clusters are 200-300
    mm apart).

    *Jumps* are never disputed: a sample whose point is farther from our label's nearest
    sample within ``window`` frames than ``jump`` x the file's 99th percentile of per-frame
    motion per frame (``kinematics_basket_sprint`` at 2855: a wheel triplet we call the
    upper arm's, 380-500 mm from where the arm was the frame before), nor one where our label
    breaks a *tight* pair (learnt spread at most ``tight_mm`` + ``tight_rel`` x the distance)
    with our own labels in the frame by more than ``own_z`` spreads (at 2806 we call a chair
    point SWL Marker4, 800 mm from our WheelchairL Marker4 where the file keeps them 464 +-
    6 mm apart): a dispute needs our labels to be possible.

    Returns the counts (``disputed``: near the reference frame, ``disputed_take``: any of
    the three) and the accuracies with them left out; with ``samples`` the wrong samples'
    frames and points and their two dispute masks instead.
    """
    from carapost.core.label_ranges import learn_ranges, range_costs
    x = trajectories_from_labels(pts, truth, M)
    ours = trajectories_from_labels(pts, labels, M)
    F = len(x)
    a, b = max(0, reference - 100), min(F, reference + 101)
    model = shape_model(x, np.unique(np.linspace(a, b - 1, min(b - a, 120)).astype(int)))
    cf = shape_costs(x, model, tau=tau, unknown=0.5 * tau * tau)
    co = shape_costs(ours, model, tau=tau, unknown=0.5 * tau * tau)
    is_m = truth >= 0
    same = is_m & (labels >= 0) & (group[np.maximum(labels, 0)] == group[np.maximum(truth, 0)])
    f, j = np.nonzero(is_m & (labels >= 0) & ~same)
    file_c, our_c = cf[f, truth[f, j]], co[f, labels[f, j]]
    disp = (file_c > 2.0) & (our_c <= file_c - 1.0)
    pres = np.isfinite(x[..., 0])
    ranges = learn_ranges(x, np.where(pres, np.arange(M)[None], -1))
    no_tight = np.zeros((M, M), bool)
    agreed = pres & np.all(x == ours, axis=-1)  # (F, M): both name the same point

    def mean_far(k, lab):
        P = np.where(agreed[k, :, None], x[k], np.nan)
        P[lab] = np.nan
        n = np.isfinite(P[:, 0]).sum()
        c = range_costs(pts[k, j_][None], P[None], ranges, tight=no_tight, labels=[lab])[1][0, 0]
        return c / n if n else 0.0

    step = np.linalg.norm(np.diff(x, axis=0), axis=-1)
    vmax = jump * float(np.percentile(step[np.isfinite(step)], 99)) if np.isfinite(step).any() else np.inf
    ours_pres = np.isfinite(ours[..., 0])

    def jumps(k, L):
        """Our label's nearest own sample within ``window`` frames is out of reach."""
        for dk in range(1, window + 1):
            near = [kk for kk in (k - dk, k + dk) if 0 <= kk < F and ours_pres[kk, L]]
            if near:
                return min(np.linalg.norm(ours[kk, L] - pts[k, j_]) for kk in near) > vmax * dk
        return False

    tight = ranges.spread <= tight_mm + tight_rel * np.nan_to_num(ranges.dist, nan=np.inf)

    def breaks_own(k, L):
        """Our label breaks a tight pair (file-learnt) with our own labels in the frame."""
        q = np.flatnonzero(tight[L] & ours_pres[k])
        q = q[q != L]
        if not q.size:
            return False
        z = (np.linalg.norm(ours[k, q] - pts[k, j_], axis=-1) - ranges.dist[L, q]) / ranges.spread[L, q]
        return bool(np.abs(z).max() > own_z)

    def apart_mm(m, L):
        both = pres[:, m] & pres[:, L]
        return float(np.median(np.linalg.norm(x[both, m] - x[both, L], axis=-1))) if both.any() else 0.0

    # the file's runs of presence: where each marker's run starts and ends (frame of each sample)
    run_start = np.zeros((F, M), np.int64)
    run_end = np.zeros((F, M), np.int64)
    for m in range(M):
        idx = np.flatnonzero(pres[:, m])
        if idx.size:
            cut = np.flatnonzero(np.diff(idx) > 1)
            s0, s1 = idx[np.r_[0, cut + 1]], idx[np.r_[cut, idx.size - 1]]
            k = np.searchsorted(s0, idx, side="right") - 1
            run_start[idx, m], run_end[idx, m] = s0[k], s1[k]

    def renamed(k, m, L):
        """The file's run of ``m`` through frame ``k`` starts (ends) within ``still`` mm of
        where its ``L`` ended (starts) in the frame before (after): one point, renamed."""
        a, b = run_start[k, m], run_end[k, m]
        if apart_mm(m, L) < apart:
            return False
        return bool((a > 0 and pres[a - 1, L] and np.linalg.norm(x[a - 1, L] - x[a, m]) <= still)
                    or (b < F - 1 and pres[b + 1, L] and np.linalg.norm(x[b + 1, L] - x[b, m]) <= still))

    take = disp.copy()
    far_cost = np.full((len(f), 2), np.nan)
    for i, (k, j_) in enumerate(zip(f.tolist(), j.tolist())):
        m, L = int(truth[k, j_]), int(labels[k, j_])
        if jumps(k, L) or breaks_own(k, L):
            disp[i] = take[i] = False
        elif not take[i]:
            ff, fo = far_cost[i] = mean_far(k, m), mean_far(k, L)
            take[i] = (ff > far and fo <= ff - lower) or renamed(k, m, L)
    n_all = int(is_m.sum())
    n_disp, n_take = int(disp.sum()), int(take.sum())
    if samples:  # the wrong samples (frame, point) and which of them are disputed, for audits
        return {"frame": f, "point": j, "disputed": disp, "disputed_take": take, "far_cost": far_cost}
    return {"disputed": n_disp, "accuracy_undisputed": round(int(same.sum()) / max(n_all - n_disp, 1), 6),
            "disputed_take": n_take,
            "accuracy_undisputed_take": round(int(same.sum()) / max(n_all - n_take, 1), 6)}


def _worst(labels, truth, group, names: list[str], n: int = 3) -> list:
    """The ``n`` markers with the most samples not given their name: [name, samples]."""
    is_m = truth >= 0
    ok = is_m & (labels >= 0) & (group[np.maximum(labels, 0)] == group[np.maximum(truth, 0)])
    bad = np.bincount(truth[is_m & ~ok], minlength=len(names))
    return [[names[m], int(bad[m])] for m in np.argsort(-bad, kind="stable")[:n] if bad[m] > 0]


def _methods(pts, truth, h, M, skeleton=None, group=None, reference=None, names=None) -> dict:
    out = {}
    r, dt = _timed(lambda: label_assignment(pts, h, M))
    out["assignment"] = {**_score(r.labels, truth, group), "fps": round(len(pts) / dt),
                         "rigid_renamed": r.report.get("rigid_renamed", 0),
                         "shape_repairs": r.report.get("shape_repairs", 0),
                         "impossible_unnamed": r.report.get("impossible_unnamed", 0),
                         "unseen_named": r.report.get("unseen_named", 0),
                         "attached_relabelled": r.report.get("attached_relabelled", 0),
                         "take_renamed": r.report.get("take_renamed", 0),
                         "range_renamed": r.report.get("range_named", 0) + r.report.get("range_unnamed", 0),
                         "motion_bridged": r.report.get("motion_bridged", 0)}
    if reference is not None:
        out["assignment"].update(_disputed(pts, r.labels, truth, group, M, reference))
    if names is not None and group is not None:
        out["assignment"]["worst_markers"] = _worst(r.labels, truth, group, names)
    r, dt = _timed(lambda: label_nearest(pts, h, M, skeleton=skeleton))
    out["nearest"] = {**_score(r.labels, truth, group), "fps": round(len(pts) / dt)}
    return out


def synthetic(quick: bool) -> tuple[list, list]:
    F = 1200 if quick else 3000
    cases = []
    for rate in (60.0, 120.0, 240.0):
        cases.append((f"face 80 markers {rate:g} Hz", face_motion(80, F, rate, seed=int(rate)), 0.1))
        cases.append((f"body 47 markers {rate:g} Hz", body_motion(F, rate, seed=int(rate)), 0.3))
    lab_rows, swap_rows = [], []
    for name, m, noise in cases:
        c = corrupt(m, seed=7, noise_mm=noise, gap_rate=0.002, spurious_rate=0.1, ghost_tracks=5, n_swaps=6,
                    swap_length=(5, 200))
        pts, truth = points_from_trajectories(c.clean_labels_xyz, c.spurious, seed=7)
        h = np.full(truth.shape, -1, np.int32)
        h[0] = truth[0]
        res = _methods(pts, truth, h, m.n_markers, skeleton_from_sticks(m.sticks, m.n_markers))
        lab_rows.append({"case": name, "frames": m.n_frames, **res})
        rep = detect_swaps(c.xyz)
        fixed = apply_relabel(c.xyz, rep.relabels)
        ok = np.isfinite(c.clean_labels_xyz[..., 0])
        wrong = int((ok & ~(fixed[..., 0] == c.clean_labels_xyz[..., 0])).sum())
        found = {frozenset(p) for r in rep.relabels for p in r.pairs}
        injected = {frozenset((a, b)) for a, b, _, _ in c.swaps}
        false = len(detect_swaps(c.clean_labels_xyz).relabels)
        swap_rows.append({"case": name, "injected": len(injected), "repaired": len(injected & found),
                          "wrong_samples_after": wrong, "false_relabels_clean": false})
    return lab_rows, swap_rows


def synth_take() -> dict:
    from carapost.synth import SynthConfig, generate_take
    st = generate_take(SynthConfig(n_frames=300, n_markers=80, frame_rate=60.0))
    m_xyz = st.truth.xyz
    from carapost.synth.mocap import MarkerMotion
    m = MarkerMotion(list(st.truth.names), m_xyz, 60.0)
    c = corrupt(m, seed=3, noise_mm=0.1, gap_rate=0.002, spurious_rate=0.1, ghost_tracks=3)
    pts, truth = points_from_trajectories(c.clean_labels_xyz, c.spurious, seed=3)
    h = np.full(truth.shape, -1, np.int32)
    h[0] = truth[0]
    return {"case": "carapost.synth face take truth, 80 markers 60 Hz", "frames": 300,
            **_methods(pts, truth, h, m.n_markers)}


def real(root: Path) -> tuple[list, list]:
    from carapost.io.c3d import read_c3d
    rows, swaps = [], []
    for rel in REAL:
        p = root / rel
        if not p.exists():
            continue
        d = read_c3d(p)
        idx = d.marker_indices()
        names = [d.labels[i] for i in idx]
        named = np.array([not UNLABELLED_NAME.match(n) for n in names], bool)
        x = d.xyz[:, idx[named]]  # the file's unlabelled columns ("*39", "Unlabeled1") are extra points
        extra = d.xyz[:, idx[~named]]
        names = [n for n, k in zip(names, named) if k]
        M = x.shape[1]
        valid = np.isfinite(x).all(-1)
        full = np.flatnonzero(valid.all(1))
        f0 = int(full[0]) if len(full) else int(np.argmax(valid.sum(1)))
        pts, truth = points_from_trajectories(x, extra, seed=1)
        h = np.full(truth.shape, -1, np.int32)
        h[f0] = truth[f0]
        group = _equivalence(x, names)
        file_swaps = len(detect_swaps(x).relabels)
        rows.append({"file": rel, "markers": M, "unlabelled_columns": int((~named).sum()), "frames": len(x),
                     "rate": d.frame_rate, "reference_frame": f0, "file_swaps": file_swaps,
                     **_methods(pts, truth, h, M, group=group, reference=f0, names=names)})
        if file_swaps == 0 and M > 3:  # inject swaps into files that have none of their own
            rng = np.random.default_rng(3)
            y = x.copy()
            sub = x[::max(1, len(x) // 100)]
            med = np.array([np.median(sub[np.isfinite(sub[:, m, 0]), m], axis=0) if np.isfinite(sub[:, m, 0]).any()
                            else np.full(3, 1e9 * (m + 1)) for m in range(M)])
            inj: list[tuple[int, int, int]] = []
            used: set[int] = set()
            for a in rng.permutation(M):
                if len(inj) == 3:
                    break
                dist = np.linalg.norm(med - med[a], axis=1)
                dist[a] = np.inf
                b = int(np.argmin(dist))
                starts = [s for s in range(20, len(x) - 80, 7) if valid[s:s + 60, [a, b]].all()]
                if a in used or b in used or not starts:
                    continue
                s = int(rng.choice(starts))
                y[s:s + 60, [a, b]] = y[s:s + 60, [b, a]]
                inj.append((int(a), b, s))
                used.update((int(a), b))
            rep = detect_swaps(y)
            fixed = apply_relabel(y, rep.relabels)
            ok = valid
            restored = [bool((fixed[s:s + 60, [a, b], 0] == x[s:s + 60, [a, b], 0]).all()) for a, b, s in inj]
            swaps.append({"file": rel, "injected": len(inj), "repaired": int(sum(restored)),
                          "wrong_samples_after": int((ok & ~(fixed[..., 0] == x[..., 0])).sum())})
    return rows, swaps


def speed(quick: bool) -> dict:
    F = 2000 if quick else 6000
    m = face_motion(100, F, 60.0, seed=11)
    out = {"markers": 100, "frames": F}
    for tag, kw in (("moderate", dict(gap_rate=0.0005, spurious_rate=0.02)),
                    ("heavy", dict(gap_rate=0.002, spurious_rate=0.1, ghost_tracks=5))):
        c = corrupt(m, seed=2, noise_mm=0.1, **kw)
        pts, truth = points_from_trajectories(c.clean_labels_xyz, c.spurious, seed=2)
        h = np.full(truth.shape, -1, np.int32)
        h[0] = truth[0]
        best = min(_timed(lambda: label_assignment(pts, h, 100))[1] for _ in range(3))
        best_nn = min(_timed(lambda: label_nearest(pts, h, 100))[1] for _ in range(2))
        out[f"fps_assignment_{tag}"] = round(F / best)
        out[f"fps_nearest_{tag}"] = round(F / best_nn)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter synthetic takes")
    ap.add_argument("--synth-take", action="store_true", help="also a face from carapost.synth (slow)")
    ap.add_argument("--real", default=None, help="folder of the real test data (default: ../shared/data/real)")
    args = ap.parse_args()
    root = Path(args.real) if args.real else Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
    t0 = time.perf_counter()
    lab, sw = synthetic(args.quick)
    if args.synth_take:
        lab.append(synth_take())
    rl, rsw = real(root) if root.is_dir() else ([], [])
    sp = speed(args.quick)
    synth_ok = all(r["assignment"]["accuracy"] >= 0.999 for r in lab)
    swaps_ok = all(r["repaired"] == r["injected"] and r["wrong_samples_after"] == 0 for r in sw + rsw)
    emit("labelling", synthetic=lab, swaps=sw, real=rl, real_swaps=rsw, speed=sp,
         targets={"synthetic_accuracy_999": synth_ok,
                  "real_accuracy_999": {r["file"]: bool(r["assignment"]["accuracy"] >= 0.999) for r in rl},
                  # the same against the file's labels with the samples they dispute left out
                  # (audited segment by segment in docs/labelling.md)
                  "real_accuracy_999_undisputed": {
                      r["file"]: bool(r["assignment"]["accuracy_undisputed_take"] >= 0.999) for r in rl},
                  "every_injected_swap_repaired": swaps_ok,
                  "fps_5000_100_markers": bool(sp["fps_assignment_moderate"] >= 5000)},
         wall_s=round(time.perf_counter() - t0, 1))


if __name__ == "__main__":
    main()
