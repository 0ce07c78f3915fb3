"""Target Tracker operations: the Tracker pane, Add/Edit Target Track, Gaps To Keys, keyframe navigation.

Selections are explicit arguments (point *columns*, a camera, a frame); images come from a
callable ``image(camera, frame) -> (H, W)`` grey array such as
:meth:`carapost.ops.session.Session.image`. Every function returns one undoable change and
leaves the take untouched; the tracking functions also report what happened (``.report``).

A keyframe is a row of :attr:`Take.keyframes` (keyed position, pattern box, search box, all in
absolute raw pixels) and the point's observation in that camera and frame, marked
:attr:`ObsSource.KEYFRAME` with quality 1. Positions found by tracking are marked
:attr:`ObsSource.TARGET` with their match quality in ``obs_q``. Target-track observations are not
blob detections (``obs_det`` is -1).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from carapost.core.target_tracker import STOP_CANCELLED, TrackKeys, TrackSeed, point_on_ray, track_targets
from carapost.model.params import TrackerSettings
from carapost.model.take import POINT_ARRAYS, Keyframes, ObsSource, PointKind, Recon, Take

from .change import AttributeChange, CancelFn, Change, Composite, PointsAdded, ProgressFn
from .points import PointBlock

__all__ = [
    "ImageFn",
    "default_boxes",
    "add_target_track",
    "edit_target_track",
    "adjust_keyframe",
    "add_keyframes",
    "clear_tracked_points",
    "gaps_to_keys",
    "next_keyframe",
    "prev_keyframe",
    "TrackerFrame",
    "TrackReport",
    "TargetTrackChange",
    "track",
    "track_forward_one_frame",
    "track_back_one_frame",
    "track_forward_to_end",
    "track_back_to_start",
]

ImageFn = Callable[[int, int], np.ndarray]
Row = tuple[int, int, int, np.ndarray, np.ndarray, np.ndarray]  # frame, point id, camera, xy, pattern, search


# ----------------------------------------------------------------------------- helpers
def default_boxes(take: Take, xy: np.ndarray, *, radius: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Default pattern and search boxes (absolute ``(x0, y0, x1, y1)``, px) around ``xy``.

    With a known marker ``radius`` (px) the pattern box is 2.5 marker diameters wide (the
    guide: "two to three times the diameter"), else Patch Match Size wide. The search box adds
    a margin of at least 6 px (and at least half the pattern) on every side.
    """
    half = float(np.clip(2.5 * radius, 4.0, 40.0)) if radius is not None and radius > 0 else \
        take.params.tracking.patch_match_size / 2.0
    margin = max(6.0, half)
    x, y = float(xy[0]), float(xy[1])
    return (np.array([x - half, y - half, x + half, y + half], np.float32),
            np.array([x - half - margin, y - half - margin, x + half + margin, y + half + margin], np.float32))


def _cols(take: Take, points: Sequence[int], what: str) -> np.ndarray:
    cols = np.unique(np.asarray(list(points), dtype=np.int64))
    if len(cols) == 0:
        raise ValueError(f"{what}: select at least one point")
    if cols.min() < 0 or cols.max() >= take.n_points:
        raise ValueError(f"{what}: a selected point does not exist (the take has {take.n_points} points)")
    return cols


def _check_frame(take: Take, frame: int, what: str) -> int:
    if not 0 <= int(frame) < take.n_frames:
        raise ValueError(f"{what}: frame {frame} outside 0..{take.n_frames - 1}")
    return int(frame)


def _check_camera(take: Take, camera: int, what: str) -> int:
    if not 0 <= int(camera) < take.n_cameras:
        raise ValueError(f"{what}: camera {camera} outside 0..{take.n_cameras - 1}")
    return int(camera)


def _check_xy(take: Take, camera: int, xy: Sequence[float], what: str) -> np.ndarray:
    p = np.asarray(xy, dtype=float).reshape(-1)
    if p.shape != (2,) or not np.isfinite(p).all():
        raise ValueError(f"{what}: a position must be two finite numbers, got {xy!r}")
    w, h = take.cameras[camera].image_size
    if w > 0 and h > 0 and not (-0.5 <= p[0] <= w - 0.5 and -0.5 <= p[1] <= h - 0.5):
        raise ValueError(f"{what}: position ({p[0]:.1f}, {p[1]:.1f}) is outside camera {camera}'s "
                         f"{w} x {h} image")
    return p


