"""Synthetic Initialize-from-ROM cases with ground truth (shared by the ROM tests and benchmark).

* The **ROM** is a synthetic take (one seed) solved from the truth in its ROM frame
  (:func:`track_cases.truth_case`: true poses, one point per marker and brim dot attached to its
  detections), with the markers' names as labels and a few sticks.
* The **new take** is another synthetic take of the same actor, rig and markers (another seed:
  other expressions, helmet slip, flex, skin noise) starting at frame ``start`` of its motion, so
  that its first frame shows a different expression and head position. Its detections are the
  truth (dot centroids + noise + clutter); its cameras hold the nominal calibration.

:func:`score_init` scores an initialized frame by the identity of every attached detection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from track_cases import truth_case, truth_detections

from carapost.model.take import CameraInfo, PointKind, Take


@dataclass
class RomCase:
    rom: Take                #: the solved ROM take (ROM frame ``rom_frame``)
    rom_frame: int
    synth: object            #: the new take's synthetic take
    take: Take               #: the new take (frames ``start ..`` of ``synth``)
    labels: list[dict[int, np.ndarray]]   #: per camera {take frame: truth id of each detection}
    start: int

    @property
    def truth(self):
        return self.synth.truth


def rom_take(config, rom_frame: int = 0) -> Take:
    """A ROM take solved from the truth in ``rom_frame``, labelled, with sticks."""
    case = truth_case(config, start=rom_frame)
    rom = case.take
    rom.labels = [lab for lab in rom.points.labels if lab]
    face = rom.face_points()
    ids = rom.points.ids
    rom.sticks = np.array([[ids[face[i]], ids[face[i + 1]]] for i in range(0, 10, 2)], np.int64)
    rom.stick_colours = np.full((len(rom.sticks), 3), 200, np.uint8)
    rom.name = "ROM"
    return rom


def new_take(config, start: int, n_frames: int, *, seed: int = 5) -> tuple[object, Take, list[dict[int, np.ndarray]]]:
    """The frames ``start .. start + n_frames - 1`` of a synthetic take as a new, uninitialized take."""
    from carapost.synth import generate_take

    synth = generate_take(config)
    tr = synth.truth
    frames = range(start, start + n_frames)
    tables, labels = truth_detections(tr, frames, seed=seed, brim_polarity=synth.brim.polarity)
    W, H = tr.image_size
    cams = [CameraInfo(f"cam{c}", c, tr.intrinsics[c], (W, H)) for c in range(len(tables))]
    take = Take.new(cams, n_frames, tr.frame_rate, R=tr.nominal_R, t=tr.nominal_t, name="New")
    for c in range(len(cams)):
        take.detections[c] = take.detections[c].with_frames({f - start: tb for f, tb in tables[c].items()})
    shifted = [{f - start: lab for f, lab in labels[c].items()} for c in range(len(cams))]
    return synth, take, shifted


def rom_case(rom_config, new_config, *, start: int, n_frames: int = 8, rom_frame: int = 0) -> RomCase:
    synth, take, labels = new_take(new_config, start, n_frames)
    return RomCase(rom_take(rom_config, rom_frame), rom_frame, synth, take, labels, start)


@dataclass
class InitScore:
    coverage: float       #: markers seen by >= 2 cameras that were initialized
    wrong_obs: int        #: attached detections of another dot or clutter
    wrong_labels: int     #: initialized face points carrying another marker's label
    brim_found: int
    median_mm: float
    max_mm: float

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else int(v)) for k, v in self.__dict__.items()}


def score_init(case: RomCase, names: list[str], kind: np.ndarray, xyz: np.ndarray, recon: np.ndarray,
               obs_det: np.ndarray, frame: int = 0) -> InitScore:
    """Score points (``names``, ``kind (Q,)``, ``xyz (Q, 3)``, ``recon (Q,)``, ``obs_det (Q, C)``)
    initialized in take frame ``frame`` against the truth. A face point's truth is the marker
    its label names; a brim point's the brim dot of the same order."""
    tr = case.truth
    f = case.start + frame
    M = tr.visible.shape[1]
    marker = {n: i for i, n in enumerate(tr.names)}
    face = np.flatnonzero(kind == PointKind.FACE)
    brim = np.flatnonzero(kind == PointKind.BRIM)
    own = np.full(len(names), -1)
    own[face] = [marker[names[i]] for i in face]
    own[brim] = M + np.arange(len(brim))
    wrong = 0
    for c in range(obs_det.shape[1]):
        m = obs_det[:, c] >= 0
        wrong += int((case.labels[c][frame][obs_det[m, c]] != own[m]).sum())
    found = recon >= 2
    seen2 = tr.visible[f].sum(-1) >= 2
    got = np.zeros(M, bool)
    got[own[face][found[face]]] = True
    err = np.linalg.norm(xyz[face] - tr.xyz[f, own[face]], axis=-1)[found[face]]
    wrong_labels = int((err > 2.0).sum())
    return InitScore(coverage=float((got & seen2).sum() / max(seen2.sum(), 1)), wrong_obs=wrong,
                     wrong_labels=wrong_labels, brim_found=int(found[brim].sum()),
                     median_mm=float(np.median(err)) if len(err) else float("nan"),
                     max_mm=float(err.max()) if len(err) else float("nan"))
