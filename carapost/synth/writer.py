"""Write a synthetic take to disk as a capture would be: pico files, calibration, brim, seeds, truth."""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from carapost.io.atomic import atomic_write_bytes
from carapost.io.brim import save_brim_json, write_brim_svg
from carapost.io.seeds import write_seeds
from carapost.model.params import BlobParameters

from .seeds import seeds_for

if TYPE_CHECKING:  # pragma: no cover
    from .take import SynthTake

__all__ = ["write_take", "nominal_calibration"]


def nominal_calibration(synth: "SynthTake"):  # -> carapost.io.calibration.Calibration
    """The take's *nominal* calibration: true intrinsics, rig poses without flex (frame 0 slip-free).

    This is what a calibration of the rig gives before the take: a brim solve still has
    work to do (the true per-frame poses include the arms' flex).
    """
    from carapost.io.calibration import Calibration, CameraCalibration

    tr = synth.truth
    cams = []
    for c, name in enumerate(synth.camera_names):
        cams.append(CameraCalibration(name=name, device_id=f"SYNTH{c:02d}", user_id=str(c + 1),
                                      intrinsics=tr.intrinsics[c], frames=np.array([0]),
                                      R=tr.nominal_R[c][None], t=tr.nominal_t[c][None],
                                      image_error=np.array([0.0]), world_error=np.array([0.0])))
    return Calibration(cameras=cams, source="", format="xcp")


def write_take(synth: "SynthTake", out_dir: str | os.PathLike, name: str = "Synth", *,
               progress: Callable[[int, int], None] | None = None, frames: range | None = None,
               codec: str = "jpeg") -> dict[str, Path]:
    """Write a synthetic take as a capture folder.

    Files: ``name_0.pico`` .. ``name_3.pico`` (JPEG at the config's quality), ``name.xcp``
    (:func:`nominal_calibration`), ``name_brim.json`` and ``name_brim.svg``, ``name_seeds.json``
    (:func:`~carapost.synth.seeds.seeds_for` at frame 0), ``name_truth.npz`` (every array of
    :class:`~carapost.synth.take.GroundTruth`).

    Parameters
    ----------
    synth : SynthTake
    out_dir : path-like
        Created if missing.
    name : str
        Take name (file prefix).
    progress : callable, optional
        ``progress(frames_done, frames_total)`` after each frame.
    frames : range, optional
        Frames to write (default all).
    codec : {"jpeg", "lossless"}

    Returns
    -------
    dict
        ``{"pico_0": Path, ..., "xcp": ..., "brim_json": ..., "brim_svg": ..., "seeds": ...,
        "truth": ...}``.
    """
    from carapost.io.calibration import save_calibration
    from carapost.io.pico import PicoMetadata, PicoWriter

    if not name or any(ch in name for ch in "/\\"):
        raise ValueError(f"invalid take name {name!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = synth.config
    frames = range(synth.n_frames) if frames is None else frames
    if len(frames) == 0 or frames[0] < 0 or frames[-1] >= synth.n_frames:
        raise ValueError(f"frames must be a non-empty range within 0..{synth.n_frames - 1}")
    paths: dict[str, Path] = {}
    blob = BlobParameters(find_black_blobs=cfg.marker_colour == "black",
                          find_white_blobs=cfg.marker_colour == "white").to_dict()
    with ExitStack() as stack:
        writers = []
        for c in range(synth.n_cameras):
            p = out / f"{name}_{c}.pico"
            meta = PicoMetadata(logger_name="SynthLogger", logger_description="carapost.synth synthetic take",
                                logger_id=f"synth-{cfg.seed:08x}", camera_name=synth.camera_names[c], channel=c,
                                frame_rate=cfg.frame_rate, start_timecode="00:00:00:00", width=cfg.width,
                                height=cfg.height, rotation=0, blob_parameters=blob,
                                extra={"synth_config": cfg.to_dict(), "first_frame": int(frames[0])})
            writers.append(stack.enter_context(PicoWriter(p, meta, codec=codec, quality=cfg.jpeg_quality)))
            paths[f"pico_{c}"] = p
        for i, f in enumerate(frames):
            imgs = synth.images(f)
            for c, w in enumerate(writers):
                w.write(imgs[c])
            if progress is not None:
                progress(i + 1, len(frames))
    paths["xcp"] = out / f"{name}.xcp"
    save_calibration(paths["xcp"], nominal_calibration(synth))
    paths["brim_json"] = save_brim_json(out / f"{name}_brim.json", synth.brim,
                                        version=cfg.brim[1:], description=f"brim of synthetic take {name}")
    paths["brim_svg"] = write_brim_svg(out / f"{name}_brim.svg", synth.brim)
    seeds = seeds_for(synth, frame=frames[0])
    paths["seeds"] = out / f"{name}_seeds.json"
    write_seeds(paths["seeds"], seeds)
    paths["truth"] = out / f"{name}_truth.npz"
    arrays = synth.truth.arrays()
    arrays["config_json"] = np.array(json.dumps(cfg.to_dict()))

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(paths["truth"], buf.getvalue())
    return paths
