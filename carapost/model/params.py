"""Parameters: one typed dataclass per section of the reference guide's Properties pane.

Every field carries metadata — the guide's label, unit, range and help text — from which the
Properties pane and the scripting API's ``get_property`` / ``set_property`` are generated.
Validation rejects out-of-range values with a message naming the section, the property and
the allowed range.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar

__all__ = [
    "ParamSection",
    "DisplayParameters",
    "SelectionParameters",
    "BlobParameters",
    "Initialize3DParameters",
    "RomParameters",
    "TrackingParameters",
    "GapFillingParameters",
    "FILL_METHODS",
    "StabilizationParameters",
    "ExportParameters",
    "ShowAgainFlags",
    "TrackerSettings",
    "Parameters",
    "restore_defaults",
    "dense_156_preset",
    "sparse_35_preset",
    "PRESETS",
]


def p(default: Any, label: str, *, unit: str = "", lo: float | None = None, hi: float | None = None,
      choices: tuple[str, ...] | None = None, help: str = "") -> Any:
    """A parameter field with its Properties-pane metadata."""
    return field(default=default, metadata={"label": label, "unit": unit, "lo": lo, "hi": hi,
                                            "choices": choices, "help": help})


@dataclass
class ParamSection:
    """Base class of a Properties-pane section."""

    title: ClassVar[str] = ""

    def __post_init__(self) -> None:
        self.validate()

    # -- metadata ------------------------------------------------------------------------
    @classmethod
    def fields(cls) -> tuple[dataclasses.Field, ...]:
        return dataclasses.fields(cls)

    @classmethod
    def field_by_label(cls, name: str) -> dataclasses.Field:
        """Find a field by attribute name or by the guide's label (case-insensitive)."""
        key = _norm(name)
        for f in cls.fields():
            if _norm(f.name) == key or _norm(f.metadata["label"]) == key:
                return f
        raise KeyError(f"{cls.title}: no property named {name!r}; "
                       f"known: {', '.join(f.metadata['label'] for f in cls.fields())}")

    # -- values --------------------------------------------------------------------------
    def validate(self) -> None:
        for f in self.fields():
            setattr(self, f.name, _check(self.title, f, getattr(self, f.name)))

    def set(self, name: str, value: Any) -> None:
        """Set a property by name or label, validating it first (the value is unchanged on error)."""
        f = self.field_by_label(name)
        setattr(self, f.name, _check(self.title, f, value))

    def get(self, name: str) -> Any:
        return getattr(self, self.field_by_label(name).name)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in self.fields()}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "ParamSection":
        """Build from a dict, ignoring unknown keys (written by a newer version)."""
        known = {f.name for f in cls.fields()}
        return cls(**{k: v for k, v in values.items() if k in known})


def _norm(s: str) -> str:
    return "".join(ch for ch in s.lower() if ch.isalnum())


def _check(section: str, f: dataclasses.Field, value: Any) -> Any:
    md = f.metadata
    label = md["label"]
    default = f.default
    where = f"{section}: {label}"
    if isinstance(default, bool):
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0"):
            value = value.lower() in ("true", "1")
        if not isinstance(value, (bool, int)) or isinstance(value, float):
            raise ValueError(f"{where} must be True or False, got {value!r}")
        return bool(value)
    if isinstance(default, (int, float)):
        try:
            num = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{where} must be a number, got {value!r}") from None
        if num != num:
            raise ValueError(f"{where} must be a number, got NaN")
        lo, hi = md["lo"], md["hi"]
        if (lo is not None and num < lo) or (hi is not None and num > hi):
            rng = f"{'-inf' if lo is None else format(lo, 'g')} to {'inf' if hi is None else format(hi, 'g')}"
            unit = f" {md['unit']}" if md["unit"] else ""
            raise ValueError(f"{where} must be in the range {rng}{unit}, got {value!r}")
        if isinstance(default, int):
            if num != int(num):
                raise ValueError(f"{where} must be a whole number, got {value!r}")
            return int(num)
        return num
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ValueError(f"{where} must be text, got {value!r}")
        if md["choices"] and value not in md["choices"]:
            raise ValueError(f"{where} must be one of {', '.join(md['choices'])}, got {value!r}")
        return value
    return value


@dataclass
class DisplayParameters(ParamSection):
    title: ClassVar[str] = "Display"
    point_labels_all: bool = p(False, "Point Labels : All", help="Show every assigned point label in 2D and 3D views.")
    point_labels_selected: bool = p(True, "Point Labels : Selected", help="Show labels of selected points.")
    point_labels_preselected: bool = p(True, "Point Labels : Pre-Selected", help="Show labels of points under the mouse.")
    font_size: int = p(10, "Font Size", unit="pt", lo=4, hi=72, help="Font size of point labels.")


