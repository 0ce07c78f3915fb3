"""Initialize from ROM: find a solved ROM take's points in a frame of a new take.

The reference guide's "Initialize from ROM algorithm": the automatic tracker matches the brim
markers and facial markers *from a frame in the ROM take to a frame in the uninitialized
take*. This module does exactly that: it builds a two-frame *bridge* take whose frame 0 is the
ROM frame (the ROM's cameras and their poses, its brim and face points with their 3D positions
and attached detections) and whose frame 1 holds the new take's detections, and runs one step
of :func:`carapost.core.tracking.track` from frame 0 to frame 1 with the *Initialize From ROM
Parameters* in place of their tracking counterparts:

=====================================  ==========================================
Initialize From ROM Parameters         replaces (Tracking Parameters)
=====================================  ==========================================
ROM Face Point Tracking Distance       Face Point Tracking Distance
ROM Brim Point Tracking Distance       Brim Point Tracking Distance
ROM Max Allowed 3D Point Error         Max Allowed 3D Point Error
=====================================  ==========================================

Every other tracking parameter (Remove Bad 2D Projections, Remove Bad 3D Points, Blob Size
Difference Threshold, Patch Match ...) applies as in tracking. The tracker's frame step matches
the brim dots within the brim distance of where the ROM poses project them, re-estimates every
camera's pose from the brim and the matched face points (a bundle adjustment with the brim
fixed), predicts the remaining face points elastically from their matched neighbours, and
rejects 2D and 3D outliers. The world frame stays the brim's, so the new take's points are in
the ROM's coordinates.

:func:`match_rom_frame` is pure: the ROM take is read, never modified; the result holds the new
frame's arrays for the ROM's points and the re-estimated poses. :mod:`carapost.ops.rom` turns it
into one undoable change. See ``docs/rom.md``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from carapost.model.detections import Detections
from carapost.model.params import RomParameters, TrackingParameters
from carapost.model.take import CameraInfo, PointKind, Recon, Take

from .tracking import track

__all__ = ["RomMatch", "rom_tracking_parameters", "check_rom", "match_rom_frame"]

ImageFn = Callable[[int, int], np.ndarray]   # (camera, frame) -> uint8 (H, W)
Table = Mapping[str, np.ndarray]


@dataclass
class RomMatch:
    """The ROM's points found in the new frame (``Q`` ROM points, ``C`` cameras).

    Attributes
    ----------
    rom_points : int array (Q,)
        Columns of the ROM take that were looked for (those with a 3D position in the ROM
        frame; brim points only for *[Brim Only]*), in ROM column order.
    xyz : float64 array (Q, 3)
        Positions in the new frame, mm, world (= brim) frame; NaN = not found.
    recon : uint8 array (Q,)
        :class:`~carapost.model.take.Recon` of each point.
    obs_xy : float32 array (Q, C, 2)
    obs_det : int32 array (Q, C)
    obs_src : uint8 array (Q, C)
    obs_q : float32 array (Q, C)
        The attached detections of the new frame (indices into the new frame's detection
        tables), as the take stores them.
    R : float64 array (C, 3, 3)
    t : float64 array (C, 3)
        Camera poses of the new frame re-estimated from the brim (world to camera).
    found : bool array (Q,)
        Points reconstructed in the new frame (multi-view or single-sensor).
    report : dict
        ``found_face``, ``found_brim``, ``face``, ``brim`` counts, ``not_found`` (the ROM
        names of the points not found), ``cameras_updated`` and the tracker's frame report.
    """

    rom_points: np.ndarray
    xyz: np.ndarray
    recon: np.ndarray
    obs_xy: np.ndarray
    obs_det: np.ndarray
    obs_src: np.ndarray
    obs_q: np.ndarray
    R: np.ndarray
    t: np.ndarray
    found: np.ndarray
    report: dict = field(default_factory=dict)


def rom_tracking_parameters(tracking: TrackingParameters, rom: RomParameters) -> TrackingParameters:
    """The Tracking Parameters with the Initialize From ROM Parameters' distances and 3D error."""
    return dataclasses.replace(
        tracking,
        face_point_tracking_distance=float(rom.rom_face_point_tracking_distance),
        brim_point_tracking_distance=float(rom.rom_brim_point_tracking_distance),
        max_allowed_3d_point_error=float(rom.rom_max_allowed_3d_point_error))


def check_rom(rom: Take, rom_frame: int, *, name: str = "the ROM take") -> None:
    """Raise ``ValueError`` (naming ``name``) unless ``rom`` can initialize another take from
    ``rom_frame``: cameras, a brim model, solved poses and brim points with positions there."""
    if rom.n_cameras == 0:
        raise ValueError(f"{name} has no cameras")
    if not 0 <= rom_frame < rom.n_frames:
        raise ValueError(f"ROM Frame Index {rom_frame} is outside {name} (frames 0..{rom.n_frames - 1})")
    if rom.brim is None or len(rom.brim_points()) == 0:
        raise ValueError(f"{name} has no calibration brim: solve the brim in the ROM take first")
    ok = np.isfinite(rom.R[rom_frame]).all((1, 2)) & np.isfinite(rom.t[rom_frame]).all(1)
    if not ok.any():
        raise ValueError(f"{name} has no camera poses in frame {rom_frame}: choose a solved ROM Frame Index")
    brim_known = np.isfinite(rom.xyz[rom_frame, rom.brim_points()]).all(-1)
    if not brim_known.any():
        raise ValueError(f"{name} has no brim point positions in frame {rom_frame}")