def _check_box(box: Sequence[float] | None, xy: np.ndarray, what: str, name: str) -> np.ndarray | None:
    if box is None:
        return None
    b = np.asarray(box, dtype=np.float32).reshape(-1)
    if b.shape != (4,) or not np.isfinite(b).all() or b[2] <= b[0] or b[3] <= b[1]:
        raise ValueError(f"{what}: the {name} box must be (x0, y0, x1, y1) with x0 < x1 and y0 < y1, got {box!r}")
    if not (b[0] <= xy[0] <= b[2] and b[1] <= xy[1] <= b[3]):
        raise ValueError(f"{what}: the {name} box {b.tolist()} does not contain the keyed position")
    return b


def _with_rows(kf: Keyframes, rows: Sequence[Row], drop: np.ndarray | None = None) -> Keyframes:
    """``kf`` without the ``drop`` rows and the rows keyed like ``rows``, plus ``rows``; sorted
    by (frame, point id, camera)."""
    keep = np.ones(len(kf), bool) if drop is None else ~np.asarray(drop, bool)
    if rows and len(kf):
        new_keys = {(int(r[0]), int(r[1]), int(r[2])) for r in rows}
        old_keys = zip(kf.frame.tolist(), kf.point_id.tolist(), kf.camera.tolist())
        keep &= np.array([k not in new_keys for k in old_keys], bool)
    n = len(rows)
    frame = np.concatenate([kf.frame[keep], np.array([r[0] for r in rows], np.int32).reshape(n)])
    pid = np.concatenate([kf.point_id[keep], np.array([r[1] for r in rows], np.int64).reshape(n)])
    cam = np.concatenate([kf.camera[keep], np.array([r[2] for r in rows], np.int16).reshape(n)])
    xy = np.concatenate([kf.xy[keep], np.array([r[3] for r in rows], np.float32).reshape(n, 2)])
    pat = np.concatenate([kf.pattern[keep], np.array([r[4] for r in rows], np.float32).reshape(n, 4)])
    sea = np.concatenate([kf.search[keep], np.array([r[5] for r in rows], np.float32).reshape(n, 4)])
    order = np.lexsort((cam, pid, frame))
    return Keyframes(frame[order], pid[order], cam[order], xy[order], pat[order], sea[order])


def _row_of(kf: Keyframes, frame: int, pid: int, camera: int) -> int:
    hit = np.flatnonzero((kf.frame == frame) & (kf.point_id == pid) & (kf.camera == camera))
    return int(hit[0]) if len(hit) else -1


def _radius(take: Take, frame: int, col: int, camera: int) -> float | None:
    det = int(take.obs_det[frame, col, camera])
    major = take.detections[camera].frame(frame)["major"]
    return float(major[det]) if 0 <= det < len(major) else None


def _key_obs(blk: PointBlock, fi: int, pj: int, camera: int, xy: np.ndarray) -> None:
    a = blk.arrays
    a["obs_xy"][fi, pj, camera] = xy
    a["obs_det"][fi, pj, camera] = -1
    a["obs_src"][fi, pj, camera] = ObsSource.KEYFRAME
    a["obs_q"][fi, pj, camera] = 1.0


def _new_row(take: Take, frame: int, col: int, camera: int, xy: np.ndarray) -> Row:
    pat, sea = default_boxes(take, xy, radius=_radius(take, frame, col, camera))
    return frame, int(take.points.ids[col]), camera, np.asarray(xy, np.float32), pat, sea


