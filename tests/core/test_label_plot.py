"""Inspection plots (cv2 drawing)."""

import numpy as np
import pytest

from carapost.core.label_plot import render_markers


def test_render_markers_draws_markers_names_and_notes():
    xyz = np.array([[0.0, 0, 0], [100, 0, 0], [0, 100, 50], [np.nan, np.nan, np.nan]])
    img = render_markers(xyz, ["a", "b", "c", "d"], sticks=np.array([[0, 1], [1, 3]]),
                         highlight=np.array([False, True, False, False]), notes=["b <- c"], title="Frame: 3")
    assert img.shape == (640, 1500, 3) and img.dtype == np.uint8
    red = (img[..., 2] > 180) & (img[..., 0] < 60) & (img[..., 1] < 60)
    assert red.sum() > 50  # the highlighted marker and the note
    dark = (img < 100).all(-1)
    assert dark.sum() > 200
    blank = render_markers(np.full((2, 3), np.nan), ["a", "b"])
    assert (blank[60:, :1400] >= 199).all()  # nothing but frames and text


def test_render_markers_rejects_bad_shapes():
    with pytest.raises(ValueError):
        render_markers(np.zeros((2, 2)), ["a", "b"])
