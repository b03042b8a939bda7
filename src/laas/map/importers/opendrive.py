"""ASAM OpenDRIVE roads into the GeoJSON lane-map format.

Reading. The ``.xodr`` file is parsed with ``lxml`` (no entities, no network). The road
geometry is evaluated here, on numpy, with ``scipy.special.fresnel`` for spirals; no
OpenDRIVE library is used (see ``docs/maps/opendrive.md`` for why not ``pyxodr``).

Reference line. A road's ``planView`` is a chain of geometries, each starting at
``(x, y)`` with heading ``hdg`` (radians, counter-clockwise from the x axis) and running
``length`` metres of arc length ``ds``. In the geometry's own frame (origin at its start,
u along ``hdg``, v to the left) the point at ``ds`` is:

- ``line``: ``(ds, 0)``, heading 0;
- ``arc`` of curvature k: heading ``k ds``, chord ``2 sin(k ds / 2) / k`` in the
  direction ``k ds / 2`` (written with ``sinc``, exact also for k = 0);
- ``spiral`` (clothoid) with curvature changing linearly from ``curvStart`` k0 to
  ``curvEnd`` k1, ``c = (k1 - k0) / length``: it is the piece ``t in [t0, t0 + length]``,
  ``t0 = k0 / c``, of the standard clothoid of curvature ``c t``, whose points are
  ``(a C(t / a), sign(c) a S(t / a))`` with ``a = sqrt(pi / |c|)`` and the Fresnel
  integrals ``S, C``; it is moved so that ``t0`` lies at the origin with heading 0
  (rotated by ``-c t0^2 / 2``). This is exact for any k0, also when the curvature
  changes sign (t passes 0). Where ``|t| / a`` would exceed 1000 (a curvature change
  that is tiny against the curvature) the arc of the mean curvature is used; its error
  is below a millimetre there. c = 0 is an arc;
- ``poly3``: ``(u, a + b u + c u^2 + d u^3)``; u is found from ds by the arc length
  ``int sqrt(1 + v'(u)^2) du`` (a table at 5 cm, inverted by interpolation);
- ``paramPoly3``: ``(U(p), V(p))``, cubics in p, ``p in [0, length]`` (``pRange``
  ``arcLength``, the default) or ``[0, 1]`` (``normalized``); p is found from ds by the
  curve's true arc length, scaled so that ``ds = length`` falls on the last p.

A point of the geometry frame ``(u, v)`` is ``(x + u cos hdg - v sin hdg, y + u sin hdg
+ v cos hdg)`` in the road's inertial frame, its heading ``hdg`` + the local heading.

Lanes. At a station s of the reference line with heading h, a point at lateral
coordinate t (positive to the left) is ``(X - t sin h, Y + t cos h)``. The centre lane
lies at ``t = laneOffset(s)`` (a piecewise cubic in ``s - s_record``). Going outwards
from it, each lane's inner border is the previous lane's outer border, and its outer
border is the inner one plus (left lanes) or minus (right lanes) its ``width`` (a
piecewise cubic in ``s - (laneSection s + sOffset)``, negative values read as 0) or,
for a lane with ``border`` records and no ``width``, the border polynomial itself, a
t coordinate measured from the reference line. The lane's centre line is the curve at
``t = (inner + outer) / 2``, sampled at ``ceil(L / step) + 1`` equally spaced stations
of the section (so both section ends are stations).

Road elements. Each laneSection is a segment ``road<id>-s<k>`` (k counts the road's
laneSections from 0), origin ``road <id> laneSection s=<s>``. Our lane 0 is the
leftmost lane looking along s: left lanes by falling id (3, 2, 1), then right lanes
(-1, -2, -3); every centre line runs along s. Lane types map as ``driving`` (and
``entry``, ``exit``, ``onRamp``, ``offRamp``, ``connectingRamp``, ``bidirectional``,
``mwyEntry``, ``mwyExit``, ``slipLane``, ``bus``, ``taxi``, ``HOV``) -> driving,
``biking`` -> bicycle, ``sidewalk``/``walking`` -> sidewalk, ``parking`` -> parking.
Other types (``shoulder``, ``border``, ``median``, ``curb``, ``restricted``, ``none``,
``stop``, ``tram``, ...) are not written but keep their width, so the lanes beyond
them stay where they are; they are counted by type.

The loader wants one width per lane. A section is cut into pieces (``road<id>-s<k>.<j>``)
so that within a piece no written lane's width varies by more than ``WIDTH_RANGE``
(0.5 m); each lane gets its mean width over the piece. Where a lane's mean width in a
piece is below ``MIN_WIDTH`` (0.5 m; a taper's thin end) it is left out there
(counted), and a lane of zero width over the whole section is left out (counted). A
section whose reference turns by more than ``MAX_TURN_DEG`` (170 degrees) in all is
first cut into equal shares of its turning, and a piece is halved at the middle of
its turning until the loader's frame (:class:`laas.map.frame.Frame`, built on the
piece's lane 0) puts every lane vertex where it belongs (a long straight followed by
a bend of more than 90 degrees is misread as one element). A lane whose centre lies
inside a curve at ``t * curvature >= FOLD`` (0.9) would fold back on itself and is
left out (counted).

Left-out lanes in the middle (a median, a wide border) leave a gap between written
neighbours: their centres lie further apart than the mean of their widths, and the
loader refuses a segment where the gap exceeds its tolerance ``max(35 %, 0.75 m)``
(:func:`laas.map.geojson.gap_tolerance`). Where any station's gap is more than 0.8 of
that tolerance off, the piece is split there into side-by-side segments ``a``, ``b``,
... from the left (``road<id>-s<k>a``): each keeps its exact centre lines, and nothing
is widened or invented.

Direction. Right-hand traffic (``rule="RHT"``, the default): right lanes travel along s
(``forward``), left lanes against it (``backward``); ``rule="LHT"`` mirrors this. The
OpenDRIVE 1.7 lane attribute ``direction`` (``standard`` | ``reversed`` | ``both``)
overrides; sidewalks and ``bidirectional`` lanes are ``both``.

Successors (in the reference direction, as the lane map defines them): the next piece
of the section, else the first piece of the next laneSection, else, after a road's
last section, the first section of each road whose start touches this road's end: a
road link (``successor`` with ``contactPoint="start"``, or the other road's
``predecessor`` with ``contactPoint="end"``) or a junction connection whose
connecting road starts (or, for an incoming road whose *start* is at the junction,
ends) there. A link where two roads' ends or two starts meet runs head-on: neither
continues the other along its reference direction, so it is not written as a
successor; it is counted. Where a piece has more than one side-by-side segment, lane
links (and lane ids within a road) decide which segment follows which.

Georeference. With ``origin=(lat, lon)`` the inertial x/y are metres east/north in a
transverse Mercator projection centred there (the header's ``geoReference`` and
``offset`` are then ignored). Otherwise the header's ``<geoReference>`` (a PROJ
string, EPSG code or WKT; vertical grids such as ``+geoidgrids`` are dropped, only the
horizontal position is used) converts ``x/y`` after the header's ``<offset>``
(``R(hdg) (x, y) + (x_off, y_off)``) to longitude/latitude with pyproj. A file with
neither is refused with a :class:`MapError` that asks for ``--origin LAT,LON``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import numpy.typing as npt
import pyproj
from lxml import etree  # type: ignore[import-untyped]
from scipy.special import fresnel  # type: ignore[import-untyped]

from laas.errors import MapError
from laas.map.frame import Frame
from laas.map.geojson import cover_tolerance, gap_tolerance
from laas.map.hdmap import Direction, LaneType
from laas.map.importers.common import ImportReport, ImportResult, LaneDraft, finish, no_lanes

__all__ = ["LANE_TYPES", "MAX_TURN_DEG", "MIN_WIDTH", "WIDTH_RANGE", "import_opendrive"]

FloatArray = npt.NDArray[np.float64]
Side = Literal["left", "right"]

WIDTH_RANGE = 0.5  # m: a written lane's width varies at most this much within one segment
MIN_WIDTH = 0.5  # m: narrower (mean over a piece) lanes are left out there
MIN_SECTION = 0.1  # m: shorter laneSections are left out
MAX_TURN_DEG = 170.0  # a segment's reference turns at most this much in all (see _pieces)
FOLD = 0.9  # a lane at t with t * curvature >= this (inside a tight curve) is left out
GAP_SAFETY = 0.8  # split side by side where a gap uses more than this share of the tolerance
_COVER_SAFETY = 0.8  # share of the loader's station tolerance (`cover_tolerance`) pieces keep to
_TABLE_STEP = 0.05  # m: arc-length table spacing for poly3 and paramPoly3
_FRESNEL_MAX = 1000.0  # beyond this Fresnel argument a spiral is taken as its mean arc

_DRIVING = (
    "driving",
    "entry",
    "exit",
    "onramp",
    "offramp",
    "connectingramp",
    "bidirectional",
    "mwyentry",
    "mwyexit",
    "slipLane",
    "bus",
    "taxi",
    "hov",
)
LANE_TYPES: dict[str, LaneType] = {
    **{t.lower(): "driving" for t in _DRIVING},
    "biking": "bicycle",
    "sidewalk": "sidewalk",
    "walking": "sidewalk",
    "parking": "parking",
}
"""OpenDRIVE lane type (lower case) -> our lane type; other types are not written."""
_NOT_FOR_USERS = frozenset(
    t.lower()
    for t in (
        "shoulder",
        "border",
        "median",
        "curb",
        "restricted",
        "none",
        "stop",
        "roadWorks",
        "tram",
        "rail",
        "special1",
        "special2",
        "special3",
    )
)
_BOTH_WAYS = frozenset({"sidewalk", "walking", "bidirectional"})


# ----------------------------------------------------------------------------------------------
# The parsed file
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Cubic:
    """A piecewise cubic ``a + b ds + c ds^2 + d ds^3``, ``ds = s - start`` of the last
    record starting at or before s; before the first record: `before`."""

    starts: FloatArray
    coef: FloatArray  # (n, 4)
    before: Literal["zero", "first"] = "zero"

    def __call__(self, s: FloatArray) -> FloatArray:
        if len(self.starts) == 0:
            return np.zeros_like(s)
        idx = np.searchsorted(self.starts, s, side="right") - 1
        early = idx < 0
        idx = np.clip(idx, 0, None)
        ds = s - self.starts[idx]
        a, b, c, d = (self.coef[idx, k] for k in range(4))
        out: FloatArray = a + ds * (b + ds * (c + ds * d))
        if np.any(early):
            out[early] = 0.0 if self.before == "zero" else self.coef[0, 0]
        return out


@dataclass
class _Geometry:
    s: float
    x: float
    y: float
    hdg: float
    length: float
    kind: str
    p: dict[str, float]
    normalized: bool = False
    _table: tuple[FloatArray, FloatArray] | None = field(default=None, repr=False)

    def evaluate(self, ds: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Inertial x, y and heading at arc length ds (clipped to [0, length])."""
        ds = np.clip(ds, 0.0, self.length)
        u, v, h = self._local(ds)
        ch, sh = math.cos(self.hdg), math.sin(self.hdg)
        return self.x + ch * u - sh * v, self.y + sh * u + ch * v, self.hdg + h

    def _local(self, ds: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        p = self.p
        if self.kind == "line":
            return ds, np.zeros_like(ds), np.zeros_like(ds)
        if self.kind == "arc":
            return _arc(p["curvature"], ds)
        if self.kind == "spiral":
            return _spiral(p["curvStart"], p["curvEnd"], self.length, ds)
        s_tab, q_tab = self._arc_table()
        q = np.interp(ds, s_tab, q_tab)
        if self.kind == "poly3":
            v = p["a"] + q * (p["b"] + q * (p["c"] + q * p["d"]))
            dv = p["b"] + q * (2.0 * p["c"] + 3.0 * q * p["d"])
            return q, v, np.arctan(dv)
        u = p["aU"] + q * (p["bU"] + q * (p["cU"] + q * p["dU"]))
        v = p["aV"] + q * (p["bV"] + q * (p["cV"] + q * p["dV"]))
        du, dv = self._derivatives(q)
        return u, v, np.arctan2(dv, du)

    def _derivatives(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        p = self.p
        if self.kind == "poly3":
            return np.ones_like(q), p["b"] + q * (2.0 * p["c"] + 3.0 * q * p["d"])
        du = p["bU"] + q * (2.0 * p["cU"] + 3.0 * q * p["dU"])
        dv = p["bV"] + q * (2.0 * p["cV"] + 3.0 * q * p["dV"])
        return du, dv

    def _arc_table(self) -> tuple[FloatArray, FloatArray]:
        """(arc length, curve parameter) on a fine grid: poly3 u in [0, length] (its arc
        length reaches `length` at or before u = length), paramPoly3 p over its range with
        the arc length scaled to end at `length`."""
        if self._table is None:
            q_end = 1.0 if (self.kind == "paramPoly3" and self.normalized) else self.length
            n = max(101, math.ceil(self.length / _TABLE_STEP) + 1)
            q = np.linspace(0.0, q_end, n)
            du, dv = self._derivatives(q)
            speed = np.hypot(du, dv)
            arc = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(q))])
            if self.kind == "paramPoly3" and arc[-1] > 0.0:
                arc = arc * (self.length / arc[-1])
            self._table = (arc, q)
        return self._table


