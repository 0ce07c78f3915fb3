"""Synthetic labelled marker trajectories for the labelling algorithms (no images).

Two kinds of marker sets, both in millimetres:

* :func:`face_motion` - a face-like set: markers spread over a curved ~150 x 200 mm surface with
  upper / lower lip rows a few millimetres apart, deformed by smooth expression channels (jaw,
  smile, brow raise, pucker, lip press, a random low-frequency field) on top of head motion.
* :func:`body_motion` - a body-like set: an articulated figure (pelvis, torso, head, arms,
  hands, legs, feet) with 2-5 markers per segment, walking forward with swinging limbs.

:func:`corrupt` then makes the "recorded" data: measurement noise, dropouts (gaps), spurious
points (isolated ones anywhere in the capture volume and ghost tracks next to real markers) and
swapped pairs of labels. :func:`carapost.core.labelling.points_from_trajectories` hides the
labels (shuffled per frame).

Everything is deterministic given the seed. The face markers of :mod:`carapost.synth.take` are
the truth for full synthetic takes; these generators are faster (no surface or visibility) and
cover body-like data too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MarkerMotion", "Corruption", "face_motion", "body_motion", "corrupt"]


@dataclass
class MarkerMotion:
    """Ground-truth labelled trajectories.

    Attributes
    ----------
    names : list of str (M,)
    xyz : float64 (F, M, 3)
        Exact marker positions, mm (no gaps).
    frame_rate : float
        Hz.
    sticks : int64 (S, 2)
        Marker index pairs (segments / neighbours), for display and skeleton tests.
    """

    names: list[str]
    xyz: np.ndarray
    frame_rate: float
    sticks: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))

    @property
    def n_frames(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.xyz.shape[1])


@dataclass
class Corruption:
    """Recorded data made from a :class:`MarkerMotion` by :func:`corrupt`.

    Attributes
    ----------
    xyz : float64 (F, M, 3)
        Noisy labelled positions with NaN gaps, and with the injected swaps applied.
    clean_labels_xyz : float64 (F, M, 3)
        The same samples (noise and gaps) with the correct labels (no swaps).
    spurious : float64 (F, S, 3)
        Spurious points per frame (NaN padded).
    swaps : list of (int, int, int, int)
        Injected swaps ``(a, b, start, end)``: columns ``a`` and ``b`` exchanged in frames
        ``start <= f < end``.
    """

    xyz: np.ndarray
    clean_labels_xyz: np.ndarray
    spurious: np.ndarray
    swaps: list[tuple[int, int, int, int]]


# ------------------------------------------------------------------------------ helpers
def _smooth_signal(rng: np.random.Generator, t: np.ndarray, n: int, fmin: float, fmax: float) -> np.ndarray:
    """``n`` smooth random signals in [-1, 1] (sums of sinusoids), shape (F, n)."""
    k = 4
    freq = rng.uniform(fmin, fmax, (n, k))
    phase = rng.uniform(0, 2 * np.pi, (n, k))
    amp = rng.uniform(0.3, 1.0, (n, k))
    s = (amp[None] * np.sin(2 * np.pi * freq[None] * t[:, None, None] + phase[None])).sum(-1)
    return s / amp.sum(-1)[None]


def _rot(axis_angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) (Rodrigues)."""
    th = np.linalg.norm(axis_angle, axis=-1, keepdims=True)
    k = axis_angle / np.where(th > 0, th, 1.0)
    K = np.zeros(axis_angle.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    s, c = np.sin(th)[..., None], np.cos(th)[..., None]
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + s * K + (1 - c) * (K @ K)


def _poisson_disk(rng: np.random.Generator, n: int, half_w: float, half_h: float, spacing: float,
                  exclude: np.ndarray) -> np.ndarray:
    """``n`` points in the ellipse (half_w, half_h), at least ``spacing`` from each other and
    from ``exclude`` (dart throwing, spacing relaxed if the ellipse is full)."""
    pts = [p for p in exclude]
    out: list[np.ndarray] = []
    s = spacing
    tries = 0
    while len(out) < n:
        c = rng.uniform(-1, 1, 2) * (half_w, half_h)
        tries += 1
        if (c[0] / half_w) ** 2 + (c[1] / half_h) ** 2 > 1:
            continue
        if pts and np.min(np.linalg.norm(np.asarray(pts) - c, axis=1)) < s:
            if tries > 4000:
                s *= 0.95
                tries = 0
            continue
        pts.append(c)
        out.append(c)
    return np.asarray(out).reshape(-1, 2)


# ----------------------------------------------------------------------------- face set
def face_motion(n_markers: int = 80, n_frames: int = 600, frame_rate: float = 60.0, *, seed: int = 0,
                head_motion: float = 1.0, expression: float = 1.0, lip_gap_mm: float = 6.0) -> MarkerMotion:
    """A face-like marker set moving with expressions and head motion.

    Parameters
    ----------
    n_markers : int
        At least 20; 16 of them (8 upper-lip and 8 lower-lip markers) sit on two rows
        ``lip_gap_mm`` apart at rest.
    n_frames : int
    frame_rate : float
        Hz; the motion is defined in seconds, so higher rates give smaller steps per frame.
    seed : int
    head_motion : float
        Scale of the rigid head motion (1: about +-12 degrees and +-30 mm).
    expression : float
        Scale of the expressions (1: jaw opening up to ~25 mm, smiles ~10 mm).
    lip_gap_mm : float
        Rest distance between the lip rows (lip presses bring them to ~40 % of it).

    Returns
    -------
    MarkerMotion
    """
    if n_markers < 20:
        raise ValueError(f"a face marker set needs at least 20 markers, got {n_markers}")
    if n_frames < 1 or frame_rate <= 0:
        raise ValueError("n_frames must be >= 1 and frame_rate positive")
    rng = np.random.default_rng(seed)
    # Rest layout (head frame: x right, y up, z towards the viewer), mouth centred at y = -40.
    lip_x = np.linspace(-22, 22, 8)
    upper = np.stack([lip_x, -40 + lip_gap_mm / 2 + 2 * (1 - (lip_x / 22) ** 2)], 1)
    lower = np.stack([lip_x, -40 - lip_gap_mm / 2 - 2 * (1 - (lip_x / 22) ** 2)], 1)
    lips = np.concatenate([upper, lower])
    spacing = 0.9 * np.sqrt(np.pi * 75 * 100 / max(n_markers - 16, 1))
    rest2d = np.concatenate([lips, _poisson_disk(rng, n_markers - 16, 75, 100, spacing, lips)])
    x, y = rest2d[:, 0], rest2d[:, 1]
    z = 60 - x ** 2 / 150 - y ** 2 / 260 + 18 * np.exp(-(x ** 2 + (y + 5) ** 2) / 300)  # nose bump
    rest = np.stack([x, y, z], 1)
    names = [f"LipUpper_{i + 1}" for i in range(8)] + [f"LipLower_{i + 1}" for i in range(8)]
    names += [f"Face_{i + 1}" for i in range(n_markers - 16)]

    t = np.arange(n_frames) / frame_rate
    ch = 0.5 * (1 + _smooth_signal(rng, t, 6, 0.1, 0.8))  # (F, 6) in [0, 1]
    jaw, smile, brow, pucker, press, field_amp = (ch[:, k] for k in range(6))
    press = np.clip(2 * press - 1, 0, 1) * (1 - jaw)  # presses only when the jaw is closed
    e = expression
    below = 1 / (1 + np.exp(-(-40 - y) / 4))  # 1 under the mouth
    below[8:16] = 1.0
    below[:8] = 0.0
    disp = np.zeros((n_frames, n_markers, 3))
    disp += e * 25 * jaw[:, None, None] * below[None, :, None] * np.array([0, -1, -0.35])
    for side in (-1, 1):
        w = np.exp(-((x - side * 25) ** 2 + (y + 40) ** 2) / (2 * 22 ** 2))
        disp += e * 10 * smile[:, None, None] * w[None, :, None] * np.array([side * 0.8, 0.6, 0.2])
    above = 1 / (1 + np.exp(-(y - 45) / 6))
    disp += e * 8 * brow[:, None, None] * above[None, :, None] * np.array([0, 1, 0.1])
    wm = np.exp(-(x ** 2 + (y + 40) ** 2) / (2 * 18 ** 2))
    disp += e * 6 * pucker[:, None, None] * wm[None, :, None] * np.stack([-x / 25, np.zeros_like(x),
                                                                            np.ones_like(x)], 1)[None]
    lip_sign = np.zeros(n_markers)
    lip_sign[:8], lip_sign[8:16] = -1, 1
    disp[..., 1] += (0.3 * lip_gap_mm) * press[:, None] * lip_sign[None] * e
    centres = rng.uniform(-1, 1, (5, 2)) * (60, 80)
    dirs = rng.normal(size=(5, 3))
    amps = _smooth_signal(rng, t, 5, 0.05, 0.5) * field_amp[:, None]
    for k in range(5):
        w = np.exp(-((x - centres[k, 0]) ** 2 + (y - centres[k, 1]) ** 2) / (2 * 35 ** 2))
        disp += e * 3 * amps[:, k, None, None] * w[None, :, None] * dirs[k][None, None]
    local = rest[None] + disp
    rv = head_motion * np.deg2rad(12) * _smooth_signal(rng, t, 3, 0.05, 0.4)
    tr = head_motion * 30 * _smooth_signal(rng, t, 3, 0.05, 0.4) + np.array([0, 0, 1500.0])
    R = _rot(rv)
    xyz = np.einsum("fij,fmj->fmi", R, local) + tr[:, None, :]
    # Sticks: each marker to its two nearest neighbours at rest (unique pairs).
    d = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    nn = np.argsort(d, axis=1)[:, :2]
    pairs = {tuple(sorted((i, int(j)))) for i in range(n_markers) for j in nn[i]}
    return MarkerMotion(names, xyz, float(frame_rate), np.array(sorted(pairs), np.int64).reshape(-1, 2))


# ----------------------------------------------------------------------------- body set
# (name, parent, offset of the joint in the parent's frame (mm), segment axis length (mm),
#  marker count, swing axis, swing amplitude (deg), phase (cycles))
_SEGMENTS = [
    ("Pelvis", -1, (0, 0, 0), 120, 4, (0, 0, 1), 6, 0.0),
    ("Torso", 0, (0, 0, 100), 420, 5, (1, 0, 0), 6, 0.25),
    ("Head", 1, (0, 0, 420), 200, 4, (0, 1, 0), 10, 0.1),
    ("LUpperArm", 1, (0, 190, 380), -290, 3, (0, 1, 0), 25, 0.5),
    ("LForearm", 3, (0, 0, -290), -260, 3, (0, 1, 0), 20, 0.6),
    ("LHand", 4, (0, 0, -260), -90, 3, (1, 0, 0), 15, 0.7),
    ("RUpperArm", 1, (0, -190, 380), -290, 3, (0, 1, 0), 25, 0.0),
    ("RForearm", 6, (0, 0, -290), -260, 3, (0, 1, 0), 20, 0.1),
    ("RHand", 7, (0, 0, -260), -90, 3, (1, 0, 0), 15, 0.2),
    ("LThigh", 0, (0, 95, -40), -420, 3, (0, 1, 0), 30, 0.0),
    ("LShank", 9, (0, 0, -420), -410, 3, (0, 1, 0), 35, 0.2),
    ("LFoot", 10, (0, 0, -410), 160, 2, (0, 1, 0), 15, 0.35),
    ("RThigh", 0, (0, -95, -40), -420, 3, (0, 1, 0), 30, 0.5),
    ("RShank", 12, (0, 0, -420), -410, 3, (0, 1, 0), 35, 0.7),
    ("RFoot", 13, (0, 0, -410), 160, 2, (0, 1, 0), 15, 0.85),
]


def body_motion(n_frames: int = 600, frame_rate: float = 120.0, *, seed: int = 0, speed_mm_s: float = 1300.0,
                cadence_hz: float = 0.9, min_spacing_mm: float = 40.0) -> MarkerMotion:
    """A body-like articulated marker set walking forward.

    Parameters
    ----------
    n_frames : int
    frame_rate : float
        Hz.
    seed : int
        Marker placement and motion variation.
    speed_mm_s : float
        Forward walking speed.
    cadence_hz : float
        Gait cycles per second (limb swing frequency).
    min_spacing_mm : float
        Markers are placed at least this far apart in the rest pose (real marker sets keep
        markers apart so that cameras can separate them).

    Returns
    -------
    MarkerMotion
        47 markers named ``<Segment>_<k>``; sticks join the markers of each segment in a chain
        and each segment's first marker to its parent's first marker.
    """
    if n_frames < 1 or frame_rate <= 0:
        raise ValueError("n_frames must be >= 1 and frame_rate positive")
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / frame_rate
    S = len(_SEGMENTS)
    seg_R = np.zeros((n_frames, S, 3, 3))
    seg_o = np.zeros((n_frames, S, 3))
    names: list[str] = []
    local: list[np.ndarray] = []
    owner: list[int] = []
    wobble = _smooth_signal(rng, t, S, 0.2, 1.5)
    placed: list[np.ndarray] = []  # rest-pose (frame 0) positions, for the spacing rule
    for s, (name, parent, off, length, n_m, axis, amp, phase) in enumerate(_SEGMENTS):
        ang = np.deg2rad(amp) * np.sin(2 * np.pi * (cadence_hz * t + phase)) + np.deg2rad(4) * wobble[:, s]
        R_loc = _rot(np.asarray(axis, float)[None] * ang[:, None])
        if parent < 0:
            yaw = np.deg2rad(10) * np.sin(2 * np.pi * 0.1 * t)
            R_root = _rot(np.stack([np.zeros_like(yaw), np.zeros_like(yaw), yaw], 1))
            seg_R[:, s] = R_root @ R_loc
            seg_o[:, s] = np.stack([speed_mm_s * t, 50 * np.sin(2 * np.pi * 0.1 * t),
                                    950 + 25 * np.sin(4 * np.pi * cadence_hz * t)], 1)
        else:
            seg_R[:, s] = seg_R[:, parent] @ R_loc
            seg_o[:, s] = seg_o[:, parent] + np.einsum("fij,j->fi", seg_R[:, parent], np.asarray(off, float))
        radius = 45 if "Arm" in name or "arm" in name or "Hand" in name else 65
        for k in range(n_m):
            spacing = min_spacing_mm
            for attempt in range(400):
                along = (k + rng.uniform(0.2, 0.8)) / n_m * length
                az = rng.uniform(0, 2 * np.pi)
                p = np.array([radius * np.cos(az), radius * np.sin(az), along])
                if name in ("Pelvis", "Torso", "Head"):
                    p = np.array([rng.uniform(-1, 1) * 110, rng.uniform(-1, 1) * 150, along])
                if "Foot" in name:
                    p = np.array([along, rng.uniform(-40, 40), -30])
                w = seg_R[0, s] @ p + seg_o[0, s]
                if not placed or np.min(np.linalg.norm(np.asarray(placed) - w, axis=1)) >= spacing:
                    break
                if attempt % 100 == 99:
                    spacing *= 0.9
            placed.append(w)
            names.append(f"{name}_{k + 1}")
            local.append(p)
            owner.append(s)
    local_a = np.asarray(local)
    own = np.asarray(owner)
    xyz = np.einsum("fmij,mj->fmi", seg_R[:, own], local_a) + seg_o[:, own]
    sticks = []
    first = {}
    for m, s in enumerate(own):
        if s in first:
            sticks.append((m - 1, m))
        else:
            first[s] = m
    for s, (_, parent, *_r) in enumerate(_SEGMENTS):
        if parent >= 0:
            sticks.append((first[parent], first[s]))
    return MarkerMotion(names, xyz, float(frame_rate), np.array(sticks, np.int64))


# ----------------------------------------------------------------------------- corruption
def corrupt(motion: MarkerMotion, *, seed: int = 0, noise_mm: float = 0.1, gap_rate: float = 0.002,
            mean_gap: float = 8.0, spurious_rate: float = 0.05, ghost_tracks: int = 0, n_swaps: int = 0,
            swap_length: tuple[int, int] = (10, 200)) -> Corruption:
    """Recorded data from exact trajectories.

    Parameters
    ----------
    motion : MarkerMotion
    seed : int
    noise_mm : float
        Standard deviation of the Gaussian measurement noise, mm (each coordinate).
    gap_rate : float
        Probability per marker and frame that a gap starts.
    mean_gap : float
        Mean gap length, frames (geometric distribution).
    spurious_rate : float
        Mean number of isolated spurious points per frame (Poisson), uniform in the markers'
        bounding box grown by 20 %.
    ghost_tracks : int
        Spurious tracks of 5-60 frames following a random marker at 6-15 mm (reflections).
    n_swaps : int
        Pairs of neighbouring markers whose labels are exchanged over a random range.
    swap_length : (int, int)
        Range of swap lengths, frames.

    Returns
    -------
    Corruption
    """
    rng = np.random.default_rng(seed)
    F, M, _ = motion.xyz.shape
    xyz = motion.xyz + rng.normal(0, noise_mm, motion.xyz.shape)
    gap = np.zeros((F, M), bool)
    starts = rng.random((F, M)) < gap_rate
    for f, m in zip(*np.nonzero(starts)):
        L = int(rng.geometric(1.0 / max(mean_gap, 1.0)))
        gap[f:f + L, m] = True
    xyz[gap] = np.nan
    clean = xyz.copy()
    # Spurious points
    lo = np.nanmin(motion.xyz, axis=1)
    hi = np.nanmax(motion.xyz, axis=1)
    pad = 0.2 * (hi - lo)
    counts = rng.poisson(spurious_rate, F)
    ghost_len = rng.integers(5, 61, ghost_tracks) if ghost_tracks else np.zeros(0, int)
    ghost_start = rng.integers(0, max(F - 1, 1), ghost_tracks) if ghost_tracks else np.zeros(0, int)
    ghost_m = rng.integers(0, M, ghost_tracks)
    ghost_off = rng.normal(size=(ghost_tracks, 3))
    ghost_off *= rng.uniform(6, 15, (ghost_tracks, 1)) / np.linalg.norm(ghost_off, axis=1, keepdims=True)
    per_frame_ghosts = np.zeros(F, int)
    for s0, L in zip(ghost_start, ghost_len):
        per_frame_ghosts[s0:s0 + L] += 1
    S = int(max((counts + per_frame_ghosts).max(initial=0), 0))
    spur = np.full((F, S, 3), np.nan)
    fill = np.zeros(F, int)
    for f in np.flatnonzero(counts):
        k = counts[f]
        spur[f, :k] = rng.uniform(lo[f] - pad[f], hi[f] + pad[f], (k, 3))
        fill[f] = k
    for g in range(ghost_tracks):
        for f in range(ghost_start[g], min(ghost_start[g] + ghost_len[g], F)):
            spur[f, fill[f]] = motion.xyz[f, ghost_m[g]] + ghost_off[g] + rng.normal(0, noise_mm, 3)
            fill[f] += 1
    # Swaps between neighbours (distinct markers per swap)
    swaps: list[tuple[int, int, int, int]] = []
    used: set[int] = set()
    rest = motion.xyz[F // 2]
    d = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    out = xyz.copy()
    for _ in range(n_swaps):
        for _try in range(100):
            a = int(rng.integers(M))
            b = int(np.argsort(d[a])[rng.integers(3)])
            if a not in used and b not in used:
                break
        else:
            break
        used.update((a, b))
        L = int(rng.integers(swap_length[0], swap_length[1] + 1))
        s0 = int(rng.integers(1, max(F - L, 2)))
        e0 = min(s0 + L, F)
        out[s0:e0, [a, b]] = out[s0:e0, [b, a]]
        swaps.append((a, b, s0, e0))
    return Corruption(out, clean, spur, swaps)
