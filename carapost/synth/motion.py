"""Motion over a take: expression curves, blinks, helmet slip and camera flex.

Everything is drawn from ``numpy`` generators seeded from the take's seed, so a config
always produces the same motion. Frame 0 is neutral (no expression, no slip) so seeds and
the nominal calibration are easy to use; camera flex is already present at frame 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carapost.core.camera import rodrigues

from .expressions import CHANNELS

__all__ = ["Motion", "make_motion", "BLINK_HIDDEN_LEVEL"]

#: Blink amplitude from which the upper-lid markers are hidden (lost in the lashes and fold).
BLINK_HIDDEN_LEVEL = 0.5
_CH = {name: i for i, name in enumerate(CHANNELS)}


@dataclass(frozen=True)
class Motion:
    """Per-frame motion of a take.

    Attributes
    ----------
    expression : array (F, K)
        Expression amplitudes per frame (channels :data:`~carapost.synth.expressions.CHANNELS`).
    head_R, head_t : arrays (F, 3, 3), (F, 3)
        Head-to-world pose per frame (rest pose plus helmet slip).
    R, t : arrays (F, C, 3, 3), (F, C, 3)
        World-to-camera poses per frame (nominal plus flex).
    events : list of (str, int, int)
        ``(channel, first frame, last frame)`` of each expression event and blink.
    """

    expression: np.ndarray
    head_R: np.ndarray
    head_t: np.ndarray
    R: np.ndarray
    t: np.ndarray
    events: list[tuple[str, int, int]]

    @property
    def blink(self) -> np.ndarray:
        """Blink amplitude per frame and eye, (F, 2) for (left, right)."""
        return self.expression[:, [_CH["blink_L"], _CH["blink_R"]]]


def _pulse(n: int, start: float, rise: float, hold: float, fall: float) -> np.ndarray:
    """0..1 raised-cosine pulse over frames ``0..n-1`` (times in frames)."""
    f = np.arange(n, dtype=float)
    up = np.clip((f - start) / max(rise, 1e-9), 0.0, 1.0)
    down = np.clip((f - start - rise - hold) / max(fall, 1e-9), 0.0, 1.0)
    return 0.5 * (1 - np.cos(np.pi * up)) * 0.5 * (1 + np.cos(np.pi * down))


def _expressions(n: int, fps: float, rng: np.random.Generator, *, expressions: bool, blinks: bool,
                 high_motion: bool) -> tuple[np.ndarray, list[tuple[str, int, int]]]:
    curves = np.zeros((n, len(CHANNELS)))
    events: list[tuple[str, int, int]] = []
    if expressions:
        kinds = ["jaw", "smile", "pucker", "puff", "brow", "jaw+smile", "jaw+brow", "smile_L", "smile_R", "brow_L"]
        order: list[str] = []
        t = (0.1 if high_motion else 0.15) * fps + rng.uniform(0, 0.1) * fps
        while t < n:
            if not order:  # every kind once, in a random order, before any repeats
                order = [kinds[i] for i in rng.permutation(len(kinds))]
            kind = order.pop()
            if high_motion:
                dur = rng.uniform(0.2, 0.45) * fps
                amp = rng.uniform(0.8, 1.0)
                gap = rng.uniform(0.03, 0.2) * fps
            else:
                dur = rng.uniform(0.6, 1.4) * fps
                amp = rng.uniform(0.5, 1.0)
                gap = rng.uniform(0.1, 0.5) * fps
            rise = dur * rng.uniform(0.25, 0.4)
            fall = dur * rng.uniform(0.25, 0.4)
            hold = max(dur - rise - fall, 0.0)
            p = _pulse(n, t, rise, hold, fall)
            chans: dict[str, float] = {}
            for part in kind.split("+"):
                if part in ("smile", "brow"):
                    asym = rng.uniform(0.75, 1.0)
                    first = rng.integers(2)
                    chans[f"{part}_L"] = amp * (asym if first else 1.0)
                    chans[f"{part}_R"] = amp * (1.0 if first else asym)
                else:
                    chans[part] = amp
            for ch, a in chans.items():
                curves[:, _CH[ch]] = np.maximum(curves[:, _CH[ch]], a * p)
                events.append((ch, int(np.floor(t)), int(np.ceil(t + dur))))
            t += dur * rng.uniform(0.5, 0.8) + gap
    if blinks and n >= 12:
        interval = (0.8, 2.0) if high_motion else (1.5, 4.0)
        # the first blink falls inside short takes too
        t = min(rng.uniform(0.3, 1.2) * fps, max(n / 2 - 8.0, 1.0))
        while t + 6 < n:
            rise = rng.uniform(0.05, 0.07) * fps
            hold = rng.uniform(0.03, 0.06) * fps
            fall = rng.uniform(0.08, 0.12) * fps
            p = _pulse(n, t, rise, hold, fall)
            for ch in ("blink_L", "blink_R"):
                curves[:, _CH[ch]] = np.maximum(curves[:, _CH[ch]], p)
                events.append((ch, int(np.floor(t)), int(np.ceil(t + rise + hold + fall))))
            t += rng.uniform(*interval) * fps
    return curves, events


def _smooth_random(n: int, fps: float, rng: np.random.Generator, shape: tuple[int, ...],
                   freqs: tuple[float, float], k: int = 3) -> np.ndarray:
    """Sum of ``k`` random sinusoids per component, unit RMS, array (n,) + shape."""
    t = np.arange(n) / fps
    out = np.zeros((n,) + shape)
    for _ in range(k):
        f = rng.uniform(*freqs, size=shape)
        ph = rng.uniform(0, 2 * np.pi, size=shape)
        out += np.sin(2 * np.pi * f * t.reshape((n,) + (1,) * len(shape)) + ph)
    return out / np.sqrt(k / 2.0)


def make_motion(n_frames: int, fps: float, rig_R: np.ndarray, rig_t: np.ndarray, head_R: np.ndarray,
                head_t: np.ndarray, seed: int, *, expressions: bool = True, blinks: bool = True,
                high_motion: bool = False, slip_mm: float = 2.0, flex: bool = True,
                caddies: tuple[tuple[int, int], ...] = ((0, 1), (2, 3))) -> Motion:
    """Draw the motion of a take.

    Parameters
    ----------
    n_frames, fps : int, float
    rig_R, rig_t : arrays (C, 3, 3), (C, 3)
        Nominal world-to-camera poses.
    head_R, head_t : arrays (3, 3), (3,)
        Rest head-to-world pose.
    seed : int

    Returns
    -------
    Motion
    """
    ss = np.random.SeedSequence([int(seed), 4242])
    r_expr, r_slip, r_flex = (np.random.default_rng(s) for s in ss.spawn(3))
    n = int(n_frames)
    curves, events = _expressions(n, fps, r_expr, expressions=expressions, blinks=blinks, high_motion=high_motion)

    # helmet slip: a slow, mostly vertical drift of the head with a little pitch, plus a wobble
    frac = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    ramp = frac * frac * (3 - 2 * frac)
    d = np.array([r_slip.normal(0, 0.4), -1.0, r_slip.normal(0, 0.3)])
    d /= np.linalg.norm(d)
    trans = slip_mm * ramp[:, None] * d
    wob_f = r_slip.uniform(0.3, 0.7)
    tt = np.arange(n) / fps
    trans = trans + 0.08 * slip_mm * np.sin(2 * np.pi * wob_f * tt)[:, None] * r_slip.normal(0, 1, 3)
    axis = np.array([1.0, r_slip.normal(0, 0.3), r_slip.normal(0, 0.3)])
    axis /= np.linalg.norm(axis)
    ang = np.deg2rad(0.15) * slip_mm * ramp
    Rs = rodrigues(ang[:, None] * axis)
    pivot = head_R @ np.array([0.0, -20.0, -70.0]) + head_t  # about the middle of the head
    hR = Rs @ head_R
    ht = np.einsum("fij,j->fi", Rs, head_t - pivot) + pivot + trans

    # camera flex: each arm bends about its mount on the helmet, plus per-camera jitter
    C = rig_R.shape[0]
    R = np.broadcast_to(rig_R, (n, C, 3, 3)).copy()
    t = np.broadcast_to(rig_t, (n, C, 3)).copy()
    if flex:
        centres = -np.einsum("cji,cj->ci", rig_R, rig_t)
        for cams in caddies:
            cams = [c for c in cams if c < C]
            if not cams:
                continue
            mount = centres[cams].mean(axis=0) * np.array([1.0, 0.0, 0.0]) + np.array([0.0, 30.0, 20.0])
            w_arm = np.deg2rad(0.022) * _smooth_random(n, fps, r_flex, (3,), (0.3, 3.0))
            Ra = rodrigues(w_arm)
            for c in cams:
                w_cam = np.deg2rad(0.008) * r_flex.standard_normal((n, 3))
                d_cam = 0.02 * r_flex.standard_normal((n, 3))
                Rf = rodrigues(w_cam) @ Ra
                Cc = np.einsum("fij,j->fi", Ra, centres[c] - mount) + mount + d_cam
                R[:, c] = np.einsum("ij,fkj->fik", rig_R[c], Rf)
                t[:, c] = -np.einsum("fij,fj->fi", R[:, c], Cc)
    return Motion(expression=curves, head_R=hR, head_t=ht, R=R, t=t, events=events)