def _arc(k: float, ds: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    h = k * ds
    chord = ds * np.sinc(h / (2.0 * math.pi))  # 2 sin(k ds / 2) / k
    return chord * np.cos(h / 2.0), chord * np.sin(h / 2.0), h


def _spiral(
    k0: float, k1: float, length: float, ds: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    if length <= 0.0 or k1 == k0:
        return _arc(k0, ds)
    c = (k1 - k0) / length
    a = math.sqrt(math.pi / abs(c))
    t0 = k0 / c
    if max(abs(t0), abs(t0 + length)) / a > _FRESNEL_MAX:
        return _arc(0.5 * (k0 + k1), ds)
    s_all, c_all = fresnel((t0 + ds) / a)
    s0, c0 = fresnel(t0 / a)
    x = a * (c_all - c0)
    y = math.copysign(a, c) * (s_all - s0)
    phi0 = 0.5 * c * t0 * t0
    cp, sp = math.cos(phi0), math.sin(phi0)
    h = ds * (k0 + 0.5 * c * ds)
    return cp * x + sp * y, -sp * x + cp * y, h


class _PlanView:
    """A road's reference line: the chain of its geometries."""

    def __init__(self, geometries: Sequence[_Geometry]) -> None:
        self.geometries = list(geometries)
        self.starts = np.array([g.s for g in self.geometries])
        last = self.geometries[-1]
        self.end = last.s + last.length

    def evaluate(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Inertial x, y and heading of the reference line at stations s."""
        idx = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, None)
        x, y, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
        for i in np.unique(idx):
            sel = idx == i
            g = self.geometries[int(i)]
            x[sel], y[sel], h[sel] = g.evaluate(s[sel] - g.s)
        return x, y, h


@dataclass
class _Lane:
    id: int
    side: Side
    type: str
    width: _Cubic | None  # None: the lane has border records instead
    border: _Cubic | None
    direction: str | None
    successors: tuple[int, ...]
    predecessors: tuple[int, ...]


@dataclass
class _Section:
    index: int
    s0: float
    s1: float
    lanes: list[_Lane]  # left to right: left lanes by falling id, then right lanes
    single_side: bool = False


@dataclass(frozen=True)
class _Link:
    kind: str  # "road" | "junction"
    id: str
    contact: str | None


@dataclass
class _Road:
    id: str
    junction: str
    rule: str
    plan: _PlanView
    lane_offset: _Cubic
    sections: list[_Section]
    predecessor: _Link | None
    successor: _Link | None


@dataclass(frozen=True)
class _Connection:
    incoming: str
    connecting: str
    contact: str
    lane_links: tuple[tuple[int, int], ...]


# ----------------------------------------------------------------------------------------------
# Parsing
# ----------------------------------------------------------------------------------------------


class _Parser:
    """Reads the XML tree into roads and junctions; errors name the road."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, problem: str) -> MapError:
        return MapError(f"{self.source}: {where}: {problem}")

    def num(self, el: Any, attr: str, where: str, default: float | None = None) -> float:
        raw = el.get(attr)
        if raw is None:
            if default is None:
                raise self.fail(where, f"<{el.tag}> has no attribute {attr!r}; add it")
            return default
        try:
            value = float(raw)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise self.fail(where, f"<{el.tag}> attribute {attr}={raw!r} is not a finite number")
        return value

    def integer(self, el: Any, attr: str, where: str) -> int:
        raw = el.get(attr)
        try:
            return int(str(raw).strip())
        except ValueError:
            raise self.fail(
                where, f"<{el.tag}> attribute {attr}={raw!r} is not an integer"
            ) from None

    def cubic(
        self, els: Iterable[Any], key: str, where: str, base: float, before: str
    ) -> _Cubic | None:
        records = sorted(
            (
                (
                    base + self.num(el, key, where, 0.0),
                    [self.num(el, c, where, 0.0) for c in "abcd"],
                )
                for el in els
            ),
            key=lambda r: r[0],
        )
        if not records:
            return None
        return _Cubic(
            np.array([r[0] for r in records]),
            np.array([r[1] for r in records], dtype=np.float64),
            cast(Literal["zero", "first"], before),
        )

    def geometry(self, el: Any, where: str) -> _Geometry | None:
        at = f"{where} geometry s={el.get('s')}"
        s = self.num(el, "s", at)
        x, y, hdg = self.num(el, "x", at), self.num(el, "y", at), self.num(el, "hdg", at)
        length = self.num(el, "length", at)
        if length < 0.0:
            raise self.fail(at, f"negative length {length}")
        kinds = [c for c in el if isinstance(c.tag, str)]
        if len(kinds) != 1:
            raise self.fail(at, "needs exactly one of line, arc, spiral, poly3, paramPoly3")
        k = kinds[0]
        names = {
            "line": (),
            "arc": ("curvature",),
            "spiral": ("curvStart", "curvEnd"),
            "poly3": ("a", "b", "c", "d"),
            "paramPoly3": ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV"),
        }
        if k.tag not in names:
            raise self.fail(
                at, f"unknown geometry <{k.tag}> (expected line, arc, spiral, poly3, paramPoly3)"
            )
        params = {n: self.num(k, n, at) for n in names[k.tag]}
        p_range = k.get("pRange", "arcLength")
        if k.tag == "paramPoly3" and p_range not in ("arcLength", "normalized"):
            raise self.fail(at, f"paramPoly3 pRange={p_range!r} (expected arcLength or normalized)")
        if length == 0.0:
            return None
        return _Geometry(s, x, y, hdg, length, k.tag, params, p_range == "normalized")

    def link(self, el: Any | None, where: str) -> _Link | None:
        if el is None:
            return None
        kind = el.get("elementType", "road")
        ident = el.get("elementId")
        if ident is None:
            raise self.fail(where, f"<{el.tag}> has no elementId")
        return _Link(kind, str(ident), el.get("contactPoint"))

    def lane(self, el: Any, side: Side, s0: float, where: str) -> _Lane:
        lid = self.integer(el, "id", where)
        at = f"{where} lane {lid}"
        widths = self.cubic(el.iterchildren("width"), "sOffset", at, s0, "first")
        borders = self.cubic(el.iterchildren("border"), "sOffset", at, s0, "first")
        link = el.find("link")
        succ: list[int] = []
        pred: list[int] = []
        if link is not None:
            succ = [self.integer(e, "id", at) for e in link.iterchildren("successor")]
            pred = [self.integer(e, "id", at) for e in link.iterchildren("predecessor")]
        return _Lane(
            lid,
            side,
            str(el.get("type", "none")),
            widths if widths is not None or borders is None else None,
            borders if widths is None else None,
            el.get("direction"),
            tuple(succ),
            tuple(pred),
        )

    def road(self, el: Any) -> _Road:
        rid = str(el.get("id"))
        where = f"road {rid}"
        plan_el = el.find("planView")
        if plan_el is None:
            raise self.fail(where, "has no <planView> (its reference line); add one")
        geoms = [self.geometry(g, where) for g in plan_el.iterchildren("geometry")]
        usable = sorted((g for g in geoms if g is not None), key=lambda g: g.s)
        if not usable:
            raise self.fail(where, "<planView> has no geometry of positive length")
        plan = _PlanView(usable)
        lanes_el = el.find("lanes")
        if lanes_el is None:
            raise self.fail(where, "has no <lanes>; add them")
        rule = el.get("rule", "RHT")
        if rule not in ("RHT", "LHT"):
            raise self.fail(where, f"rule={rule!r} (expected RHT or LHT)")
        offset = self.cubic(lanes_el.iterchildren("laneOffset"), "s", where, 0.0, "zero")
        sec_els = list(lanes_el.iterchildren("laneSection"))
        if not sec_els:
            raise self.fail(where, "<lanes> has no <laneSection>")
        starts = [self.num(sec, "s", where) for sec in sec_els]
        order = sorted(range(len(sec_els)), key=lambda i: starts[i])
        sections = []
        for k, i in enumerate(order):
            s0 = starts[i]
            s1 = starts[order[k + 1]] if k + 1 < len(order) else plan.end
            sec_where = f"{where} laneSection s={s0:g}"
            lanes: list[_Lane] = []
            for side in ("left", "right"):
                box = sec_els[i].find(side)
                if box is None:
                    continue
                found = [self.lane(ln, side, s0, sec_where) for ln in box.iterchildren("lane")]
                lanes += sorted(found, key=lambda ln: -ln.id)
            single = str(sec_els[i].get("singleSide", "false")).lower() == "true"
            sections.append(_Section(k, s0, min(s1, plan.end), lanes, single))
        link_el = el.find("link")
        pred = succ = None
        if link_el is not None:
            pred = self.link(link_el.find("predecessor"), where)
            succ = self.link(link_el.find("successor"), where)
        return _Road(
            rid,
            str(el.get("junction", "-1")),
            rule,
            plan,
            offset if offset is not None else _Cubic(np.empty(0), np.empty((0, 4))),
            sections,
            pred,
            succ,
        )

    def junction(self, el: Any) -> list[_Connection]:
        where = f"junction {el.get('id')}"
        out = []
        for c in el.iterchildren("connection"):
            # a direct junction (1.7) links the incoming road straight to its linkedRoad
            inc, con = c.get("incomingRoad"), c.get("connectingRoad", c.get("linkedRoad"))
            if inc is None or con is None:
                raise self.fail(
                    where, "a <connection> lacks incomingRoad or connectingRoad (linkedRoad)"
                )
            links = tuple(
                (self.integer(ll, "from", where), self.integer(ll, "to", where))
                for ll in c.iterchildren("laneLink")
            )
            out.append(_Connection(str(inc), str(con), c.get("contactPoint", "start"), links))
        return out


def _read_tree(path: Path, source: str) -> Any:
    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, remove_comments=True, remove_pis=True
    )
    try:
        root = etree.parse(str(path), parser).getroot()
    except OSError as exc:
        raise MapError(f"{source}: cannot read the OpenDRIVE file: {exc}") from exc
    except etree.XMLSyntaxError as exc:
        line = exc.position[0] if exc.position else "?"
        raise MapError(f"{source}: not valid XML at line {line}: {exc.msg}") from exc
    for el in root.iter():
        if isinstance(el.tag, str) and el.tag.startswith("{"):
            el.tag = el.tag.split("}", 1)[1]  # OpenDRIVE 1.8 files may carry a namespace
    if root.tag != "OpenDRIVE":
        raise MapError(f"{source}: the root element is <{root.tag}>, not <OpenDRIVE>")
    return root


# ----------------------------------------------------------------------------------------------
# Georeference
# ----------------------------------------------------------------------------------------------


def _to_lonlat(
    root: Any, origin: tuple[float, float] | None, source: str
) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """The function from inertial x, y to (n, 2) lon/lat."""
    header = root.find("header")
    if origin is not None:
        lat, lon = (float(v) for v in origin)
        if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) < 85 and abs(lon) <= 180):
            raise MapError(f"{source}: origin ({lat}, {lon}) is not a LAT,LON position")
        crs = pyproj.CRS.from_proj4(
            f"+proj=tmerc +lat_0={lat!r} +lon_0={lon!r} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 "
            "+units=m +no_defs"
        )
        rot, dx, dy = 0.0, 0.0, 0.0
    else:
        geo = header.find("geoReference") if header is not None else None
        text = " ".join((geo.text or "").split()) if geo is not None else ""
        if not text:
            raise MapError(
                f"{source}: the header has no <geoReference>, so the map's place on Earth "
                "is unknown; give its local origin with --origin LAT,LON "
                "(origin=(lat, lon) in Python)"
            )
        if text.startswith("+") or "+proj=" in text:
            drop = ("+geoidgrids=", "+vunits=", "+vto_meter=", "+geoid_crs=")
            text = " ".join(w for w in text.split() if not w.startswith(drop))
        try:
            crs = pyproj.CRS.from_user_input(text)
        except pyproj.exceptions.CRSError as exc:
            raise MapError(
                f"{source}: header <geoReference> {text!r} is not a usable projection "
                f"({exc}); fix it or give --origin LAT,LON"
            ) from exc
        if crs.is_geographic:
            raise MapError(
                f"{source}: header <geoReference> {text!r} is geographic (degrees), but "
                "OpenDRIVE x/y are metres; give --origin LAT,LON instead"
            )
        off = header.find("offset")
        rot = dx = dy = 0.0
        if off is not None:
            p = _Parser(source)
            dx = p.num(off, "x", "header offset", 0.0)
            dy = p.num(off, "y", "header offset", 0.0)
            rot = p.num(off, "hdg", "header offset", 0.0)
    transformer = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    cr, sr = math.cos(rot), math.sin(rot)

    def convert(x: FloatArray, y: FloatArray) -> FloatArray:
        wx, wy = dx + cr * x - sr * y, dy + sr * x + cr * y
        lon, lat = transformer.transform(wx, wy)
        out = np.column_stack([np.asarray(lon, dtype=np.float64), np.asarray(lat)])
        if not np.all(np.isfinite(out)) or np.any(np.abs(out[:, 1]) > 90.0):
            raise MapError(
                f"{source}: the geoReference puts the map outside the Earth (x/y cannot be "
                "projected); check it or give --origin LAT,LON"
            )
        return out

    return convert


