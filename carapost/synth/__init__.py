"""Synthetic takes with exact ground truth: a head-mounted-camera capture of a painted face.

>>> from carapost.synth import SynthConfig, generate_take
>>> take = generate_take(SynthConfig(n_frames=5, width=640, height=360))
>>> take.images(0).shape
(4, 360, 640)

See ``docs/synth.md``. Modules: :mod:`.config` (the knobs), :mod:`.face` (rest face),
:mod:`.expressions` (deformations), :mod:`.markers` (marker sets), :mod:`.rig` (cameras, brim,
lights), :mod:`.motion` (expressions, blinks, slip, flex over time), :mod:`.surface` (the skin
as a height field, ray casting), :mod:`.builder` (the skin of each frame), :mod:`.rays` (the
shading rays), :mod:`.texture` (skin albedo, eyes), :mod:`.dots` (exact dot images),
:mod:`.card` (the brim card), :mod:`.render` (image formation), :mod:`.take` (ground truth,
:class:`SynthTake`), :mod:`.seeds` (seed correspondences), :mod:`.writer` (files on disk).
"""

from .config import SynthConfig
from .seeds import seeds_for
from .take import GroundTruth, SynthTake, generate_take
from .writer import nominal_calibration, write_take

__all__ = ["SynthConfig", "GroundTruth", "SynthTake", "generate_take", "write_take", "seeds_for",
           "nominal_calibration"]
