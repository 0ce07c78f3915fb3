"""Calibration targets: their geometry, their detection in an image, and synthetic renders.

A target is a flat, printed pattern of known layout: a checkerboard (its *inner* corners are
the points) or a grid of dots (OpenCV's symmetric and asymmetric circle grids). Points are
numbered row by row, ``cols`` per row, ``rows`` rows; point ``i * cols + j`` lies at
``(j * spacing, i * spacing, 0)`` mm in the *target frame* (asymmetric grid:
``((2 j + i % 2) * spacing, i * spacing, 0)``, OpenCV's layout).

Ordering is made consistent between images and cameras, so that the same physical corner
gets the same index wherever it is seen (multi-camera extrinsics depend on it):

* the target's ``x`` (along a row) and ``y`` (down the rows) axes appear in the image with the
  same handedness as the image's own ``x`` (right) and ``y`` (down): the camera looks at the
  printed face, along the target's ``+z``;
* checkerboard: the square between the first four corners (``0, 1, cols, cols + 1``) is the
  dark one. This fixes the last ambiguity (a half-turn) when ``cols + rows`` is odd, the
  usual advice for calibration boards (:attr:`TargetSpec.orientation_unique`);
* asymmetric circle grid with an odd number of rows: unique by its layout;
* otherwise (a square board, a checkerboard with ``cols + rows`` even, a symmetric dot grid) a
  half-turn of the target looks the same; we take the ordering whose first point is nearest
  the image's top-left corner, which is consistent only while every camera sees the target
  roughly upright.

Nothing here reads files; images are numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Intrinsics, undistort

__all__ = ["TargetSpec", "target_points", "detect_target", "canonical_order", "render_target"]

_KINDS = ("checkerboard", "circles", "asymmetric_circles")


@dataclass(frozen=True)
class TargetSpec:
    """Layout of a flat calibration target.

    Attributes
    ----------
    kind : {"checkerboard", "circles", "asymmetric_circles"}
        A checkerboard (points are its inner corners), a symmetric grid of dark dots, or
        OpenCV's asymmetric grid of dark dots (rows offset by half a pitch).
    cols, rows : int
        Points per row and number of rows: a board of 8 x 5 squares has 7 x 4 (or 4 x 7)
        inner corners. OpenCV's ``patternSize`` is ``(cols, rows)``.
    spacing_mm : float
        Checkerboard: the side of a square. Symmetric dots: the centre distance between
        neighbouring dots. Asymmetric dots: the distance between neighbouring rows (half the
        centre distance between neighbouring dots of one row), as in OpenCV's samples.

    Raises
    ------
    ValueError
        Unknown kind, fewer than 2 points per row or column (3 for dots), or a spacing
        that is not positive.
    """

    kind: str
    cols: int
    rows: int
    spacing_mm: float

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ValueError(f"target kind must be one of {', '.join(_KINDS)}, got {self.kind!r}")
        least = 2 if self.kind == "checkerboard" else 3
        if int(self.cols) != self.cols or int(self.rows) != self.rows or min(self.cols, self.rows) < least:
            raise ValueError(f"a {self.kind} target needs at least {least} x {least} points, "
                             f"got cols={self.cols}, rows={self.rows}")
        if not np.isfinite(self.spacing_mm) or self.spacing_mm <= 0:
            raise ValueError(f"target spacing must be a positive number of mm, got {self.spacing_mm}")

    @property
    def n_points(self) -> int:
        return int(self.cols * self.rows)

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV's ``patternSize``: ``(cols, rows)``."""
        return int(self.cols), int(self.rows)

    @property
    def orientation_unique(self) -> bool:
        """True when every view of the target numbers its points the same way.

        False for layouts a half-turn maps onto themselves (see the module notes): then two
        cameras may number the same target differently unless both see it upright.
        """
        if self.kind == "checkerboard":
            return self.cols != self.rows and (self.cols + self.rows) % 2 == 1
        if self.kind == "asymmetric_circles":
            return self.rows % 2 == 1
        return False


