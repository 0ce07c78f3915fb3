"""Import Calibration Brim [svg]: a planar brim drawn as circles in an SVG file.

A custom brim is edited in Inkscape (or any SVG editor): every visible, filled ``<circle>``,
``<ellipse>`` and Inkscape arc (``<path sodipodi:type="arc">`` drawing a whole ellipse) is
one dot. ``docs/brim.md`` is the user's guide to it.

Geometry
--------
* Transforms of every ancestor (``matrix``, ``translate``, ``scale``, ``rotate``,
  ``skewX``, ``skewY`` and lists of them) are applied, as are ``<use>`` clones.
* The root's ``width``/``height`` (mm, cm, in, pt, pc, Q, px or plain numbers = px) and
  ``viewBox`` give the size of one user unit in millimetres (96 px per inch, the SVG
  spec; 90 for documents saved by Inkscape before 0.92, which used 90). Without a
  ``viewBox``, or without an absolute ``width``/``height``, a user unit is one px.
* Brim frame: ``X`` along the SVG ``x`` axis, ``Y`` against the SVG ``y`` axis (SVG ``y``
  points down), ``Z = 0`` on the card, ``+Z`` towards the cameras. The origin is the SVG
  user-space origin (or the centre of the dots' bounding box with ``centre=True``).
* Dot ``i`` is the ``i``-th dot in document order. Its radius is the mean of the semi-axes
  of the transformed ellipse; its polarity comes from its fill colour (dark = black dot =
  -1, light = white dot = +1; no fill given = black, as in SVG).

Ignored: hidden elements (``display:none`` on the element or an ancestor, ``visibility:
hidden``, ``opacity:0``), unfilled circles (``fill:none``: outlines, guides), partial arcs,
anything inside ``<defs>``, ``<clipPath>``, ``<mask>``, ``<pattern>``, ``<marker>``,
``<symbol>`` (unless cloned by ``<use>``), ``<metadata>`` and text. Circles converted to
plain paths ("Object to Path") are not recognised.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from lxml import etree

from carapost.model.take import BrimModel

__all__ = ["BrimSvgError", "read_brim_svg", "parse_brim_svg", "parse_transform", "MIN_DOTS"]

#: Fewest dots a brim needs (the brim solve needs 4 correspondences per camera).
MIN_DOTS = 4

SVG_NS = "http://www.w3.org/2000/svg"
XLINK_NS = "http://www.w3.org/1999/xlink"
SODIPODI_NS = "http://sodipodi.sourceforge.net/DTD/sodipodi-0.dtd"
INKSCAPE_NS = "http://www.inkscape.org/namespaces/inkscape"

#: Millimetres per unit (``px`` is handled separately: it depends on the px-per-inch).
_MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "in": 25.4, "pt": 25.4 / 72.0, "pc": 25.4 / 6.0, "q": 0.25}
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUMBER_RE = re.compile(_NUMBER)
_LENGTH_RE = re.compile(rf"^\s*({_NUMBER})\s*([a-zA-Z%]*)\s*$")
_TRANSFORM_RE = re.compile(r"\s*,?\s*([a-zA-Z]+)\s*\(([^)]*)\)\s*,?")
_CLASS_RULE_RE = re.compile(r"([^{}]+)\{([^{}]*)\}")
_CONTAINERS = {"g", "a", "switch", "svg"}
_SKIP = {"defs", "clipPath", "mask", "pattern", "marker", "symbol", "metadata", "title", "desc", "text",
         "style", "script", "foreignObject", "linearGradient", "radialGradient", "filter"}
_MAX_USE_DEPTH = 16
_INHERITED = ("fill", "fill-opacity", "color", "visibility")

# CSS Color Module Level 4 named colours (only their lightness matters here).
_CSS_COLOURS = dict(kv.split(":") for kv in """
aliceblue:f0f8ff antiquewhite:faebd7 aqua:00ffff aquamarine:7fffd4 azure:f0ffff beige:f5f5dc
bisque:ffe4c4 black:000000 blanchedalmond:ffebcd blue:0000ff blueviolet:8a2be2 brown:a52a2a
burlywood:deb887 cadetblue:5f9ea0 chartreuse:7fff00 chocolate:d2691e coral:ff7f50
cornflowerblue:6495ed cornsilk:fff8dc crimson:dc143c cyan:00ffff darkblue:00008b darkcyan:008b8b
darkgoldenrod:b8860b darkgray:a9a9a9 darkgreen:006400 darkgrey:a9a9a9 darkkhaki:bdb76b
darkmagenta:8b008b darkolivegreen:556b2f darkorange:ff8c00 darkorchid:9932cc darkred:8b0000
darksalmon:e9967a darkseagreen:8fbc8f darkslateblue:483d8b darkslategray:2f4f4f
darkslategrey:2f4f4f darkturquoise:00ced1 darkviolet:9400d3 deeppink:ff1493 deepskyblue:00bfff
dimgray:696969 dimgrey:696969 dodgerblue:1e90ff firebrick:b22222 floralwhite:fffaf0
forestgreen:228b22 fuchsia:ff00ff gainsboro:dcdcdc ghostwhite:f8f8ff gold:ffd700
goldenrod:daa520 gray:808080 green:008000 greenyellow:adff2f grey:808080 honeydew:f0fff0
hotpink:ff69b4 indianred:cd5c5c indigo:4b0082 ivory:fffff0 khaki:f0e68c lavender:e6e6fa
lavenderblush:fff0f5 lawngreen:7cfc00 lemonchiffon:fffacd lightblue:add8e6 lightcoral:f08080
lightcyan:e0ffff lightgoldenrodyellow:fafad2 lightgray:d3d3d3 lightgreen:90ee90 lightgrey:d3d3d3
lightpink:ffb6c1 lightsalmon:ffa07a lightseagreen:20b2aa lightskyblue:87cefa
lightslategray:778899 lightslategrey:778899 lightsteelblue:b0c4de lightyellow:ffffe0 lime:00ff00
limegreen:32cd32 linen:faf0e6 magenta:ff00ff maroon:800000 mediumaquamarine:66cdaa
mediumblue:0000cd mediumorchid:ba55d3 mediumpurple:9370db mediumseagreen:3cb371
mediumslateblue:7b68ee mediumspringgreen:00fa9a mediumturquoise:48d1cc mediumvioletred:c71585
midnightblue:191970 mintcream:f5fffa mistyrose:ffe4e1 moccasin:ffe4b5 navajowhite:ffdead
navy:000080 oldlace:fdf5e6 olive:808000 olivedrab:6b8e23 orange:ffa500 orangered:ff4500
orchid:da70d6 palegoldenrod:eee8aa palegreen:98fb98 paleturquoise:afeeee palevioletred:db7093
papayawhip:ffefd5 peachpuff:ffdab9 peru:cd853f pink:ffc0cb plum:dda0dd powderblue:b0e0e6
purple:800080 rebeccapurple:663399 red:ff0000 rosybrown:bc8f8f royalblue:4169e1
saddlebrown:8b4513 salmon:fa8072 sandybrown:f4a460 seagreen:2e8b57 seashell:fff5ee sienna:a0522d
silver:c0c0c0 skyblue:87ceeb slateblue:6a5acd slategray:708090 slategrey:708090 snow:fffafa
springgreen:00ff7f steelblue:4682b4 tan:d2b48c teal:008080 thistle:d8bfd8 tomato:ff6347
turquoise:40e0d0 violet:ee82ee wheat:f5deb3 white:ffffff whitesmoke:f5f5f5 yellow:ffff00
yellowgreen:9acd32""".split())


class BrimSvgError(ValueError):
    """An SVG file that cannot be imported as a brim; the message names the file and the problem."""


@dataclass(frozen=True)
class _Dot:
    centre: np.ndarray  # (2,) mm, SVG axes (y down)
    radius: float       # mm
    polarity: int


# ------------------------------------------------------------------------------ public API
def read_brim_svg(path: str | os.PathLike, *, layer: str | None = None, centre: bool = False,
                  px_per_inch: float | None = None) -> BrimModel:
    """Read a planar calibration brim from an SVG file (File > Import Calibration Brim [svg]).

    Parameters
    ----------
    path : path-like
        The SVG file.
    layer : str, optional
        Only read dots inside the Inkscape layer (or group) with this ``inkscape:label``
        (or ``id``); default: every visible dot in the document.
    centre : bool
        Put the origin at the centre of the dots' bounding box instead of the SVG origin.
    px_per_inch : float, optional
        Size of a ``px`` (and of a unitless length); default 96 (the SVG spec), or 90 for
        files written by Inkscape before 0.92.

    Returns
    -------
    BrimModel
        ``name`` the file's stem; ``xyz (N, 3)`` mm with ``Z = 0``; ``radius (N,)`` mm;
        ``polarity (N,)`` int8 (-1 black, +1 white); ``svg`` the file's text.

    Raises
    ------
    BrimSvgError
        If the file is not XML, not SVG, has malformed geometry, has no dots, fewer than
        :data:`MIN_DOTS` dots, or overlapping dots (the message names the file).
    FileNotFoundError
        If the file does not exist.
    """
    path = Path(path)
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    return _parse(data, text, source=str(path), name=path.stem, layer=layer, centre=centre,
                  px_per_inch=px_per_inch)


def parse_brim_svg(text: str, *, name: str = "brim", source: str = "<svg>", layer: str | None = None,
                   centre: bool = False, px_per_inch: float | None = None) -> BrimModel:
    """:func:`read_brim_svg` on SVG source text; ``source`` names it in error messages."""
    return _parse(text.encode("utf-8"), text, source=source, name=name, layer=layer, centre=centre,
                  px_per_inch=px_per_inch)


# ------------------------------------------------------------------------------ parsing
def _parse(data: bytes, text: str, *, source: str, name: str, layer: str | None, centre: bool,
           px_per_inch: float | None) -> BrimModel:
    def fail(msg: str) -> BrimSvgError:
        return BrimSvgError(f"{source}: {msg}")

    parser = etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=False, remove_comments=True)
    try:
        root = etree.fromstring(data, parser)
    except etree.XMLSyntaxError as exc:
        raise fail(f"not an XML file ({exc})") from None
    if not isinstance(root.tag, str) or etree.QName(root).localname != "svg" or \
            etree.QName(root).namespace not in (SVG_NS, None):
        tag = etree.QName(root).localname if isinstance(root.tag, str) else "?"
        raise fail(f"not an SVG file (the root element is <{tag}>, expected <svg>)")
    if px_per_inch is None:
        px_per_inch = 90.0 if _old_inkscape(root) else 96.0
    if not (math.isfinite(px_per_inch) and px_per_inch > 0):
        raise ValueError(f"px_per_inch must be positive, got {px_per_inch}")
    reader = _Reader(root, fail, px_per_inch)
    start = root
    if layer is not None:
        start = reader.find_layer(layer)
    dots = list(reader.dots(start))
    if not dots:
        raise fail("no dots found (expected filled <circle>, <ellipse> or Inkscape arc elements"
                   + (f" in layer {layer!r})" if layer is not None else ")"))
    if len(dots) < MIN_DOTS:
        raise fail(f"a brim needs at least {MIN_DOTS} dots, found {len(dots)}")
    c = np.array([d.centre for d in dots])
    xy = np.c_[c[:, 0], -c[:, 1]]  # Y against SVG y
    rad = np.array([d.radius for d in dots])
    _check_overlaps(xy, rad, fail)
    if centre:
        xy = xy - (xy.min(axis=0) + xy.max(axis=0)) / 2
    xyz = np.c_[xy, np.zeros(len(xy))]
    pol = np.array([d.polarity for d in dots], np.int8)
    return BrimModel(name=name, xyz=xyz, radius=rad, polarity=pol, svg=text)


def _old_inkscape(root: etree._Element) -> bool:
    """True for documents saved by Inkscape before 0.92 (90 px per inch)."""
    ver = root.get(f"{{{INKSCAPE_NS}}}version")
    if not ver:
        return False
    m = re.match(r"\s*(\d+)\.(\d+)", ver)
    return bool(m) and (int(m.group(1)), int(m.group(2))) < (0, 92)


def _check_overlaps(xy: np.ndarray, rad: np.ndarray, fail) -> None:
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    overlap = d < (rad[:, None] + rad[None]) * 0.999
    np.fill_diagonal(overlap, False)
    if np.any(overlap):
        i, j = np.argwhere(overlap)[0]
        raise fail(f"dots {i} and {j} overlap (centres {d[i, j]:.3f} mm apart, radii {rad[i]:.3f} and "
                   f"{rad[j]:.3f} mm); every dot must be one separate circle")


class _Reader:
    """Walks the document, tracking transforms and inherited style."""

    def __init__(self, root: etree._Element, fail, px_per_inch: float):
        self.root = root
        self.fail = fail
        self.mm_per_px = 25.4 / px_per_inch
        self.ids = {el.get("id"): el for el in root.iter() if isinstance(el.tag, str) and el.get("id")}
        self.classes = self._class_rules()

    # -- document-level ---------------------------------------------------------------
    def root_matrix(self) -> np.ndarray:
        """User units of the root to mm: (3, 3) affine (no translation)."""
        root = self.root
        w = self._abs_length(root.get("width"))
        h = self._abs_length(root.get("height"))
        vb = root.get("viewBox")
        if vb is None:
            return np.diag([self.mm_per_px, self.mm_per_px, 1.0])
        v = [float(x) for x in _NUMBER_RE.findall(vb)]
        if len(v) != 4 or v[2] <= 0 or v[3] <= 0:
            raise self.fail(f"invalid viewBox {vb!r} (expected 'min-x min-y width height')")
        if w is None and h is None:
            return np.diag([self.mm_per_px, self.mm_per_px, 1.0])
        sx = w / v[2] if w is not None else None
        sy = h / v[3] if h is not None else None
        par = (root.get("preserveAspectRatio") or "xMidYMid meet").split()
        if sx is None or sy is None:
            sx = sy = sx if sx is not None else sy
        elif par and par[0] == "none":
            pass
        elif len(par) > 1 and par[1] == "slice":
            sx = sy = max(sx, sy)
        else:
            sx = sy = min(sx, sy)
        return np.diag([sx, sy, 1.0])

    def _abs_length(self, s: str | None) -> float | None:
        """An absolute length in mm, or None if missing or relative (%, em, ex)."""
        if s is None:
            return None
        m = _LENGTH_RE.match(s)
        if not m:
            raise self.fail(f"invalid length {s!r} on the <svg> element")
        value, unit = float(m.group(1)), m.group(2).lower()
        if unit in ("", "px"):
            return value * self.mm_per_px
        if unit in _MM_PER_UNIT:
            return value * _MM_PER_UNIT[unit]
        return None  # %, em, ex: no physical size

    def find_layer(self, layer: str) -> etree._Element:
        for el in self.root.iter(f"{{{SVG_NS}}}g"):
            if el.get(f"{{{INKSCAPE_NS}}}label") == layer:
                return el
        if layer in self.ids:
            return self.ids[layer]
        labels = [el.get(f"{{{INKSCAPE_NS}}}label") for el in self.root.iter(f"{{{SVG_NS}}}g")
                  if el.get(f"{{{INKSCAPE_NS}}}groupmode") == "layer"]
        raise self.fail(f"no layer named {layer!r} (layers: {', '.join(map(repr, labels)) or 'none'})")

    def _class_rules(self) -> dict[str, dict[str, str]]:
        """Declarations of simple ``.class { ... }`` rules in ``<style>`` elements."""
        rules: dict[str, dict[str, str]] = {}
        for st in self.root.iter(f"{{{SVG_NS}}}style"):
            css = re.sub(r"/\*.*?\*/", "", st.text or "", flags=re.S)
            for sel, body in _CLASS_RULE_RE.findall(css):
                decl = _declarations(body)
                for s in sel.split(","):
                    s = s.strip()
                    if re.fullmatch(r"\.[-\w]+", s):
                        rules.setdefault(s[1:], {}).update(decl)
        return rules

    # -- traversal --------------------------------------------------------------------
    def dots(self, start: etree._Element) -> Iterator[_Dot]:
        """Dots in document order below ``start`` (included), with ancestors' state applied."""
        M = self.root_matrix()
        style: dict[str, str] = {}
        chain = list(reversed(list(start.iterancestors())))
        for anc in chain:
            st = self._style(anc)
            if self._hidden(st):
                return
            if anc is not self.root:
                M = M @ self._transform(anc)
            style = _inherit(style, st)
        yield from self._walk(start, M, style, 0, ())

    def _walk(self, el: etree._Element, M: np.ndarray, style: dict[str, str], depth: int,
              using: tuple[str, ...]) -> Iterator[_Dot]:
        if not isinstance(el.tag, str):
            return
        q = etree.QName(el)
        if q.namespace not in (SVG_NS, None):
            return
        tag = q.localname
        if tag in _SKIP and not (tag == "symbol" and using):
            return
        st = self._style(el)
        if self._hidden(st):
            return
        own = _inherit(style, st)
        if el is not self.root:
            M = M @ self._transform(el)
        if tag in _CONTAINERS or (tag == "symbol" and using):
            if tag == "svg" and el is not self.root:
                M = M @ _translate(self._coord(el, "x"), self._coord(el, "y"))
            children = [ch for ch in el if isinstance(ch.tag, str)]
            if tag == "switch":  # renders its first child only
                children = children[:1]
            for child in children:
                yield from self._walk(child, M, own, depth, using)
        elif tag == "use":
            yield from self._use(el, M, own, depth, using)
        elif tag in ("circle", "ellipse", "path"):
            dot = self._dot(el, tag, M, own)
            if dot is not None:
                yield dot

    def _use(self, el, M, style, depth, using) -> Iterator[_Dot]:
        href = el.get(f"{{{XLINK_NS}}}href") or el.get("href") or ""
        ref_id = href[1:] if href.startswith("#") else None
        if ref_id is None or ref_id not in self.ids:
            return
        if ref_id in using or depth >= _MAX_USE_DEPTH:
            raise self.fail(f"<use id={el.get('id')!r}> refers to itself (#{ref_id})")
        M = M @ _translate(self._coord(el, "x"), self._coord(el, "y"))
        yield from self._walk(self.ids[ref_id], M, style, depth + 1, using + (ref_id,))

    # -- one element ------------------------------------------------------------------
    def _dot(self, el, tag: str, M: np.ndarray, style: dict[str, str]) -> _Dot | None:
        if tag == "circle":
            cx, cy, r = self._coord(el, "cx"), self._coord(el, "cy"), self._coord(el, "r")
            rx = ry = r
        elif tag == "ellipse":
            cx, cy = self._coord(el, "cx"), self._coord(el, "cy")
            rx, ry = self._coord(el, "rx", None), self._coord(el, "ry", None)
            if rx is None and ry is None:
                return None
            rx = ry if rx is None else rx  # SVG 2: "auto" takes the other radius
            ry = rx if ry is None else ry
        else:
            if el.get(f"{{{SODIPODI_NS}}}type") != "arc":
                return None
            cx, cy = self._coord(el, f"{{{SODIPODI_NS}}}cx"), self._coord(el, f"{{{SODIPODI_NS}}}cy")
            rx, ry = self._coord(el, f"{{{SODIPODI_NS}}}rx"), self._coord(el, f"{{{SODIPODI_NS}}}ry")
            if not self._whole_arc(el):
                return None
        assert rx is not None and ry is not None
        if style.get("visibility", "").lower() in ("hidden", "collapse"):
            return None
        if rx < 0 or ry < 0:
            raise self.fail(f"<{tag} id={el.get('id')!r}> has a negative radius")
        if rx == 0 or ry == 0:
            return None  # not rendered (SVG spec)
        polarity = self._polarity(el, tag, style)
        if polarity is None:
            return None
        A = M[:2, :2]
        centre = A @ np.array([cx, cy]) + M[:2, 2]
        sv = np.linalg.svd(A @ np.diag([rx, ry]), compute_uv=False)
        return _Dot(centre=centre, radius=float(sv.mean()), polarity=polarity)

    def _whole_arc(self, el) -> bool:
        a0 = el.get(f"{{{SODIPODI_NS}}}start")
        a1 = el.get(f"{{{SODIPODI_NS}}}end")
        if a0 is None or a1 is None:
            return True
        try:
            span = abs(float(a1) - float(a0))
        except ValueError:
            raise self.fail(f"<path id={el.get('id')!r}>: invalid arc start/end {a0!r}, {a1!r}") from None
        return span < 1e-6 or abs(span - 2 * math.pi) < 1e-4

    def _polarity(self, el, tag: str, style: dict[str, str]) -> int | None:
        fill = style.get("fill", "black").strip()
        if fill.startswith("url("):
            fb = fill[fill.index(")") + 1:].strip()  # fallback colour after the paint server
            fill = fb or "black"
        if fill.lower() == "currentcolor":
            fill = style.get("color", "black").strip()
        if fill.lower() in ("none", "transparent"):
            return None
        for key in ("fill-opacity", "opacity"):
            if key in style and _opacity(style[key]) == 0.0:
                return None
        rgb = _colour(fill)
        if rgb is None:
            raise self.fail(f"<{tag} id={el.get('id')!r}>: unknown fill colour {fill!r}")
        luma = 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
        return 1 if luma >= 0.5 else -1

    def _style(self, el) -> dict[str, str]:
        """Presentation attributes, then class rules, then the ``style`` attribute."""
        out: dict[str, str] = {}
        for key in ("fill", "display", "visibility", "opacity", "fill-opacity", "color"):
            v = el.get(key)
            if v is not None:
                out[key] = v.strip()
        for cls in (el.get("class") or "").split():
            out.update(self.classes.get(cls, {}))
        out.update(_declarations(el.get("style") or ""))
        return out

    @staticmethod
    def _hidden(st: dict[str, str]) -> bool:
        return st.get("display", "").lower() == "none" or ("opacity" in st and _opacity(st["opacity"]) == 0.0)

    def _coord(self, el, attr: str, default: float | None = 0.0) -> float:
        s = el.get(attr)
        if s is None:
            return default  # type: ignore[return-value]
        m = _LENGTH_RE.match(s)
        if not m:
            raise self.fail(f"<{etree.QName(el).localname} id={el.get('id')!r}>: invalid {etree.QName(attr).localname}"
                            f"={s!r}")
        value, unit = float(m.group(1)), m.group(2).lower()
        if unit in ("", "px"):
            return value
        if unit in _MM_PER_UNIT:
            return value * _MM_PER_UNIT[unit] / self.mm_per_px  # absolute units are fixed px multiples
        raise self.fail(f"<{etree.QName(el).localname} id={el.get('id')!r}>: unsupported unit in "
                        f"{etree.QName(attr).localname}={s!r}")

    def _transform(self, el) -> np.ndarray:
        s = el.get("transform")
        if not s:
            return np.eye(3)
        try:
            return parse_transform(s)
        except ValueError as exc:
            raise self.fail(f"<{etree.QName(el).localname} id={el.get('id')!r}>: {exc}") from None


