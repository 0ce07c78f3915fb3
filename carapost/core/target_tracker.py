"""The Target Tracker: template tracking of points between user keyframes.

Each *track* is one point in one camera. It starts from a 2D position in a start frame and steps
frame by frame in one direction. In every new frame the pattern is searched for in the search window
placed around the last position (no motion prediction: as the guide says, widen the search box
for fast motion; a prediction would also let a lost track run away); the pattern comes from
the **previous keyframe** (the nearest keyframe at or behind the current frame in the tracking
direction) and, when there is one, the **next keyframe** ahead. Their score maps are blended
with weights that favour the nearer keyframe; the quality of a frame is the blended (or, with
``quality="min"``, the lower) normalised cross-correlation at the best position, clipped to
0..1. A track stops when

* the quality falls below the Break Threshold (that frame is not kept),
* the position leaves the image,
* the next frame already holds 2D data (other than one of the track's keyframes) and existing
  tracks must not be overwritten (``blocked``), or
* the frames to track run out (Stop after N Frames and Stop On Next Keyframe are applied by
  the caller, who chooses the frames).

A keyframe of the track met on the way is not re-tracked: its keyed position is taken and it
becomes the new previous keyframe. A track with no keyframe behind it uses its own start
position as a temporary reference (not stored).

Matching is :func:`carapost.core.target_match.locate` (one small ``matchTemplate`` per template
per frame, done per track: the number of target tracks is the user's selection, so the loop over
tracks is not the hot path; the image work inside OpenCV is). :func:`point_on_ray` gives the 3D
position of a point seen by one camera only (Allow Single Sensor Tracking).
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .camera import Intrinsics, backproject
from .target_match import MIN_TEMPLATE_STD, BoxGeometry, box_geometry, cut_patch, locate

__all__ = [
    "TrackKeys",
    "TrackSeed",
    "TargetTrackResult",
    "track_targets",
    "point_on_ray",
    "STOP_END",
    "STOP_BREAK",
    "STOP_IMAGE",
    "STOP_EXISTING",
    "STOP_FLAT",
    "STOP_CANCELLED",
]

STOP_END = "end of frames"          #: ran through every frame it was given
STOP_BREAK = "break threshold"      #: match quality below the Break Threshold
STOP_IMAGE = "left the image"       #: the position left the image
STOP_EXISTING = "existing track"    #: next frame holds 2D data that must not be overwritten
STOP_FLAT = "featureless pattern"   #: the pattern has no contrast to match
STOP_CANCELLED = "cancelled"        #: the caller cancelled

ImageFn = Callable[[int, int], np.ndarray]  # (camera, frame) -> (H, W) grey image


@dataclass(frozen=True)
class TrackKeys:
    """The keyframes of one track (one point in one camera), sorted by frame.

    Attributes
    ----------
    frames : int array (K,)
    xy : float array (K, 2)
        Keyed positions, raw px.
    pattern, search : float arrays (K, 4)
        Pattern and search boxes ``(x0, y0, x1, y1)`` *relative to* the keyed position, px.
    """

    frames: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    pattern: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    search: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def __post_init__(self) -> None:
        frames = np.asarray(self.frames, np.int64).reshape(-1)
        xy = np.asarray(self.xy, float).reshape(-1, 2)
        pattern = np.asarray(self.pattern, float).reshape(-1, 4)
        search = np.asarray(self.search, float).reshape(-1, 4)
        if not (len(xy) == len(pattern) == len(search) == len(frames)):
            raise ValueError("keyframes: frames, xy, pattern and search must have the same length")
        order = np.argsort(frames, kind="stable")
        for name, arr in (("frames", frames), ("xy", xy), ("pattern", pattern), ("search", search)):
            object.__setattr__(self, name, arr[order])

    def __len__(self) -> int:
        return len(self.frames)

    def index(self, frame: int) -> int:
        """Row of the keyframe at ``frame`` or -1."""
        i = bisect_left(self.frames.tolist(), frame)
        return i if i < len(self) and self.frames[i] == frame else -1

    def behind(self, frame: int, direction: int) -> int:
        """Row of the nearest keyframe at or behind ``frame`` in the tracking direction, or -1."""
        fr = self.frames.tolist()
        if direction > 0:
            i = bisect_right(fr, frame) - 1
            return i if i >= 0 else -1
        i = bisect_left(fr, frame)
        return i if i < len(fr) else -1

    def ahead(self, frame: int, direction: int) -> int:
        """Row of the nearest keyframe strictly ahead of ``frame`` in the tracking direction, or -1."""
        fr = self.frames.tolist()
        if direction > 0:
            i = bisect_right(fr, frame)
            return i if i < len(fr) else -1
        i = bisect_left(fr, frame) - 1
        return i if i >= 0 else -1


@dataclass(frozen=True)
class TrackSeed:
    """Where one track starts.

    Attributes
    ----------
    camera : int
    xy : array (2,)
        Position in the start frame, raw px.
    keys : TrackKeys
        The track's keyframes (any frames).
    pattern, search : arrays (4,)
        Boxes relative to the position, used when no keyframe lies behind the start frame.
    blocked : bool array (F,) or None
        Frames holding 2D data that must not be overwritten (the track stops before them; the
        track's own keyframes are passed, not overwritten).
    """

    camera: int
    xy: np.ndarray
    keys: TrackKeys = field(default_factory=TrackKeys)
    pattern: np.ndarray = field(default_factory=lambda: np.array([-7.5, -7.5, 7.5, 7.5]))
    search: np.ndarray = field(default_factory=lambda: np.array([-15.0, -15.0, 15.0, 15.0]))
    blocked: np.ndarray | None = None


@dataclass
class TargetTrackResult:
    """What :func:`track_targets` found (``S`` steps, ``N`` tracks).

    Attributes
    ----------
    frames : int array (S,)
        The frames stepped into, in tracking order (all that were asked for).
    xy : float array (S, N, 2)
        Tracked positions, raw px; NaN where the track had stopped.
    quality : float32 array (S, N)
        Match quality 0..1 (1 on keyframes); NaN where not tracked.
    keyed : bool array (S, N)
        The frame was one of the track's keyframes (position taken from it).
    stop_reason : list of str (N,)
        Why each track stopped (``STOP_*``).
    stop_frame : int array (N,)
        The first frame not tracked (-1 if the track ran through every frame).
    n_done : int
        Steps completed (less than ``S`` when cancelled or when every track stopped).
    """

    frames: np.ndarray
    xy: np.ndarray
    quality: np.ndarray
    keyed: np.ndarray
    stop_reason: list[str]
    stop_frame: np.ndarray
    n_done: int = 0

    @property
    def tracked(self) -> np.ndarray:
        """(S, N) mask of the positions found by matching (not keyframes)."""
        return np.isfinite(self.xy[..., 0]) & ~self.keyed


class _Reference:
    """The patterns one track compares against, cut from keyframe images with one geometry."""

    def __init__(self, frame: int, xy: np.ndarray, pattern: np.ndarray, search: np.ndarray) -> None:
        self.frame = frame
        self.xy = xy
        self.pattern = box_geometry(pattern)
        self.search = box_geometry(search)
        tw, th = self.pattern.size
        sw, sh = self.search.size
        self.search = BoxGeometry((max(sw, tw + 2), max(sh, th + 2)), self.search.offset)


class _State:
    def __init__(self, seed: TrackSeed, start_frame: int, direction: int) -> None:
        self.seed = seed
        self.active = True
        self.last = np.asarray(seed.xy, float).copy()
        keys = seed.keys
        i = keys.behind(start_frame, direction)
        if i >= 0:
            self.ref = _Reference(int(keys.frames[i]), keys.xy[i], keys.pattern[i], keys.search[i])
        else:  # a temporary reference at the start position
            self.ref = _Reference(start_frame, self.last.copy(), np.asarray(seed.pattern, float),
                                  np.asarray(seed.search, float))


def track_targets(seeds: Sequence[TrackSeed], image: ImageFn, start_frame: int, frames: Sequence[int], *,
                  break_threshold: float = 0.9, quality: str = "blend",
                  progress: Callable[[int, int], None] | None = None, cancel: Callable[[], bool] | None = None,
                  on_step: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> TargetTrackResult:
    """Track points frame by frame with the Target Tracker.

    Parameters
    ----------
    seeds : sequence of N TrackSeed
        One per (point, camera) to track.
    image : callable (camera, frame) -> array (H, W)
        Grey image of a camera at a frame (uint8 or float32).
    start_frame : int
        The frame the seeds' positions are in.
    frames : sequence of S int
        Frames to step into, consecutive, all after (or all before) ``start_frame``.
    break_threshold : float
        A frame whose quality is below this stops the track (0..1).
    quality : {"blend", "min"}
        How the previous and next keyframes' scores make the quality: weighted by nearness, or
        the lower of the two.
    progress : callable (done, total), optional
    cancel : callable () -> bool, optional
        Checked before each step; frames already done are kept.
    on_step : callable (frame, xy (N, 2), quality (N,)), optional
        Called after each step with that frame's results.

    Returns
    -------
    TargetTrackResult

    Raises
    ------
    ValueError
        For frames that are not consecutive steps away from ``start_frame``, a bad threshold or
        quality mode, or an image that is not 2D.
    """
    frames_a = np.asarray(list(frames), dtype=np.int64)
    S, N = len(frames_a), len(seeds)
    if quality not in ("blend", "min"):
        raise ValueError(f"quality must be 'blend' or 'min', got {quality!r}")
    if not 0.0 <= break_threshold <= 1.0:
        raise ValueError(f"break threshold must be within 0..1, got {break_threshold}")
    direction = 1
    if S:
        direction = 1 if frames_a[0] > start_frame else -1
        steps = np.diff(np.concatenate([[start_frame], frames_a]))
        if not np.all(steps == direction):
            raise ValueError("frames must step one at a time away from the start frame")
    res = TargetTrackResult(frames_a, np.full((S, N, 2), np.nan), np.full((S, N), np.nan, np.float32),
                            np.zeros((S, N), bool), [STOP_END] * N, np.full(N, -1, np.int64))
    states = [_State(s, start_frame, direction) for s in seeds]
    cache: dict[tuple, tuple[np.ndarray, bool]] = {}  # template, featureless
    images: dict[tuple[int, int], np.ndarray] = {}

    def get_image(cam: int, frame: int) -> np.ndarray:
        key = (cam, frame)
        if key not in images:
            img = np.asarray(image(cam, frame))
            if img.ndim != 2:
                raise ValueError(f"camera {cam} frame {frame}: expected a grey (H, W) image, got shape {img.shape}")
            if img.dtype not in (np.uint8, np.float32):
                img = img.astype(np.float32)
            images[key] = img
        return images[key]

    def template(cam: int, frame: int, xy: np.ndarray, ref: _Reference) -> tuple[np.ndarray, bool]:
        key = (cam, frame, float(xy[0]), float(xy[1]), ref.pattern.size, tuple(ref.pattern.offset))
        if key not in cache:
            patch = cut_patch(get_image(cam, frame), xy + ref.pattern.offset, ref.pattern.size)
            cache[key] = (patch, float(patch.std()) < MIN_TEMPLATE_STD)
        return cache[key]

    def stop(j: int, k: int, reason: str) -> None:
        states[j].active = False
        res.stop_reason[j] = reason
        res.stop_frame[j] = int(frames_a[k])

    for k, f in enumerate(frames_a.tolist()):
        if cancel is not None and cancel():
            for j, st in enumerate(states):
                if st.active:
                    stop(j, k, STOP_CANCELLED)
            break
        for j, st in enumerate(states):
            if not st.active:
                continue
            seed = st.seed
            cam = seed.camera
            ki = seed.keys.index(f)
            if ki >= 0:  # a keyframe on the way: take it and make it the reference
                xy = seed.keys.xy[ki]
                st.ref = _Reference(f, xy, seed.keys.pattern[ki], seed.keys.search[ki])
                res.xy[k, j], res.quality[k, j], res.keyed[k, j] = xy, 1.0, True
                st.last = np.asarray(xy, float)
                continue
            if seed.blocked is not None and bool(seed.blocked[f]):
                stop(j, k, STOP_EXISTING)
                continue
            img = get_image(cam, f)
            ref = st.ref
            cut = [template(cam, ref.frame, ref.xy, ref)]
            d_prev = abs(f - ref.frame)
            weights = [1.0]
            na = seed.keys.ahead(f, direction)
            if na >= 0:
                nf = int(seed.keys.frames[na])
                d_next = abs(nf - f)
                cut.append(template(cam, nf, seed.keys.xy[na], ref))
                weights = [d_next / (d_prev + d_next), d_prev / (d_prev + d_next)]
            if any(flat for _, flat in cut):
                stop(j, k, STOP_FLAT)
                continue
            templates = [t for t, _ in cut]
            m = locate(img, templates, weights, window_centre=st.last + ref.search.offset,
                       window_size=ref.search.size)
            xy = m.centre - ref.pattern.offset
            h, w = img.shape
            if not (-0.5 <= xy[0] <= w - 0.5 and -0.5 <= xy[1] <= h - 0.5):
                stop(j, k, STOP_IMAGE)
                continue
            sc = np.clip(m.scores, 0.0, 1.0)
            q = float(sc.min()) if quality == "min" else float(np.dot(weights, sc))
            if q < break_threshold:
                stop(j, k, STOP_BREAK)
                continue
            res.xy[k, j], res.quality[k, j] = xy, q
            st.last = xy
        images.clear()  # the cut templates are cached; no image is needed again
        res.n_done = k + 1
        if on_step is not None:
            on_step(f, res.xy[k].copy(), res.quality[k].copy())
        if progress is not None:
            progress(k + 1, S)
        if not any(st.active for st in states):
            break
    return res


def point_on_ray(xy: np.ndarray, intr: Intrinsics, R: np.ndarray, t: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """3D points constrained to the rays of single observations, nearest to reference positions.

    Parameters
    ----------
    xy : array (N, 2)
        Raw-pixel observations in one camera.
    intr : Intrinsics
    R, t : arrays (N, 3, 3), (N, 3) or (3, 3), (3,)
        World-to-camera pose(s).
    ref : array (N, 3)
        Predicted positions (e.g. the last known 3D position), mm.

    Returns
    -------
    array (N, 3)
        The point of each ray nearest to its reference (never behind the camera), mm; NaN where
        the observation or the reference is missing.
    """
    xy = np.asarray(xy, float).reshape(-1, 2)
    ref = np.asarray(ref, float).reshape(-1, 3)
    if len(ref) != len(xy):
        raise ValueError(f"point_on_ray: {len(xy)} observations but {len(ref)} reference positions")
    o, d = backproject(xy, intr, R, t)
    s = np.maximum(np.einsum("ni,ni->n", ref - o, d), 0.0)
    return o + s[:, None] * d