def target_points(spec: TargetSpec) -> np.ndarray:
    """Target points ``(N, 3)`` in mm in the target frame (``z = 0``), in detection order."""
    i, j = np.divmod(np.arange(spec.n_points), spec.cols)
    x = (2 * j + i % 2) if spec.kind == "asymmetric_circles" else j
    return np.stack([x * spec.spacing_mm, i * spec.spacing_mm, np.zeros(spec.n_points)], axis=1).astype(float)


# --------------------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------------------


def _as_gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2 or min(img.shape) < 8:
        raise ValueError(f"expected a grey (H, W) or colour (H, W, 3) image, got shape {np.shape(image)}")
    if img.dtype != np.uint8:
        if not np.issubdtype(img.dtype, np.number):
            raise ValueError(f"image must be numeric, got {img.dtype}")
        lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
        img = np.clip((img - lo) * (255.0 / max(hi - lo, 1e-12)), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def _min_spacing(grid: np.ndarray) -> float:
    """Smallest distance between neighbouring points of a (rows, cols, 2) grid, px."""
    d = [np.linalg.norm(np.diff(grid, axis=a), axis=-1).min() for a in (0, 1)]
    return float(min(d))


def _refine_corners(gray: np.ndarray, corners: np.ndarray, spec: TargetSpec) -> np.ndarray:
    """``cv2.cornerSubPix`` with a window that stays inside a square."""
    d = _min_spacing(corners.reshape(spec.rows, spec.cols, 2))
    half = int(np.clip(0.3 * d, 2, 15))
    pts = corners.reshape(-1, 1, 2).astype(np.float32).copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    cv2.cornerSubPix(gray, pts, (half, half), (-1, -1), crit)
    return pts.reshape(-1, 2).astype(float)


def _find_checkerboard(gray: np.ndarray, spec: TargetSpec, max_side: int) -> np.ndarray | None:
    scale = min(1.0, max_side / max(gray.shape))
    small = gray if scale == 1.0 else cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    # 1. The classic detector, then 2. the sector-based one (finds boards cut by the image
    # border, blurred or with glare), both on a reduced copy (fast) and refined on the full image.
    for find, flags in ((cv2.findChessboardCorners, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE),
                        (cv2.findChessboardCornersSB, cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_NORMALIZE_IMAGE)):
        ok, c = find(small, spec.pattern_size, flags=flags)
        if ok:
            # Pixel centres: x_full = (x_small + 0.5) / scale - 0.5.
            c = (c.reshape(-1, 2).astype(float) + 0.5) / scale - 0.5
            return _refine_corners(gray, c, spec)
    if scale < 1.0:  # 3. last resort: the sector-based detector on the full image
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, c = cv2.findChessboardCornersSB(gray, spec.pattern_size, flags=flags)
        if ok:
            return c.reshape(-1, 2).astype(float)
    return None


def _find_circles(gray: np.ndarray, spec: TargetSpec) -> np.ndarray | None:
    params = cv2.SimpleBlobDetector_Params()
    params.minArea = 8.0
    params.maxArea = float(gray.size) / max(spec.n_points, 1)
    params.minDistBetweenBlobs = 2.0
    detector = cv2.SimpleBlobDetector_create(params)
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.kind == "asymmetric_circles" else cv2.CALIB_CB_SYMMETRIC_GRID
    ok, c = cv2.findCirclesGrid(gray, spec.pattern_size, flags=flags | cv2.CALIB_CB_CLUSTERING,
                                blobDetector=detector)
    if not ok:
        ok, c = cv2.findCirclesGrid(gray, spec.pattern_size, flags=flags, blobDetector=detector)
    return c.reshape(-1, 2).astype(float) if ok else None


def _cell_mean(gray: np.ndarray, quad: np.ndarray) -> float:
    """Mean grey level in the middle of a cell given its 4 corners (4, 2)."""
    c = quad.mean(axis=0)
    pts = c + 0.4 * (quad - c)  # a shrunk copy of the cell
    x0, y0 = np.floor(pts.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0)).astype(int)
    h, w = gray.shape
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1 + 1, w), min(y1 + 1, h)
    if x1 <= x0 or y1 <= y0:
        return float(gray[int(np.clip(round(c[1]), 0, h - 1)), int(np.clip(round(c[0]), 0, w - 1))])
    return float(gray[y0:y1, x0:x1].mean())