# ----------------------------------------------------------------------------------------------
# Road elements
# ----------------------------------------------------------------------------------------------


@dataclass
class _Group:
    """One road element: written lanes side by side over one piece of a laneSection."""

    segment: str
    lanes: frozenset[int]
    drafts: list[LaneDraft]
    successors: set[str] = field(default_factory=set)


@dataclass
class _SectionOut:
    pieces: list[list[_Group]]


def _direction(lane: _Lane, rule: str) -> Direction:
    if lane.type.lower() in _BOTH_WAYS or lane.direction == "both":
        return "both"
    forward = (lane.side == "right") == (rule == "RHT")
    if lane.direction == "reversed":
        forward = not forward
    return "forward" if forward else "backward"


def _pieces(widths: FloatArray, heading: FloatArray) -> list[tuple[int, int]]:
    """Station index ranges [i, j] (consecutive ones share a station): the section cut
    into equal shares of its turning, each at most MAX_TURN_DEG, and each of those where
    a row of `widths` would vary more than WIDTH_RANGE.

    Why the turning: the loader's frame finds a point's piece of the reference by
    bisection over the vertex normals, which fails beyond 180 degrees (and earlier for
    a long straight followed by a bend: `_frame_reads` checks each element)."""
    n = widths.shape[1]
    turn = np.abs((np.diff(heading) + math.pi) % (2.0 * math.pi) - math.pi)
    cum = np.concatenate([[0.0], np.cumsum(turn)])
    limit = math.radians(MAX_TURN_DEG)
    if cum[-1] > limit:  # cuts fall on stations: leave room for one station's turn
        limit = max(limit - float(turn.max()), 0.5 * limit)
    shares = max(1, math.ceil(cum[-1] / limit - 1e-9))
    cuts = [0]
    for k in range(1, shares):
        c = int(np.searchsorted(cum, cum[-1] * k / shares))
        if cuts[-1] < c < n - 1:
            cuts.append(c)
    cuts.append(n - 1)
    out = []
    for a, b in itertools.pairwise(cuts):
        out += _width_pieces(widths, a, b)
    return out


