"""OpenStreetMap ways with lane tags into the GeoJSON lane-map format.

Reading. ``osmium`` (pyosmium) reads ``.osm`` XML and ``.osm.pbf`` with a node-location
cache, so every way comes with the coordinates of its nodes. Only ``highway=*`` ways
are used; which classes are imported, and every default, is in
:mod:`laas.map.importers.osm_defaults` (documented in ``docs/maps/osm.md``).

Lanes from tags (:func:`lane_layout`). The lanes of a way are built outwards from its
*core*, the driving lanes of a road (the one lane of a cycleway or footway):

- driving lanes from ``lanes``, ``lanes:forward``, ``lanes:backward``,
  ``lanes:both_ways`` and ``oneway`` (yes/1/true, -1/reverse, no; implied on motorways
  and roundabouts). Right-hand traffic: backward lanes left of the forward ones, looking
  along the way's node order (``driving_side=left`` on the way mirrors this).
  ``oneway=-1`` keeps the node order and makes the driving lanes ``backward``;
- ``busway`` (lane on a side): the outermost driving lane of that side becomes a bus
  lane (property ``bus_lane``) when the lane count was tagged (OSM counts bus lanes in
  ``lanes``), otherwise a bus lane is added there;
- then, on each side from the core outwards: a bicycle lane (``cycleway*=lane``),
  parking (``parking:lane:*`` or ``parking:*`` with an orientation), a bicycle track
  (``cycleway*=track``), a sidewalk (``sidewalk*``).

Lane 0 is the leftmost lane looking along the node order. A two-way road with
``sidewalk=both`` and ``cycleway=lane`` is, left to right: sidewalk (both), bicycle
(backward), driving (backward), driving (forward), bicycle (forward), sidewalk (both).

Across the road. The way's line is taken to be the middle of the core: with core width
``C`` its left edge is at ``d = -C/2`` (``d`` positive to the right); the lanes are laid
edge to edge from there, each lane's centre at ``d_k = -C/2 + sum(w_j, j < k in the core)
+ w_k/2``, and the side lanes continue outwards from ``-C/2`` and ``+C/2``. A ``width``
tag is the carriageway (driving lanes, bicycle lanes, parking): the driving lanes share
what the others leave (a two-way street without lane tags too narrow for two lanes gets
one lane for both directions).

Geometry. Ways are cut where a node is shared with another imported way (an
intersection, or where one way ends and the next begins: in OSM the tags, and so the
lane layout, can only change there), at nodes missing from the file, at the edge of a
bounding box, and at a vertex where the line turns by more than 59 degrees (the loader
allows 60). Vertices closer than 0.5 m to the previous one are dropped. Each piece is
projected to the UTM zone of the data (:class:`laas.map.geo.UtmProjection`), every lane
centre line is the mitred parallel of the piece at ``d_k`` (shapely ``offset_curve``,
which keeps the direction), and the result is projected back to lon/lat. Pieces shorter
than 1 m are left out (counted); their neighbours are linked through them.

Road elements. Each piece is a segment ``way<id>-<k>`` (k counts pieces along the way in
node order), origin ``way <id>``, lane properties ``osm_way`` and ``highway``. Its
reference direction is the way's node order, unless the way was turned round (below;
property ``osm_reversed``). Its successors are the other pieces at the node where it
ends, whichever way they are drawn: the road elements beyond its end, as in
``laas.map.importers.lanelet2``. A piece drawn towards that node too (two ways meeting
head on) is a successor, and names this one in turn; its lanes that leave the node
carry on the traffic that arrives, so a oneway is kept to by the lanes' directions.

Orientation (:func:`_orient`). Two pieces that both start at a node cannot name each
other (nothing lies beyond either one's end there). Ways are turned round as a whole
(each piece's lanes then read right to left, directions flipped, ``_Piece.reverse``) so
that ways running on into each other point the same way, and each chain of them is
oriented to leave the fewest such pairs at the junctions at its ends; those left are
counted in the report.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import osmium
import shapely
from shapely import LineString

from laas.errors import ConfigError, MapError
from laas.map.geo import UtmProjection
from laas.map.geojson import MAX_TURN_DEG as LOADER_MAX_TURN_DEG
from laas.map.hdmap import Direction, LaneType
from laas.map.importers import osm_defaults as defaults
from laas.map.importers.common import ImportReport, ImportResult, LaneDraft, finish, no_lanes
from laas.map.importers.osm_defaults import ROAD_CLASSES, RoadClass

__all__ = ["LaneSpec", "Layout", "import_osm", "lane_layout"]

FloatArray = npt.NDArray[np.float64]
BBox = tuple[float, float, float, float]
Side = Literal["left", "right"]
_SIDES: tuple[Side, Side] = ("left", "right")

MAX_TURN_DEG = LOADER_MAX_TURN_DEG - 1.0  # split a way where it turns more sharply
MIN_VERTEX_GAP = 0.5  # m: interior vertices closer than this to the previous are dropped
MIN_PIECE_LENGTH = 1.0  # m: shorter pieces are left out (counted)

_YES = frozenset({"yes", "true", "1"})
_NO = frozenset({"no", "false", "0"})


# ----------------------------------------------------------------------------------------------
# Lane layout from tags
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LaneSpec:
    """One lane of a way's cross-section: type, width (m), direction along the node order,
    and properties kept in the map."""

    type: LaneType
    width: float
    direction: Direction
    properties: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True)
class Layout:
    """A way's lanes, left to right looking along its node order, and each lane centre's
    lateral offset from the way's line (metres, positive to the right)."""

    lanes: tuple[LaneSpec, ...]
    offsets: tuple[float, ...]

    @property
    def width(self) -> float:
        return sum(lane.width for lane in self.lanes)