def canonical_order(points: np.ndarray, spec: TargetSpec, image: np.ndarray | None = None) -> np.ndarray:
    """Renumber detected target points into the consistent order of the module notes.

    Parameters
    ----------
    points : array (N, 2)
        Detected points in any of the orderings OpenCV may return (rows of ``cols`` points,
        starting from any corner of the grid).
    spec : TargetSpec
    image : array (H, W), optional
        The grey image, used to tell the dark squares of a checkerboard.

    Returns
    -------
    array (N, 2)
        The same points, renumbered.
    """
    g = np.asarray(points, dtype=float).reshape(spec.rows, spec.cols, 2)
    vx = g[0, -1] - g[0, 0]
    vy = g[-1, 0] - g[0, 0]
    if vx[0] * vy[1] - vx[1] * vy[0] < 0:  # mirrored: the target's x, y would be left-handed in the image
        g = g[:, ::-1] if spec.kind != "asymmetric_circles" else g[::-1]
    if spec.kind == "checkerboard" and image is not None and (spec.cols + spec.rows) % 2 == 1:
        first = _cell_mean(image, np.stack([g[0, 0], g[0, 1], g[1, 1], g[1, 0]]))
        last = _cell_mean(image, np.stack([g[-1, -1], g[-1, -2], g[-2, -2], g[-2, -1]]))
        if first > last:
            g = g[::-1, ::-1]
    elif spec.kind == "asymmetric_circles":
        pass  # OpenCV's ordering already follows the layout (a half-turn does not fit when rows is odd)
    elif not spec.orientation_unique:
        alt = g[::-1, ::-1]
        if alt[0, 0].sum() < g[0, 0].sum():
            g = alt
    return g.reshape(-1, 2).copy()


def detect_target(image: np.ndarray, spec: TargetSpec, *, max_search_side: int = 1000) -> np.ndarray | None:
    """Find a calibration target's points in an image, to sub-pixel accuracy.

    Checkerboards: OpenCV's classic detector, else the sector-based
    ``findChessboardCornersSB`` (finds boards cut by the border, blurred or with glare), on a
    copy reduced to ``max_search_side`` pixels (fast), then ``cornerSubPix`` on the full
    image; the sector-based detector on the full image is the last resort.
    Dot grids: ``findCirclesGrid`` (blob centroids).

    Parameters
    ----------
    image : array (H, W) uint8, or (H, W, 3) BGR
        Other numeric types are rescaled to 0..255.
    spec : TargetSpec
    max_search_side : int
        Longest side of the reduced copy searched by the classic checkerboard detector.

    Returns
    -------
    array (N, 2) float or None
        Raw pixel coordinates (centre of the top-left pixel at ``(0, 0)``) of the
        ``spec.n_points`` points in the consistent order of :func:`canonical_order`, or
        ``None`` when the whole target is not found.

    Raises
    ------
    ValueError
        If ``image`` is not a 2-D grey or 3-channel colour image.
    """
    gray = _as_gray(image)
    if spec.kind == "checkerboard":
        pts = _find_checkerboard(gray, spec, int(max_search_side))
    else:
        pts = _find_circles(gray, spec)
    if pts is None or not np.isfinite(pts).all():
        return None
    return canonical_order(pts, spec, gray)


