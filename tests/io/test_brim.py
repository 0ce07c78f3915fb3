"""Brim models: default brims, our JSON format, the SVG writer, bending and flattening."""

import json

import numpy as np
import pytest
from lxml import etree

from carapost.io.brim import (
    DEFAULT_BRIMS,
    BrimFormatError,
    bend_brim,
    brim_svg_text,
    flatten_brim,
    load_brim_json,
    load_default_brim,
    save_brim_json,
    write_brim_svg,
)
from carapost.model.take import BrimModel

SVG_NS = "{http://www.w3.org/2000/svg}"


@pytest.mark.parametrize("version, n", [("v1.0", 12), ("v1.1", 14), ("v2.0", 18)])
def test_default_brims_load(version, n):
    b = load_default_brim(version)
    assert isinstance(b, BrimModel)
    assert b.name == version
    assert b.xyz.shape == (n, 3) and b.radius.shape == (n,) and b.polarity.shape == (n,)
    assert np.all(b.xyz[:, 2] == 0.0)                       # planar, Z = 0
    assert np.all((b.radius >= 2.0) & (b.radius <= 3.0))    # 2-3 mm dots
    assert np.all(b.polarity == -1)                         # black dots on a white card
    # dots are well separated (at least 4 radii centre to centre)
    d = np.linalg.norm(b.xyz[:, None] - b.xyz[None], axis=2) + np.eye(n) * 1e9
    assert d.min() > 4 * b.radius.max()
    # the layout has no symmetry that maps it onto itself (rotation by 180 degrees, mirror)
    for flip in (np.array([-1, -1, 1]), np.array([-1, 1, 1]), np.array([1, -1, 1])):
        f = b.xyz * flip
        nearest = np.min(np.linalg.norm(f[:, None] - b.xyz[None], axis=2), axis=1)
        assert nearest.max() > 1.0


def test_default_brim_version_spellings_and_errors():
    assert len(load_default_brim("2.0")) == 18
    assert len(load_default_brim("V1.1")) == 14
    assert set(DEFAULT_BRIMS) == {"v1.0", "v1.1", "v2.0"}
    with pytest.raises(ValueError, match="unknown default brim"):
        load_default_brim("v3.0")


def test_json_round_trip(tmp_path):
    b = load_default_brim("v1.1")
    p = save_brim_json(tmp_path / "b.json", b, version="1.1", description="test")
    b2 = load_brim_json(p)
    assert b2.name == b.name
    np.testing.assert_array_equal(b2.xyz, b.xyz)
    np.testing.assert_array_equal(b2.radius, b.radius)
    np.testing.assert_array_equal(b2.polarity, b.polarity)
    d = json.loads(p.read_text())
    assert d["format"] == "carapost-brim" and d["format_version"] == 1 and d["units"] == "mm"
    assert d["version"] == "1.1" and len(d["dots"]) == 14
    assert not list(tmp_path.glob(".*tmp"))  # no temporary left behind


def test_json_white_dots_and_curved_round_trip(tmp_path):
    b = bend_brim(load_default_brim("v2.0"), 150.0)
    b.polarity[:] = 1
    b2 = load_brim_json(save_brim_json(tmp_path / "c.json", b))
    np.testing.assert_allclose(b2.xyz, b.xyz, atol=1e-6)
    assert np.all(b2.polarity == 1)


@pytest.mark.parametrize("text, msg", [
    ("{not json", "invalid JSON"),
    ('{"format": "something"}', "not a brim model"),
    ('{"format": "carapost-brim", "format_version": 99, "dots": []}', "newer"),
    ('{"format": "carapost-brim", "format_version": 1, "dots": []}', "non-empty"),
    ('{"format": "carapost-brim", "format_version": 1, "dots": [{"xyz": [1, 2], "radius": 1}]}', "dot 0"),
    ('{"format": "carapost-brim", "format_version": 1, "dots": [{"xyz": [1, 2, 3], "radius": -1}]}', "radius"),
    ('{"format": "carapost-brim", "format_version": 1, "dots": [{"xyz": [1, 2, 3], "radius": 1, '
     '"polarity": "red"}]}', "polarity"),
    ('{"format": "carapost-brim", "format_version": 1, "units": "cm", "dots": []}', "units"),
])
def test_json_errors_name_the_file(tmp_path, text, msg):
    p = tmp_path / "bad.json"
    p.write_text(text)
    with pytest.raises(BrimFormatError, match=msg) as e:
        load_brim_json(p)
    assert "bad.json" in str(e.value)