# ----------------------------------------------------------------------- keyframe edits
def add_target_track(take: Take, camera: int, frame: int, xy: Sequence[float], *,
                     pattern: Sequence[float] | None = None, search: Sequence[float] | None = None) -> Composite:
    """"Add Target Track (Shift+A)": a new point with a keyframe where the user clicked.

    Parameters
    ----------
    camera, frame : int
    xy : (2,) raw px
        The click.
    pattern, search : (4,) absolute boxes, optional
        Default :func:`default_boxes`.

    Raises
    ------
    ValueError
        For a camera, frame or position outside the take, or a box not containing ``xy``.
    """
    what = "Add Target Track"
    camera, frame = _check_camera(take, camera, what), _check_frame(take, frame, what)
    p = _check_xy(take, camera, xy, what)
    dp, ds = default_boxes(take, p)
    pat = _check_box(pattern, p, what, "pattern")
    sea = _check_box(search, p, what, "search")
    arrays = {}
    for name, (trail, dtype, fill) in POINT_ARRAYS.items():
        shape = (take.n_frames, 1) + tuple(take.n_cameras if d == "C" else d for d in trail)
        arrays[name] = np.full(shape, fill, dtype=dtype)
    arrays["obs_xy"][frame, 0, camera] = p
    arrays["obs_src"][frame, 0, camera] = ObsSource.KEYFRAME
    arrays["obs_q"][frame, 0, camera] = 1.0
    pid = take.next_point_id
    add = PointsAdded(1, int(PointKind.FACE), [""], np.full(1, -1, np.int32), arrays, first_id=pid)
    row = (frame, pid, camera, p.astype(np.float32), dp if pat is None else pat, ds if sea is None else sea)
    kf = AttributeChange.capture(take, "keyframes", _with_rows(take.keyframes, [row]))
    return Composite([add, kf], f"Add Target Track: Point_{pid} in camera {camera}, frame {frame}")


def edit_target_track(take: Take, point: int, camera: int, frame: int, xy: Sequence[float], *,
                      pattern: Sequence[float] | None = None, search: Sequence[float] | None = None) -> Composite:
    """"Edit Target Track (Shift+E)": key the selected point where the user clicked in a camera.

    A detection connected to the point in that camera is disconnected and replaced by the
    keyframe; an existing keyframe there is moved (keeping its box sizes unless new boxes are
    given). The point is re-triangulated in that frame.
    """
    what = "Edit Target Track"
    col = int(_cols(take, [point], what)[0])
    camera, frame = _check_camera(take, camera, what), _check_frame(take, frame, what)
    p = _check_xy(take, camera, xy, what)
    pid = int(take.points.ids[col])
    kf = take.keyframes
    r = _row_of(kf, frame, pid, camera)
    if r >= 0:  # move the existing boxes with the keyframe
        shift = np.tile(p - kf.xy[r], 2).astype(np.float32)
        dp, ds = kf.pattern[r] + shift, kf.search[r] + shift
    else:
        dp, ds = default_boxes(take, p, radius=_radius(take, frame, col, camera))
    pat = _check_box(pattern, p, what, "pattern")
    sea = _check_box(search, p, what, "search")
    row = (frame, pid, camera, p.astype(np.float32), dp if pat is None else pat, ds if sea is None else sea)
    blk = PointBlock(take, [frame], [col])
    _key_obs(blk, 0, 0, camera, p)
    blk.retriangulate()
    changes: list[Change] = [AttributeChange.capture(take, "keyframes", _with_rows(kf, [row]))]
    changes += blk.patches()
    return Composite(changes, f"Edit Target Track: {take.points.name(col)} in camera {camera}, frame {frame}")


def adjust_keyframe(take: Take, point: int, camera: int, frame: int, *, xy: Sequence[float] | None = None,
                    pattern: Sequence[float] | None = None, search: Sequence[float] | None = None) -> Composite:
    """Move a keyframe (the nudge controls) and/or resize its pattern and search boxes (the handles).

    Moving without new boxes moves the boxes with the keyframe.

    Raises
    ------
    ValueError
        If the point has no keyframe in that camera and frame, or for bad positions or boxes.
    """
    what = "Adjust Keyframe"
    col = int(_cols(take, [point], what)[0])
    camera, frame = _check_camera(take, camera, what), _check_frame(take, frame, what)
    pid = int(take.points.ids[col])
    kf = take.keyframes
    r = _row_of(kf, frame, pid, camera)
    if r < 0:
        raise ValueError(f"{what}: {take.points.name(col)} has no keyframe in camera {camera} at frame {frame}")
    p = kf.xy[r].astype(float) if xy is None else _check_xy(take, camera, xy, what)
    shift = np.tile(p - kf.xy[r], 2).astype(np.float32)
    pat = _check_box(pattern, p, what, "pattern")
    sea = _check_box(search, p, what, "search")
    row = (frame, pid, camera, p.astype(np.float32), kf.pattern[r] + shift if pat is None else pat,
           kf.search[r] + shift if sea is None else sea)
    changes: list[Change] = [AttributeChange.capture(take, "keyframes", _with_rows(kf, [row]))]
    if xy is not None:
        blk = PointBlock(take, [frame], [col])
        _key_obs(blk, 0, 0, camera, p)
        blk.retriangulate()
        changes += blk.patches()
    return Composite(changes, f"Adjust Keyframe: {take.points.name(col)} in camera {camera}, frame {frame}")