# --------------------------------------------------------------------------------------
# Synthetic renders
# --------------------------------------------------------------------------------------


def _target_shade(u: np.ndarray, v: np.ndarray, spec: TargetSpec) -> np.ndarray:
    """Target reflectance (0 dark .. 1 white) at target-frame coordinates (mm); NaN off the card."""
    s = spec.spacing_mm
    if spec.kind == "checkerboard":
        lo_x, hi_x, lo_y, hi_y = -2 * s, (spec.cols + 1) * s, -2 * s, (spec.rows + 1) * s
        inside = (u >= -s) & (u < spec.cols * s) & (v >= -s) & (v < spec.rows * s)
        dark = inside & ((np.floor(u / s) + np.floor(v / s)) % 2 == 0)
    else:
        asym = spec.kind == "asymmetric_circles"
        pitch_x = 2 * s if asym else s  # centre distance within a row
        max_x = (2 * (spec.cols - 1) + 1) * s if asym else (spec.cols - 1) * s
        lo_x, hi_x, lo_y, hi_y = -1.5 * s, max_x + 1.5 * s, -1.5 * s, (spec.rows - 1) * s + 1.5 * s
        i = np.clip(np.round(v / s), 0, spec.rows - 1)
        off = (i % 2) * s if asym else 0.0
        j = np.clip(np.round((u - off) / pitch_x), 0, spec.cols - 1)
        dark = (u - (j * pitch_x + off)) ** 2 + (v - i * s) ** 2 <= (0.3 * s) ** 2
    card = (u >= lo_x) & (u <= hi_x) & (v >= lo_y) & (v <= hi_y)
    return np.where(card, np.where(dark, 0.0, 1.0), np.nan)


def render_target(spec: TargetSpec, intr: Intrinsics, R: np.ndarray, t: np.ndarray, *,
                  image_size: tuple[int, int] | None = None, supersample: int = 3,
                  dark: float = 30.0, light: float = 220.0, background: float = 110.0,
                  noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Render a target seen by an XCP camera, lens distortion included.

    Every raw pixel (sampled ``supersample x supersample`` times) is corrected with
    :func:`carapost.core.camera.undistort` and mapped through the inverse of the target
    plane's homography ``K [r1 r2 t]``; the target's shade there is averaged. So the image is
    exactly what the XCP model predicts, up to the anti-aliasing.

    Parameters
    ----------
    spec : TargetSpec
    intr : Intrinsics
    R : array (3, 3)
        Target-to-camera rotation.
    t : array (3,)
        Target-to-camera translation, mm.
    image_size : (width, height), optional
        Defaults to ``intr.sensor_size``.
    supersample : int
        Samples per pixel along each axis.
    dark, light, background : float
        Grey levels of the dark marks, the card and everything off the card.
    noise : float
        Standard deviation of added Gaussian noise (grey levels).
    seed : int
        Seed of the noise.

    Returns
    -------
    array (H, W) uint8
    """
    w, h = image_size if image_size is not None else intr.sensor_size
    if w <= 0 or h <= 0:
        raise ValueError(f"image size must be positive, got {(w, h)}")
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float).reshape(3)
    Hinv = np.linalg.inv(intr.K @ np.column_stack([R[:, 0], R[:, 1], t]))
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    acc = np.zeros((h, w))
    ss = max(int(supersample), 1)
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    for oy in offsets:
        for ox in offsets:
            raw = np.stack([xs + ox, ys + oy], axis=-1)
            pc = undistort(raw, intr)
            q = pc @ Hinv[:, :2].T + Hinv[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u, v = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
            shade = _target_shade(u, v, spec)
            shade = np.where(q[..., 2] > 0, shade, np.nan)
            acc += np.where(np.isfinite(shade), dark + (light - dark) * np.nan_to_num(shade), background)
    img = acc / (ss * ss)
    if noise > 0:
        img = img + np.random.default_rng(seed).normal(scale=noise, size=img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)