def _inherit(parent: dict[str, str], own: dict[str, str]) -> dict[str, str]:
    """The style of a child: fill, fill-opacity, color and visibility inherit; the rest does not."""
    out = {k: v for k, v in parent.items() if k in _INHERITED}
    out.update(own)
    return out


def _declarations(css: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in css.split(";"):
        if ":" in item:
            k, v = item.split(":", 1)
            out[k.strip().lower()] = v.replace("!important", "").strip()
    return out


def _opacity(s: str) -> float:
    s = s.strip()
    try:
        return float(s[:-1]) / 100 if s.endswith("%") else float(s)
    except ValueError:
        return 1.0


def _colour(s: str) -> tuple[float, float, float] | None:
    """An sRGB colour (components 0..1) from a CSS colour string, or None if unknown."""
    s = s.strip().lower()
    if s.startswith("#"):
        h = s[1:]
        if len(h) in (3, 4):
            h = "".join(c * 2 for c in h[:3])
        if len(h) in (6, 8) and re.fullmatch(r"[0-9a-f]+", h):
            return tuple(int(h[i:i + 2], 16) / 255 for i in (0, 2, 4))  # type: ignore[return-value]
        return None
    m = re.fullmatch(r"rgba?\((.*)\)", s)
    if m:
        parts = [p for p in re.split(r"[\s,/]+", m.group(1).strip()) if p]
        if len(parts) < 3:
            return None
        try:
            vals = [float(p[:-1]) / 100 if p.endswith("%") else float(p) / 255 for p in parts[:3]]
        except ValueError:
            return None
        return tuple(min(max(v, 0.0), 1.0) for v in vals)  # type: ignore[return-value]
    if s in _CSS_COLOURS:
        return _colour("#" + _CSS_COLOURS[s])
    return None


# ------------------------------------------------------------------------------ transforms
def _translate(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def parse_transform(s: str) -> np.ndarray:
    """The 3x3 affine matrix of an SVG ``transform`` attribute (a list, applied right to left).

    Raises
    ------
    ValueError
        On an unknown transform or a wrong number of arguments.
    """
    M = np.eye(3)
    pos = 0
    s = s.strip()
    while pos < len(s):
        m = _TRANSFORM_RE.match(s, pos)
        if not m or m.end() == pos:
            raise ValueError(f"invalid transform {s!r}")
        pos = m.end()
        name = m.group(1)
        args = [float(a) for a in _NUMBER_RE.findall(m.group(2))]
        n = len(args)
        if name == "matrix" and n == 6:
            a, b, c, d, e, f = args
            T = np.array([[a, c, e], [b, d, f], [0, 0, 1.0]])
        elif name == "translate" and n in (1, 2):
            T = _translate(args[0], args[1] if n == 2 else 0.0)
        elif name == "scale" and n in (1, 2):
            T = np.diag([args[0], args[1] if n == 2 else args[0], 1.0])
        elif name == "rotate" and n in (1, 3):
            a = math.radians(args[0])
            co, si = math.cos(a), math.sin(a)
            T = np.array([[co, -si, 0.0], [si, co, 0.0], [0.0, 0.0, 1.0]])
            if n == 3:
                T = _translate(args[1], args[2]) @ T @ _translate(-args[1], -args[2])
        elif name == "skewX" and n == 1:
            T = np.array([[1.0, math.tan(math.radians(args[0])), 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        elif name == "skewY" and n == 1:
            T = np.array([[1.0, 0.0, 0.0], [math.tan(math.radians(args[0])), 1.0, 0.0], [0.0, 0.0, 1.0]])
        else:
            raise ValueError(f"invalid transform {name}({m.group(2).strip()}) in {s!r}")
        M = M @ T
    return M
