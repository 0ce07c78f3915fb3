"""The assignment engine: labels tracklets event by event (see :mod:`carapost.core.label_assign`).

At every tracklet start (an *event*) the tracklets starting there are assigned together, by
an optimal assignment (Hungarian), to the markers unoccupied in that frame. Each marker is
predicted by the models it has data for - constant velocity, the rigid motion of its most
rigidly attached labelled neighbours since it was seen (neighbourhood shape), the template -
and the best model's -2 log-likelihood is the cost. With a *prior* (the current label of each
tracklet) the same engine relabels labelled segments (:mod:`carapost.core.swaps`).
"""

from __future__ import annotations

import bisect
import heapq
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from .label_tracks import Tracklets
from .labelling import ProgressFn

__all__ = ["AssignmentParams", "AssignmentEngine", "kabsch", "motion_scales"]

_BIG = 1e12
_UNASSIGNED = 1e9


@dataclass(frozen=True)
class AssignmentParams:
    """Tuning of the assignment engine (defaults suit face and body data at 50-250 Hz).

    Attributes
    ----------
    gate : float
        A tracklet is assigned to a marker only within ``gate`` sigmas of its prediction.
    min_sigma : float
        Lower bound of every prediction's uncertainty, mm.
    motion_sigma : float or None
        Uncertainty of a constant-velocity prediction, mm (None: the 90th percentile of the
        link residuals, at least ``min_sigma``).
    neighbours : int
        Neighbours used for the shape prediction of a missing marker.
    gap_growth : float
        Relative growth of a shape prediction's uncertainty per sqrt(frame) of gap.
    spacing_cap : float
        A point closer to an occupied marker than this fraction of a missing marker's spacing
        (distance to its nearest neighbour where last seen) is not given to that marker.
    min_samples : int
        A tracklet shorter than this is not given to a marker missing for more than two
        frames whose prediction is uncertain (sigma above three motion sigmas), unless it lies
        within one sigma of the prediction.
    prior_bonus : float
        Relabelling only: a segment keeps its current label unless another label's cost
        (squared normalised distance to its best prediction) is lower by more than this.
    history : int
        Frames of history (before the marker went missing) used to pick its most rigidly
        attached neighbours.
    prior_accept : float
        Relabelling: current labels predicted within this many sigmas are kept without
        considering other markers.
    retries : tuple of int
        Frame delays at which a tracklet left unlabelled at its start is tried again (each
        relative to the previous try, within the tracklet).
    """

    gate: float = 4.0
    min_sigma: float = 0.25
    motion_sigma: float | None = None
    neighbours: int = 6
    gap_growth: float = 0.15
    spacing_cap: float = 0.5
    min_samples: int = 3
    prior_bonus: float = 9.0
    history: int = 30
    prior_accept: float = 1.5
    retries: tuple[int, ...] = field(default=(2, 5, 15, 40, 120))


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid motion taking points ``a`` to ``b`` (least squares).

    Parameters
    ----------
    a, b : float (K, 3)
        Corresponding points, ``K >= 3`` not collinear for a unique rotation.

    Returns
    -------
    R : (3, 3)
        Rotation (det +1).
    ca, cb : (3,)
        Centroids: ``b ~ R (a - ca) + cb``.
    """
    ca, cb = a.mean(0), b.mean(0)
    H = (a - ca).T @ (b - cb)
    U, _s, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, d if d != 0 else 1.0])
    return Vt.T @ D @ U.T, ca, cb


class AssignmentEngine:
    """Assigns labels to tracklets event by event (see the module docstring).

    Parameters
    ----------
    tracks : Tracklets
    n_markers : int
    params : AssignmentParams
    motion_sigma : float
        Uncertainty of constant-velocity predictions, mm.
    template : float (M, 3), optional
        Neutral marker positions (NaN rows unknown).
    prior : int (T,), optional
        Current label of each tracklet (relabelling); -1 none.
    relative_sigma : float
        Typical motion of a marker relative to the common motion of its frame, mm per frame
        (see :func:`motion_scales`): the uncertainty of a prediction that knows the marker's
        neighbours but not its own velocity grows with it.
    max_step : float or None
        Fastest plausible marker motion, mm per frame: a marker last seen ``dt`` frames ago
        is not predicted (saving time) when every candidate point is farther than
        ``max_step * dt`` plus twice its spacing from where it was. None: no such shortcut.
    """

    def __init__(self, tracks: Tracklets, n_markers: int, params: AssignmentParams, motion_sigma: float,
                 template: np.ndarray | None = None, prior: np.ndarray | None = None,
                 relative_sigma: float = 0.0, max_step: float | None = None) -> None:
        self.tr = tracks
        self.M = int(n_markers)
        self.p = params
        self.sig_cv = float(max(motion_sigma, params.min_sigma))
        self.sig_rel = float(max(relative_sigma, 0.0))
        self.max_step = None if max_step is None else 1.5 * float(max_step) + 3 * self.sig_cv
        self._nb_cache: dict[tuple[int, int], tuple] = {}
        self.ref_spacing = np.full(self.M, np.inf)
        self.template = None if template is None else np.asarray(template, np.float64)
        self.prior = prior
        F = tracks.n_frames
        self.traj = np.full((F, self.M, 3), np.nan)
        self.label = np.full(len(tracks), -1, np.int64)
        self.starts: list[list[int]] = [[] for _ in range(self.M)]
        self.ends: list[list[int]] = [[] for _ in range(self.M)]
        self.allowed = np.ones(self.M, bool)
        self.samples = np.zeros(self.M, np.int64)  # frames each marker holds a tracklet
        self.t0 = 0
        self.events = 0
        self.assigned_events = 0
        self.conflicts = 0

    # ------------------------------------------------------------------ bookkeeping
    def occupied(self, L: int, a: int, b: int) -> bool:
        """Whether marker ``L`` has a tracklet in frames ``a..b``."""
        st, en = self.starts[L], self.ends[L]
        k = bisect.bisect_right(st, b) - 1
        return k >= 0 and en[k] >= a

    def assign(self, t: int, L: int) -> bool:
        """Give tracklet ``t`` label ``L`` (False, and nothing done, if ``L`` is taken there)."""
        tr = self.tr
        s, e = int(tr.start[t]), int(tr.end[t])
        if self.occupied(L, s, e):
            self.conflicts += 1
            return False
        k = bisect.bisect_right(self.starts[L], s)
        self.starts[L].insert(k, s)
        self.ends[L].insert(k, e)
        a, b = tr.offsets[t], tr.offsets[t + 1]
        self.traj[tr.frames[a:b], L] = tr.xyz[a:b]
        self.label[t] = L
        self.samples[L] += int(b - a)
        return True

    # ------------------------------------------------------------------ predictions
    def _neighbour_side(self, L: int, t: int, direction: int) -> int | None:
        """Nearest frame (before or after ``t``) where ``L`` is labelled, preferring the frame
        the pass comes from."""
        st, en = self.starts[L], self.ends[L]
        k = bisect.bisect_right(st, t) - 1
        left = en[k] if k >= 0 and en[k] < t else None
        right = st[k + 1] if k + 1 < len(st) else None
        if left is None:
            return right
        if right is None:
            return left
        dl, dr = t - left, right - t
        if dl == dr:
            return left if direction > 0 else right
        return left if dl < dr else right

    def predict(self, L: int, t: int, direction: int,
                rows_pos: np.ndarray | None = None) -> tuple | None:
        """Predictions of marker ``L`` at frame ``t``.

        Returns
        -------
        positions : (K, 3)
            One per model: constant velocity (when the marker was seen in the two adjacent
            frames) and neighbourhood shape (rigid motion of its most rigidly attached
            labelled neighbours since it was seen), or the template.
        sigmas : (K,)
            Their uncertainties, mm.
        spacing : float
            Distance to the marker's nearest other marker where it was last seen (and in the
            reference frames), mm; inf if unknown.
        age : float
            Frames since the marker was seen (inf for a template prediction).

        None when nothing is known about the marker, or (with ``rows_pos``, the candidate
        points) when every candidate is out of its reach (see ``max_step``).
        """
        g = self._neighbour_side(L, t, direction)
        traj = self.traj
        if g is None:
            return self._predict_template(L, t)
        side = 1 if g > t else -1
        xg = traj[g, L]
        dt = abs(g - t)
        key = (L, g)
        info = self._nb_cache.get(key)
        if info is None:
            others_g = np.isfinite(traj[g, :, 0])
            others_g[L] = False
            og = np.flatnonzero(others_g)
            spacing = float(np.sqrt(((traj[g, og] - xg) ** 2).sum(1).min())) if og.size else np.inf
            spacing = min(spacing, float(self.ref_spacing[L]))
            info = (spacing, *self._rank_neighbours(L, g, side, og))
            self._nb_cache[key] = info
        spacing, ranked, rigid = info
        if rows_pos is not None and self.max_step is not None and np.isfinite(spacing):
            reach = self.max_step * dt + 2.0 * spacing
            if float(((rows_pos - xg) ** 2).sum(1).min()) > reach * reach:
                return None
        pos: list[np.ndarray] = []
        sig: list[float] = []
        if dt == 1:
            g2 = g + side
            if 0 <= g2 < traj.shape[0] and np.isfinite(traj[g2, L, 0]):
                pos.append(2 * xg - traj[g2, L])
                sig.append(self.sig_cv)
        growth = 1.0 + self.p.gap_growth * np.sqrt(dt)
        # the marker's own, unknown, velocity matters right after it was seen (no velocity yet)
        own = self.sig_rel if (dt <= 2 and not pos) else 0.0
        present = np.isfinite(traj[t, ranked, 0]) & np.isfinite(traj[g, ranked, 0])
        near, spread = ranked[present], rigid[present]
        if near.size > 3 and np.isfinite(spread[0]):
            # only neighbours about as rigidly attached as the best (same body segment)
            ok = spread <= 3.0 * spread[0] + 0.5
            ok[:3] = True
            near, spread = near[ok], spread[ok]
        near, spread = near[:self.p.neighbours], spread[:self.p.neighbours]
        # how much the neighbours' distances to the marker varied: a floor for the uncertainty
        loose = float(spread.max()) if spread.size and np.isfinite(spread).all() else 0.0
        if near.size == 0:
            if not pos:
                pos.append(xg.copy())
                sig.append(max(self.sig_cv * (1.0 + dt), own) * growth)
        else:
            A, B = traj[g, near], traj[t, near]
            if near.size >= 3:
                R, ca, cb = kabsch(A, B)
                res = ((A - ca) @ R.T) + cb - B
                rms = float(np.sqrt((res * res).sum() / near.size))
                pos.append(R @ (xg - ca) + cb)
                sig.append(max(self.sig_cv, 1.5 * rms, own, loose) * growth)
            else:
                shift = (B - A).mean(0)
                spread_t = float(np.sqrt(((B - A - shift) ** 2).sum(1).max())) if near.size > 1 else 0.0
                pos.append(xg + shift)
                sig.append(max(self.sig_cv * 2, 1.5 * spread_t, own, loose) * growth)
        return np.asarray(pos), np.asarray(sig), spacing, float(dt)

    def _rank_neighbours(self, L: int, g: int, side: int, cand: np.ndarray, *,
                         history: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Candidates (labelled at ``g``) ordered by how rigidly they moved with ``L`` over the
        history window ending at frame ``g`` (on the side away from the event): smallest
        spread of their distance to ``L`` (mm, returned as the second array), plus a small
        preference for near ones. Only the ``4 K`` nearest at ``g`` are ranked (then the rest
        by distance, spread inf), over at most 10 history frames."""
        if cand.size == 0:
            return cand, np.zeros(0)
        traj = self.traj
        K = self.p.neighbours
        dg = traj[g, cand] - traj[g, L]
        d_g = np.sqrt((dg * dg).sum(1))
        order = np.argsort(d_g, kind="stable")
        head, tail = order[:4 * K], order[4 * K:]
        c, dh = cand[head], d_g[head]
        H = self.p.history if history is None else int(history)
        a, b = (g - H, g + 1) if side < 0 else (g, g + H + 1)
        a, b = max(a, 0), min(b, traj.shape[0])
        rows = np.unique(np.linspace(a, b - 1, min(10, b - a)).astype(int))
        diff = traj[rows][:, c] - traj[rows, L][:, None, :]
        dist = np.sqrt((diff * diff).sum(2))  # (W, C), NaN where either missing
        fin = np.isfinite(dist)
        n_ok = fin.sum(0)
        dz = np.where(fin, dist, 0.0)
        n = np.maximum(n_ok, 1)
        mean = dz.sum(0) / n
        spread = np.sqrt(np.maximum((dz * dz).sum(0) / n - mean * mean, 0.0))
        score = np.where(n_ok >= 3, spread, np.inf) + 0.02 * dh
        if not np.isfinite(score).any():
            score = dh
        o = np.argsort(score, kind="stable")
        return np.concatenate([c[o], cand[tail]]), np.concatenate([score[o], np.full(tail.size, np.inf)])

    def _predict_template(self, L: int, t: int) -> tuple | None:
        """Template model for a marker never seen: the template's local rigid fit (see
        :meth:`predict` for the returned tuple)."""
        tp = self.template
        if tp is None or not np.isfinite(tp[L]).all():
            return None
        occ = np.isfinite(self.traj[t, :, 0]) & np.isfinite(tp[:, 0])
        occ[L] = False
        idx = np.flatnonzero(occ)
        if idx.size < 3:
            return None
        d = np.linalg.norm(tp[idx] - tp[L], axis=1)
        K = min(max(self.p.neighbours, 4), idx.size)
        near = idx[np.argsort(d)[:K]]
        A, B = tp[near], self.traj[t, near]
        R, ca, cb = kabsch(A, B)
        rms = float(np.sqrt(np.mean(np.sum((((A - ca) @ R.T) + cb - B) ** 2, axis=1))))
        others = np.isfinite(tp[:, 0])
        others[L] = False
        spacing = float(np.linalg.norm(tp[others] - tp[L], axis=1).min()) if others.any() else np.inf
        return (R @ (tp[L] - ca) + cb)[None], np.array([max(self.sig_cv * 2, 1.5 * rms)]), spacing, np.inf

    # ------------------------------------------------------------------ one event
    def solve_event(self, t: int, rows: np.ndarray, direction: int) -> None:
        """Assign the tracklets ``rows`` (all starting, in the pass direction, at frame ``t``)."""
        self.events += 1
        tr = self.tr
        traj = self.traj
        open_l = np.flatnonzero(~np.isfinite(traj[t, :, 0]) & self.allowed)
        if open_l.size == 0:
            return
        pos = np.array([tr.sample_at(int(r), t) for r in rows])
        if self.prior is not None and self._keep_priors(t, rows, pos, direction):
            return
        preds = []
        for L in open_l:
            pr = self.predict(int(L), t, direction, pos)
            if pr is not None:
                preds.append((int(L), pr))
        if not preds:
            return
        lab = np.array([L for L, _ in preds])
        n, k = len(rows), len(preds)
        norm = np.empty((n, k))
        cost = np.empty((n, k))
        sharp = np.empty(k)
        for c, (_L, (P, S, _sp, _age)) in enumerate(preds):
            d2 = ((pos[:, None, :] - P[None]) ** 2).sum(-1)
            nm = d2 / S[None] ** 2
            # -2 log-likelihood of each model (up to a constant): an uncertain prediction pays
            # for its width, so it does not grab a point a sharp prediction explains; the best
            # model (motion or shape) speaks for the marker. (Relabelling asks whether the
            # current label is consistent, not which label is most likely: no width penalty.)
            cs = nm + 6.0 * np.log(S[None] / self.sig_cv) if self.prior is None else nm
            if self.prior is None:
                # a marker rarely present so far (a ghost's label) is an unlikely owner
                rate = min(1.0, self.samples[_L] / (abs(t - self.t0) + 1.0))
                cs = cs - 2.0 * np.log(max(rate, 0.01))
            best = cs.argmin(1)
            norm[:, c] = np.where((nm <= self.p.gate ** 2).any(1), np.minimum(nm[np.arange(n), best], self.p.gate ** 2),
                                  nm[np.arange(n), best])
            cost[:, c] = cs[np.arange(n), best]
            sharp[c] = S.min()
        allowed = norm <= self.p.gate ** 2
        spac = np.array([pr[2] for _, pr in preds])
        ages = np.array([pr[3] for _, pr in preds])
        # a point closer to an occupied marker than a fraction of the marker's spacing is a
        # ghost of that marker, not this one
        occ = np.flatnonzero(np.isfinite(traj[t, :, 0]) & self.allowed)
        if occ.size:
            dq = np.sqrt(((pos[:, None, :] - traj[t, occ][None]) ** 2).sum(-1)).min(1)
            allowed &= dq[:, None] >= self.p.spacing_cap * spac[None]
        # an uncertain prediction after a gap needs more than a one- or two-frame tracklet
        length = tr.offsets[rows + 1] - tr.offsets[rows]
        stale = (sharp > 3 * self.sig_cv) & (ages > 2)
        allowed &= ~(stale[None] & (length[:, None] < self.p.min_samples) & (norm > 1.0))
        if self.prior is not None:
            # relabelling: the current label is always possible and gets a bonus of
            # ``prior_bonus`` (evidence another label must beat)
            hit = self.prior[rows][:, None] == lab[None]
            capped = np.minimum(cost, 4.0 * self.p.gate ** 2) - self.p.prior_bonus
            cost = np.where(hit, capped, cost)
            allowed |= hit
        if not allowed.any():
            return
        # spans: a label already used elsewhere in a tracklet's span is not allowed
        for i, r in enumerate(rows):
            s, e = int(tr.start[r]), int(tr.end[r])
            for c in np.flatnonzero(allowed[i]):
                if self.occupied(int(lab[c]), s, e):
                    allowed[i, c] = False
        C = np.full((n, k + n), _BIG)
        C[:, :k] = np.where(allowed, cost, _BIG)
        C[np.arange(n), k + np.arange(n)] = _UNASSIGNED  # any allowed assignment is preferred
        ri, ci = linear_sum_assignment(C)
        for i, c in zip(ri, ci):
            if c < k and C[i, c] < _BIG:
                if self.assign(int(rows[i]), int(lab[c])):
                    self.assigned_events += 1

    def _keep_priors(self, t: int, rows: np.ndarray, pos: np.ndarray, direction: int) -> bool:
        """Relabelling fast path: when every row's current label is free and predicts it
        within ``prior_accept`` sigmas (and that prediction is sharp: at most two motion sigmas),
        keep the current labels without a full assignment."""
        pri = self.prior[rows]
        if (pri < 0).any() or len(np.unique(pri)) != len(pri) or not self.allowed[pri].all():
            return False
        if np.isfinite(self.traj[t, pri, 0]).any():
            return False
        for r, L, x in zip(rows, pri, pos):
            pr = self.predict(int(L), t, direction)
            if pr is None:
                return False
            ok = (pr[1] <= 2 * self.sig_cv) & (((x - pr[0]) ** 2).sum(1) <= (self.p.prior_accept * pr[1]) ** 2)
            if not ok.any():
                return False
            if self.occupied(int(L), int(self.tr.start[r]), int(self.tr.end[r])):
                return False
        for r, L in zip(rows, pri):
            self.assign(int(r), int(L))
        return True

    # ------------------------------------------------------------------ passes
    def set_reference_spacing(self, frames: np.ndarray) -> None:
        """Each marker's spacing: the smallest distance to another marker over the given
        (labelled) frames; the spacing rule uses the smaller of it and the spacing where the
        marker was last seen (a neighbour missing there would inflate the latter)."""
        for f in np.asarray(frames, np.int64).ravel():
            X = self.traj[f]
            ok = np.flatnonzero(np.isfinite(X[:, 0]))
            if ok.size < 2:
                continue
            d = np.sqrt(((X[ok, None, :] - X[None, ok, :]) ** 2).sum(-1))
            np.fill_diagonal(d, np.inf)
            self.ref_spacing[ok] = np.minimum(self.ref_spacing[ok], d.min(1))

    def run(self, t0: int, progress: ProgressFn | None = None) -> None:
        """Forward pass from ``t0`` then backward pass from ``t0``, over unlabelled tracklets.

        A tracklet left unlabelled at its start is tried again a few times further along
        (``retries`` frames later, within its span): neighbours missing at its start may be
        back, or a marker's prediction may be clearer. If it is labelled then, the whole
        tracklet takes the label.
        """
        self.t0 = int(t0)
        tr = self.tr
        un = np.flatnonzero(self.label < 0)
        fwd = un[tr.end[un] >= t0]
        bwd = un[tr.end[un] < t0]
        total = len(fwd) + len(bwd)
        done = 0
        for rows_all, direction in ((fwd, 1), (bwd, -1)):
            if len(rows_all) == 0:
                continue
            first = np.maximum(tr.start[rows_all], t0) if direction > 0 else tr.end[rows_all]
            # heap of (pass-ordered frame, retry count, tracklet)
            heap = [(int(f) * direction, 0, int(r)) for f, r in zip(first, rows_all)]
            heapq.heapify(heap)
            while heap:
                key = heap[0][0]
                batch = []
                while heap and heap[0][0] == key:
                    batch.append(heapq.heappop(heap))
                t = key * direction
                rows = np.array([r for _, _, r in batch if self.label[r] < 0], np.int64)
                if rows.size:
                    self.solve_event(t, rows, direction)
                for _, k, r in batch:
                    if self.label[r] >= 0 or k >= len(self.p.retries):
                        if k == 0:
                            done += 1
                        continue
                    nxt = t + direction * self.p.retries[k]
                    if tr.start[r] <= nxt <= tr.end[r] and tr.sample_at(r, nxt) is not None:
                        heapq.heappush(heap, (nxt * direction, k + 1, r))
                    elif k == 0:
                        done += 1
                if progress is not None and progress(done, total) is False:
                    return


