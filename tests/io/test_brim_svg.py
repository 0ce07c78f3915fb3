"""Import Calibration Brim [svg]: hand-written SVGs against hand-computed mm positions."""

import math

import numpy as np
import pytest

from carapost.io.brim import DEFAULT_BRIMS, bend_brim, brim_svg_text, flatten_brim, load_default_brim, write_brim_svg
from carapost.io.brim_svg import BrimSvgError, parse_brim_svg, parse_transform, read_brim_svg

NS = ('xmlns="http://www.w3.org/2000/svg" xmlns:xlink="http://www.w3.org/1999/xlink" '
      'xmlns:sodipodi="http://sodipodi.sourceforge.net/DTD/sodipodi-0.dtd" '
      'xmlns:inkscape="http://www.inkscape.org/namespaces/inkscape"')
MM_PER_PX = 25.4 / 96


def svg(body: str, attrs: str = 'width="100mm" height="100mm" viewBox="0 0 100 100"') -> str:
    return f'<?xml version="1.0"?>\n<svg {NS} {attrs}>\n{body}\n</svg>\n'


# four well separated "anchor" dots make any test document a valid brim
ANCHORS = "".join(f'<circle cx="{x}" cy="95" r="1"/>' for x in (60, 70, 80, 90))
ANCHOR_XY = [(x, -95.0) for x in (60, 70, 80, 90)]


def dots(text: str, **kw):
    b = parse_brim_svg(text, **kw)
    return b.xyz, b.radius, b.polarity


# ------------------------------------------------------------------------------ round trip
@pytest.mark.parametrize("version", DEFAULT_BRIMS)
def test_round_trip_of_default_brims(version, tmp_path):
    b = load_default_brim(version)
    b2 = read_brim_svg(write_brim_svg(tmp_path / f"{version}.svg", b))
    assert b2.name == version
    np.testing.assert_allclose(b2.xyz, b.xyz, atol=1e-6)
    np.testing.assert_allclose(b2.radius, b.radius, atol=1e-6)
    np.testing.assert_array_equal(b2.polarity, b.polarity)
    assert b2.xyz.dtype == np.float64 and b2.polarity.dtype == np.int8
    assert b2.svg == (tmp_path / f"{version}.svg").read_text()


def test_round_trip_white_dots_and_curved_brim():
    b = load_default_brim("v2.0")
    b.polarity[::3] = 1
    b2 = parse_brim_svg(brim_svg_text(b))
    np.testing.assert_array_equal(b2.polarity, b.polarity)
    curved = bend_brim(load_default_brim("v1.1"), 150.0)
    flat, _ = flatten_brim(curved.xyz)
    b3 = parse_brim_svg(brim_svg_text(curved))
    np.testing.assert_allclose(b3.xyz[:, :2], flat, atol=1e-4)  # the writer rounds to 1e-4 mm
    assert np.all(b3.xyz[:, 2] == 0)


# ------------------------------------------------------------------------------ transforms
def test_group_transforms():
    body = f"""
    <g transform="translate(10,20)"><circle cx="5" cy="5" r="1"/></g>
    <g transform="scale(2)"><circle cx="5" cy="5" r="1"/></g>
    <g transform="rotate(90, 50, 50)"><circle cx="60" cy="50" r="1"/></g>
    <g transform="matrix(1,0,0,1,3,4) skewX(45)"><circle cx="0" cy="10" r="1"/></g>
    <g transform="translate(10) scale(2,1)"><ellipse cx="5" cy="5" rx="2" ry="1"/></g>
    <g transform="translate(50,0)"><g transform="rotate(180)"><circle cx="-10" cy="-30" r="1"/></g></g>
    <circle cx="30" cy="70" r="1" transform="skewY(30)"/>
    {ANCHORS}"""
    xyz, rad, _ = dots(svg(body))
    expected = [(15, -25), (10, -10), (50, -60), (13, -14), (20, -5), (60, -30),
                (30, -(70 + 30 * math.tan(math.radians(30))))] + ANCHOR_XY
    np.testing.assert_allclose(xyz[:, :2], expected, atol=1e-9)
    assert np.all(xyz[:, 2] == 0)
    sk = np.linalg.svd([[1.0, 1.0], [0.0, 1.0]], compute_uv=False).mean()    # skewX(45) of a unit circle
    sky = np.linalg.svd([[1.0, 0.0], [math.tan(math.radians(30)), 1.0]], compute_uv=False).mean()
    np.testing.assert_allclose(rad[:7], [1, 2, 1, sk, 2.5, 1, sky], atol=1e-12)