class _Tags:
    """A way's tags, with the reading of numbers and words that reports what it cannot use."""

    def __init__(self, tags: Mapping[str, str], where: str, report: ImportReport | None) -> None:
        self.tags = tags
        self.where = where
        self.report = report

    def get(self, key: str) -> str | None:
        v = self.tags.get(key)
        return None if v is None else v.strip()

    def bad(self, key: str, value: str) -> None:
        """Count a value the importer does not understand; the caller uses the default."""
        if self.report is not None:
            self.report.skip(
                f"tag value not usable, default used: {key}", f"{self.where}: {key}={value!r}"
            )

    def count(self, key: str, low: int = 1) -> int | None:
        v = self.get(key)
        if v is None:
            return None
        if v.isdigit() and low <= int(v) <= defaults.MAX_LANES:
            return int(v)
        self.bad(key, v)
        return None

    def width(self, key: str, lo: float, hi: float) -> float | None:
        v = self.get(key)
        if v is None:
            return None
        w = parse_width(v)
        if w is None or not lo <= w <= hi:
            self.bad(key, v)
            return None
        return w

    def word(self, key: str, meanings: Mapping[str, str]) -> str | None:
        """The meaning of the key's value in `meanings` (None if absent or unknown)."""
        v = self.get(key)
        if v is None:
            return None
        meaning = meanings.get(v)
        if meaning is None:
            self.bad(key, v)
        return meaning


_WIDTH_M = re.compile(r"^(\d+(?:\.\d+)?)\s*(?:m)?$")
_WIDTH_FT = re.compile(r"^(\d+)\s*(?:'|ft)\s*(?:(\d+(?:\.\d+)?)\s*(?:\"|in))?$")


def parse_width(text: str) -> float | None:
    """A ``width`` value in metres: ``3``, ``3.5``, ``3.5 m``, ``12'``, ``12'6"``, ``12 ft``."""
    t = text.strip()
    m = _WIDTH_M.match(t)
    if m:
        return float(m.group(1))
    m = _WIDTH_FT.match(t)
    if m:
        return 0.3048 * float(m.group(1)) + 0.0254 * float(m.group(2) or 0.0)
    return None


_ONEWAY = {
    **dict.fromkeys(_YES, "yes"),
    **dict.fromkeys(("-1", "reverse"), "-1"),
    **dict.fromkeys(_NO, "no"),
    "reversible": "alternating",
    "alternating": "alternating",
}
_SIDEWALK = {
    "both": "both",
    "yes": "both",
    "left": "left",
    "right": "right",
    "no": "none",
    "none": "none",
    "separate": "none",
}
_SIDEWALK_SIDE = {"yes": "yes", "no": "no", "none": "no", "separate": "no"}
_CYCLEWAY = {
    "lane": "lane",
    "buffered_lane": "lane",
    "track": "track",
    "opposite_lane": "opposite_lane",
    "opposite_track": "opposite_track",
    **dict.fromkeys(
        (
            "no",
            "none",
            "separate",
            "shared_lane",
            "share_busway",
            "opposite_share_busway",
            "shoulder",
            "shared",
            "opposite",
            "crossing",
            "sidepath",
            "use_sidepath",
            "sidewalk",
        ),
        "none",
    ),
}
_SUB_ONEWAY = {
    **dict.fromkeys(_YES, "forward"),
    "-1": "backward",
    **dict.fromkeys(_NO, "both"),
}
_DIRECTIONS: dict[str, Direction] = {"forward": "forward", "backward": "backward", "both": "both"}
_PARKING_OLD = {
    "parallel": "parallel",
    "diagonal": "diagonal",
    "perpendicular": "perpendicular",
    "inline": "parallel",
    "orthogonal": "perpendicular",
    "marked": "parallel",
    "yes": "parallel",
    **dict.fromkeys(
        (
            "no",
            "none",
            "no_parking",
            "no_stopping",
            "separate",
            "drawn_separately",
            "fire_lane",
        ),
        "none",
    ),
}
_PARKING_NEW = {
    **dict.fromkeys(
        ("lane", "street_side", "on_kerb", "half_on_kerb", "shoulder", "yes"), "oriented"
    ),
    "parallel": "parallel",
    "inline": "parallel",
    "diagonal": "diagonal",
    "perpendicular": "perpendicular",
    "orthogonal": "perpendicular",
    **dict.fromkeys(("no", "none", "separate"), "none"),
}
_ORIENTATION = {"parallel": "parallel", "diagonal": "diagonal", "perpendicular": "perpendicular"}
_BUSWAY = {"lane": "lane", "opposite_lane": "opposite_lane", "no": "none", "none": "none"}
_DRIVING_SIDE = {"right": "right", "left": "left"}