def _key_existing(take: Take, fpc: np.ndarray, cols: np.ndarray, text: str) -> Composite:
    """Keyframes at the existing 2D positions ``fpc (K, 3)`` = (frame, column index into cols, camera)."""
    kf = take.keyframes
    have = set(zip(kf.frame.tolist(), kf.point_id.tolist(), kf.camera.tolist()))
    ids = take.points.ids[cols]
    fpc = np.array([r for r in fpc.tolist() if (r[0], int(ids[r[1]]), r[2]) not in have], np.int64).reshape(-1, 3)
    if len(fpc) == 0:
        return Composite([], f"{text}: nothing to add")
    frames = np.unique(fpc[:, 0])
    blk = PointBlock(take, frames, cols)
    rows = []
    for f, j, c in fpc.tolist():
        xy = take.obs_xy[f, cols[j], c].astype(float)
        rows.append(_new_row(take, f, int(cols[j]), c, xy))
        _key_obs(blk, int(np.searchsorted(frames, f)), j, c, xy)
    changes: list[Change] = [AttributeChange.capture(take, "keyframes", _with_rows(kf, rows))]
    changes += blk.patches()
    return Composite(changes, f"{text}: {len(rows)} keyframe(s)")


def add_keyframes(take: Take, points: Sequence[int], frame: int) -> Composite:
    """"Add Keyframe To Current Frame": key every selected point in every camera where it has a
    2D position in ``frame`` (existing keyframes are kept as they are).

    Raises
    ------
    ValueError
        If no selected point has a 2D position in the frame.
    """
    what = "Add Keyframe To Current Frame"
    cols = _cols(take, points, what)
    frame = _check_frame(take, frame, what)
    j, c = np.nonzero(np.isfinite(take.obs_xy[frame][cols][..., 0]))
    if len(j) == 0:
        raise ValueError(f"{what}: the selected point(s) have no 2D position in frame {frame}")
    return _key_existing(take, np.stack([np.full(len(j), frame), j, c], 1), cols, what)


def gaps_to_keys(take: Take, points: Sequence[int]) -> Composite:
    """"Gaps To Keys": keyframes either side of every gap in the selected points' 2D tracks.

    A gap is a run of frames in which a point has no 2D position in a camera, with positions
    before and after it; the last frame before and the first frame after are keyed.
    """
    what = "Gaps To Keys"
    cols = _cols(take, points, what)
    has = np.isfinite(take.obs_xy[:, cols][..., 0])  # (F, P', C)
    before = np.maximum.accumulate(has, axis=0)
    after = np.maximum.accumulate(has[::-1], axis=0)[::-1]
    gap_after = has[:-1] & ~has[1:] & after[1:]     # frame f is the last before a gap
    gap_before = ~has[:-1] & has[1:] & before[:-1]  # frame f + 1 is the first after a gap
    f1, j1, c1 = np.nonzero(gap_after)
    f2, j2, c2 = np.nonzero(gap_before)
    fpc = np.concatenate([np.stack([f1, j1, c1], 1), np.stack([f2 + 1, j2, c2], 1)])
    fpc = np.unique(fpc, axis=0) if len(fpc) else fpc.reshape(0, 3)
    return _key_existing(take, fpc, cols, what)


def clear_tracked_points(take: Take, points: Sequence[int]) -> Composite:
    """"Clear Tracked Points": delete every 2D observation (and keyframe) of the selected points.

    3D positions that rested on the observations (multi-view and single-sensor) go too;
    interpolated positions stay.
    """
    what = "Clear Tracked Points"
    cols = _cols(take, points, what)
    blk = PointBlock(take, np.arange(take.n_frames), cols)
    blk.detach(np.ones(blk.arrays["obs_det"].shape, bool))
    gone = np.isin(blk.arrays["recon"], [Recon.MULTI_VIEW, Recon.SINGLE_SENSOR])
    blk.arrays["xyz"][gone] = np.nan
    blk.arrays["recon"][gone] = Recon.NONE
    changes: list[Change] = blk.patches()
    drop = np.isin(take.keyframes.point_id, take.points.ids[cols])
    if drop.any():
        changes.insert(0, AttributeChange.capture(take, "keyframes", _with_rows(take.keyframes, [], drop)))
    return Composite(changes, f"Clear Tracked Points: {len(cols)} point(s)")