@pytest.mark.parametrize("text, M", [
    ("translate(3)", [[1, 0, 3], [0, 1, 0]]),
    ("scale(2, 3)", [[2, 0, 0], [0, 3, 0]]),
    ("rotate(90)", [[0, -1, 0], [1, 0, 0]]),
    ("translate(1,2) scale(2)", [[2, 0, 1], [0, 2, 2]]),
    ("translate(1 2),scale(2)", [[2, 0, 1], [0, 2, 2]]),
    ("matrix(1 2 3 4 5 6)", [[1, 3, 5], [2, 4, 6]]),
    ("rotate(180 1 1)", [[-1, 0, 2], [0, -1, 2]]),
])
def test_parse_transform(text, M):
    np.testing.assert_allclose(parse_transform(text)[:2], M, atol=1e-12)


@pytest.mark.parametrize("text", ["translate(1,2,3)", "spin(3)", "scale()", "translate(1) junk"])
def test_parse_transform_rejects(text):
    with pytest.raises(ValueError, match="invalid transform"):
        parse_transform(text)


# ------------------------------------------------------------------------------ units and viewBox
@pytest.mark.parametrize("attrs, xy, r", [
    ('width="100mm" height="50mm" viewBox="0 0 200 100"', (10, -20), 2),         # 0.5 mm per unit
    ('width="100mm" height="50mm" viewBox="-100 -50 200 100"', (10, -20), 2),    # origin: user space
    ('width="100mm" height="100mm" viewBox="0 0 200 100"', (10, -20), 2),        # meet: the smaller scale
    ('width="100mm" height="100mm" viewBox="0 0 200 100" preserveAspectRatio="xMinYMin slice"', (20, -40), 4),
    ('width="100mm" height="100mm" viewBox="0 0 200 100" preserveAspectRatio="none"', (10, -40), 3),
    ('width="100mm" viewBox="0 0 200 100"', (10, -20), 2),                       # height from the aspect
    ('width="10cm" height="5cm" viewBox="0 0 200 100"', (10, -20), 2),
    ('width="3.937007874in" height="1.968503937in" viewBox="0 0 200 100"', (10, -20), 2),
    ('width="283.46456693pt" height="141.73228346pt" viewBox="0 0 200 100"', (10, -20), 2),
    ('width="377.95275591px" height="188.97637795px" viewBox="0 0 200 100"', (10, -20), 2),
    ('width="377.95275591" height="188.97637795" viewBox="0 0 200 100"', (10, -20), 2),
    ('width="400" height="200"', (20 * MM_PER_PX, -40 * MM_PER_PX), 4 * MM_PER_PX),  # no viewBox: px
    ('width="100mm" height="100mm"', (20 * MM_PER_PX, -40 * MM_PER_PX), 4 * MM_PER_PX),
    ('width="100%" height="100%" viewBox="0 0 200 100"', (20 * MM_PER_PX, -40 * MM_PER_PX), 4 * MM_PER_PX),
])
def test_units_and_viewbox(attrs, xy, r):
    body = '<circle cx="20" cy="40" r="4"/>' + "".join(
        f'<circle cx="{x}" cy="80" r="1"/>' for x in (60, 80, 100, 120))
    xyz, rad, _ = dots(svg(body, attrs))
    np.testing.assert_allclose(xyz[0, :2], xy, rtol=1e-8, atol=1e-9)
    assert rad[0] == pytest.approx(r, rel=1e-8)


def test_lengths_with_units_on_elements():
    # absolute units on coordinates are converted to user units at 96 px per inch
    body = '<circle cx="10mm" cy="1in" r="2px"/>' + ANCHORS
    xyz, rad, _ = dots(svg(body))
    np.testing.assert_allclose(xyz[0, :2], [10 / MM_PER_PX, -96.0], rtol=1e-12)
    assert rad[0] == pytest.approx(2.0)


def test_old_inkscape_documents_use_90_px_per_inch():
    attrs = 'width="744.09448819" height="1052.3622047" inkscape:version="0.48.4 r9939"'
    body = "".join(f'<circle cx="{x}" cy="90" r="9"/>' for x in (90, 180, 270, 360))
    xyz, rad, _ = dots(svg(body, attrs))
    np.testing.assert_allclose(xyz[:, 0], [25.4, 50.8, 76.2, 101.6])
    np.testing.assert_allclose(rad, 2.54)
    xyz96, _, _ = dots(svg(body, attrs.replace("0.48.4", "1.2.2")))
    np.testing.assert_allclose(xyz96[0, 0], 90 * MM_PER_PX)
    xyz_forced, _, _ = dots(svg(body, attrs), px_per_inch=96)
    np.testing.assert_allclose(xyz_forced[0, 0], 90 * MM_PER_PX)