def _flip(direction: Direction) -> Direction:
    return (
        "backward" if direction == "forward" else "forward" if direction == "backward" else "both"
    )


def _other(side: Side) -> Side:
    return "right" if side == "left" else "left"


@dataclass
class _Road:
    """Working state of a road's cross-section while tags are read."""

    cls: RoadClass
    travel: int  # +1 oneway along the nodes, -1 against, 0 two-way, 2 alternating
    kerb: Side  # the side forward traffic keeps to (right-hand traffic: right)
    sides: dict[str, list[LaneSpec]] = field(
        default_factory=lambda: {"left": [], "right": []}
    )  # from the core outwards

    def side_direction(self, side: Side) -> Direction:
        """Direction of traffic on a side of the way (lanes that follow the road's flow)."""
        if self.travel == 1:
            return "forward"
        if self.travel == -1:
            return "backward"
        if self.travel == 2:
            return "both"
        return "forward" if side == self.kerb else "backward"

    def travel_kerb(self) -> Side:
        """The kerb side of a oneway road's travel (the side of an unsided cycle lane)."""
        return self.kerb if self.travel != -1 else _other(self.kerb)


def lane_layout(
    tags: Mapping[str, str], where: str = "way", report: ImportReport | None = None
) -> Layout:
    """The lanes of a way from its tags (see the module docstring); values it cannot read
    are counted in `report` (naming `where`) and replaced by defaults. Raises KeyError
    for a ``highway`` value that is not imported."""
    t = _Tags(tags, where, report)
    highway = tags["highway"]
    cls = ROAD_CLASSES[highway]
    kerb: Side = "left" if t.word("driving_side", _DRIVING_SIDE) == "left" else "right"
    oneway = t.word("oneway", _ONEWAY)
    if oneway is None:
        implied = cls.oneway or tags.get("junction") in ("roundabout", "circular")
        oneway = "yes" if implied and cls.kind == "road" else "no"
    travel = {"yes": 1, "-1": -1, "no": 0, "alternating": 2}[oneway]
    road = _Road(cls, travel, kerb)

    if cls.kind == "road":
        core, explicit = _driving_lanes(t, road)
        _cycleways(t, road)
        _parking(t, road)
        carriageway_extra = sum(
            lane.width
            for side in road.sides.values()
            for lane in side
            if lane.type == "parking" or dict(lane.properties).get("cycleway") == "lane"
        )
        _scale_driving(t, core, carriageway_extra, guessed=not explicit)
    else:
        core = [_path_lane(t, road)]
    _cycle_tracks_after_parking(road)
    if cls.kind != "foot":
        _sidewalks(t, road)
    return _assemble(core, road.sides["left"], road.sides["right"])


def _driving_lanes(t: _Tags, road: _Road) -> tuple[list[LaneSpec], bool]:
    """The driving lanes, left to right, and whether their count was tagged."""
    cls = road.cls
    width = cls.width
    total = t.count("lanes")
    fwd = t.count("lanes:forward")
    bwd = t.count("lanes:backward")
    centre = t.count("lanes:both_ways", low=0) or 0
    explicit = total is not None or fwd is not None or bwd is not None
    lanes: list[LaneSpec] = []
    if road.travel != 0:
        n = (fwd if road.travel == 1 else bwd if road.travel == -1 else None) or total
        if n is None:
            n = cls.lanes
        direction = road.side_direction(road.kerb)
        lanes = [LaneSpec("driving", width, direction) for _ in range(n)]
    else:
        if total is not None and centre > total:
            # lanes = forward + backward + both_ways (the OSM wiki): no more both_ways lanes
            # than lanes; `lanes` is the one kept
            t.bad("lanes:both_ways", str(centre))
            centre = total
        if fwd is None and bwd is None:
            rest = None if total is None else total - centre
            if (rest is None and cls.single_track) or (rest is not None and rest <= 1):
                # At most one lane besides the both_ways lanes: one lane for both directions,
                # beside centre - 1 (rest = 0: the both_ways lanes are all there is) or
                # `centre` (rest = 1: lanes=2 lanes:both_ways=1 is a through lane and a turn
                # lane) centre lanes; in all `lanes`, or max(both_ways, 1) on an untagged
                # single track.
                n = total if total is not None else max(centre, 1)
                return [LaneSpec("driving", width, "both"), *_centre(n - 1, width)], explicit
            if rest is None:
                fwd = bwd = cls.lanes
            else:
                fwd = math.ceil(rest / 2)
                bwd = rest - fwd
        elif fwd is None:
            assert bwd is not None
            fwd = max(total - centre - bwd, 1) if total is not None else cls.lanes
        elif bwd is None:
            bwd = max(total - centre - fwd, 1) if total is not None else cls.lanes
        kerb_side = [LaneSpec("driving", width, "forward") for _ in range(fwd)]
        far_side = [LaneSpec("driving", width, "backward") for _ in range(bwd)]
        mid = _centre(centre, width)
        if road.kerb == "right":
            lanes = far_side + mid + kerb_side
        else:
            lanes = kerb_side[::-1] + mid + far_side
    _busways(t, road, lanes, explicit)
    return lanes, explicit