@dataclass
class SelectionParameters(ParamSection):
    title: ClassVar[str] = "Selection"
    points: bool = p(True, "Points", help="Points are selectable in 2D and 3D views.")
    detections: bool = p(True, "Detections", help="Detections are selectable in 2D and 3D views.")
    sensors: bool = p(True, "Sensors", help="Sensors (cameras) are selectable in 2D and 3D views.")
    sticks: bool = p(True, "Sticks", help="Sticks are selectable in 2D and 3D views.")


@dataclass
class BlobParameters(ParamSection):
    title: ClassVar[str] = "Blob Parameters"
    white_min_radius: float = p(4.0, "White Min Radius", unit="px", lo=0.5, hi=500,
                                help="Minimum length of the longest ellipse axis of a white blob.")
    white_max_radius: float = p(50.0, "White Max Radius", unit="px", lo=0.5, hi=500,
                                help="Maximum length of the longest ellipse axis of a white blob.")
    black_min_radius: float = p(4.0, "Black Min Radius", unit="px", lo=0.5, hi=500,
                                help="Minimum length of the longest ellipse axis of a black blob.")
    black_max_radius: float = p(50.0, "Black Max Radius", unit="px", lo=0.5, hi=500,
                                help="Maximum length of the longest ellipse axis of a black blob.")
    find_black_blobs: bool = p(True, "Find Black Blobs", help="Search for black markers.")
    find_white_blobs: bool = p(False, "Find White Blobs", help="Search for white markers.")
    black_threshold: float = p(0.4, "Black Threshold", lo=0.0, hi=1.0,
                               help="Probability above which a pixel is taken as a black blob centre.")
    white_threshold: float = p(0.4, "White Threshold", lo=0.0, hi=1.0,
                               help="Probability above which a pixel is taken as a white blob centre.")
    adaptive_background: bool = p(False, "Adaptive Background Threshold",
                                  help="Normalise by a local per-pixel background (uneven lighting).")

    def validate(self) -> None:
        super().validate()
        for colour in ("white", "black"):
            lo, hi = getattr(self, f"{colour}_min_radius"), getattr(self, f"{colour}_max_radius")
            if lo > hi:
                raise ValueError(f"Blob Parameters: {colour.title()} Min Radius ({lo:g}) must not exceed "
                                 f"{colour.title()} Max Radius ({hi:g})")


@dataclass
class Initialize3DParameters(ParamSection):
    title: ClassVar[str] = "Initialize 3D Parameters"
    max_allowed_depth: float = p(35.0, "Max Allowed Depth", unit="mm", lo=0.0, hi=1000.0,
                                 help="Largest distance of a new 3D point from an existing one.")
    max_3d_distance_to_merge: float = p(5.0, "Max 3D Distance To Merge", unit="mm", lo=0.0, hi=100.0,
                                        help="Points of the two caddies closer than this are merged.")
    max_allowed_symmetric_epipolar_distance: float = p(
        5.0, "Max Allowed Symmetric Epipolar Distance", unit="px", lo=0.0, hi=100.0,
        help="Largest epipolar error of a match between the two cameras of a caddy.")
    auto_min_views: int = p(3, "Automatic Min Views", lo=2, hi=64,
                            help="Initialize 3D without seeds: fewest cameras a point must be verified in "
                                 "(2 accepts epipolar pairs nothing else confirms).")
    auto_max_reprojection_error: float = p(
        2.0, "Automatic Max Reprojection Error", unit="px", lo=0.1, hi=50.0,
        help="Initialize 3D without seeds: largest reprojection error of a view of a matched point.")


@dataclass
class RomParameters(ParamSection):
    title: ClassVar[str] = "Initialize From ROM Parameters"
    rom_frame_index: int = p(0, "ROM Frame Index", lo=0, help="Frame of the ROM take used to initialize.")
    rom_face_point_tracking_distance: float = p(50.0, "ROM Face Point Tracking Distance", unit="px", lo=0, hi=1000)
    rom_brim_point_tracking_distance: float = p(30.0, "ROM Brim Point Tracking Distance", unit="px", lo=0, hi=1000)
    rom_max_allowed_3d_point_error: float = p(5.0, "ROM Max Allowed 3D Point Error", unit="mm", lo=0, hi=1000)