def _frame_reads(x: FloatArray, y: FloatArray, t: FloatArray) -> bool:
    """Whether the loader's frame, built on the first row's centre line, puts every vertex
    of the other rows at its own station range and lateral offset (``t[0] - t[k]``,
    within 0.5 m), as the loader's side-by-side check needs."""
    try:
        frame = Frame(np.column_stack([x[0], y[0]]))
    except MapError:
        return False
    slack = _COVER_SAFETY * cover_tolerance(frame.length)
    for k in range(1, len(x)):
        sd = frame.frame_array(np.column_stack([x[k], y[k]]))
        if (
            float(np.max(np.abs(sd[:, 1] - (t[0] - t[k])))) > 0.5
            or float(sd[:, 0].min()) < -slack
            or float(sd[:, 0].max()) > frame.length + slack
            or np.any(np.diff(sd[:, 0]) <= 0.0)
        ):
            return False
    return True


def _width_pieces(widths: FloatArray, a: int, b: int) -> list[tuple[int, int]]:
    """[a, b] cut greedily where a row of `widths` would vary more than WIDTH_RANGE."""
    block = widths[:, a : b + 1]
    if block.shape[0] == 0 or np.all(np.ptp(block, axis=1) <= WIDTH_RANGE):
        return [(a, b)]
    out = []
    i = a
    lo, hi = widths[:, a].copy(), widths[:, a].copy()
    for j in range(a + 1, b + 1):
        lo, hi = np.minimum(lo, widths[:, j]), np.maximum(hi, widths[:, j])
        if np.any(hi - lo > WIDTH_RANGE) and j - 1 > i:
            out.append((i, j - 1))
            i = j - 1
            lo = np.minimum(widths[:, i], widths[:, j])
            hi = np.maximum(widths[:, i], widths[:, j])
    out.append((i, b))
    return out