def _centre(n: int, width: float) -> list[LaneSpec]:
    """``lanes:both_ways``: centre lanes (e.g. a shared turn lane) for both directions."""
    return [LaneSpec("driving", width, "both", (("centre_lane", True),)) for _ in range(n)]


def _busways(t: _Tags, road: _Road, lanes: list[LaneSpec], explicit: bool) -> None:
    wanted: dict[Side, Direction] = {}
    unsided = t.word("busway", _BUSWAY)
    if unsided == "lane":
        for side in _SIDES if road.travel in (0, 2) else (road.travel_kerb(),):
            wanted[side] = road.side_direction(side)
    elif unsided == "opposite_lane" and road.travel in (1, -1):
        side = _other(road.travel_kerb())
        wanted[side] = _flip(road.side_direction(side))
    if t.word("busway:both", _BUSWAY) == "lane":
        wanted = {s: road.side_direction(s) for s in _SIDES}
    for side in _SIDES:
        v = t.word(f"busway:{side}", _BUSWAY)
        if v == "lane":
            wanted[side] = road.side_direction(side)
        elif v == "opposite_lane":
            wanted[side] = _flip(road.side_direction(side))
        elif v == "none":
            wanted.pop(side, None)
    bus = (("bus_lane", True),)
    for side, direction in wanted.items():
        i = 0 if side == "left" else len(lanes) - 1
        if explicit and len(lanes) > 1 and lanes[i].direction == direction:
            lanes[i] = LaneSpec("driving", lanes[i].width, direction, bus)
        else:
            new = LaneSpec("driving", road.cls.width, direction, bus)
            lanes.insert(0 if side == "left" else len(lanes), new)


def _cycleways(t: _Tags, road: _Road) -> None:
    """Bicycle lanes and tracks per side: (kind, direction); tracks go in after parking."""
    found: dict[Side, tuple[str, Direction]] = {}
    oneway_road = road.travel in (1, -1)

    def put(side: Side, value: str) -> None:
        if value == "none":
            found.pop(side, None)
        elif value in ("lane", "track"):
            found[side] = (value, road.side_direction(side))
        else:  # opposite_lane / opposite_track: against a oneway road's traffic
            found[side] = (value.removeprefix("opposite_"), _flip(road.side_direction(side)))

    unsided = t.word("cycleway", _CYCLEWAY)
    if unsided is not None:
        if not oneway_road:
            for side in _SIDES:
                put(side, unsided.removeprefix("opposite_"))
        elif unsided.startswith("opposite"):
            put(_other(road.travel_kerb()), unsided)
        else:
            put(road.travel_kerb(), unsided)
    both = t.word("cycleway:both", _CYCLEWAY)
    if both is not None:
        for side in _SIDES:
            put(side, both)
    for side in _SIDES:
        v = t.word(f"cycleway:{side}", _CYCLEWAY)
        if v is not None:
            put(side, v)
    for side, (kind, direction) in found.items():
        sub = t.word(f"cycleway:{side}:oneway", _SUB_ONEWAY) or t.word(
            "cycleway:both:oneway", _SUB_ONEWAY
        )
        if sub is not None:
            direction = _DIRECTIONS[sub]
        default = defaults.BICYCLE_LANE_WIDTH if kind == "lane" else defaults.BICYCLE_TRACK_WIDTH
        width = (
            t.width(f"cycleway:{side}:width", *defaults.PATH_WIDTH_RANGE)
            or t.width("cycleway:both:width", *defaults.PATH_WIDTH_RANGE)
            or t.width("cycleway:width", *defaults.PATH_WIDTH_RANGE)
            or default
        )
        road.sides[side].append(LaneSpec("bicycle", width, direction, (("cycleway", kind),)))


def _parking(t: _Tags, road: _Road) -> None:
    for side in _SIDES:
        orientation = None
        for key, table in (
            (f"parking:{side}", _PARKING_NEW),
            (f"parking:lane:{side}", _PARKING_OLD),
            ("parking:both", _PARKING_NEW),
            ("parking:lane:both", _PARKING_OLD),
        ):
            if t.get(key) is None:
                continue
            orientation = t.word(key, table)
            if orientation == "oriented":
                orientation = (
                    t.word(f"parking:{side}:orientation", _ORIENTATION)
                    or t.word("parking:both:orientation", _ORIENTATION)
                    or "parallel"
                )
            break
        if orientation is None or orientation == "none":
            continue
        width = defaults.PARKING_WIDTHS[orientation]
        road.sides[side].append(
            LaneSpec("parking", width, road.side_direction(side), (("parking", orientation),))
        )


def _cycle_tracks_after_parking(road: _Road) -> None:
    """Order each side from the core: bicycle lane, parking, bicycle track."""
    rank = {"lane": 0, "track": 2}

    def key(lane: LaneSpec) -> int:
        if lane.type == "parking":
            return 1
        return rank.get(str(dict(lane.properties).get("cycleway")), 3)

    for side, lanes in road.sides.items():
        road.sides[side] = sorted(lanes, key=key)


