"""Camera calibrations in memory, and the one entry point to load and save them.

A :class:`Calibration` is a list of :class:`CameraCalibration`, one per camera, in the order
of the file. Each camera has its intrinsics and one or more *keyframes* (XCP ``<KeyFrame>``):
keyframe ``k`` holds the pose from frame ``frames[k]`` until ``frames[k+1] - 1``; frames before
the first keyframe use the first one. Static cameras have a single keyframe at frame 0.

Formats (see ``docs/camera-model.md`` and ``docs/formats/xcp.md``):

* ``.xcp``: Vicon XML (read and write, :mod:`carapost.io.xcp`);
* ``.qca`` / ``.qca.txt``: Qualisys XML (read, :mod:`carapost.io.qca`);
* ``.toml``: aniposelib / Pose2Sim OpenCV calibration (read and write,
  :mod:`carapost.io.toml_calib`).

Conventions are those of :mod:`carapost.core.camera`: ``R`` rotates world to camera,
``X_cam = R X + t`` in millimetres, raw pixels with the centre of the top-left pixel at
``(0, 0)``.

The OpenCV/Qualisys distortion models cannot be written exactly in the XCP radial form; the
readers and writers convert them with :mod:`carapost.core.lens_models` (least squares over the
image, largest residual reported in ``CameraCalibration.extra["distortion_fit"]``).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from carapost.core.camera import Intrinsics, camera_centre

from .atomic import atomic_write_bytes

__all__ = [
    "CalibrationError",
    "CameraCalibration",
    "Calibration",
    "frames_from_poses",
    "natural_sort_key",
    "load_calibration",
    "save_calibration",
    "atomic_write_bytes",
]


class CalibrationError(ValueError):
    """A calibration file is malformed or cannot be represented.

    The message always starts with the file name and, where it applies, names the camera
    (0-based index and name) and the attribute, e.g.
    ``testCalibration.xcp: camera 3 (T160_17980): ORIENTATION must have 4 numbers, got "0.3 0.9"``.
    """


# --------------------------------------------------------------------------------------
# Data classes
# --------------------------------------------------------------------------------------


@dataclass
class CameraCalibration:
    """Calibration of one camera: intrinsics and run-length encoded poses.

    Attributes
    ----------
    name : str
        Camera name (XCP ``NAME``, may be empty; QCA ``serial``; TOML ``name``).
    device_id : str
        XCP ``DEVICEID`` (QCA: the serial).
    user_id : str
        XCP ``USERID``.
    intrinsics : Intrinsics
        Intrinsics of the first keyframe (XCP keyframes may each carry their own; see
        ``keyframe_intrinsics``).
    frames : ndarray (K,) int
        First frame of each keyframe, strictly increasing.
    R : ndarray (K, 3, 3)
        World-to-camera rotations.
    t : ndarray (K, 3)
        Translations in mm: ``X_cam = R X + t``.
    image_error : ndarray (K,)
        XCP ``IMAGE_ERROR`` in pixels, NaN if absent (give ``None`` or nothing for all NaN).
    world_error : ndarray (K,)
        XCP ``WORLD_ERROR`` (QCA ``avg-residual``) in mm, NaN if absent.
    keyframe_intrinsics : tuple of Intrinsics
        Empty (every keyframe uses ``intrinsics``) or one per keyframe.
    extra : dict
        Format-specific data kept for a faithful round trip (unknown XML attributes and
        elements, TOML sections, the original distortion coefficients, fit residuals).
        Keys are prefixed by the format (``xcp_``, ``qca_``, ``toml_``) or are
        ``"distortion_fit"`` / ``"opencv_distortion"``.

    Raises
    ------
    ValueError
        If the arrays do not have matching shapes, there is no keyframe, or frames repeat.
        Keyframes given out of order are sorted.
    """

    name: str
    device_id: str
    user_id: str
    intrinsics: Intrinsics
    frames: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_error: np.ndarray = field(default_factory=lambda: np.zeros(0))
    world_error: np.ndarray = field(default_factory=lambda: np.zeros(0))
    keyframe_intrinsics: tuple[Intrinsics, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        frames = np.asarray(self.frames, dtype=np.int64).reshape(-1)
        K = frames.shape[0]
        if K == 0:
            raise ValueError(f"camera {self.name!r}: at least one keyframe is required")
        R = np.array(self.R, dtype=float).reshape(K, 3, 3) if np.size(self.R) == 9 * K else None
        t = np.array(self.t, dtype=float).reshape(K, 3) if np.size(self.t) == 3 * K else None
        if R is None or t is None:
            raise ValueError(f"camera {self.name!r}: R must be ({K}, 3, 3) and t ({K}, 3) for "
                             f"{K} keyframes, got {np.shape(self.R)} and {np.shape(self.t)}")
        errs = []
        for e in (self.image_error, self.world_error):
            a = np.full(K, np.nan) if e is None or np.size(e) == 0 else np.array(e, dtype=float).reshape(-1)
            if a.shape != (K,):
                raise ValueError(f"camera {self.name!r}: errors must have {K} values, got {a.shape}")
            errs.append(a)
        kin = tuple(self.keyframe_intrinsics)
        if kin and len(kin) != K:
            raise ValueError(f"camera {self.name!r}: keyframe_intrinsics must be empty or have "
                             f"{K} entries, got {len(kin)}")
        order = np.argsort(frames, kind="stable")
        if np.any(np.diff(frames[order]) == 0):
            raise ValueError(f"camera {self.name!r}: two keyframes have the same FRAME "
                             f"{frames[order][np.flatnonzero(np.diff(frames[order]) == 0)[0]]}")
        self.frames = frames[order]
        self.R = R[order]
        self.t = t[order]
        self.image_error = errs[0][order]
        self.world_error = errs[1][order]
        self.keyframe_intrinsics = tuple(kin[i] for i in order) if kin else ()
        if kin:
            self.intrinsics = self.keyframe_intrinsics[0]

    @property
    def n_keyframes(self) -> int:
        return int(self.frames.shape[0])

    @property
    def centres(self) -> np.ndarray:
        """Camera centres (K, 3) in world mm."""
        return camera_centre(self.R, self.t)

    @property
    def label(self) -> str:
        """A name for messages: ``name``, else ``DEVICEID``, else ``USERID``."""
        if self.name:
            return self.name
        if self.device_id:
            return f"DEVICEID {self.device_id}"
        if self.user_id:
            return f"USERID {self.user_id}"
        return "unnamed"

    def intrinsics_at(self, k: int) -> Intrinsics:
        """Intrinsics of keyframe ``k``."""
        return self.keyframe_intrinsics[k] if self.keyframe_intrinsics else self.intrinsics

    def keyframe_index(self, frames: np.ndarray | int) -> np.ndarray:
        """Index of the keyframe valid at each frame (frames before the first use 0)."""
        idx = np.searchsorted(self.frames, np.asarray(frames), side="right") - 1
        return np.maximum(idx, 0)

    def pose_at(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``(R (3, 3), t (3,))`` valid at ``frame``."""
        k = int(self.keyframe_index(frame))
        return self.R[k].copy(), self.t[k].copy()