# ------------------------------------------------------------------------------ Inkscape
INKSCAPE = """
  <sodipodi:namedview id="base" inkscape:document-units="mm"/>
  <metadata><circle cx="1" cy="1" r="1"/></metadata>
  <defs><circle id="proto" r="1.5" style="fill:#ffffff"/></defs>
  <g inkscape:groupmode="layer" inkscape:label="Guides" id="layer2" style="display:none">
    <circle cx="50" cy="50" r="3"/>
  </g>
  <g inkscape:groupmode="layer" inkscape:label="Dots" id="layer1" transform="translate(0,-10)">
    <path sodipodi:type="arc" sodipodi:cx="30" sodipodi:cy="40" sodipodi:rx="2" sodipodi:ry="2"
          d="m 32,40 a 2,2 0 0 1 -2,2 2,2 0 0 1 -2,-2 2,2 0 0 1 2,-2 2,2 0 0 1 2,2 z"
          transform="translate(5,5)" style="fill:#000000;stroke:none" id="path1"/>
    <path sodipodi:type="arc" sodipodi:cx="10" sodipodi:cy="10" sodipodi:rx="3" sodipodi:ry="1"
          sodipodi:start="0" sodipodi:end="6.2831853" d="m 13,10 z" style="fill:#1a1a1a" id="path2"/>
    <path sodipodi:type="arc" sodipodi:cx="70" sodipodi:cy="10" sodipodi:rx="2" sodipodi:ry="2"
          sodipodi:start="0" sodipodi:end="3.1415927" sodipodi:open="true" d="M 72,10 A 2,2 0 0 1 68,10"
          style="fill:#000000" id="half_arc"/>
    <path d="M 0,0 L 10,10" style="fill:#000000" id="just_a_path"/>
    <circle cx="50" cy="60" r="2" style="fill:none;stroke:#000000" id="outline"/>
    <circle cx="40" cy="60" r="2" style="display:none" id="hidden"/>
    <g style="visibility:hidden"><circle cx="45" cy="80" r="1" id="invisible"/>
      <circle cx="55" cy="80" r="1" style="visibility:visible" id="visible_again"/></g>
    <use xlink:href="#proto" x="80" y="30" id="clone1"/>
    <use href="#path1" transform="translate(20,0)" id="clone2"/>
    <text x="5" y="5">label</text>
  </g>
  <circle cx="95" cy="95" r="1" id="outside_layers"/>
"""


def test_inkscape_document():
    b = parse_brim_svg(svg(INKSCAPE), name="custom")
    assert b.name == "custom"
    expected = [(35, -35), (10, 0), (55, -70), (80, -20), (55, -35), (95, -95)]
    np.testing.assert_allclose(b.xyz[:, :2], expected, atol=1e-9)
    np.testing.assert_allclose(b.radius, [2, 2, 1, 1.5, 2, 1])
    np.testing.assert_array_equal(b.polarity, [-1, -1, -1, 1, -1, -1])


def test_layer_option():
    b = parse_brim_svg(svg(INKSCAPE), layer="Dots")
    assert len(b) == 5  # the circle outside the layers is left out
    np.testing.assert_allclose(b.xyz[0, :2], (35, -35))
    with pytest.raises(BrimSvgError, match=r"no layer named 'Nope' \(layers: 'Guides', 'Dots'\)"):
        parse_brim_svg(svg(INKSCAPE), layer="Nope", source="x.svg")
    with pytest.raises(BrimSvgError, match="no dots found"):
        parse_brim_svg(svg(INKSCAPE), layer="Guides")  # hidden


def test_centre_option():
    b = parse_brim_svg(svg(INKSCAPE), centre=True)
    xy = b.xyz[:, :2]
    np.testing.assert_allclose((xy.min(axis=0) + xy.max(axis=0)) / 2, 0, atol=1e-12)
    np.testing.assert_allclose(xy[1] - xy[0], np.subtract((10, 0), (35, -35)))