def _sidewalks(t: _Tags, road: _Road) -> None:
    on = {"left": False, "right": False}
    main = t.word("sidewalk", _SIDEWALK)
    if main is not None:
        on["left"] = main in ("both", "left")
        on["right"] = main in ("both", "right")
    both = t.word("sidewalk:both", _SIDEWALK_SIDE)
    if both is not None:
        on["left"] = on["right"] = both == "yes"
    for side in _SIDES:
        v = t.word(f"sidewalk:{side}", _SIDEWALK_SIDE)
        if v is not None:
            on[side] = v == "yes"
    for side in _SIDES:
        if on[side]:
            width = (
                t.width(f"sidewalk:{side}:width", *defaults.PATH_WIDTH_RANGE)
                or t.width("sidewalk:both:width", *defaults.PATH_WIDTH_RANGE)
                or t.width("sidewalk:width", *defaults.PATH_WIDTH_RANGE)
                or road.cls.sidewalk
            )
            road.sides[side].append(LaneSpec("sidewalk", width, "both"))


def _path_lane(t: _Tags, road: _Road) -> LaneSpec:
    """The one lane of a cycleway, footway, path or pedestrian street."""
    cls = road.cls
    width = t.width("width", *defaults.PATH_WIDTH_RANGE) or cls.width
    bicycle = cls.kind == "cycle" or (
        t.get("highway") == "path"
        and t.get("bicycle") == "designated"
        and t.get("foot") != "designated"
    )
    if not bicycle:
        return LaneSpec("sidewalk", width, "both")
    direction: Direction = (
        "forward" if road.travel == 1 else "backward" if road.travel == -1 else "both"
    )
    return LaneSpec("bicycle", width, direction)


def _scale_driving(t: _Tags, core: list[LaneSpec], extra: float, guessed: bool) -> None:
    """Fit the driving lanes to a ``width`` tag (the carriageway, with `extra` metres of
    bicycle lanes and parking in it; or, if that leaves too little, the driving lanes).
    A two-way road whose lane count was `guessed` and that is too narrow for two lanes
    becomes one lane for both directions."""
    key = "width:carriageway" if t.get("width:carriageway") is not None else "width"
    text = t.get(key)
    if text is None:
        return
    total = parse_width(text)
    lo, hi = defaults.DRIVING_WIDTH_RANGE
    n = len(core)
    for share in (None if total is None else total - extra, total):
        if share is None:
            continue
        if lo <= share / n <= hi:
            w = share / n
            core[:] = [LaneSpec(lane.type, w, lane.direction, lane.properties) for lane in core]
            return
        single = [(lane.direction, lane.properties) for lane in core] == [
            ("backward", ()),
            ("forward", ()),
        ]
        if guessed and single and lo <= share <= hi:
            core[:] = [LaneSpec("driving", share, "both")]
            return
    t.bad(key, text)


def _assemble(core: list[LaneSpec], left: list[LaneSpec], right: list[LaneSpec]) -> Layout:
    lanes = [*left[::-1], *core, *right]
    core_width = sum(lane.width for lane in core)
    edge = -core_width / 2.0 - sum(lane.width for lane in left)
    offsets = []
    for lane in lanes:
        offsets.append(edge + lane.width / 2.0)
        edge += lane.width
    return Layout(tuple(lanes), tuple(offsets))


def skip_reason(tags: Mapping[str, str]) -> str | None:
    """Why a ``highway=*`` way is not imported (the report's kind), or None."""
    highway = tags.get("highway", "")
    if tags.get("area") == "yes":
        return "area=yes (a surface, not a road)"
    if highway not in ROAD_CLASSES:
        return f"highway={highway}"
    return None


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------


@dataclass
class _Way:
    id: int
    tags: dict[str, str]
    refs: list[int]
    lonlat: list[tuple[float, float] | None]


def _read(path: Path, report: ImportReport) -> list[_Way]:
    """Every ``highway=*`` way with its node locations (None where a node is missing)."""
    if not path.is_file():
        raise MapError(f"{path}: no such OSM file")
    ways: list[_Way] = []
    relations: list[int] = []
    try:
        fp = (
            osmium.FileProcessor(str(path))
            .with_locations()
            .with_filter(osmium.filter.KeyFilter("highway"))
        )
        for obj in fp:
            if isinstance(obj, osmium.osm.Way):
                nodes: list[tuple[float, float] | None] = []
                refs: list[int] = []
                for nd in obj.nodes:
                    refs.append(nd.ref)
                    loc = nd.location
                    nodes.append((loc.lon, loc.lat) if loc.valid() else None)
                ways.append(_Way(obj.id, {tag.k: tag.v for tag in obj.tags}, refs, nodes))
            elif isinstance(obj, osmium.osm.Relation):
                relations.append(obj.id)
    except (RuntimeError, ValueError, osmium.InvalidLocationError) as exc:
        raise MapError(
            f"{path}: cannot read the OSM file ({exc}); give an OSM XML (.osm) or PBF "
            "(.osm.pbf) file"
        ) from exc
    for rid in relations:
        report.skip("relation with highway=* (areas and routes are not read)", f"relation {rid}")
    return ways


# ----------------------------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------------------------