# --------------------------------------------------------------------------- navigation
def _key_frames_of(take: Take, points: Sequence[int]) -> np.ndarray:
    if len(points) == 0 or take.n_points == 0:
        return np.zeros(0, np.int64)
    cols = _cols(take, points, "Key frame navigation")
    return np.unique(take.keyframes.frame[np.isin(take.keyframes.point_id, take.points.ids[cols])]).astype(np.int64)


def next_keyframe(take: Take, points: Sequence[int], frame: int) -> int:
    """"Next Key Frame (Shift+Right)": the selected points' next keyframe (any camera), wrapping
    to the first; without keyframes, the next frame (the last frame stays)."""
    frames = _key_frames_of(take, points)
    if len(frames) == 0:
        return min(int(frame) + 1, take.n_frames - 1)
    later = frames[frames > frame]
    return int(later[0] if len(later) else frames[0])


def prev_keyframe(take: Take, points: Sequence[int], frame: int) -> int:
    """"Prev Key Frame (Shift+Left)": the previous keyframe, wrapping to the last; without
    keyframes, the previous frame (frame 0 stays)."""
    frames = _key_frames_of(take, points)
    if len(frames) == 0:
        return max(int(frame) - 1, 0)
    earlier = frames[frames < frame]
    return int(earlier[-1] if len(earlier) else frames[-1])


# ----------------------------------------------------------------------------- tracking
@dataclass
class TrackerFrame:
    """Sent to ``on_frame`` after each tracked frame when Update Timeline Every Frame or Update
    2D View Every Frame is on.

    Attributes
    ----------
    frame : int
        The frame just tracked.
    show_frame : bool
        Update 2D View Every Frame: the views should display ``frame``.
    update_timeline : bool
        Update Timeline Every Frame: the Continuity chart / Selected Point pane should show the
        qualities so far.
    points, cameras : int arrays (N,)
        Point column and camera of each track.
    xy : array (N, 2)
        Positions in ``frame`` (NaN where a track has stopped).
    quality : array (N,)
    """

    frame: int
    show_frame: bool
    update_timeline: bool
    points: np.ndarray
    cameras: np.ndarray
    xy: np.ndarray
    quality: np.ndarray


@dataclass
class TrackReport:
    """What a tracking run did.

    Attributes
    ----------
    points, cameras : int arrays (N,)
        Point column and camera of each track.
    n_tracked : int array (N,)
        Frames found by matching per track.
    stop_reason : list of str (N,)
    stop_frame : int array (N,)
        First frame not tracked (-1: ran to the end of the frames asked for).
    frames : int array (S,)
        The frames the run was allowed to step into.
    keyframes_added : int
    cancelled : bool
    """

    points: np.ndarray
    cameras: np.ndarray
    n_tracked: np.ndarray
    stop_reason: list[str]
    stop_frame: np.ndarray
    frames: np.ndarray
    keyframes_added: int = 0
    cancelled: bool = False


@dataclass
class TargetTrackChange(Composite):
    """The change made by a tracking run, with its :class:`TrackReport`."""

    report: TrackReport | None = field(default=None)


def _frames_to_track(take: Take, cols: np.ndarray, frame: int, direction: int, one: bool,
                     s: TrackerSettings, kf: Keyframes) -> np.ndarray:
    end = take.n_frames - 1 if direction > 0 else 0
    frames = np.arange(frame + direction, end + direction, direction)
    if one:
        frames = frames[:1]
    elif s.stop_after_n_frames:
        frames = frames[:max(1, int(s.n_frames))]
    if s.stop_on_next_keyframe and len(frames):
        mine = kf.frame[np.isin(kf.point_id, take.points.ids[cols])]
        ahead = mine[(mine - frame) * direction > 0]
        if len(ahead):
            stop = int(ahead.min() if direction > 0 else ahead.max())
            frames = frames[(stop - frames) * direction > 0]
    return frames