@dataclass
class Calibration:
    """All cameras of one calibration file, in file order.

    Attributes
    ----------
    cameras : list of CameraCalibration
    source : str
        Path the calibration was read from ("" if built in memory).
    format : str
        ``"xcp"``, ``"qca"`` or ``"toml"`` ("" if built in memory).
    extra : dict
        Format-specific file-level data (XCP root attributes and unknown elements, TOML
        metadata, detected units).
    """

    cameras: list[CameraCalibration]
    source: str = ""
    format: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @property
    def intrinsics(self) -> list[Intrinsics]:
        return [c.intrinsics for c in self.cameras]

    def order_by_name(self) -> list[int]:
        """Camera indices sorted by name numerically (``cam_2`` before ``cam_10``)."""
        return sorted(range(len(self.cameras)), key=lambda i: natural_sort_key(self.cameras[i].name))

    def poses(self, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame poses of every camera.

        Parameters
        ----------
        n_frames : int
            Number of frames ``F`` of the take.

        Returns
        -------
        R : ndarray (F, C, 3, 3)
            World-to-camera rotations; keyframe ``k`` is valid from ``frames[k]`` until
            ``frames[k+1] - 1``, frames before the first keyframe use the first.
        t : ndarray (F, C, 3)
            Translations, mm.
        """
        F = int(n_frames)
        if F < 0:
            raise ValueError(f"n_frames must be >= 0, got {n_frames}")
        C = len(self.cameras)
        R = np.empty((F, C, 3, 3))
        t = np.empty((F, C, 3))
        fr = np.arange(F)
        for c, cam in enumerate(self.cameras):
            k = cam.keyframe_index(fr)
            R[:, c] = cam.R[k]
            t[:, c] = cam.t[k]
        return R, t

    def with_poses(self, R: np.ndarray, t: np.ndarray, *, atol: float = 0.0) -> "Calibration":
        """A copy whose cameras' keyframes encode per-frame poses (moving cameras).

        Parameters
        ----------
        R : array (F, C, 3, 3)
            World-to-camera rotations per frame; NaN frames (unsolved) keep the previous pose.
        t : array (F, C, 3)
            Translations per frame, mm.
        atol : float
            A new keyframe starts when any element of ``R`` or ``t`` differs from the current
            keyframe by more than ``atol`` (0: any change).

        Returns
        -------
        Calibration
            Same intrinsics; image/world errors are NaN (they belonged to the old poses).
            Where a camera's intrinsics change between its old keyframes, those frames
            also start new keyframes.
        """
        R = np.asarray(R, dtype=float)
        t = np.asarray(t, dtype=float)
        C = len(self.cameras)
        if R.ndim != 4 or R.shape[1:] != (C, 3, 3) or t.shape != R.shape[:2] + (3,):
            raise ValueError(f"expected R (F, {C}, 3, 3) and t (F, {C}, 3), got {R.shape} and {t.shape}")
        F = R.shape[0]
        cams = []
        for c, cam in enumerate(self.cameras):
            breaks: np.ndarray = np.zeros(0, dtype=np.int64)
            if cam.keyframe_intrinsics:
                ki = cam.keyframe_intrinsics
                change = [k for k in range(1, len(ki)) if ki[k] != ki[k - 1]]
                breaks = cam.frames[change]
                breaks = breaks[(breaks > 0) & (breaks < F)]
            frames, Rk, tk = frames_from_poses(R[:, c], t[:, c], atol=atol, breaks=breaks)
            kin: tuple[Intrinsics, ...] = ()
            if breaks.size:
                kin = tuple(cam.intrinsics_at(int(k)) for k in cam.keyframe_index(frames))
            stale = ("xcp_keyframe_extra", "xcp_keyframe_pose")  # belonged to the old keyframes
            extra = {k: v for k, v in cam.extra.items() if k not in stale}
            cams.append(replace(cam, frames=frames, R=Rk, t=tk, image_error=np.zeros(0),
                                world_error=np.zeros(0), keyframe_intrinsics=kin, extra=extra))
        return replace(self, cameras=cams)


def frames_from_poses(R: np.ndarray, t: np.ndarray, *, atol: float = 0.0,
                      breaks: Sequence[int] | np.ndarray = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run-length encode per-frame poses of one camera into keyframes.

    Parameters
    ----------
    R : array (F, 3, 3)
        Rotations per frame. Frames with any NaN (unsolved) keep the previous valid pose;
        leading NaN frames take the first valid pose.
    t : array (F, 3)
        Translations per frame, mm.
    atol : float
        Tolerance: a keyframe starts at the first frame whose pose differs from the current
        keyframe's by more than ``atol`` in any element (0 = any change).
    breaks : sequence of int
        Extra frames that must start a keyframe.

    Returns
    -------
    frames : ndarray (K,) int
        First frame of each keyframe (``frames[0] == 0``).
    R : ndarray (K, 3, 3)
    t : ndarray (K, 3)

    Raises
    ------
    ValueError
        If shapes are wrong or no frame has a finite pose.
    """
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
        raise ValueError(f"expected R (F, 3, 3) and t (F, 3), got {R.shape} and {t.shape}")
    F = R.shape[0]
    valid = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    if not valid.any():
        raise ValueError("no frame has a finite pose")
    idx = np.where(valid, np.arange(F), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.argmax(valid))
    P = np.concatenate([R[idx].reshape(F, 9), t[idx]], axis=1)  # (F, 12) filled poses
    forced = np.zeros(F, dtype=bool)
    b = np.asarray(breaks, dtype=np.int64)
    forced[b[(b > 0) & (b < F)]] = True
    starts = [0]
    s = 0
    while True:
        rest = P[s + 1:]
        moved = np.any(np.abs(rest - P[s]) > atol, axis=1) | forced[s + 1:]
        if not moved.any():
            break
        s = s + 1 + int(np.argmax(moved))
        starts.append(s)
    frames = np.asarray(starts, dtype=np.int64)
    return frames, P[frames, :9].reshape(-1, 3, 3), P[frames, 9:].copy()


def natural_sort_key(name: str) -> tuple:
    """Sort key ordering digits numerically: ``cam_2 < cam_10`` (case-insensitive)."""
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower())
                 for p in re.split(r"(\d+)", name) if p != "")


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------