@dataclass
class TrackingParameters(ParamSection):
    title: ClassVar[str] = "Tracking Parameters"
    patch_match_threshold: float = p(0.8, "Patch Match Threshold", lo=0.0, hi=1.0,
                                     help="Score above which two detections or patches match.")
    face_point_tracking_distance: float = p(35.0, "Face Point Tracking Distance", unit="px", lo=0, hi=1000)
    face_point_max_elastic_prediction_distance: float = p(
        15.0, "Face Point Max Elastic Prediction Distance", unit="px", lo=0, hi=1000)
    brim_point_tracking_distance: float = p(15.0, "Brim Point Tracking Distance", unit="px", lo=0, hi=1000)
    patch_match_size: int = p(15, "Patch Match Size", unit="px", lo=3, hi=201)
    remove_bad_2d_projections: bool = p(True, "Remove Bad 2D Projections")
    max_allowed_2d_projection_error: float = p(5.0, "Max Allowed 2D Projection Error", unit="px", lo=0, hi=1000)
    remove_bad_3d_points: bool = p(True, "Remove Bad 3D Points")
    max_allowed_3d_point_error: float = p(5.0, "Max Allowed 3D Point Error", unit="mm", lo=0, hi=1000)
    allow_single_sensor_tracking: bool = p(True, "Allow Single Sensor Tracking")
    single_sensor_tracking_threshold: float = p(0.5, "Single Sensor Tracking Threshold", unit="mm", lo=0, hi=1000)
    blob_size_difference_threshold: float = p(0.75, "Blob Size Difference Threshold", lo=0.0, hi=1.0)


#: Interpolate Gaps methods: the guide's neighbour interpolation, seed 001's face model, and the
#: neighbour method with eyelid blink pulses (``docs/gap-filling.md``).
FILL_METHODS = ("neighbours", "face_model", "blink")


@dataclass
class GapFillingParameters(ParamSection):
    title: ClassVar[str] = "Gap-Filling Parameters"
    overwrite_existing_filled_gaps: bool = p(False, "Overwrite Existing Filled Gaps")
    use_forwards_prediction: bool = p(True, "Use Forwards Prediction")
    use_backwards_prediction: bool = p(True, "Use Backwards Prediction")
    allow_single_sensor_tracking_gap_filling: bool = p(True, "Allow Single Sensor Tracking Gap-Filling")
    method: str = p("neighbours", "Method", choices=FILL_METHODS,
                    help="neighbours: the guide's gap interpolation; face_model: a face model learnt from the "
                         "take (or the loaded ROM); blink: neighbours plus eyelid blink pulses, their depth taken "
                         "from the loaded ROM when there is one, else from the eye's geometry (Lid Marker "
                         "Offset, Palpebral Fissure) (not in Vicon CaraPost; docs/gap-filling.md).")
    # The blink method's eye geometry without a ROM (carapost.core.gapfill_lid): the closed-lid
    # depth is the upper-to-lower lid marker distance minus twice this offset, or the fissure
    # for a labelled upper-lid marker with no lower-lid marker below it.
    lid_marker_offset: float = p(2.5, "Lid Marker Offset", unit="mm", lo=0.0, hi=10.0,
                                 help="blink: how far the eyelid markers are painted from the lid margins "
                                      "(1 mm here is 2 mm of closed-lid depth).")
    palpebral_fissure: float = p(9.7, "Palpebral Fissure", unit="mm", lo=1.0, hi=20.0,
                                 help="blink: the open eye's height between the lid margins, used for an "
                                      "upper-lid marker without a lower-lid marker (mean 9.7 mm, sd 1.2).")


@dataclass
class StabilizationParameters(ParamSection):
    title: ClassVar[str] = "Stabilization Parameters"
    use_brim_points: bool = p(False, "Use Brim Points")
    base_frame_weighting: float = p(1.0, "Base Frame Weighting", lo=0.0)
    inter_frame_weighting: float = p(1.0, "Inter Frame Weighting", lo=0.0)
    stable_points_percent: float = p(0.25, "Stable Points Percent", lo=0.0, hi=1.0)
    max_processing_iterations: int = p(50, "Max Processing Iterations", lo=1, hi=100000)


@dataclass
class ExportParameters(ParamSection):
    title: ClassVar[str] = "Export"
    units: str = p("mm", "Units", choices=("mm", "cm"), help="Length unit of exported FBX data.")
    up_axis: str = p("Y", "Up Axis", choices=("Y", "Z"), help="Up axis of exported FBX data.")
    use_stabilized: bool = p(False, "Export Stabilized Data", help="Export stabilized rather than raw 3D data.")
    selected_only: bool = p(False, "Selected Points Only", help="Export only the selected points.")
    include_brim: bool = p(True, "Include Brim Points", help="Export calibration brim points too.")
    include_cameras: bool = p(True, "Include Cameras", help="Export camera nodes (FBX).")


@dataclass
class ShowAgainFlags(ParamSection):
    title: ClassVar[str] = "Show Again Flags"
    show_version_check_dialog_on_startup: bool = p(False, "Show Version Check Dialog On Startup",
                                                   help="This build never checks online for updates.")


