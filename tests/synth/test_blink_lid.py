"""The synthetic blink's lid anatomy (carapost.synth.expressions.blink_displacement)."""

import numpy as np
import pytest

from carapost.synth.expressions import (CHANNELS, LID_LO, LID_UP, PRESEPTAL_FADE_MM, TARSAL_HEIGHT_MM,
                                        Deformer, blink_displacement, eye_opening)
from carapost.synth.face import EYE
from carapost.synth.markers import marker_set

FULL = 0.97 * (LID_UP + LID_LO)          # the margin's travel at the middle of the eye, mm


def blink_state(amount=1.0):
    st = np.zeros(len(CHANNELS))
    st[CHANNELS.index("blink_L")] = st[CHANNELS.index("blink_R")] = amount
    return st


def test_pretarsal_skin_follows_the_lid_margin():
    v = EYE[1] + LID_UP + np.linspace(0.0, TARSAL_HEIGHT_MM, 33)
    d = blink_displacement(np.full_like(v, EYE[0]), v, 1)
    np.testing.assert_allclose(d[:, 0], -FULL, atol=1e-9)          # the whole tarsus comes down 9.2 mm
    np.testing.assert_allclose(d[:, 1], 1.2 * FULL / 9.5, atol=1e-9)  # lifted over the eyeball
    # above the tarsus the displacement fades out, and is gone PRESEPTAL_FADE_MM higher up
    above = EYE[1] + LID_UP + TARSAL_HEIGHT_MM + np.array([0.5, 1.75, 3.0, PRESEPTAL_FADE_MM, 6.0])
    dy = blink_displacement(np.full_like(above, EYE[0]), above, 1)[:, 0]
    assert -FULL < dy[0] < dy[1] < dy[2] < 0.0 and dy[3] == 0.0 and dy[4] == 0.0
    # towards the corners the tarsus (and its travel) follows the margin's profile
    u = EYE[0] + 10.0
    lo, up, _ = eye_opening(np.array([u]), np.array([0.0]), 1)
    s = (up[0] - lo[0]) / (LID_UP + LID_LO)
    d = blink_displacement(np.array([u, u]), up + np.array([0.0, 0.99 * TARSAL_HEIGHT_MM * s]), 1)
    np.testing.assert_allclose(d[:, 0], -0.97 * (up[0] - lo[0]), atol=1e-9)


def test_the_closed_lid_keeps_its_marker_offset():
    """Margin and a marker 2.5 mm above it stay 2.5 mm apart (in v) when the eye closes; the
    margin ends 3 % of the fissure above the lower margin (the slit)."""
    u = np.full(2, EYE[0])
    lo = EYE[1] - LID_LO
    v = np.array([EYE[1] + LID_UP, EYE[1] + LID_UP + 2.5])
    P = Deformer(u, v)(blink_state())
    assert P[1, 1] - P[0, 1] == pytest.approx(2.5, abs=1e-9)
    assert P[0, 1] - lo == pytest.approx(0.03 * (LID_UP + LID_LO), abs=1e-9)


@pytest.mark.parametrize("n", [35, 80, 156])
def test_only_the_upper_lids_move_in_a_blink(n):
    ms = marker_set(n)
    d = Deformer(ms.uv[:, 0], ms.uv[:, 1])
    move = np.linalg.norm(d(blink_state()) - d(np.zeros(len(CHANNELS))), axis=-1)
    lids = np.concatenate([ms.eyelid["L"], ms.eyelid["R"]])
    others = np.setdiff1d(np.arange(len(ms)), lids)
    assert move[others].max() == 0.0                      # brows, lower lids, forehead: still
    # the lid markers travel with their margin: 9.29 mm at the middle of the eye (80 and 35
    # markers), 8.24 mm 6 mm to either side of it (156 markers)
    np.testing.assert_allclose(move[lids], 9.288 if n < 156 else 8.240, atol=1e-3)


def test_the_blink_map_stays_one_to_one_and_spares_the_brow():
    """Along every column through the eye the closing lid's map v -> v + dy is increasing (no
    fold), and nothing moves at or above the brow's hair (texture.py: its lower edge)."""
    u = np.arange(EYE[0] - 14.0, EYE[0] + 14.01, 0.5)
    v = np.arange(-8.0, 40.0, 0.01)
    U, V = np.meshgrid(u, v, indexing="ij")
    for amount in (0.3, 0.7, 1.0):
        y = V + amount * blink_displacement(U, V, 1)[..., 0]
        assert np.diff(y, axis=1).min() > 0.0
    x = U
    half = 3.2 * np.clip(1.0 - np.abs((x - 28.0) / 26.0) ** 3, 0.0, 1.0)
    brow_low = 15.5 + 5.0 * np.sin(np.pi * (x - 10.0) / 42.0) - half
    dy = blink_displacement(U, V, 1)[..., 0]
    assert np.abs(dy[V >= brow_low]).max() == 0.0