def track(take: Take, points: Sequence[int], frame: int, image: ImageFn, *, direction: int = 1,
          to_end: bool = True, settings: TrackerSettings | None = None, progress: ProgressFn | None = None,
          cancel: CancelFn | None = None, on_frame: Callable[[TrackerFrame], None] | None = None) -> TargetTrackChange:
    """Target-track the selected points from ``frame``, in every camera where they have a 2D point.

    Parameters
    ----------
    take : Take
    points : sequence of int
        Point columns.
    frame : int
        The current frame.
    image : callable (camera, frame) -> array (H, W)
        E.g. ``session.image``.
    direction : {1, -1}
        Forward or back.
    to_end : bool
        Track to the end (start) of the take, within the settings; False: one frame.
    settings : TrackerSettings, optional
        Default ``take.params.tracker``.
    progress, cancel : callables, optional
        ``progress(done, total)``; ``cancel()`` is polled each frame and keeps the frames done.
    on_frame : callable (TrackerFrame), optional
        Called after each frame when Update Timeline / 2D View Every Frame is on.

    Returns
    -------
    TargetTrackChange
        Keyframes added (Automatically Add Keyframes), the tracked observations (source
        ``TARGET``, quality in ``obs_q``) and the re-triangulated (or, with Allow Single Sensor
        Tracking, ray-constrained) positions; ``.report`` says where and why tracks stopped.

    Raises
    ------
    ValueError
        For a bad selection, frame or direction, or when no selected point has a 2D position
        in ``frame``.
    """
    name = {(1, True): "Track Forward To End", (1, False): "Track Forward One Frame",
            (-1, True): "Track Back To Start", (-1, False): "Track Back One Frame"}.get((direction, bool(to_end)))
    if name is None:
        raise ValueError(f"Track: direction must be 1 or -1, got {direction}")
    cols = _cols(take, points, name)
    frame = _check_frame(take, frame, name)
    s = settings if settings is not None else take.params.tracker
    j_idx, cams = np.nonzero(np.isfinite(take.obs_xy[frame][cols][..., 0]))
    if len(j_idx) == 0:
        raise ValueError(f"{name}: the selected point(s) have no 2D position in frame {frame}")
    ids = take.points.ids[cols]
    kf = take.keyframes
    rows: list[Row] = []
    if s.automatically_add_keyframes:
        have = set(zip(kf.frame.tolist(), kf.point_id.tolist(), kf.camera.tolist()))
        rows = [_new_row(take, frame, int(cols[j]), int(c), take.obs_xy[frame, cols[j], c].astype(float))
                for j, c in zip(j_idx.tolist(), cams.tolist()) if (frame, int(ids[j]), int(c)) not in have]
        kf = _with_rows(kf, rows) if rows else kf
    frames = _frames_to_track(take, cols, frame, direction, not to_end, s, kf)
    seeds = []
    for j, c in zip(j_idx.tolist(), cams.tolist()):
        m = (kf.point_id == ids[j]) & (kf.camera == c)
        rel = np.tile(kf.xy[m], 2).astype(float)
        keys = TrackKeys(kf.frame[m], kf.xy[m], kf.pattern[m] - rel, kf.search[m] - rel)
        xy = take.obs_xy[frame, cols[j], c].astype(float)
        pat, sea = default_boxes(take, xy, radius=_radius(take, frame, int(cols[j]), c))
        blocked = None if s.overwrite_existing_tracks else np.isfinite(take.obs_xy[:, cols[j], c, 0])
        seeds.append(TrackSeed(c, xy, keys, pat - np.tile(xy, 2), sea - np.tile(xy, 2), blocked))
    step: Callable[[int, np.ndarray, np.ndarray], None] | None = None
    if on_frame is not None and (s.update_timeline_every_frame or s.update_2d_view_every_frame):
        tell = on_frame

        def _step(f: int, xy: np.ndarray, q: np.ndarray) -> None:
            tell(TrackerFrame(f, bool(s.update_2d_view_every_frame), bool(s.update_timeline_every_frame),
                              cols[j_idx], cams.copy(), xy, q))
        step = _step
    res = track_targets(seeds, image, frame, frames, break_threshold=float(s.break_threshold),
                        progress=progress, cancel=cancel, on_step=step)
    done = res.frames[:res.n_done]
    found = np.isfinite(res.xy[:res.n_done, :, 0])  # (S', N)
    used = done[found.any(1)]
    blk_frames = np.unique(np.concatenate([used, [frame] if rows else []]).astype(np.int64))
    changes: list[Change] = []
    if rows:
        changes.append(AttributeChange.capture(take, "keyframes", kf))
    if len(blk_frames):
        blk = PointBlock(take, blk_frames, cols)
        for f, pid, c, xy, _, _ in rows:
            pj = int(np.searchsorted(cols, take.points.index_of(pid)))
            _key_obs(blk, int(np.searchsorted(blk_frames, f)), pj, c, xy)
        a = blk.arrays
        k, n = np.nonzero(found)
        fi = np.searchsorted(blk_frames, done[k])
        pj, cc = j_idx[n], cams[n]
        keyed = res.keyed[k, n]
        a["obs_xy"][fi, pj, cc] = res.xy[k, n]
        a["obs_det"][fi, pj, cc] = -1
        a["obs_src"][fi, pj, cc] = np.where(keyed, ObsSource.KEYFRAME, ObsSource.TARGET)
        a["obs_q"][fi, pj, cc] = res.quality[k, n]
        blk.retriangulate()
        if s.allow_single_sensor_tracking:
            _single_sensor(take, blk, frame, direction)
        changes += blk.patches()
    n_tracked = res.tracked[:res.n_done].sum(0)
    cancelled = STOP_CANCELLED in res.stop_reason
    report = TrackReport(cols[j_idx], cams.copy(), n_tracked, list(res.stop_reason), res.stop_frame.copy(),
                         frames, len(rows), cancelled)
    reasons = sorted(set(res.stop_reason))
    text = (f"{name}: {len(cols)} point(s), {len(seeds)} camera track(s), {int(n_tracked.sum())} position(s)"
            f" ({', '.join(reasons)})")
    return TargetTrackChange(changes, text, report)


