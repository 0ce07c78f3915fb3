"""Initialize from ROM (core): a solved ROM take's points found in another take of the same actor.

The ROM (seed 1, neutral frame 0) and the new take (seed 2 from frame 45: the right side
smiling, the head slipped about 1.5 mm in the helmet, other camera flex) are synthetic with
ground truth; detections are the truth's dot centroids + 0.05 px noise + clutter.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from rom_cases import rom_case, score_init  # noqa: E402

from carapost.core.rom_init import check_rom, match_rom_frame, rom_tracking_parameters  # noqa: E402
from carapost.model.params import RomParameters, TrackingParameters  # noqa: E402
from carapost.model.take import PointKind  # noqa: E402
from carapost.synth import SynthConfig  # noqa: E402

ROM_CONFIG = SynthConfig(n_markers=80, n_frames=2, seed=1)
NEW_CONFIG = SynthConfig(n_markers=80, n_frames=50, seed=2)


@pytest.fixture(scope="module")
def case():
    return rom_case(ROM_CONFIG, NEW_CONFIG, start=45, n_frames=2)


def _tables(case, frame=0):
    return [case.take.detections[c].frame(frame) for c in range(case.take.n_cameras)]


def _score(case, res):
    rom = case.rom
    names = [rom.points.labels[i] for i in res.rom_points]
    return score_init(case, names, rom.points.kind[res.rom_points], res.xyz, res.recon, res.obs_det)


def test_finds_face_and_brim_in_a_different_expression(case):
    tr = case.truth
    # the new frame really differs from the ROM frame: markers moved up to ~17 px
    moved = np.linalg.norm(case.rom.obs_xy[0, :80] - tr.centroid_xy[case.start], axis=-1)
    assert np.nanmax(moved) > 12 and np.nanmedian(moved) > 2
    res = match_rom_frame(case.rom, 0, _tables(case))
    s = _score(case, res)
    assert s.coverage >= 0.97
    assert s.wrong_obs == 0 and s.wrong_labels == 0
    assert s.brim_found == 18
    assert s.median_mm <= 0.2 and s.max_mm <= 1.0
    assert res.report["found_brim"] == 18 and res.report["found_face"] >= 78
    assert res.report["cameras_updated"]
    # the poses are re-estimated for the new frame's flex (not the ROM's)
    assert np.abs(res.R - tr.R[case.start]).max() < 1e-3
    assert np.abs(res.t - tr.t[case.start]).max() < 0.1
    assert res.report["not_found"] == [case.rom.points.labels[i] for i in res.rom_points[~res.found]]


def test_brim_only(case):
    tr = case.truth
    res = match_rom_frame(case.rom, 0, _tables(case), brim_only=True)
    assert (case.rom.points.kind[res.rom_points] == PointKind.BRIM).all() and len(res.rom_points) == 18
    s = _score(case, res)
    assert s.brim_found == 18 and s.wrong_obs == 0
    assert res.report["face"] == 0 and res.report["found_brim"] == 18
    assert np.abs(res.R - tr.R[case.start]).max() < 2e-3
    assert np.abs(res.t - tr.t[case.start]).max() < 0.2


def test_rom_parameters_replace_the_tracking_distances(case):
    tracking = TrackingParameters(face_point_tracking_distance=1.0, brim_point_tracking_distance=1.0,
                                  max_allowed_3d_point_error=0.1)
    p = rom_tracking_parameters(tracking, RomParameters())
    assert (p.face_point_tracking_distance, p.brim_point_tracking_distance, p.max_allowed_3d_point_error) == (
        50.0, 30.0, 5.0)
    # the tiny tracking distances are not used: everything is still found
    res = match_rom_frame(case.rom, 0, _tables(case), tracking=tracking)
    assert _score(case, res).coverage >= 0.97
    # a tiny ROM Face Point Tracking Distance loses the face points that moved (not the brim)
    small = match_rom_frame(case.rom, 0, _tables(case), rom_params=RomParameters(rom_face_point_tracking_distance=1.0))
    s = _score(case, small)
    assert s.coverage < 0.5 and s.brim_found == 18 and s.wrong_obs == 0
    # a tiny ROM Brim Point Tracking Distance loses the brim
    nobrim = match_rom_frame(case.rom, 0, _tables(case), brim_only=True,
                             rom_params=RomParameters(rom_brim_point_tracking_distance=0.01))
    assert nobrim.report["found_brim"] < 18
    # a tiny ROM Max Allowed 3D Point Error rejects points, unless Remove Bad 3D Points is off
    strict = RomParameters(rom_max_allowed_3d_point_error=0.02)
    few = match_rom_frame(case.rom, 0, _tables(case), rom_params=strict).report["found_face"]
    off = dataclasses.replace(TrackingParameters(), remove_bad_3d_points=False)
    all_ = match_rom_frame(case.rom, 0, _tables(case), rom_params=strict, tracking=off).report["found_face"]
    assert few < all_


def test_bad_rom_and_bad_input(case):
    rom = case.rom
    with pytest.raises(ValueError, match="ROM Frame Index 5"):
        check_rom(rom, 5)
    with pytest.raises(ValueError, match="3 cameras|4 cameras"):
        match_rom_frame(rom, 0, _tables(case)[:3])
    unsolved = dataclasses.replace(rom, R=np.full_like(rom.R, np.nan))
    with pytest.raises(ValueError, match="no camera poses in frame 0"):
        check_rom(unsolved, 0)
    nobrim = dataclasses.replace(rom, brim=None)
    with pytest.raises(ValueError, match="no calibration brim"):
        match_rom_frame(nobrim, 0, _tables(case))
    with pytest.raises(ValueError, match="images are 1280 x 720"):
        match_rom_frame(rom, 0, _tables(case), image_size=[(640, 360)] * 4)