def match_rom_frame(rom: Take, rom_frame: int, tables: Sequence[Table], *, brim_only: bool = False,
                    tracking: TrackingParameters | None = None, rom_params: RomParameters | None = None,
                    image: ImageFn | None = None, rom_image: ImageFn | None = None,
                    image_size: Sequence[tuple[int, int]] | None = None) -> RomMatch:
    """Find the ROM frame's points among a new frame's detections.

    Parameters
    ----------
    rom : Take
        The solved ROM take (not modified): cameras with poses in ``rom_frame``, brim model,
        brim and face points with 3D positions and attached detections in ``rom_frame``.
    rom_frame : int
        The ROM Frame Index.
    tables : sequence of C detection tables
        The new frame's blob detections per camera (``x, y, major, minor, angle, polarity,
        score`` arrays; raw px), in the ROM's camera order.
    brim_only : bool
        Look for the brim points only (*Initialize from ROM [Brim Only]*).
    tracking : TrackingParameters, optional
        Default: the ROM's. Its distances and 3D error are replaced by ``rom_params``'.
    rom_params : RomParameters, optional
        Default: the ROM's.
    image : callable ``camera -> uint8 (H, W)``, optional
        The new frame's images (``image(c, 0)``; the frame argument is ignored).
    rom_image : callable ``(camera, frame) -> uint8 (H, W)``, optional
        The ROM take's video. Appearance checks and patch tracking need both; otherwise blobs
        are matched by position, polarity and size.
    image_size : sequence of (width, height), optional
        The new take's image sizes (checked against the ROM's when both are known).

    Returns
    -------
    RomMatch

    Raises
    ------
    ValueError
        The ROM cannot initialize (see :func:`check_rom`), or ``tables`` does not have one
        table per ROM camera, or the image sizes differ.
    """
    check_rom(rom, rom_frame)
    C = rom.n_cameras
    if len(tables) != C:
        raise ValueError(f"the ROM take has {C} cameras but the take has {len(tables)}: "
                         f"a ROM must come from the same camera rig")
    if image_size is not None:
        for c, (cam, size) in enumerate(zip(rom.cameras, image_size)):
            if min(cam.image_size) > 0 and min(size) > 0 and tuple(cam.image_size) != tuple(size):
                raise ValueError(f"camera {c}: the ROM's images are {cam.image_size[0]} x {cam.image_size[1]} "
                                 f"but the take's are {size[0]} x {size[1]}")
    tracking = rom.params.tracking if tracking is None else tracking
    rom_params = rom.params.rom if rom_params is None else rom_params
    params = rom_tracking_parameters(tracking, rom_params)
    known = np.isfinite(rom.xyz[rom_frame]).all(-1)
    kinds = rom.points.kind
    wanted = known & ((kinds == PointKind.BRIM) if brim_only else np.ones(rom.n_points, bool))
    cols = np.flatnonzero(wanted)
    bridge = _bridge_take(rom, rom_frame, cols, tables)
    bridge_image = None
    if image is not None and rom_image is not None:
        def bridge_image(c: int, f: int) -> np.ndarray:
            return rom_image(c, rom_frame) if f == 0 else image(c, 0)
    res = track(bridge, 0, direction=1, n_frames=1, image=bridge_image, params=params)
    Q = len(cols)
    xyz = res.xyz[0] if res.frames else np.full((Q, 3), np.nan)
    recon = res.recon[0] if res.frames else np.zeros(Q, np.uint8)
    found = recon >= Recon.SINGLE_SENSOR
    is_brim = kinds[cols] == PointKind.BRIM
    names = rom.points.names()
    report = {
        "face": int((~is_brim).sum()), "brim": int(is_brim.sum()),
        "found_face": int((found & ~is_brim).sum()), "found_brim": int((found & is_brim).sum()),
        "not_found": [names[int(c)] for c in cols[~found]],
        "cameras_updated": bool(res.cameras_updated),
        "tracker": res.report.get("per_frame", [{}])[0] if res.report.get("per_frame") else {},
    }
    return RomMatch(rom_points=cols, xyz=xyz, recon=recon, obs_xy=res.obs_xy[0], obs_det=res.obs_det[0],
                    obs_src=res.obs_src[0], obs_q=res.obs_q[0], R=res.R[0], t=res.t[0], found=found,
                    report=report)


def _bridge_take(rom: Take, rom_frame: int, cols: np.ndarray, tables: Sequence[Table]) -> Take:
    """A two-frame take: the ROM frame (points ``cols``, poses, detections) then the new frame's
    detections, with the ROM's poses as the new frame's starting poses."""
    cams = [CameraInfo(cam.name, cam.channel, cam.intrinsics, cam.image_size) for cam in rom.cameras]
    R0, t0 = rom.R[rom_frame], rom.t[rom_frame]
    bridge = Take.new(cams, 2, rom.frame_rate, R=R0, t=t0, caddies=list(rom.caddies))
    for c in range(rom.n_cameras):
        new = {k: np.asarray(v) for k, v in tables[c].items()}
        bridge.detections[c] = Detections.from_frames(2, {0: rom.detections[c].frame(rom_frame), 1: new})
    bridge.brim = rom.brim
    bridge.params = rom.params
    bridge.add_points(len(cols))
    bridge.points.kind[:] = rom.points.kind[cols]
    bridge.points.brim_index[:] = rom.points.brim_index[cols]
    for name in ("xyz", "recon", "obs_xy", "obs_det", "obs_src", "obs_q"):
        getattr(bridge, name)[0] = getattr(rom, name)[rom_frame, cols]
    return bridge
