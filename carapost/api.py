"""CaraPost scripting API (what the reference guide calls PyCara).

One import gives everything a script needs::

    import carapost.api as cp

=========================  ==================================================================
guide's sub-package        here
=========================  ==================================================================
PyCaraProcess              :class:`CaraProcess` — create a take from ``.pico`` files (or open a
                           ``.cara``), detect blobs, get/set properties, brim, Initialize 3D,
                           gap filling, stabilization, undo/redo, save, export.
PyCaraExport               :class:`CaraExport` — read a ``.cara`` (or ``.c3d``) for custom
                           exports: points, labels, ``xyz (F, P, 3)`` mm, reconstruction types,
                           brim, cameras and per-frame poses, 2D tracks, frame rate, time.
PyPico                     :class:`Pico` — a ``.pico`` file's capture metadata and frames.
PyDebugServices            :func:`set_log_verbosity` / :func:`get_log_verbosity` — show or hide
                           log messages (the ``"carapost"`` logger).
(time)                     :class:`TimeBase`, :func:`timecode_to_count`, :func:`count_to_timecode`
                           — frame index <-> burnt-in frame number <-> SMPTE timecode.
=========================  ==================================================================

Every processing method runs the same operation as the GUI and the ``carapost`` command, so a
script and the application give the same result. ``help(cp.CaraProcess.detect_blobs)`` (and
so on) documents each call; ``docs/scripting.md`` is the guide, and ``examples/`` holds working
equivalents of the guide's ten example scripts.

Examples
--------
>>> import carapost.api as cp
>>> take = cp.CaraProcess.from_pico("Example_0.pico")     # doctest: +SKIP
>>> take.detect_blobs()                                    # doctest: +SKIP
True
>>> take.save("Example_b.cara")                            # doctest: +SKIP
>>> exp = cp.CaraExport("Example_b.cara")                  # doctest: +SKIP
>>> exp.frame_to_timecode(0)                               # doctest: +SKIP
'00:00:00:00'
"""

from __future__ import annotations

from .api_export import CaraExport, ObsSource, PointInfo, PointKind, Recon
from .api_log import LOG_LEVELS, get_log_verbosity, set_log_verbosity
from .api_pico import Pico, PicoError
from .api_process import CaraProcess, default_properties, find_calibration
from .core.timecode import TimeBase, TimecodeError, count_to_timecode, is_drop_frame_rate, nominal_rate, \
    timecode_to_count

__all__ = [
    "CaraProcess",
    "CaraExport",
    "Pico",
    "PicoError",
    "PointInfo",
    "Recon",
    "ObsSource",
    "PointKind",
    "TimeBase",
    "TimecodeError",
    "timecode_to_count",
    "count_to_timecode",
    "nominal_rate",
    "is_drop_frame_rate",
    "set_log_verbosity",
    "get_log_verbosity",
    "LOG_LEVELS",
    "find_calibration",
    "default_properties",
]
