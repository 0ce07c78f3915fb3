"""Marker sets, configuration checks, the rig and the face."""

import re

import numpy as np
import pytest

from carapost.core.camera import project
from carapost.io.brim import load_default_brim
from carapost.synth import SynthConfig
from carapost.synth.expressions import CHANNELS, Deformer
from carapost.synth.face import rest_height
from carapost.synth.markers import marker_set
from carapost.synth.rig import nominal_rig
from carapost.synth.builder import build_surface, rest_surface


@pytest.mark.parametrize("n", [35, 80, 156])
def test_marker_sets_have_unique_readable_names(n):
    ms = marker_set(n)
    assert len(ms) == n == len(set(ms.names))
    assert ms.uv.shape == (n, 2)
    for name in ms.names:
        assert re.fullmatch(r"[A-Z][A-Za-z]*(_[A-Z][a-z]*)*(_[LRC])?(_\d+)?", name), name
    for must in ("Nose_Tip", "Mouth_Corner_L", "Mouth_Corner_R", "Lid_Upper_L", "Lid_Upper_R") if n < 156 else \
            ("Nose_Tip", "Mouth_Corner_L", "Brow_L_2", "Lid_Upper_L_1", "Lid_Upper_R_2"):
        assert must in ms.names
    # left and right are mirror images (u -> -u)
    for i, name in enumerate(ms.names):
        parts = name.split("_")
        if "L" in parts:
            j = ms.names.index("_".join("R" if p == "L" else p for p in parts))
            np.testing.assert_allclose(ms.uv[j], ms.uv[i] * [-1, 1])
    # markers do not touch: at least 4 mm between centres (3 mm dots)
    d = np.linalg.norm(ms.uv[:, None] - ms.uv[None], axis=2) + np.eye(n) * 1e9
    assert d.min() > 4.0
    # the eyelid markers are the upper-lid markers
    lids = np.sort(np.concatenate([ms.eyelid["L"], ms.eyelid["R"]]))
    assert [ms.names[i] for i in lids] == sorted((nm for nm in ms.names if nm.startswith("Lid_Upper")),
                                                 key=ms.names.index)


def test_denser_sets_are_denser_around_mouth_and_eyes():
    def near(ms, centre, r):
        return int(np.sum(np.linalg.norm(ms.uv - centre, axis=1) < r))
    for region, centre in (("mouth", (0, -67)), ("left eye", (32, 0))):
        counts = [near(marker_set(n), np.array(centre, float), 25.0) for n in (35, 80, 156)]
        assert counts[0] < counts[1] < counts[2], (region, counts)


def test_marker_set_rejects_other_counts():
    with pytest.raises(ValueError, match="35, 80 or 156"):
        marker_set(50)


@pytest.mark.parametrize("bad, msg", [
    (dict(n_markers=50), "n_markers"),
    (dict(n_frames=0), "n_frames"),
    (dict(marker_colour="red"), "marker_colour"),
    (dict(brim="v9"), "brim"),
    (dict(width=10), "image size"),
    (dict(shading_scale=3), "shading_scale"),
    (dict(jpeg_quality=0), "jpeg_quality"),
])
def test_config_validation(bad, msg):
    with pytest.raises(ValueError, match=msg):
        SynthConfig(**bad)


def test_rig_frames_the_face_and_the_brim():
    rig = nominal_rig(1280, 720)
    assert rig.n_cameras == 4 and rig.caddies == ((0, 1), (2, 3))
    C = rig.centres()
    # caddy 0 on the actor's left (+X), caddy 1 on the right; vertical pairs, 40-60 mm apart
    assert np.all(C[[0, 1], 0] > 60) and np.all(C[[2, 3], 0] < -60)
    for a, b in rig.caddies:
        base = C[a] - C[b]
        assert 40 <= np.linalg.norm(base) <= 60
        assert abs(base[0]) < 1.0
    brim = load_default_brim("v2.0")
    ms = marker_set(80)
    face = np.c_[ms.uv, rest_height(ms.uv[:, 0], ms.uv[:, 1])] @ rig.head_R.T + rig.head_t
    for c in range(4):
        bxy = project(brim.xyz, rig.intrinsics[c], rig.R[c], rig.t[c])
        fxy = project(face, rig.intrinsics[c], rig.R[c], rig.t[c])
        assert np.all((bxy >= 0) & (bxy < [1280, 720]))          # whole brim in view ...
        assert np.median(bxy[:, 1]) < np.median(fxy[:, 1]) - 200   # ... above the face
        nose = fxy[ms.index("Nose_Tip")]
        assert 200 < nose[0] < 1080 and 200 < nose[1] < 620        # the face centre is in view
        # lens distortion: a few pixels at the corners
        k1, k2, _ = rig.intrinsics[c].radial
        r = np.hypot(640, 360)
        assert 0.5 < (k1 * r ** 2 + k2 * r ** 4) * r < 4.0


def test_surface_matches_deformed_markers():
    ms = marker_set(156)
    deform = Deformer(ms.uv[:, 0], ms.uv[:, 1])
    rng = np.random.default_rng(3)
    for _ in range(4):
        state = rng.uniform(0, 1, len(CHANNELS)) * (rng.uniform(0, 1, len(CHANNELS)) < 0.5)
        surf = build_surface(state)
        P = deform(state)
        H, _, _, U, V = surf.sample(P[:, 0], P[:, 1])
        # markers lie on the height field and map back to their material coordinates
        assert np.max(np.abs(H - P[:, 2])) < 0.35
        assert np.max(np.hypot(U - ms.uv[:, 0], V - ms.uv[:, 1])) < 0.5


def test_ray_cast_finds_the_first_hit():
    surf = rest_surface()
    # straight down onto the nose tip from above: hits the tip, not the face behind it
    x, y = 0.0, -36.0
    top = float(rest_height(np.array(x), np.array(y)))
    s = surf.cast(np.array([x, y, 200.0]), np.array([[0.0, 0.0, -1.0]]))
    assert s[0] == pytest.approx(200.0 - top, abs=0.1)
    # a ray from the side through the nose to the far cheek: blocked
    cheek = np.array([-30.0, -36.0, float(rest_height(np.array(-30.0), np.array(-36.0)))])
    eye = np.array([90.0, -36.0, cheek[2] + 10.0])
    assert surf.occluded(eye, cheek[None])[0]
    # the same cheek seen from its own side is not
    assert not surf.occluded(np.array([-90.0, -36.0, 150.0]), cheek[None])[0]