class _Builder:
    def __init__(
        self,
        roads: dict[str, _Road],
        junctions: dict[str, list[_Connection]],
        to_lonlat: Callable[[FloatArray, FloatArray], FloatArray],
        step: float,
        report: ImportReport,
    ) -> None:
        self.roads = roads
        self.junctions = junctions
        self.to_lonlat = to_lonlat
        self.step = step
        self.report = report
        self.out: dict[str, list[_SectionOut]] = {}

    # -- one laneSection ----------------------------------------------------------------------

    def section(self, road: _Road, sec: _Section) -> _SectionOut:
        where = f"road {road.id} laneSection s={sec.s0:g}"
        length = sec.s1 - sec.s0
        if length < MIN_SECTION:
            self.report.skip(f"laneSection shorter than {MIN_SECTION} m", where)
            return _SectionOut([])
        n = max(2, math.ceil(length / self.step) + 1)
        s = np.linspace(sec.s0, sec.s1, n)
        x, y, h = road.plan.evaluate(s)
        offset = road.lane_offset(s)
        widths = np.zeros((len(sec.lanes), n))
        centres = np.zeros((len(sec.lanes), n))
        for side, sign in (("left", 1.0), ("right", -1.0)):
            inner = offset
            idx = [i for i, ln in enumerate(sec.lanes) if ln.side == side]
            for i in sorted(idx, key=lambda i: abs(sec.lanes[i].id)):
                lane = sec.lanes[i]
                if lane.width is not None:
                    w = np.maximum(lane.width(s), 0.0)
                    outer = inner + sign * w
                elif lane.border is not None:
                    outer = lane.border(s)
                    w = np.maximum(sign * (outer - inner), 0.0)
                else:
                    w = np.zeros(n)
                    outer = inner
                widths[i], centres[i] = w, 0.5 * (inner + outer)
                inner = outer

        if sec.single_side:
            self.report.skip(
                "singleSide laneSection (read as a full section: the other side is missing)", where
            )
        # curvature of the reference; a lane whose centre is at t >= 1 / curvature on the
        # inside of a curve folds back on itself
        curvature = np.gradient(np.unwrap(h), s)
        written: list[int] = []
        for i, lane in enumerate(sec.lanes):
            at = f"{where} lane {lane.id}"
            t = lane.type.lower()
            if t not in LANE_TYPES:
                kind = "not a lane for road users" if t in _NOT_FOR_USERS else "unknown type"
                self.report.skip(f"lane of type {lane.type!r} ({kind}; its width is kept)", at)
            elif float(widths[i].max()) <= 1e-6:
                self.report.skip("lane of zero width", at)
            elif float(np.max(centres[i] * curvature)) >= FOLD:
                self.report.skip(
                    "lane inside a curve tighter than its distance from the reference", at
                )
            else:
                written.append(i)

        cx, cy = x - centres * np.sin(h), y + centres * np.cos(h)
        turn = np.abs((np.diff(h) + math.pi) % (2.0 * math.pi) - math.pi)

        def layout(a: int, b: int) -> tuple[dict[int, float], list[list[int]]]:
            """Mean widths over stations a..b, and the written lanes that run side by side
            there, in groups from the left."""
            sl = slice(a, b + 1)
            span = float(s[b] - s[a])
            ds = np.diff(s[sl])
            mean = {
                i: float(np.sum(0.5 * (widths[i, a:b] + widths[i, a + 1 : b + 1]) * ds) / span)
                if span > 0
                else 0.0
                for i in written
            }
            groups: list[list[int]] = []
            for i in (i for i in written if mean[i] >= MIN_WIDTH):
                if groups:
                    k = groups[-1][-1]
                    gap = centres[k, sl] - centres[i, sl]
                    expected = 0.5 * (mean[k] + mean[i])
                    tol = gap_tolerance(expected)
                    if float(np.max(np.abs(gap - expected))) <= GAP_SAFETY * tol:
                        groups[-1].append(i)
                        continue
                groups.append([i])
            return mean, groups

        def settle(a: int, b: int) -> list[tuple[int, int, dict[int, float], list[list[int]]]]:
            """Stations a..b as road elements, halved at the middle of their turning
            until the loader's frame reads every lane right."""
            mean, groups = layout(a, b)
            sl = slice(a, b + 1)
            if b - a < 2 or all(
                _frame_reads(cx[g, sl], cy[g, sl], centres[g, sl]) for g in groups if len(g) > 1
            ):
                return [(a, b, mean, groups)]
            cum = np.cumsum(turn[a:b])
            m = a + 1 + int(np.searchsorted(cum, 0.5 * cum[-1])) if cum[-1] > 0 else (a + b) // 2
            m = min(max(m, a + 1), b - 1)
            return settle(a, m) + settle(m, b)

        ranges = [p for a, b in _pieces(widths[written], h) for p in settle(a, b)]
        pieces: list[list[_Group]] = []
        for i in written:
            if any(mean[i] < MIN_WIDTH for _, _, mean, _ in ranges):
                self.report.skip(
                    f"lane narrower than {MIN_WIDTH} m over part of its laneSection "
                    "(left out there)",
                    f"{where} lane {sec.lanes[i].id}",
                )
        for j, (a, b, mean, groups) in enumerate(ranges):
            sl = slice(a, b + 1)
            base = f"road{road.id}-s{sec.index}" + (f".{j}" if len(ranges) > 1 else "")
            origin = f"road {road.id} laneSection s={sec.s0:g}" + (
                f" (s={s[a]:.1f}..{s[b]:.1f})" if len(ranges) > 1 else ""
            )
            out: list[_Group] = []
            for g, members in enumerate(groups):
                seg = base + (_letter(g) if len(groups) > 1 else "")
                drafts = [
                    self.draft(
                        road,
                        sec,
                        seg,
                        origin,
                        k,
                        sec.lanes[i],
                        centres[i, sl],
                        widths[i, sl],
                        mean[i],
                        x[sl],
                        y[sl],
                        h[sl],
                    )
                    for k, i in enumerate(members)
                ]
                out.append(_Group(seg, frozenset(sec.lanes[i].id for i in members), drafts))
            pieces.append(out)
        return _SectionOut(pieces)

    def draft(
        self,
        road: _Road,
        sec: _Section,
        segment: str,
        origin: str,
        index: int,
        lane: _Lane,
        t: FloatArray,
        w: FloatArray,
        mean: float,
        x: FloatArray,
        y: FloatArray,
        h: FloatArray,
    ) -> LaneDraft:
        cx, cy = x - t * np.sin(h), y + t * np.cos(h)
        props: dict[str, Any] = {
            "opendrive_road": road.id,
            "opendrive_section": sec.index,
            "opendrive_lane": lane.id,
            "opendrive_type": lane.type,
        }
        if road.junction != "-1":
            props["opendrive_junction"] = road.junction
        lo, hi = float(w.min()), float(w.max())
        if hi - lo > 0.01:
            props["opendrive_width_range"] = [round(lo, 3), round(hi, 3)]
        return LaneDraft(
            segment=segment,
            index=index,
            type=LANE_TYPES[lane.type.lower()],
            width=mean,
            direction=_direction(lane, road.rule),
            lonlat=self.to_lonlat(cx, cy),
            origin=origin,
            properties=props,
        )

    # -- successors ---------------------------------------------------------------------------

    def link_all(self) -> None:
        for road in self.roads.values():
            secs = [p for so in self.out[road.id] for p in so.pieces if p]
            for here, there in itertools.pairwise(secs):
                _connect(here, there, self.section_lane_map(road, here, there))
        heads: set[tuple[tuple[str, str], tuple[str, str]]] = set()
        edges: dict[tuple[str, str], dict[int, set[int]]] = {}

        def edge(src: str, dst: str, pairs: Iterable[tuple[int, int]]) -> None:
            m = edges.setdefault((src, dst), {})
            for a, b in pairs:
                m.setdefault(a, set()).add(b)

        def head_on(a: str, a_end: str, b: str, b_end: str) -> None:
            x, y = sorted([(a, a_end), (b, b_end)])
            heads.add((x, y))

        for road in self.roads.values():
            first, last = road.sections[0], road.sections[-1]
            for which, link in (("successor", road.successor), ("predecessor", road.predecessor)):
                if link is None:
                    continue
                where = f"road {road.id} {which} {link.kind} {link.id}"
                mine = "end" if which == "successor" else "start"
                if link.kind == "junction":
                    conns = self.junctions.get(link.id)
                    if conns is None:
                        self.report.skip("road link to a missing road or junction", where)
                        continue
                    for c in conns:
                        if c.incoming != road.id or c.connecting not in self.roads:
                            continue
                        if mine == "end" and c.contact == "start":
                            edge(road.id, c.connecting, c.lane_links)
                        elif mine == "start" and c.contact == "end":
                            edge(c.connecting, road.id, ((b, a) for a, b in c.lane_links))
                        else:
                            head_on(road.id, mine, c.connecting, c.contact)
                    continue
                other = self.roads.get(link.id)
                if other is None:
                    self.report.skip("road link to a missing road or junction", where)
                    continue
                theirs = link.contact or ("start" if which == "successor" else "end")
                if mine == "end" and theirs == "start":
                    edge(
                        road.id, other.id, ((ln.id, t) for ln in last.lanes for t in ln.successors)
                    )
                elif mine == "start" and theirs == "end":
                    edge(
                        other.id,
                        road.id,
                        ((f, ln.id) for ln in first.lanes for f in ln.predecessors),
                    )
                else:
                    head_on(road.id, mine, other.id, theirs)
        for (src, dst), lane_map in edges.items():
            a_secs = [p for so in self.out[src] for p in so.pieces if p]
            b_secs = [p for so in self.out[dst] for p in so.pieces if p]
            if a_secs and b_secs:
                _connect(a_secs[-1], b_secs[0], lane_map or None)
        for (a, ea), (b, eb) in sorted(heads):
            self.report.skip(
                "road link where the reference lines meet head-on (no successor written)",
                f"road {a} {ea} - road {b} {eb}",
            )

    def section_lane_map(
        self, road: _Road, a: list[_Group], b: list[_Group]
    ) -> dict[int, set[int]] | None:
        """Lane links from piece a to the following piece b of the same road: identity
        within a section, the lanes' links across sections (identity if there are none)."""
        sec_a = self.section_of(road, a)
        sec_b = self.section_of(road, b)
        if sec_a is sec_b:
            return {ln.id: {ln.id} for ln in sec_a.lanes}
        m: dict[int, set[int]] = {}
        for ln in sec_a.lanes:
            for t in ln.successors:
                m.setdefault(ln.id, set()).add(t)
        for ln in sec_b.lanes:
            for f in ln.predecessors:
                m.setdefault(f, set()).add(ln.id)
        return m or {ln.id: {ln.id} for ln in sec_a.lanes}

    def section_of(self, road: _Road, piece: list[_Group]) -> _Section:
        for sec, so in zip(road.sections, self.out[road.id], strict=True):
            if any(p is piece for p in so.pieces):
                return sec
        raise AssertionError("piece not found")  # pragma: no cover

    def drafts(self) -> list[LaneDraft]:
        out = []
        for road_out in self.out.values():
            for so in road_out:
                for piece in so.pieces:
                    for g in piece:
                        for d in g.drafts:
                            d.successors = tuple(sorted(g.successors))
                            out.append(d)
        return out


