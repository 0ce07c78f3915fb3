"""Configuration of a synthetic take."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

__all__ = ["SynthConfig", "MARKER_COUNTS", "BRIM_VERSIONS"]

#: Marker sets the generator knows (see :mod:`carapost.synth.markers`).
MARKER_COUNTS = (35, 80, 156)
#: Default brim models shipped in ``carapost/resources/brims``.
BRIM_VERSIONS = ("v1.0", "v1.1", "v2.0")


@dataclass(frozen=True)
class SynthConfig:
    """Everything that defines a synthetic take; same config (and seed) -> same take.

    Attributes
    ----------
    n_markers : int
        35, 80 or 156 painted face markers.
    n_frames : int
        Number of frames.
    frame_rate : float
        Frames per second.
    width, height : int
        Image size in pixels (every camera).
    seed : int
        Seed of every random choice (expression timing, flex, slip, noise, skin texture).
    marker_colour : {"black", "white"}
        Paint colour of the face markers.
    marker_radius_mm : float
        Radius of the painted dots, mm.
    brim : {"v1.0", "v1.1", "v2.0"}
        Default brim model on the helmet.
    brim_colour : {"model", "black", "white"}
        Colour of the brim dots: as in the brim model (black on a white card), or forced
        (``"white"`` gives white dots on a black card).
    curved_brim : bool
        Bend the brim card onto a vertical cylinder (radius ``brim_curvature_mm``).
    brim_curvature_mm : float
        Radius of the curved brim's cylinder, mm.
    expressions : bool
        Animate jaw, smile, brow raise, cheek puff and pucker.
    blinks : bool
        Animate blinks (eyelid markers hidden while the lid is more than half closed).
    high_motion : bool
        Fast, large expressions (several pixels per frame) for tracking stress tests.
    slip_mm : float
        Magnitude of the slow slip of the head inside the helmet over the take, mm.
    flex : bool
        Per-frame camera flex (arm bending and jitter; sub-mm, sub-0.1 degree).
    distortion : bool
        Radial lens distortion (about 2 px at the image corners).
    focal_length : float
        Nominal focal length in pixels at 1280 x 720; scaled with the image height.
    blur_sigma : float
        Optical blur (Gaussian sigma, pixels at full resolution); 0 disables it.
    noise : bool
        Shot and read noise.
    read_noise : float
        Read-noise standard deviation in grey levels.
    shot_noise : float
        Shot-noise gain: variance added per grey level of signal.
    vignetting : float
        Relative brightness loss at the image corners (0 disables it).
    jpeg_quality : int
        JPEG quality used by :func:`~carapost.synth.writer.write_take`.
    shading_scale : int
        The skin's shading and geometry are computed on a grid ``shading_scale`` times
        coarser than the image and interpolated (dots are always rendered at full
        resolution). 1 is exact and slow; 2 is the default.
    exposure : float
        Grey level of a white (albedo 1) surface lit head-on at 200 mm.
    """

    n_markers: int = 80
    n_frames: int = 120
    frame_rate: float = 60.0
    width: int = 1280
    height: int = 720
    seed: int = 0
    marker_colour: str = "black"
    marker_radius_mm: float = 1.5
    brim: str = "v2.0"
    brim_colour: str = "model"
    curved_brim: bool = False
    brim_curvature_mm: float = 150.0
    expressions: bool = True
    blinks: bool = True
    high_motion: bool = False
    slip_mm: float = 2.0
    flex: bool = True
    distortion: bool = True
    focal_length: float = 515.0
    blur_sigma: float = 0.7
    noise: bool = True
    read_noise: float = 1.2
    shot_noise: float = 0.035
    vignetting: float = 0.25
    jpeg_quality: int = 92
    shading_scale: int = 2
    exposure: float = 270.0
    caddies: tuple[tuple[int, int], ...] = field(default=((0, 1), (2, 3)))

    def __post_init__(self) -> None:
        if self.n_markers not in MARKER_COUNTS:
            raise ValueError(f"n_markers must be one of {MARKER_COUNTS}, got {self.n_markers}")
        if self.n_frames < 1:
            raise ValueError(f"n_frames must be at least 1, got {self.n_frames}")
        if not self.frame_rate > 0:
            raise ValueError(f"frame_rate must be positive, got {self.frame_rate}")
        if self.width < 64 or self.height < 36:
            raise ValueError(f"image size must be at least 64 x 36, got {self.width} x {self.height}")
        if self.marker_colour not in ("black", "white"):
            raise ValueError(f"marker_colour must be 'black' or 'white', got {self.marker_colour!r}")
        if not 0.3 <= self.marker_radius_mm <= 5.0:
            raise ValueError(f"marker_radius_mm must be within 0.3..5 mm, got {self.marker_radius_mm}")
        if self.brim not in BRIM_VERSIONS:
            raise ValueError(f"brim must be one of {BRIM_VERSIONS}, got {self.brim!r}")
        if self.brim_colour not in ("model", "black", "white"):
            raise ValueError(f"brim_colour must be 'model', 'black' or 'white', got {self.brim_colour!r}")
        if self.brim_curvature_mm < 60:
            raise ValueError(f"brim_curvature_mm must be at least 60 mm, got {self.brim_curvature_mm}")
        if not 0 <= self.slip_mm <= 20:
            raise ValueError(f"slip_mm must be within 0..20 mm, got {self.slip_mm}")
        if self.blur_sigma < 0 or self.read_noise < 0 or self.shot_noise < 0:
            raise ValueError("blur_sigma, read_noise and shot_noise must not be negative")
        if not 0 <= self.vignetting < 1:
            raise ValueError(f"vignetting must be within 0..1, got {self.vignetting}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be within 1..100, got {self.jpeg_quality}")
        if self.shading_scale not in (1, 2, 4):
            raise ValueError(f"shading_scale must be 1, 2 or 4, got {self.shading_scale}")
        if not self.focal_length > 0 or not self.exposure > 0:
            raise ValueError("focal_length and exposure must be positive")
        if tuple(map(tuple, self.caddies)) != ((0, 1), (2, 3)):
            raise ValueError("the synthetic rig has exactly the caddies (0, 1) and (2, 3)")

    @property
    def n_cameras(self) -> int:
        return 4

    def to_dict(self) -> dict:
        """Plain-JSON form (stored with the written take)."""
        d = asdict(self)
        d["caddies"] = [list(c) for c in self.caddies]
        return d
