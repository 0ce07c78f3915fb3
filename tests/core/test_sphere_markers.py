"""Shaded marker spheres (:mod:`carapost.core.sphere_markers`) on rendered images with known centres."""

import cv2
import numpy as np
import pytest

from carapost.core.sphere_markers import SphereParameters, detect_spheres, fit_spheres, sphere_candidates
from carapost.model.detections import DETECTION_FIELDS

SS = 8  # supersampling of the renderer


def render_spheres(shape, centres, radii, lights, *, background=160.0, gradient=(0.05, -0.03),
                   ambient=80.0, diffuse=150.0, specular=60.0, blur=0.8, noise=1.5, seed=0):
    """Grey image (uint8) of shaded spheres on a sloping background (the Pose2Sim markers'
    look: a dark shadow side below the background, a lit side and a highlight above it).

    centres (N, 2) px (pixel centres at integers), radii (N,) px, lights (N, 3) unit vectors
    towards the light (x right, y down, z towards the camera). Supersampled x8, blurred with a
    Gaussian of ``blur`` px, Gaussian noise of ``noise`` grey levels.
    """
    H, W = shape
    yy, xx = np.mgrid[0:H * SS, 0:W * SS]
    x = (xx + 0.5) / SS - 0.5
    y = (yy + 0.5) / SS - 0.5
    img = background + gradient[0] * (x - W / 2) + gradient[1] * (y - H / 2)
    for (cx, cy), r, L in zip(centres, radii, lights):
        y0, y1 = max(int((cy - r - 1) * SS), 0), min(int((cy + r + 2) * SS), H * SS)
        x0, x1 = max(int((cx - r - 1) * SS), 0), min(int((cx + r + 2) * SS), W * SS)
        u, v = (x[y0:y1, x0:x1] - cx) / r, (y[y0:y1, x0:x1] - cy) / r
        rho2 = u * u + v * v
        nz = np.sqrt(np.clip(1.0 - rho2, 0.0, 1.0))
        ndl = np.clip(u * L[0] + v * L[1] + nz * L[2], 0.0, None)
        half = np.array(L) + np.array([0.0, 0.0, 1.0])
        half /= np.linalg.norm(half)
        spec = np.clip(u * half[0] + v * half[1] + nz * half[2], 0.0, None) ** 20
        box = img[y0:y1, x0:x1]
        img[y0:y1, x0:x1] = np.where(rho2 < 1.0, ambient + diffuse * ndl + specular * spec, box)
    img = cv2.resize(img.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _scene(n=16, seed=1, radius=(3.0, 4.5), shape=(160, 200)):
    rng = np.random.default_rng(seed)
    gy, gx = np.mgrid[0:4, 0:4]
    centres = np.c_[25 + 45 * gx.ravel()[:n], 25 + 35 * gy.ravel()[:n]] + rng.uniform(-3, 3, (n, 2))
    radii = rng.uniform(*radius, n)
    az = rng.uniform(0, 2 * np.pi, n)
    el = rng.uniform(0.2, 0.7, n)  # light from the side: a shadow crescent on the far side
    lights = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    return render_spheres(shape, centres, radii, lights, seed=seed), centres, radii


def _match(det, centres, max_px=2.0):
    xy = np.c_[det["x"], det["y"]]
    d = np.linalg.norm(centres[:, None] - xy[None], axis=-1)
    j = np.argmin(d, axis=1)
    found = d[np.arange(len(centres)), j] < max_px
    return found, xy[j] - centres, j


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_sphere_centres_sub_pixel(seed):
    img, centres, radii = _scene(seed=seed)
    det = detect_spheres(img)
    found, err, j = _match(det, centres)
    assert found.all(), (found, det["x"].size)
    e = np.linalg.norm(err, axis=1)
    # the centre of the sphere, not of its highlight (which lies 1-3 px off it)
    assert np.median(e) <= 0.25 and e.max() <= 0.5, e
    assert np.allclose(det["major"][j], radii, atol=0.6), (det["major"][j], radii)
    assert len(det["x"]) == len(centres)  # nothing else on a smooth background


def test_highlight_is_not_the_centre():
    # one sphere lit from the right: its brightest pixel is well off the centre, the fit is not
    c = np.array([[40.3, 30.6]])
    img = render_spheres((64, 80), c, [4.0], [(0.9, 0.0, 0.44)], noise=1.0)
    yb, xb = np.unravel_index(np.argmax(img), img.shape)
    assert xb - c[0, 0] >= 1.5
    det = detect_spheres(img)
    assert len(det["x"]) == 1
    assert np.hypot(det["x"][0] - c[0, 0], det["y"][0] - c[0, 1]) <= 0.3


def test_layout_and_polarity():
    img, centres, _ = _scene(n=4, seed=4)
    det = detect_spheres(img)
    assert list(det) == list(DETECTION_FIELDS)
    for k, dt in DETECTION_FIELDS.items():
        assert det[k].dtype == dt and det[k].shape == det["x"].shape
    assert (det["polarity"] == 1).all() and np.all((det["score"] > 0) & (det["score"] <= 1))
    assert np.all(np.diff(det["y"]) >= 0)  # sorted by y


def test_edges_and_texture_are_rejected():
    # a bright bar, a dark step and a ramp: no sphere
    img = np.full((120, 160), 150.0)
    img[:, 80:] = 90.0
    img[30:34, 10:70] = 230.0
    img += np.linspace(0, 20, 160)[None]
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8)
    img = np.clip(img + np.random.default_rng(5).normal(0, 1.5, img.shape), 0, 255).astype(np.uint8)
    assert len(detect_spheres(img)["x"]) == 0


def test_mask_and_bad_input():
    img, centres, _ = _scene(n=4, seed=6)
    mask = np.zeros(img.shape, bool)
    mask[:, :70] = True
    det = detect_spheres(img, mask=mask)
    assert len(det["x"]) == int((centres[:, 0] >= 70).sum()) and det["x"].min() >= 70
    with pytest.raises(ValueError, match="uint8"):
        detect_spheres(img.astype(float))
    with pytest.raises(ValueError, match="mask"):
        detect_spheres(img, mask=mask[:10])
    with pytest.raises(ValueError, match="radii"):
        SphereParameters(min_radius=5, max_radius=3)


def test_fit_from_offset_candidates():
    # the fit recovers the centre from candidates up to 1.5 px away
    c = np.array([[50.4, 40.7]])
    img = render_spheres((80, 100), c, [3.5], [(-0.6, -0.6, 0.53)], noise=1.0)
    p = SphereParameters()
    xs, ys = np.meshgrid(np.arange(49, 53), np.arange(39, 43))
    fit = fit_spheres(img, xs.ravel(), ys.ravel(), p)
    e = np.hypot(fit["x"] - c[0, 0], fit["y"] - c[0, 1])
    assert e.max() <= 0.3, e
    cx, cy = sphere_candidates(img, p)
    assert np.min(np.hypot(cx - c[0, 0], cy - c[0, 1])) <= 1.5