def _circles(svg_path):
    root = etree.parse(str(svg_path)).getroot()
    assert root.tag == SVG_NS + "svg"
    return root, root.findall(".//" + SVG_NS + "circle")


@pytest.mark.parametrize("version", DEFAULT_BRIMS)
def test_svg_is_valid_with_one_circle_per_dot_in_order(tmp_path, version):
    b = load_default_brim(version)
    p = write_brim_svg(tmp_path / f"{version}.svg", b)
    root, circles = _circles(p)
    assert len(circles) == len(b)
    vb = [float(v) for v in root.get("viewBox").split()]
    assert len(vb) == 4 and vb[2] > 0 and vb[3] > 0
    assert root.get("width").endswith("mm") and root.get("height").endswith("mm")
    cx = np.array([float(c.get("cx")) for c in circles])
    cy = np.array([float(c.get("cy")) for c in circles])
    r = np.array([float(c.get("r")) for c in circles])
    np.testing.assert_allclose(cx, b.xyz[:, 0], atol=1e-3)   # X along SVG x
    np.testing.assert_allclose(cy, -b.xyz[:, 1], atol=1e-3)  # Y against SVG y
    np.testing.assert_allclose(r, b.radius, atol=1e-3)
    # every circle lies inside the viewBox
    assert np.all(cx - r >= vb[0]) and np.all(cx + r <= vb[0] + vb[2])
    assert np.all(cy - r >= vb[1]) and np.all(cy + r <= vb[1] + vb[3])
    assert all(c.get("fill") == "#000000" for c in circles)


def test_svg_of_curved_brim_is_flattened(tmp_path):
    flat = load_default_brim("v2.0")
    curved = bend_brim(flat, 140.0)
    assert np.ptp(curved.xyz[:, 2]) > 5.0
    text = brim_svg_text(curved)
    assert "flattened" in text
    _, circles = _circles(write_brim_svg(tmp_path / "c.svg", curved))
    cx = np.array([float(c.get("cx")) for c in circles])
    np.testing.assert_allclose(cx, flat.xyz[:, 0], atol=1e-6)


def test_bend_and_flatten_round_trip():
    flat = load_default_brim("v1.0")
    curved = bend_brim(flat, 120.0)
    # the dots stay on the cylinder and keep their arc-length layout
    x, z = curved.xyz[:, 0], curved.xyz[:, 2]
    np.testing.assert_allclose(np.hypot(x, z + 120.0), 120.0, atol=1e-9)
    xy, r = flatten_brim(curved.xyz)
    assert r == pytest.approx(120.0, rel=1e-9)
    np.testing.assert_allclose(xy, flat.xyz[:, :2], atol=1e-9)
    assert flatten_brim(flat.xyz)[1] is None
    with pytest.raises(ValueError):
        bend_brim(curved, 100.0)


@pytest.mark.parametrize("version", DEFAULT_BRIMS)
@pytest.mark.parametrize("colour", [-1, 1])
def test_svg_round_trips_through_the_svg_importer(tmp_path, version, colour):
    brim_svg = pytest.importorskip("carapost.io.brim_svg")
    b = load_default_brim(version)
    b.polarity[:] = colour
    back = brim_svg.read_brim_svg(write_brim_svg(tmp_path / "b.svg", b))
    np.testing.assert_allclose(back.xyz, b.xyz, atol=1e-3)
    np.testing.assert_allclose(back.radius, b.radius, atol=1e-3)
    np.testing.assert_array_equal(back.polarity, b.polarity)