@dataclass
class _Piece:
    way: _Way
    layout: Layout
    refs: list[int]
    xy: FloatArray
    id: str = ""
    start: int = 0
    end: int = 0
    short: bool = False
    reversed: bool = False  # the reference runs against the way's node order (`_orient`)

    def reverse(self) -> None:
        """Turn the piece round: its reference runs the other way, so its lanes are the
        same lanes seen from the other end (right to left, directions flipped, offsets
        negated), as when a mapper reverses a way and swaps its forward and backward tags."""
        lanes = self.layout.lanes
        self.layout = Layout(
            tuple(LaneSpec(x.type, x.width, _flip(x.direction), x.properties) for x in lanes[::-1]),
            tuple(-d for d in self.layout.offsets[::-1]),
        )
        self.refs = self.refs[::-1]
        self.xy = self.xy[::-1]
        self.start, self.end = self.end, self.start
        self.reversed = not self.reversed


def _runs(way: _Way, report: ImportReport, bbox: BBox | None) -> list[tuple[list[int], FloatArray]]:
    """The way's stretches of located nodes (refs, lon/lat), clipped to `bbox`: every run of
    nodes inside it, with one node beyond each end where the way leaves the box."""
    where = f"way {way.id}"
    missing = sum(1 for ll in way.lonlat if ll is None)
    if missing:
        report.skip("node missing from the file (the way is cut there)", where, missing)
    runs: list[tuple[list[int], FloatArray]] = []
    current: list[int] = []
    coords: list[tuple[float, float]] = []
    for ref, loc in [*zip(way.refs, way.lonlat, strict=True), (0, None)]:
        if loc is None:
            if len(current) >= 2:
                runs.append((current, np.asarray(coords, dtype=np.float64)))
            current, coords = [], []
        else:
            current.append(ref)
            coords.append(loc)
    if not runs:
        report.skip("way with fewer than 2 nodes in the file", where)
        return []
    if bbox is None:
        return runs
    w, s, e, n = bbox
    clipped: list[tuple[list[int], FloatArray]] = []
    for refs, ll in runs:
        inside = (ll[:, 0] >= w) & (ll[:, 0] <= e) & (ll[:, 1] >= s) & (ll[:, 1] <= n)
        idx = np.flatnonzero(inside)
        if len(idx) == 0:
            continue
        breaks = np.flatnonzero(np.diff(idx) > 1)
        starts = [idx[0], *idx[breaks + 1]]
        ends = [*idx[breaks], idx[-1]]
        for a, b in zip(starts, ends, strict=True):
            lo, hi = max(int(a) - 1, 0), min(int(b) + 1, len(refs) - 1)
            if hi > lo:
                clipped.append((refs[lo : hi + 1], ll[lo : hi + 1]))
    if not clipped:
        report.skip("way outside the bbox", where)
    return clipped


def _touches(way: _Way, bbox: BBox) -> bool:
    """Whether a node of the way lies inside the box."""
    w, s, e, n = bbox
    return any(ll is not None and w <= ll[0] <= e and s <= ll[1] <= n for ll in way.lonlat)


def _turns(xy: FloatArray) -> FloatArray:
    """Turn angle in degrees at each interior vertex."""
    v = np.diff(xy, axis=0)
    a = np.arctan2(v[:, 1], v[:, 0])
    return np.degrees(np.abs((np.diff(a) + math.pi) % (2 * math.pi) - math.pi))


def _thin(refs: list[int], xy: FloatArray) -> tuple[list[int], FloatArray]:
    """Drop interior vertices within MIN_VERTEX_GAP of the previous kept one (and the last
    interior one if it is that close to the end)."""
    keep = [0]
    for i in range(1, len(xy) - 1):
        if math.dist(xy[i], xy[keep[-1]]) >= MIN_VERTEX_GAP:
            keep.append(i)
    last = len(xy) - 1
    if len(keep) > 1 and math.dist(xy[keep[-1]], xy[last]) < MIN_VERTEX_GAP:
        keep.pop()
    keep.append(last)
    return [refs[i] for i in keep], xy[keep]


def _cut(refs: list[int], xy: FloatArray, at: Iterable[int]) -> list[tuple[list[int], FloatArray]]:
    out = []
    start = 0
    for i in [*sorted(set(at)), len(refs) - 1]:
        if i > start:
            out.append((refs[start : i + 1], xy[start : i + 1]))
            start = i
    return out