def read_bytes(path: str | os.PathLike) -> bytes:
    """File contents; an unreadable file raises :class:`CalibrationError` naming it."""
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise CalibrationError(f"{Path(path).name}: cannot read the file ({e.strerror or e})") from e


def _kind(path: Path, head: bytes) -> str:
    name = path.name.lower()
    if name.endswith(".xcp"):
        return "xcp"
    if name.endswith(".qca") or name.endswith(".qca.txt"):
        return "qca"
    if name.endswith(".toml"):
        return "toml"
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if text.startswith(b"<"):
        m = re.search(rb"<\s*([A-Za-z_][\w.-]*)", re.sub(rb"<[?!][^>]*>", b"", text))
        if m and m.group(1) == b"Cameras":
            return "xcp"
        if m and m.group(1) == b"calibration":
            return "qca"
    elif re.search(rb"^\s*\[", text, re.M):
        return "toml"
    raise CalibrationError(f"{path.name}: not a known calibration format "
                           "(expected .xcp, .qca, .qca.txt or .toml)")


def load_calibration(path: str | os.PathLike, **options: Any) -> Calibration:
    """Read a camera calibration, choosing the reader by extension, else by content.

    Parameters
    ----------
    path : path-like
        ``.xcp`` (Vicon), ``.qca`` / ``.qca.txt`` (Qualisys), ``.toml`` (aniposelib/Pose2Sim).
    **options
        Passed to the reader: ``binning`` and ``fit_centre`` for QCA, ``units`` and
        ``fit_centre`` for TOML.

    Raises
    ------
    CalibrationError
        For an unreadable, unknown or malformed file (the message names the file).
    """
    p = Path(path)
    data = read_bytes(p)
    kind = _kind(p, data[:4096])
    if kind == "xcp":
        from carapost.io.xcp import parse_xcp
        return parse_xcp(data, source=str(p), **options)
    if kind == "qca":
        from carapost.io.qca import parse_qca
        return parse_qca(data, source=str(p), **options)
    from carapost.io.toml_calib import parse_toml
    return parse_toml(data, source=str(p), **options)


def save_calibration(path: str | os.PathLike, calib: Calibration, **options: Any) -> None:
    """Write a calibration as ``.xcp`` or ``.toml`` (by extension), atomically.

    Parameters
    ----------
    path : path-like
    calib : Calibration
    **options
        For TOML: ``units`` (``"m"``, ``"cm"``, ``"mm"``), ``frame`` (moving cameras),
        ``rational`` (8 distortion coefficients).

    Raises
    ------
    CalibrationError
        For another extension, or a calibration that cannot be written.
    """
    p = Path(path)
    name = p.name.lower()
    if name.endswith(".xcp"):
        from carapost.io.xcp import write_xcp
        write_xcp(p, calib, **options)
    elif name.endswith(".toml"):
        from carapost.io.toml_calib import write_toml
        write_toml(p, calib, **options)
    else:
        raise CalibrationError(f"{p.name}: cannot save a calibration with this extension "
                               "(use .xcp or .toml)")