def motion_scales(points: np.ndarray, links: np.ndarray, *, sample: int = 300) -> tuple[float, float]:
    """Typical motion of the linked points, from at most ``sample`` evenly spaced frames.

    Returns
    -------
    relative : float
        90th percentile of how much a point's step differs from the median step of its frame,
        mm per frame (0 without enough links).
    fastest : float
        99.9th percentile of the step lengths, mm per frame.
    """
    F = points.shape[0]
    if F < 2:
        return 0.0, 0.0
    idx = np.unique(np.linspace(1, F - 1, min(F - 1, sample)).astype(int))
    lk = links[idx]
    ok = lk >= 0
    prev = np.take_along_axis(points[idx - 1], np.maximum(lk, 0)[..., None], axis=1)
    step = np.where(ok[..., None], points[idx] - prev, np.nan)
    cnt = ok.sum(1)
    if int(ok.sum()) < 10:
        return 0.0, 0.0
    srt = np.sort(step, axis=1)  # NaN last
    r = np.arange(len(idx))
    lo, hi = np.maximum((cnt - 1) // 2, 0), np.maximum(cnt // 2, 0)
    med = 0.5 * (srt[r, lo] + srt[r, hi])  # (S, 3)
    dev = np.linalg.norm(step - med[:, None, :], axis=2)[ok]
    mag = np.linalg.norm(step, axis=2)[ok]
    return float(np.percentile(dev, 90)), float(np.percentile(mag, 99.9))