# ------------------------------------------------------------------------------ polarity
def test_polarity_from_fill():
    fills = ['fill="#fff"', 'style="fill:rgb(250, 250, 250)"', 'fill="navy"', 'fill="#808080"',
             'style="fill:#FFFFFF !important"', 'class="w"', 'fill="currentColor" color="white"',
             'fill="url(#grad) white"', 'fill="black" style="fill:white"', "", 'fill="rgb(10%, 10%, 10%)"',
             'fill="#000000ff"']
    body = '<style>.w { fill: #ffffff; } .other{stroke:red}</style>' + "".join(
        f'<circle cx="{10 + 8 * i}" cy="10" r="2" {f}/>' for i, f in enumerate(fills))
    body += '<g fill="white"><circle cx="10" cy="40" r="2"/><circle cx="20" cy="40" r="2" fill="black"/></g>'
    _, _, pol = dots(svg(body))
    np.testing.assert_array_equal(pol, [1, 1, -1, 1, 1, 1, 1, 1, 1, -1, -1, -1, 1, -1])


def test_unknown_colour_is_an_error():
    body = '<circle cx="10" cy="10" r="2" id="c1" fill="blurple"/>' + ANCHORS
    with pytest.raises(BrimSvgError, match=r"b\.svg: <circle id='c1'>: unknown fill colour 'blurple'"):
        parse_brim_svg(svg(body), source="b.svg")


# ------------------------------------------------------------------------------ errors
def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_errors_name_the_file(tmp_path):
    cases = [
        ("notxml.svg", "<svg <<", "not an XML file"),
        ("html.svg", "<html><body/></html>", r"not an SVG file \(the root element is <html>"),
        ("empty.svg", svg('<rect x="0" y="0" width="10" height="10"/>'), "no dots found"),
        ("three.svg", svg('<circle cx="10" cy="10" r="1"/><circle cx="20" cy="10" r="1"/>'
                          '<circle cx="30" cy="10" r="1"/>'), "needs at least 4 dots, found 3"),
        ("overlap.svg", svg(ANCHORS + '<circle cx="61" cy="95" r="1"/>'), "dots 0 and 4 overlap"),
        ("transform.svg", svg(ANCHORS + '<g transform="wobble(3)"><circle cx="5" cy="5" r="1"/></g>'),
         "invalid transform"),
        ("viewbox.svg", svg(ANCHORS, 'width="10mm" height="10mm" viewBox="0 0 0 10"'), "invalid viewBox"),
        ("radius.svg", svg(ANCHORS + '<circle cx="5" cy="5" r="-1"/>'), "negative radius"),
        ("number.svg", svg(ANCHORS + '<circle cx="five" cy="5" r="1"/>'), "invalid cx='five'"),
        ("percent.svg", svg(ANCHORS + '<circle cx="5%" cy="5" r="1"/>'), "unsupported unit"),
        ("selfuse.svg", svg(ANCHORS + '<g id="g1"><use href="#g1"/></g>'), "refers to itself"),
    ]
    for name, text, msg in cases:
        p = write(tmp_path, name, text)
        with pytest.raises(BrimSvgError, match=msg) as info:
            read_brim_svg(p)
        assert str(p) in str(info.value), name
        assert isinstance(info.value, ValueError)
    with pytest.raises(FileNotFoundError):
        read_brim_svg(tmp_path / "missing.svg")


def test_zero_radius_and_unknown_elements_are_skipped():
    body = ANCHORS + '<circle cx="5" cy="5" r="0"/><ellipse cx="5" cy="5"/><foo:bar xmlns:foo="urn:x"/>'
    assert len(parse_brim_svg(svg(body))) == 4


def test_no_external_entities(tmp_path):
    secret = write(tmp_path, "secret.txt", "42")
    text = (f'<?xml version="1.0"?><!DOCTYPE svg [<!ENTITY x SYSTEM "file://{secret}">]>'
            f'<svg xmlns="http://www.w3.org/2000/svg" width="100mm" height="100mm" viewBox="0 0 100 100">'
            f'<desc>&x;</desc>{ANCHORS}</svg>')
    b = parse_brim_svg(text)
    assert len(b) == 4 and "42" not in b.svg.replace(str(secret), "")


def test_layer_inherits_the_root_style():
    body = '<g inkscape:groupmode="layer" inkscape:label="L">' + ANCHORS + "</g>"
    b = parse_brim_svg(svg(body, 'width="100mm" height="100mm" viewBox="0 0 100 100" fill="white"'), layer="L")
    assert np.all(b.polarity == 1)