@dataclass
class TrackerSettings(ParamSection):
    """The Tracker pane's settings (target tracking)."""

    title: ClassVar[str] = "Tracker"
    stop_after_n_frames: bool = p(False, "Stop after N Frames")
    n_frames: int = p(10, "N", lo=1, help="Frames tracked per step when Stop after N Frames is on.")
    overwrite_existing_tracks: bool = p(False, "Overwrite Existing Tracks")
    automatically_add_keyframes: bool = p(True, "Automatically Add Keyframes")
    stop_on_next_keyframe: bool = p(True, "Stop On Next Keyframe")
    allow_single_sensor_tracking: bool = p(False, "Allow Single Sensor Tracking")
    break_threshold: float = p(0.9, "Break Threshold", lo=0.0, hi=1.0)
    update_timeline_every_frame: bool = p(False, "Update Timeline Every Frame")
    update_2d_view_every_frame: bool = p(False, "Update 2D View Every Frame")


SECTIONS: dict[str, type[ParamSection]] = {
    "display": DisplayParameters,
    "selection": SelectionParameters,
    "blobs": BlobParameters,
    "init3d": Initialize3DParameters,
    "rom": RomParameters,
    "tracking": TrackingParameters,
    "gapfill": GapFillingParameters,
    "stabilization": StabilizationParameters,
    "export": ExportParameters,
    "show_again": ShowAgainFlags,
    "tracker": TrackerSettings,
}


@dataclass
class Parameters:
    """All parameter sections of a take."""

    display: DisplayParameters = field(default_factory=DisplayParameters)
    selection: SelectionParameters = field(default_factory=SelectionParameters)
    blobs: BlobParameters = field(default_factory=BlobParameters)
    init3d: Initialize3DParameters = field(default_factory=Initialize3DParameters)
    rom: RomParameters = field(default_factory=RomParameters)
    tracking: TrackingParameters = field(default_factory=TrackingParameters)
    gapfill: GapFillingParameters = field(default_factory=GapFillingParameters)
    stabilization: StabilizationParameters = field(default_factory=StabilizationParameters)
    export: ExportParameters = field(default_factory=ExportParameters)
    show_again: ShowAgainFlags = field(default_factory=ShowAgainFlags)
    tracker: TrackerSettings = field(default_factory=TrackerSettings)

    def sections(self) -> list[tuple[str, ParamSection]]:
        return [(key, getattr(self, key)) for key in SECTIONS]

    def section(self, name: str) -> ParamSection:
        """Find a section by key (``"tracking"``) or by the guide's title (``"Tracking Parameters"``)."""
        key = _norm(name)
        for k, sec in self.sections():
            if _norm(k) == key or _norm(sec.title) == key:
                return sec
        raise KeyError(f"no property group named {name!r}; known: "
                       f"{', '.join(s.title for _, s in self.sections())}")

    def get(self, group: str, name: str) -> Any:
        return self.section(group).get(name)

    def set(self, group: str, name: str, value: Any) -> None:
        self.section(group).set(name, value)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {k: s.to_dict() for k, s in self.sections()}

    @classmethod
    def from_dict(cls, values: dict[str, dict[str, Any]]) -> "Parameters":
        kwargs = {k: SECTIONS[k].from_dict(v) for k, v in values.items() if k in SECTIONS}
        return cls(**kwargs)  # type: ignore[arg-type]

    def copy(self) -> "Parameters":
        return Parameters.from_dict(self.to_dict())


def restore_defaults(params: Parameters) -> None:
    """"Restore Properties To Defaults": reset every section in place."""
    for key, cls in SECTIONS.items():
        setattr(params, key, cls())


def dense_156_preset(params: Parameters | None = None) -> Parameters:
    """The guide's settings for a dense 156-marker set (Initialize 3D and Tracking)."""
    out = Parameters() if params is None else params.copy()
    out.init3d = Initialize3DParameters(max_allowed_depth=16.0, max_3d_distance_to_merge=5.0,
                                        max_allowed_symmetric_epipolar_distance=5.0)
    out.tracking = TrackingParameters()  # "identical to the default settings"
    return out


def sparse_35_preset(params: Parameters | None = None) -> Parameters:
    """The guide's settings for a sparse 35-marker set (Initialize 3D and Tracking)."""
    out = Parameters() if params is None else params.copy()
    out.init3d = Initialize3DParameters(max_allowed_depth=60.0, max_3d_distance_to_merge=5.0,
                                        max_allowed_symmetric_epipolar_distance=5.0)
    out.tracking = TrackingParameters(face_point_max_elastic_prediction_distance=25.0,
                                      max_allowed_3d_point_error=10.0,
                                      allow_single_sensor_tracking=False)
    return out


PRESETS = {"default": lambda params=None: Parameters(), "dense": dense_156_preset, "sparse": sparse_35_preset}