def _single_sensor(take: Take, blk: PointBlock, frame: int, direction: int) -> None:
    """Allow Single Sensor Tracking: put points seen by one camera on its ray, nearest to the
    position they had (or, failing that, the last position along the tracking direction)."""
    a = blk.arrays
    seen = np.isfinite(a["obs_xy"][..., 0])  # (F', P', C)
    single = seen.sum(-1) == 1
    if not single.any():
        return
    order = np.argsort(blk.frames * direction, kind="stable")
    last = take.xyz[frame, blk.cols].copy()  # the start frame's positions
    intr = take.intrinsics()
    for fi in order.tolist():
        f = int(blk.frames[fi])
        ref = take.xyz[f, blk.cols].copy()
        ref = np.where(np.isfinite(ref).all(-1, keepdims=True), ref, last)
        for c in range(take.n_cameras):
            m = single[fi] & seen[fi, :, c] & np.isfinite(ref).all(-1)
            if m.any():
                a["xyz"][fi, m] = point_on_ray(a["obs_xy"][fi, m, c], intr[c], take.R[f, c], take.t[f, c], ref[m])
                a["recon"][fi, m] = Recon.SINGLE_SENSOR
        ok = np.isfinite(a["xyz"][fi]).all(-1)
        last = np.where(ok[:, None], a["xyz"][fi], last)


def track_forward_one_frame(take: Take, points: Sequence[int], frame: int, image: ImageFn,
                            **kw: object) -> TargetTrackChange:
    """The Tracker pane's "Track forward one frame" (see :func:`track`)."""
    return track(take, points, frame, image, direction=1, to_end=False, **kw)  # type: ignore[arg-type]


def track_back_one_frame(take: Take, points: Sequence[int], frame: int, image: ImageFn,
                         **kw: object) -> TargetTrackChange:
    """The Tracker pane's "Track back one frame" (see :func:`track`)."""
    return track(take, points, frame, image, direction=-1, to_end=False, **kw)  # type: ignore[arg-type]


def track_forward_to_end(take: Take, points: Sequence[int], frame: int, image: ImageFn,
                         **kw: object) -> TargetTrackChange:
    """The Tracker pane's "Track forward to end" (see :func:`track`)."""
    return track(take, points, frame, image, direction=1, to_end=True, **kw)  # type: ignore[arg-type]


def track_back_to_start(take: Take, points: Sequence[int], frame: int, image: ImageFn,
                        **kw: object) -> TargetTrackChange:
    """The Tracker pane's "Track back to start" (see :func:`track`)."""
    return track(take, points, frame, image, direction=-1, to_end=True, **kw)  # type: ignore[arg-type]