def _letter(g: int) -> str:
    return chr(ord("a") + g) if g < 26 else f"-{g}"


def _connect(a: list[_Group], b: list[_Group], lane_map: dict[int, set[int]] | None) -> None:
    """Make the groups of piece b successors of those of piece a: all of them when either
    side is one group or nothing is known of the lanes, else where a lane link joins them."""
    for g in a:
        for k in b:
            if (
                len(a) == 1
                or len(b) == 1
                or lane_map is None
                or any(lane_map.get(ln, set()) & k.lanes for ln in g.lanes)
            ):
                g.successors.add(k.segment)


# ----------------------------------------------------------------------------------------------
# Entry point
# ----------------------------------------------------------------------------------------------


def import_opendrive(
    path: str | Path, origin: tuple[float, float] | None = None, step: float = 1.0
) -> ImportResult:
    """Import an OpenDRIVE ``.xodr`` file (see the module docstring for the mapping).

    `origin` is (latitude, longitude) of the inertial origin, needed when the file has
    no ``geoReference`` (it then overrides it); `step` is the station spacing of the
    lane centre lines in metres. Raises `MapError` naming the road (and laneSection) on
    a file it cannot read.
    """
    p = Path(path)
    source = str(p)
    step = float(step)
    if not (math.isfinite(step) and step > 0.0):
        raise ValueError(f"step must be a positive number of metres, got {step}")
    root = _read_tree(p, source)
    to_lonlat = _to_lonlat(root, origin, source)
    parser = _Parser(source)
    report = ImportReport(source)
    roads: dict[str, _Road] = {}
    for el in root.iterchildren("road"):
        road = parser.road(el)
        if road.id in roads:
            raise MapError(f"{source}: road {road.id}: the id is used by two roads")
        roads[road.id] = road
        for kind, tag in (("road object", "objects/object"), ("signal", "signals/signal")):
            found = el.findall(tag)
            if found:
                report.skip(f"{kind} (not imported)", f"road {road.id}", len(found))
    if not roads:
        raise MapError(f"{source}: the file has no <road>")
    junctions = {str(j.get("id")): parser.junction(j) for j in root.iterchildren("junction")}
    builder = _Builder(roads, junctions, to_lonlat, step, report)
    for road in roads.values():
        builder.out[road.id] = [builder.section(road, sec) for sec in road.sections]
    builder.link_all()
    drafts = builder.drafts()
    if not drafts:
        raise no_lanes(source, report)
    return finish(drafts, report)