def _pieces(
    ways: list[tuple[_Way, Layout, list[tuple[list[int], FloatArray]]]],
    proj: UtmProjection,
    report: ImportReport,
) -> list[_Piece]:
    """Cut the ways at shared nodes, closed loops and sharp vertices."""
    usage: Counter[int] = Counter()
    for _, _, runs in ways:
        for refs, _ll in runs:
            usage.update(refs)
    pieces: list[_Piece] = []
    for way, layout, runs in ways:
        k = 0
        for refs, ll in runs:
            xy = proj.to_utm_array(ll[:, 0], ll[:, 1])
            shared = [i for i in range(1, len(refs) - 1) if usage[refs[i]] > 1]
            for prefs, pxy in _cut(refs, xy, shared):
                parts = [(prefs, pxy)]
                if prefs[0] == prefs[-1] or math.dist(pxy[0], pxy[-1]) < 0.01:
                    if len(prefs) <= 2:
                        report.skip("closed way of fewer than 3 nodes", f"way {way.id}")
                        continue
                    parts = _cut(prefs, pxy, [len(prefs) // 2])
                for qrefs, qxy in parts:
                    trefs, txy = _thin(qrefs, qxy)
                    sharp = []
                    if len(txy) > 2:
                        sharp = [int(i) + 1 for i in np.flatnonzero(_turns(txy) > MAX_TURN_DEG)]
                    for rrefs, rxy in _cut(trefs, txy, sharp):
                        piece = _Piece(way, layout, rrefs, rxy, id=f"way{way.id}-{k}")
                        piece.start, piece.end = rrefs[0], rrefs[-1]
                        piece.short = float(LineString(rxy).length) < MIN_PIECE_LENGTH
                        pieces.append(piece)
                        k += 1
    return pieces


def _orient(pieces: list[_Piece], report: ImportReport) -> None:
    """Turn ways round where that links pieces that could not be linked as drawn.

    A piece's successors are the pieces at the node where it ends, whichever way they are
    drawn (`_successors`). Two pieces that both *start* at a node cannot name each other:
    nothing lies beyond either one's end there. Turning a way round (each piece's lanes are
    then the same lanes seen from the other end, `_Piece.reverse`) moves its start to its
    other end. A way is turned round as a whole, so its own pieces stay linked, and the
    links at the nodes inside it do not change: only the two nodes at its ends do.

    1. Chains: ways that run on into each other at nodes where only those two meet are
       oriented alike, one after the other, so that each such node has an end and a start.
    2. An open chain then starts at one of its two outer nodes (junctions or dead ends)
       and ends at the other. Chain by chain, in file order, the orientation is taken
       that leaves fewer pairs of pieces starting at the same outer node, the chains not
       yet seen as drawn (ties: fewer pieces turned round, then the first way as drawn).

    The pairs that still start at the same node are counted in the report.
    """
    # units: runs of consecutive pieces of one way, turned round as a whole
    units: list[list[int]] = []
    for i, p in enumerate(pieces):
        last = pieces[units[-1][-1]] if units else None
        if last is not None and last.way is p.way and last.end == p.start:
            units[-1].append(i)
        else:
            units.append([i])
    meets: dict[int, list[tuple[int, bool]]] = {}  # node -> (unit, True where it ends there)
    for u, members in enumerate(units):
        for i in members:
            meets.setdefault(pieces[i].start, []).append((u, False))
            meets.setdefault(pieces[i].end, []).append((u, True))

    def partner(u: int, node: int) -> tuple[int, bool] | None:
        """The other way at a node where exactly two ways meet."""
        here = meets[node]
        if len(here) != 2 or here[0][0] == here[1][0]:
            return None
        return here[1] if here[0][0] == u else here[0]

    turned = [False] * len(units)

    def lost(node: int) -> int:
        """Pairs of pieces that start at the node: s (s - 1) / 2."""
        s = sum(at_end == turned[u] for u, at_end in meets[node])
        return s * (s - 1) // 2

    # 1. chains, each unit turned relative to the chain's first one
    chains: list[list[int]] = []
    seen: set[int] = set()
    for first in range(len(units)):
        if first in seen:
            continue
        seen.add(first)
        chain, queue = [first], [first]
        while queue:
            u = queue.pop()
            ends = ((pieces[units[u][0]].start, False), (pieces[units[u][-1]].end, True))
            for node, at_end in ends:
                other = partner(u, node)
                if other is None or other[0] in seen:
                    continue
                k, k_at_end = other
                # unit u ends here (as turned) => the other one must start here
                turned[k] = k_at_end == (at_end != turned[u])
                seen.add(k)
                chain.append(k)
                queue.append(k)
        chains.append(chain)

    # 2. the orientation of each chain, by the pairs that start at its outer nodes
    def flip(chain: list[int]) -> None:
        for u in chain:
            turned[u] = not turned[u]

    def cost(chain: list[int], outer: list[int]) -> tuple[int, int]:
        return (
            sum(lost(node) for node in outer),
            sum(len(units[u]) for u in chain if turned[u]),
        )

    outers = [
        sorted(
            {
                node
                for u in chain
                for node in (pieces[units[u][0]].start, pieces[units[u][-1]].end)
                if partner(u, node) is None
            }
        )
        for chain in chains
    ]
    for chain, outer in zip(chains, outers, strict=True):
        as_is = cost(chain, outer)
        flip(chain)
        if not cost(chain, outer) < as_is:
            flip(chain)

    for u, members in enumerate(units):
        if turned[u]:
            for i in members:
                pieces[i].reverse()
    starting: dict[int, list[_Piece]] = {}
    for p in pieces:
        if not p.short:
            starting.setdefault(p.start, []).append(p)
    for node, here in starting.items():
        if len(here) > 1:
            ways = ", ".join(str(w) for w in sorted({p.way.id for p in here}))
            report.skip(
                "connection lost: two road elements start at the same node",
                f"node {node} (ways {ways})",
                len(here) * (len(here) - 1) // 2,
            )


def _successors(pieces: list[_Piece]) -> dict[str, tuple[str, ...]]:
    """The pieces at each piece's end node, whichever way they are drawn; short (left-out)
    pieces are passed through to the pieces at their other node."""
    at: dict[int, list[_Piece]] = {}
    for p in pieces:
        at.setdefault(p.start, []).append(p)
        if p.end != p.start:
            at.setdefault(p.end, []).append(p)

    def follow(node: int, seen: set[str]) -> list[str]:
        out: list[str] = []
        for q in at.get(node, []):
            if q.id in seen:
                continue
            seen.add(q.id)
            if q.short:
                out.extend(follow(q.end if q.start == node else q.start, seen))
            else:
                out.append(q.id)
        return out

    return {p.id: tuple(dict.fromkeys(follow(p.end, {p.id}))) for p in pieces if not p.short}


def _lane_lines(piece: _Piece) -> list[FloatArray] | None:
    """Each lane's centre line (UTM), the mitred parallel of the piece; None if one collapses."""
    line = LineString(piece.xy)
    out = []
    for off in piece.layout.offsets:
        if abs(off) < 1e-9:
            out.append(piece.xy)
            continue
        # shapely: a positive distance is to the LEFT; the direction is kept
        lane = shapely.offset_curve(line, -off, join_style="mitre", mitre_limit=10.0)
        if not isinstance(lane, LineString):
            # GEOS may return the parallel in pieces at an almost straight vertex
            lane = shapely.line_merge(lane)
        if not isinstance(lane, LineString) or lane.is_empty or len(lane.coords) < 2:
            return None
        xy = np.asarray(lane.coords, dtype=np.float64)[:, :2]
        if np.dot(xy[-1] - xy[0], piece.xy[-1] - piece.xy[0]) < 0.0:
            xy = xy[::-1]  # line_merge does not promise the direction
        out.append(xy)
    return out


# ----------------------------------------------------------------------------------------------
# The importer
# ----------------------------------------------------------------------------------------------


def _check_bbox(bbox: BBox | None) -> BBox | None:
    if bbox is None:
        return None
    try:
        w, s, e, n = (float(v) for v in bbox)
    except (TypeError, ValueError):
        raise ConfigError(
            f"bbox must be (min_lon, min_lat, max_lon, max_lat), got {bbox!r}"
        ) from None
    if not all(math.isfinite(v) for v in (w, s, e, n)) or not (
        -180.0 <= w < e <= 180.0 and -90.0 <= s < n <= 90.0
    ):
        raise ConfigError(
            f"bbox {bbox!r} is empty or out of range: (min_lon, min_lat, max_lon, max_lat) "
            "with min < max"
        )
    return w, s, e, n


def import_osm(path: str | Path, bbox: BBox | None = None) -> ImportResult:
    """Import the ``highway=*`` ways of an OSM file (.osm or .osm.pbf) as lane-map road
    elements (see the module docstring); `bbox` = (min_lon, min_lat, max_lon, max_lat)
    keeps the ways with a node inside it, cut one node beyond its edge.

    Raises `MapError` for a file osmium cannot read or one without usable roads; what
    is left out is counted in the result's report."""
    box = _check_bbox(bbox)
    src = Path(path)
    report = ImportReport(str(src))
    ways = _read(src, report)

    used: list[tuple[_Way, Layout, list[tuple[list[int], FloatArray]]]] = []
    for way in ways:
        if box is not None and not _touches(way, box):
            report.skip("way outside the bbox", f"way {way.id}")
            continue
        reason = skip_reason(way.tags)
        if reason is not None:
            report.skip(reason, f"way {way.id}")
            continue
        runs = _runs(way, report, box)
        if not runs:
            continue
        layout = lane_layout(way.tags, f"way {way.id}", report)
        used.append((way, layout, runs))
    if not used:
        raise no_lanes(str(src), report)

    all_ll = np.concatenate([ll for _, _, runs in used for _, ll in runs])
    proj = UtmProjection.for_location(float(all_ll[:, 0].mean()), float(all_ll[:, 1].mean()))
    pieces = _pieces(used, proj, report)
    _orient(pieces, report)
    for p in pieces:
        if p.short:
            report.skip(
                f"piece shorter than {MIN_PIECE_LENGTH:g} m between junctions", f"way {p.way.id}"
            )
    successors = _successors(pieces)

    lines: list[tuple[_Piece, list[FloatArray]]] = []
    for p in pieces:
        if p.short:
            continue
        lane_xy = _lane_lines(p)
        if lane_xy is None:
            report.skip("piece too sharply curved for its width (a lane collapses)", p.id)
            continue
        lines.append((p, lane_xy))
    if not lines:
        raise no_lanes(str(src), report)

    flat = np.concatenate([xy for _, lane_xy in lines for xy in lane_xy])
    lonlat = proj.to_wgs84_array(flat[:, 0], flat[:, 1])
    drafts: list[LaneDraft] = []
    at = 0
    for p, lane_xy in lines:
        succ = successors.get(p.id, ())
        base: dict[str, Any] = {"osm_way": p.way.id, "highway": p.way.tags["highway"]}
        if p.reversed:
            base["osm_reversed"] = True
        for k, (spec, xy) in enumerate(zip(p.layout.lanes, lane_xy, strict=True)):
            drafts.append(
                LaneDraft(
                    segment=p.id,
                    index=k,
                    type=spec.type,
                    width=spec.width,
                    direction=spec.direction,
                    lonlat=lonlat[at : at + len(xy)],
                    origin=f"way {p.way.id}",
                    successors=succ,
                    properties={**base, **dict(spec.properties)},
                )
            )
            at += len(xy)
    return finish(drafts, report)
