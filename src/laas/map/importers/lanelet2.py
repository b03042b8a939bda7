"""Lanelet2 maps (Autoware, research) into the GeoJSON lane-map format.

Reading. The ``lanelet2`` package reads the OSM file (``lanelet2.io.loadRobust``) with a
``UtmProjector`` around an origin: every point's ``(x, y)`` is its UTM position (the
origin's zone) minus the origin's, in metres. The origin is the caller's ``(lat, lon)`` or,
without one, the mean latitude and longitude of the file's nodes. Everything metric happens
in that plane; every position written is projected back with the same projector
(``projector.reverse``), so the written latitude and longitude are the real ones whatever
the origin (the Karlsruhe sample's nodes survive the round trip to 1e-13 degrees). A
primitive the parser reports as broken (a way with a missing node, a lanelet without
exactly one left and one right bound) costs the lanelets that use it, each counted and
named.

Lane types from ``subtype`` (:data:`SUBTYPES`): road, highway, bus_lane, play_street,
emergency_lane -> driving; bicycle_lane -> bicycle; walkway, shared_walkway, stairs ->
sidewalk; parking -> parking. Crosswalk, exit and rail lanelets are left out, counted: the
first two cross roads and walkways, rails have no lane type. Each lane keeps
``"lanelet": id`` and ``"subtype"`` in its properties and has origin ``"lanelet <id>"``.
Areas (multipolygons) with subtype parking or walkway that share a boundary linestring
with the outer bound of a driving or bicycle lanelet become a parking or sidewalk lane
beside it (:data:`AREA_LANES`): its width is the median depth of the area measured along
normals of that bound (capped: a square beside a road gives a strip), its centre line the
mitred parallel of the bound at half that width outwards. A strip that would make its
element fail the loader's checks is left out (counted).

Direction: ``one_way:<participant>`` (vehicle, bicycle, pedestrian by lane type), else
``one_way`` (not for pedestrians), else the Lanelet2 default: one way, except that
pedestrians use lanelets in both directions. A one-way lane is ``forward`` when the lanelet
runs along the element's reference direction, ``backward`` otherwise; the others ``both``.

Road elements. Lanelets side by side share boundary points: X's right bound runs over the
same consecutive points as Y's left bound (same direction), or as Y's right bound reversed
(Y runs the other way). The neighbour of every bound edge is found from the points' ids, so
a neighbour may cover part of a bound. A lanelet is *cut* at the bound vertex where the
neighbour on a side changes; a cut at station s of X's centre line is carried across X to
the point of its other bound nearest to the centre line at s, and from there into the
neighbour on that side, and so on, until every lanelet of a row is cut at common stations
(cuts closer than :data:`MIN_PIECE` to another cut or to an end are dropped). The pieces
between cuts that are mutual neighbours chain into rows: one road element per row, lane 0
its leftmost piece looking along the reference direction. Lanelets that overlap another
(more than :data:`JUNCTION_OVERLAP` m^2 of common area: the lanelets of a junction) are
road elements of one lanelet each.

Fitting the loader. Each row is checked against the loader's rules for a road element
(``laas.map.geojson``, whose tolerances are used by name: lane 0 turns at most
``MAX_TURN_DEG`` = 60 degrees at a vertex; every lane spans lane 0's stations within
``cover_tolerance``; neighbouring centres are (w_k + w_k+1) / 2 apart within
``gap_tolerance``, max(35 %, 0.75 m)), with a margin. A row that fails is repaired and the
rows rebuilt, until all pass or nothing more can be done: lane 0's sharp vertex becomes a
cut; lanes that drift apart (a lane widening at a junction) are cut in the middle while
the row is at least 2 x :data:`MIN_SPLIT` long; shorter rows, and rows with a lane that
does not span lane 0, are split left of the offending lane into two elements.

Reference direction. An element's reference is the direction of its first lanelet (lowest
id), reversed when that makes it run on from an element already oriented (elements are
oriented one after the other, each as the one it connects to): along a two-way road the
elements then all point the same way, and a connection is only lost where two elements
start at the same place (counted), since successors name what follows an element's end.

Successors. Lanelet ends meet where they share both end points (ids): X's left and right
end points are Y's left and right start points (Y follows X), or Y's end points in the
other order (head on). A segment's successors are the segments with a piece on the far
side of the place where the segment ends in its reference direction, whatever the travel
direction of that piece: for a ``backward`` lane, what lies beyond the element's end is
where its traffic comes from. Junction lanelets that start at the same stop line share it,
so an approach lists all of them.

Geometry. A lane's centre line is Lanelet2's own (``lanelet.centerline``), cut to the piece
and reversed for lanelets running against the reference; vertices within 5 cm of the
previous one are dropped. Its width is the mean, over stations every metre, of the
distances from the centre line to the two bounds. Lanelets whose centre line is shorter than
:data:`MIN_LENGTH`, narrower than :data:`MIN_WIDTH` or self-intersecting are left out
(counted).
"""

from __future__ import annotations

import itertools
import math
import xml.etree.ElementTree as ET
from collections import defaultdict, deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lanelet2
import numpy as np
import numpy.typing as npt
import shapely
from lanelet2.core import BasicPoint3d
from lanelet2.io import Origin
from lanelet2.projection import UtmProjector
from shapely import LineString, Point, Polygon
from shapely.ops import substring

from laas.errors import ConfigError, MapError
from laas.map.frame import MIN_PIECE as FRAME_MIN_PIECE
from laas.map.frame import Frame, dedupe, sharpest_turn
from laas.map.geojson import MAX_TURN_DEG as LOADER_MAX_TURN_DEG
from laas.map.geojson import cover_tolerance, gap_stations, gap_tolerance
from laas.map.hdmap import Direction, LaneType
from laas.map.importers.common import ImportReport, ImportResult, LaneDraft, finish

__all__ = [
    "AREA_LANES",
    "JUNCTION_OVERLAP",
    "LEFT_OUT",
    "MIN_LENGTH",
    "MIN_PIECE",
    "MIN_WIDTH",
    "SUBTYPES",
    "file_origin",
    "import_lanelet2",
    "to_lonlat",
]

FloatArray = npt.NDArray[np.float64]

SUBTYPES: Mapping[str, LaneType] = {
    "road": "driving",
    "highway": "driving",
    "bus_lane": "driving",
    "play_street": "driving",
    "emergency_lane": "driving",
    "bicycle_lane": "bicycle",
    "walkway": "sidewalk",
    "shared_walkway": "sidewalk",
    "stairs": "sidewalk",
    "parking": "parking",
}
"""Lanelet subtype -> lane type. A lanelet without subtype is read as ``road``."""

LEFT_OUT: Mapping[str, str] = {
    "crosswalk": "crosswalk lanelet (crosses roads)",
    "exit": "exit lanelet (crosses a walkway)",
    "rail": "rail lanelet (no lane type for rails)",
}
"""Lanelet subtypes left out on purpose, with the kind they are counted as."""

AREA_LANES: Mapping[str, tuple[LaneType, float]] = {
    "parking": ("parking", 6.0),
    "walkway": ("sidewalk", 3.0),
}
"""Area subtype -> (lane type, largest width in m) of the lane it makes beside a lanelet."""

JUNCTION_OVERLAP = 1.0  # m^2: lanelets overlapping by more are junction lanelets
MIN_LENGTH = 0.5  # m: shorter lanelet centre lines are left out
MIN_WIDTH = 0.3  # m: narrower lanelets are left out
MIN_PIECE = 1.0  # m: cuts closer than this to another cut or to a lanelet end are dropped
MIN_SPLIT = 5.0  # m: rows whose lanes are not side by side are halved down to this length
_MAX_TURN = LOADER_MAX_TURN_DEG - 1.0  # degrees: sharper turns of a reference are cut
_FIT = 0.9  # share of the loader's side-by-side tolerances that rows are made to meet
_COVER_MARGIN = 0.5  # m: rows keep this much inside the loader's station tolerance
_MAX_ROUNDS = 40  # rounds of cutting and splitting rows
_STEP = 1.0  # m: station spacing for widths and area depths
_VERTEX_GAP = 0.05  # m: centre-line vertices closer than this to the previous are dropped
_RAY = 40.0  # m: longest area depth looked for
_AREA_COVER = 0.5  # share of an area lane's stations where the area must be found
_AREA_MIN_WIDTH = 0.5  # m: narrower area strips make no lane
_TAG_YES = frozenset({"yes", "true", "1"})
_TAG_NO = frozenset({"no", "false", "0"})
_PARTICIPANT: Mapping[str, str] = {
    "driving": "vehicle",
    "parking": "vehicle",
    "bicycle": "bicycle",
    "sidewalk": "pedestrian",
}

LEFT, RIGHT = 0, 1
Neighbour = tuple[int, bool]  # (index of the neighbouring lanelet, runs the other way)
PieceKey = tuple[int, int]  # (index of the lanelet, index of the piece along it)
PortKey = tuple[str, int, int]


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------


def file_origin(path: str | Path) -> tuple[float, float]:
    """(lat, lon): the mean of the file's node coordinates; raises `MapError` if none."""
    p = Path(path)
    lat_sum = lon_sum = 0.0
    n = 0
    try:
        for _event, elem in ET.iterparse(p, events=("end",)):
            if elem.tag == "node":
                try:
                    lat, lon = float(elem.get("lat", "nan")), float(elem.get("lon", "nan"))
                except ValueError:
                    lat = lon = math.nan
                if math.isfinite(lat) and math.isfinite(lon):
                    lat_sum += lat
                    lon_sum += lon
                    n += 1
                elem.clear()
            elif elem.tag in ("way", "relation"):
                elem.clear()
    except OSError as exc:
        raise MapError(f"{p}: cannot read the Lanelet2 map: {exc.strerror or exc}") from exc
    except ET.ParseError as exc:
        raise MapError(f"{p}: not an OSM XML file: {exc}") from exc
    if n == 0:
        raise MapError(f"{p}: no nodes with lat/lon found; is this a Lanelet2 .osm file?")
    return lat_sum / n, lon_sum / n


def to_lonlat(projector: UtmProjector, xy: FloatArray) -> FloatArray:
    """Projected (n, 2) metres -> (n, 2) longitude, latitude with the projector's inverse."""
    out = np.empty((len(xy), 2))
    for i, (x, y) in enumerate(np.asarray(xy, dtype=np.float64)):
        g = projector.reverse(BasicPoint3d(float(x), float(y), 0.0))
        out[i] = g.lon, g.lat
    return out


class _Broken:
    """The parser's error lines by the id of the primitive they name, and which of them
    cost a lanelet or an area (the others are counted on their own)."""

    def __init__(self, errors: Sequence[str]) -> None:
        lines: dict[int, list[str]] = defaultdict(list)
        for line in errors:
            text = line.strip().lstrip("-").strip()
            for marker in ("primitive with id ", "primitive "):
                at = text.find(marker)
                if at < 0:
                    continue
                digits = text[at + len(marker) :].split(" ")[0].rstrip(":")
                if digits.lstrip("-").isdigit():
                    lines[int(digits)].append(text)
                break
        self.lines = {k: "; ".join(v) for k, v in lines.items()}
        self.used: set[int] = set()

    def problems(self, *ids: int) -> str | None:
        """The complaints about any of `ids` (a primitive and its parts), or None."""
        found = [i for i in dict.fromkeys(ids) if i in self.lines]
        self.used.update(found)
        return "; ".join(self.lines[i] for i in found) if found else None

    def report_unused(self, report: ImportReport) -> None:
        for i, text in self.lines.items():
            if i not in self.used:
                report.skip("primitive the Lanelet2 parser could not read", f"{i}: {text}")


def _xy(points: Any) -> FloatArray:
    return np.array([(p.x, p.y) for p in points], dtype=np.float64).reshape(-1, 2)


def _tag(attrs: Any, key: str) -> str | None:
    return str(attrs[key]).strip() if key in attrs else None


# ----------------------------------------------------------------------------------------------
# Lanelets
# ----------------------------------------------------------------------------------------------


@dataclass
class _Lanelet:
    """A usable lanelet in the projected plane; sides are indexed LEFT, RIGHT."""

    id: int
    subtype: str
    type: LaneType
    one_way: bool
    bounds: tuple[FloatArray, FloatArray]  # along the lanelet
    point_ids: tuple[list[int], list[int]]
    linestrings: tuple[int, int]  # ids of the bound linestrings
    center: LineString
    junction: bool = False
    lines: tuple[LineString, LineString] = field(init=False)
    cum: tuple[FloatArray, FloatArray] = field(init=False)
    neighbours: tuple[list[Neighbour | None], list[Neighbour | None]] = field(init=False)
    cuts: list[float] = field(default_factory=list)
    stations: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        self.lines = (LineString(self.bounds[LEFT]), LineString(self.bounds[RIGHT]))
        cums = []
        for b in self.bounds:
            seg = np.hypot(*np.diff(b, axis=0).T)
            cums.append(np.concatenate([[0.0], np.cumsum(seg)]))
        self.cum = (cums[0], cums[1])
        self.neighbours = (
            [None] * (len(self.bounds[LEFT]) - 1),
            [None] * (len(self.bounds[RIGHT]) - 1),
        )

    @property
    def length(self) -> float:
        return float(self.center.length)

    def bound_point(self, side: int, s: float) -> tuple[Point, int]:
        """The point of a bound nearest to the centre line at station s, and its edge."""
        t = float(self.lines[side].project(self.center.interpolate(s)))
        edge = int(np.searchsorted(self.cum[side], t, side="right")) - 1
        edge = min(max(edge, 0), len(self.bounds[side]) - 2)
        return self.lines[side].interpolate(t), edge

    def add_cut(self, s: float) -> bool:
        if s < MIN_PIECE or s > self.length - MIN_PIECE:
            return False
        if any(abs(s - c) < MIN_PIECE for c in self.cuts):
            return False
        self.cuts.append(s)
        return True

    def piece_at(self, s: float) -> int:
        k = int(np.searchsorted(self.stations, s, side="right")) - 1
        return min(max(k, 0), len(self.stations) - 2)

    def width(self, a: float, b: float) -> float:
        """Mean distance between the bounds over stations a..b of the centre line."""
        n = max(5, math.ceil((b - a) / _STEP) + 1)
        pts = shapely.line_interpolate_point(self.center, np.linspace(a, b, n))
        w = shapely.distance(pts, self.lines[LEFT]) + shapely.distance(pts, self.lines[RIGHT])
        return float(np.mean(w))


def _one_way(attrs: Any, lane_type: LaneType, where: str, report: ImportReport) -> bool:
    participant = _PARTICIPANT[lane_type]
    keys = [f"one_way:{participant}"]
    if participant != "pedestrian":
        keys.append("one_way")
    for key in keys:
        value = _tag(attrs, key)
        if value is None:
            continue
        if value.lower() in _TAG_YES:
            return True
        if value.lower() in _TAG_NO:
            return False
        report.skip(f"tag value not usable, default used: {key}", f"{where}: {key}={value!r}")
    return participant != "pedestrian"


def _read_lanelets(lmap: Any, broken: _Broken, report: ImportReport) -> list[_Lanelet]:
    """The lanelets LaaS can use, in id order; every other one is counted."""
    out: list[_Lanelet] = []
    for ll in sorted(lmap.laneletLayer, key=lambda ll: ll.id):
        lid = int(ll.id)
        where = f"lanelet {lid}"
        attrs = ll.attributes
        subtype = _tag(attrs, "subtype") or "road"
        if subtype in LEFT_OUT:
            report.skip(LEFT_OUT[subtype], where)
            continue
        lane_type = SUBTYPES.get(subtype)
        if lane_type is None:
            report.skip(f"lanelet of unknown subtype {subtype!r}", where)
            continue
        left, right = ll.leftBound, ll.rightBound
        problem = broken.problems(lid, int(left.id), int(right.id))
        if len(left) < 2 or len(right) < 2:
            problem = problem or "a bound has fewer than 2 points"
        if problem is not None:
            report.skip("lanelet with a missing or broken bound", f"{where}: {problem}")
            continue
        try:
            center_xy = dedupe(_xy(ll.centerline), _VERTEX_GAP)
        except RuntimeError as exc:  # Lanelet2 cannot compute a centre line
            report.skip("degenerate lanelet", f"{where}: no centre line ({exc})")
            continue
        center = LineString(center_xy) if len(center_xy) >= 2 else LineString()
        if center.is_empty or center.length < MIN_LENGTH:
            report.skip("degenerate lanelet", f"{where}: centre line shorter than {MIN_LENGTH} m")
            continue
        if not center.is_simple:
            report.skip("degenerate lanelet", f"{where}: centre line intersects itself")
            continue
        lanelet = _Lanelet(
            lid,
            subtype,
            lane_type,
            _one_way(attrs, lane_type, where, report),
            (_xy(left), _xy(right)),
            ([int(p.id) for p in left], [int(p.id) for p in right]),
            (int(left.id), int(right.id)),
            center,
        )
        if lanelet.width(0.0, lanelet.length) < MIN_WIDTH:
            report.skip("degenerate lanelet", f"{where}: narrower than {MIN_WIDTH} m")
            continue
        out.append(lanelet)
    return out


def _mark_junctions(lanelets: Sequence[_Lanelet]) -> None:
    """Flag lanelets that overlap another by more than JUNCTION_OVERLAP square metres."""
    polys = []
    for ll in lanelets:
        ring = np.vstack([ll.bounds[LEFT], ll.bounds[RIGHT][::-1]])
        poly = Polygon(ring) if len(ring) >= 3 else Polygon()
        polys.append(poly if poly.is_valid else shapely.make_valid(poly))
    tree = shapely.STRtree(polys)
    a, b = tree.query(polys, predicate="intersects")
    keep = a < b
    a, b = a[keep], b[keep]
    if len(a) == 0:
        return
    arr = np.asarray(polys, dtype=object)
    areas = shapely.area(shapely.intersection(arr[a], arr[b]))
    for i, j, area in zip(a, b, areas, strict=True):
        if area > JUNCTION_OVERLAP:
            lanelets[int(i)].junction = True
            lanelets[int(j)].junction = True


def _find_neighbours(lanelets: Sequence[_Lanelet]) -> None:
    """Per bound edge, the lanelet on the other side of it (see the module docstring)."""
    edges: dict[tuple[int, int], list[tuple[int, int]]] = defaultdict(list)
    for i, ll in enumerate(lanelets):
        if ll.junction:
            continue
        for side in (LEFT, RIGHT):
            ids = ll.point_ids[side]
            for a, b in itertools.pairwise(ids):
                edges[(a, b)].append((i, side))
    for i, ll in enumerate(lanelets):
        if ll.junction:
            continue
        for side in (LEFT, RIGHT):
            ids = ll.point_ids[side]
            for e, (a, b) in enumerate(itertools.pairwise(ids)):
                found: Neighbour | None = None
                for j, other_side in edges.get((a, b), ()):
                    if j != i and other_side != side:
                        found = (j, False)
                        break
                if found is None:
                    for j, other_side in edges.get((b, a), ()):
                        if j != i and other_side == side:
                            found = (j, True)
                            break
                ll.neighbours[side][e] = found


def _cut(lanelets: Sequence[_Lanelet]) -> None:
    """Cut lanelets where a neighbour changes, and carry the cuts across rows."""
    work: list[tuple[int, float]] = []
    for i, ll in enumerate(lanelets):
        for side in (LEFT, RIGHT):
            nb = ll.neighbours[side]
            for v in range(1, len(nb)):
                if nb[v] != nb[v - 1]:
                    s = float(ll.center.project(Point(ll.bounds[side][v])))
                    if ll.add_cut(s):
                        work.append((i, s))
    _propagate(lanelets, work)


def _propagate(lanelets: Sequence[_Lanelet], work: list[tuple[int, float]]) -> None:
    """Carry new cuts (lanelet, station) into the neighbours, then renew the stations."""
    while work:
        i, s = work.pop()
        ll = lanelets[i]
        for side in (LEFT, RIGHT):
            q, edge = ll.bound_point(side, s)
            nb = ll.neighbours[side][edge]
            if nb is None:
                continue
            other = lanelets[nb[0]]
            t = float(other.center.project(q))
            if other.add_cut(t):
                work.append((nb[0], t))
    for ll in lanelets:
        ll.stations = np.array([0.0, *sorted(ll.cuts), ll.length])


def _links(
    lanelets: Sequence[_Lanelet], forbidden: set[frozenset[int]]
) -> dict[PieceKey, list[tuple[PieceKey, bool] | None]]:
    """The mutual left and right neighbour of every piece (with: runs the other way),
    except between the `forbidden` pairs of lanelets."""
    links: dict[PieceKey, list[tuple[PieceKey, bool] | None]] = {}
    for i, ll in enumerate(lanelets):
        for k in range(len(ll.stations) - 1):
            found: list[tuple[PieceKey, bool] | None] = [None, None]
            if not ll.junction:
                mid = 0.5 * (ll.stations[k] + ll.stations[k + 1])
                for side in (LEFT, RIGHT):
                    q, edge = ll.bound_point(side, mid)
                    nb = ll.neighbours[side][edge]
                    if nb is not None and frozenset((i, nb[0])) not in forbidden:
                        other = lanelets[nb[0]]
                        j = other.piece_at(float(other.center.project(q)))
                        found[side] = ((nb[0], j), nb[1])
            links[(i, k)] = found
    mutual: dict[PieceKey, list[tuple[PieceKey, bool] | None]] = {}
    for key, found in links.items():
        mutual[key] = [None, None]
        for side in (LEFT, RIGHT):
            link = found[side]
            if link is None:
                continue
            peer, flip = link
            back = links[peer][side if flip else 1 - side]
            if back == (key, flip):
                mutual[key][side] = link
    return mutual


# ----------------------------------------------------------------------------------------------
# Rows, orientation, connections
# ----------------------------------------------------------------------------------------------


@dataclass
class _Row:
    """One road element: pieces left to right looking along the seed lanelet, with their
    orientation relative to it (+1 along, -1 against); `sign` flips the whole row."""

    pieces: list[tuple[PieceKey, int]]
    seed: PieceKey
    sign: int = 1
    id: str = ""


def _rows(
    lanelets: Sequence[_Lanelet], links: Mapping[PieceKey, list[tuple[PieceKey, bool] | None]]
) -> list[_Row]:
    rows: list[_Row] = []
    seen: set[PieceKey] = set()
    for seed in sorted(links):
        if seed in seen:
            continue
        # walk to the leftmost piece, then collect to the right
        key, r = seed, 1
        visited = {key}
        while True:
            link = links[key][LEFT if r > 0 else RIGHT]
            if link is None or link[0] in visited or link[0] in seen:
                break
            key, r = link[0], (-r if link[1] else r)
            visited.add(key)
        pieces = [(key, r)]
        seen.add(key)
        while True:
            link = links[key][RIGHT if r > 0 else LEFT]
            if link is None or link[0] in seen:
                break
            key, r = link[0], (-r if link[1] else r)
            pieces.append((key, r))
            seen.add(key)
        if seed not in {p for p, _ in pieces}:  # a broken chain: keep the seed's part
            pieces = [(seed, 1)]
            seen.add(seed)
        rows.append(_Row(pieces, seed))
    return rows


def _piece_xy(ll: _Lanelet, k: int, along: int) -> FloatArray:
    """Piece k's centre line, (n, 2) metres, in the direction `along` (+1: the lanelet's)."""
    a, b = float(ll.stations[k]), float(ll.stations[k + 1])
    xy = np.asarray(substring(ll.center, a, b).coords, dtype=np.float64)[:, :2]
    return dedupe(xy if along > 0 else xy[::-1], _VERTEX_GAP)


Fault = tuple[str, int, float]


def _fault(lanes: Sequence[tuple[FloatArray, float]]) -> Fault | None:
    """The first of the loader's rules for a road element (``laas.map.geojson``) that lanes
    (centre line in metres along the reference, width) left to right break, with a margin:
    ("turn", 0, station of the vertex on lane 0), ("coverage", lane, 0), ("gap", lane,
    station), ("short", 0, 0); None if they pass."""
    ref = lanes[0][0]
    turn, vertex = sharpest_turn(ref)
    if turn > _MAX_TURN:
        c = dedupe(ref, FRAME_MIN_PIECE)
        return "turn", 0, float(np.sum(np.hypot(*np.diff(c[: vertex + 1], axis=0).T)))
    try:
        frame = Frame(ref)
    except MapError:
        return "short", 0, 0.0
    length = frame.length
    tol_s = cover_tolerance(length) - _COVER_MARGIN
    curves = [(np.array([0.0, length]), np.array([0.0, 0.0]))]
    for j, (xy, _w) in enumerate(lanes[1:], start=1):
        dense = np.asarray(shapely.segmentize(LineString(xy), _STEP).coords)[:, :2]
        sd = frame.frame_array(dense)
        lo, hi = float(sd[:, 0].min()), float(sd[:, 0].max())
        if sd[-1, 0] <= sd[0, 0] or abs(lo) > tol_s or abs(hi - length) > tol_s:
            return "coverage", j, 0.0
        order = np.argsort(sd[:, 0], kind="stable")
        curves.append((sd[order, 0], sd[order, 1]))
    for st in gap_stations(length):
        offsets = [float(np.interp(st, s_, d_)) for s_, d_ in curves]
        for k in range(len(lanes) - 1):
            gap = offsets[k + 1] - offsets[k]
            expected = (lanes[k][1] + lanes[k + 1][1]) / 2.0
            if gap <= 0.0 or abs(gap - expected) > _FIT * gap_tolerance(expected):
                return "gap", k + 1, float(st)
    return None


def _row_lanes(lanelets: Sequence[_Lanelet], row: _Row) -> list[tuple[FloatArray, float]]:
    """The row's lanes (centre line, width) left to right, looking along its seed lanelet."""
    out = []
    for (i, k), r in row.pieces:
        ll = lanelets[i]
        out.append(
            (_piece_xy(ll, k, r), ll.width(float(ll.stations[k]), float(ll.stations[k + 1])))
        )
    return out


def _build_rows(lanelets: Sequence[_Lanelet]) -> list[_Row]:
    """Rows that pass the loader's checks where cuts or splits can make them: a sharp turn
    of lane 0 is cut at its vertex; lanes not side by side are cut in the middle while the
    row is at least 2 x MIN_SPLIT long, else (and for a lane that does not span the row)
    the row is split left of the offending lane."""
    forbidden: set[frozenset[int]] = set()
    checked: dict[tuple[tuple[int, float, float, int], ...], Fault | None] = {}
    for _round in range(_MAX_ROUNDS):
        rows = _rows(lanelets, _links(lanelets, forbidden))
        work: list[tuple[int, float]] = []
        changed = False
        for row in rows:
            sig = tuple(
                (i, float(lanelets[i].stations[k]), float(lanelets[i].stations[k + 1]), r)
                for (i, k), r in row.pieces
            )
            if sig not in checked:
                checked[sig] = _fault(_row_lanes(lanelets, row))
            fault = checked[sig]
            if fault is None:
                continue
            kind, lane, station = fault
            (i0, k0), r0 = row.pieces[0]
            first = lanelets[i0]
            a, b = float(first.stations[k0]), float(first.stations[k0 + 1])
            if kind == "turn":
                s = a + station if r0 > 0 else b - station
                if first.add_cut(s):
                    work.append((i0, s))
            elif kind == "gap" and b - a >= 2 * MIN_SPLIT:
                if first.add_cut(0.5 * (a + b)):
                    work.append((i0, 0.5 * (a + b)))
            elif kind in ("gap", "coverage"):
                pair = frozenset((row.pieces[lane - 1][0][0], row.pieces[lane][0][0]))
                if pair not in forbidden:
                    forbidden.add(pair)
                    changed = True
        if work:
            _propagate(lanelets, work)
            changed = True
        if not changed:
            return rows
    return _rows(lanelets, _links(lanelets, forbidden))


def _port(a: int, b: int, side: int) -> tuple[PortKey, int]:
    """A lanelet end as (canonical key, side): (left id, right id) looking from the
    piece before it to the piece after it; side +1 = the piece lies after it."""
    return (("p", a, b), side) if a <= b else (("p", b, a), -side)


def _ports(ll: _Lanelet, i: int, k: int) -> tuple[tuple[PortKey, int], tuple[PortKey, int]]:
    """(travel start, travel end) ports of piece k of lanelet i."""
    last = len(ll.stations) - 2
    start = (
        _port(ll.point_ids[LEFT][0], ll.point_ids[RIGHT][0], +1)
        if k == 0
        else (("c", i, k - 1), +1)
    )
    end = (
        _port(ll.point_ids[LEFT][-1], ll.point_ids[RIGHT][-1], -1)
        if k == last
        else (("c", i, k), -1)
    )
    return start, end


def _orient_and_link(
    lanelets: Sequence[_Lanelet], rows: Sequence[_Row], report: ImportReport
) -> dict[int, list[int]]:
    """Choose each row's sign (see the module docstring); return each row's successors."""
    row_of: dict[PieceKey, tuple[int, int]] = {}
    for g, row in enumerate(rows):
        for key, r in row.pieces:
            row_of[key] = (g, r)
    # port -> [(row, r * e, side)]: e = +1 where the lanelet's travel ends
    at: dict[PortKey, list[tuple[int, int, int]]] = defaultdict(list)
    for (i, k), (g, r) in row_of.items():
        start, end = _ports(lanelets[i], i, k)
        at[start[0]].append((g, -r, start[1]))
        at[end[0]].append((g, r, end[1]))
    adjacency: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for entries in at.values():
        for g, re_g, side_g in entries:
            for h, re_h, side_h in entries:
                if side_g > 0 > side_h and g != h:
                    c = -re_g * re_h
                    adjacency[g].append((h, c))
                    adjacency[h].append((g, c))
    signs: dict[int, int] = {}
    for first in range(len(rows)):
        if first in signs:
            continue
        signs[first] = 1
        queue = deque([first])
        while queue:
            g = queue.popleft()
            for h, c in adjacency[g]:
                if h not in signs:
                    signs[h] = signs[g] * c
                    queue.append(h)
    for g, row in enumerate(rows):
        row.sign = signs[g]
    # successors: rows on the far side of where a row ends in its reference direction
    succ: dict[int, list[int]] = {g: [] for g in range(len(rows))}
    lost: set[frozenset[int]] = set()
    for entries in at.values():
        for g, re_g, side_g in entries:
            ends_here = rows[g].sign * re_g > 0  # the reference of row g runs into the port
            for h, re_h, side_h in entries:
                if h == g or side_h != -side_g:
                    continue
                if ends_here:
                    if h not in succ[g]:
                        succ[g].append(h)
                elif rows[h].sign * re_h < 0:
                    lost.add(frozenset((g, h)))
    for pair in sorted(lost, key=sorted):
        g, h = sorted(pair)
        report.skip(
            "connection lost: two road elements start at the same place",
            f"lanelets {lanelets[rows[g].seed[0]].id} and {lanelets[rows[h].seed[0]].id}",
        )
    return succ


# ----------------------------------------------------------------------------------------------
# Areas beside lanelets
# ----------------------------------------------------------------------------------------------


@dataclass
class _Area:
    id: int
    subtype: str
    polygon: Polygon
    used: bool = False


def _read_areas(
    lmap: Any, broken: _Broken, report: ImportReport
) -> tuple[dict[int, list[_Area]], list[_Area]]:
    """Parking and walkway areas by the ids of their outer linestrings; others counted."""
    by_linestring: dict[int, list[_Area]] = defaultdict(list)
    areas: list[_Area] = []
    for area in sorted(lmap.areaLayer, key=lambda a: a.id):
        aid = int(area.id)
        subtype = _tag(area.attributes, "subtype") or "(none)"
        where = f"area {aid}"
        if subtype not in AREA_LANES:
            report.skip(f"area of subtype {subtype!r} (not a lane)", where)
            continue
        outer = list(area.outerBound)
        problem = broken.problems(aid, *(int(ls.id) for ls in outer))
        if problem is None and any(len(ls) < 2 for ls in outer):
            problem = "a boundary has fewer than 2 points"
        poly = Polygon()
        if problem is None:
            ring = _xy(area.outerBoundPolygon())
            poly = Polygon(ring) if len(ring) >= 3 else Polygon()
            poly = poly if poly.is_valid else shapely.make_valid(poly)
            if poly.is_empty or poly.area <= 0.0:
                problem = "its outline has no area"
        if problem is not None:
            report.skip(f"{subtype} area with a broken outline", f"{where}: {problem}")
            continue
        item = _Area(aid, subtype, poly)
        areas.append(item)
        for ls in outer:
            by_linestring[int(ls.id)].append(item)
    return by_linestring, areas


# ----------------------------------------------------------------------------------------------
# The importer
# ----------------------------------------------------------------------------------------------


def _load(path: Path, origin: tuple[float, float]) -> tuple[Any, UtmProjector, list[str]]:
    lat, lon = origin
    if not (math.isfinite(lat) and math.isfinite(lon) and -80 <= lat <= 84 and -180 <= lon <= 180):
        raise ConfigError(
            f"origin must be (lat, lon) in degrees within UTM's range (-80..84), got {origin!r}"
        )
    projector = UtmProjector(Origin(lat, lon))
    try:
        lmap, errors = lanelet2.io.loadRobust(str(path), projector)
    except RuntimeError as exc:
        raise MapError(f"{path}: Lanelet2 cannot read the file: {exc}") from exc
    return lmap, projector, [e for e in errors if e.strip() and not e.startswith("Errors ")]


def import_lanelet2(path: str | Path, origin: tuple[float, float] | None = None) -> ImportResult:
    """Import a Lanelet2 ``.osm`` map (see the module docstring).

    `origin` is the (lat, lon) of the projection's origin; by default the mean of the
    file's nodes. It only sets the plane the geometry is computed in: the written
    coordinates are real latitudes and longitudes either way.
    """
    p = Path(path)
    report = ImportReport(str(p))
    if origin is None:
        origin = file_origin(p)
    lmap, projector, errors = _load(p, (float(origin[0]), float(origin[1])))
    broken = _Broken(errors)

    lanelets = _read_lanelets(lmap, broken, report)
    if not lanelets:
        raise _nothing(report)
    _mark_junctions(lanelets)
    _find_neighbours(lanelets)
    _cut(lanelets)
    rows = _build_rows(lanelets)
    successors = _orient_and_link(lanelets, rows, report)
    by_linestring, areas = _read_areas(lmap, broken, report)
    for reg in lmap.regulatoryElementLayer:
        report.skip("regulatory element (not used)", f"regulatory element {reg.id}")
    broken.report_unused(report)

    for row in rows:
        i, k = row.seed
        ll = lanelets[i]
        row.id = f"ll{ll.id}" if len(ll.stations) == 2 else f"ll{ll.id}-{k}"
    drafts = list(_drafts(lanelets, rows, successors, by_linestring, projector, report))
    for area in areas:
        if not area.used:
            report.skip(f"{area.subtype} area that makes no lane", f"area {area.id}")
    if not drafts:
        raise _nothing(report)
    return finish(drafts, report)


def _nothing(report: ImportReport) -> MapError:
    """The error of an import that found no lane: what was left out, by kind."""
    lines = report.lines()[1:]
    return MapError(
        f"{report.source}: no lanelet that LaaS can use; " + "; ".join(lines)
        if report.skipped
        else f"{report.source}: the file has no lanelets"
    )


def _direction(ll: _Lanelet, along: int) -> Direction:
    if not ll.one_way:
        return "both"
    return "forward" if along > 0 else "backward"


def _drafts(
    lanelets: Sequence[_Lanelet],
    rows: Sequence[_Row],
    successors: Mapping[int, list[int]],
    by_linestring: Mapping[int, list[_Area]],
    projector: UtmProjector,
    report: ImportReport,
) -> Iterator[LaneDraft]:
    for g, row in enumerate(rows):
        pieces = row.pieces if row.sign > 0 else row.pieces[::-1]
        succ = tuple(rows[h].id for h in sorted(successors[g], key=lambda h: rows[h].id))
        lanes: list[tuple[LaneDraft, FloatArray]] = []
        for (i, k), r in pieces:
            ll = lanelets[i]
            along = r * row.sign
            a, b = float(ll.stations[k]), float(ll.stations[k + 1])
            props: dict[str, Any] = {"lanelet": ll.id, "subtype": ll.subtype}
            if ll.junction:
                props["junction"] = True
            xy = _piece_xy(ll, k, along)
            draft = LaneDraft(
                row.id,
                0,
                ll.type,
                ll.width(a, b),
                _direction(ll, along),
                xy,
                f"lanelet {ll.id}",
                succ,
                props,
            )
            lanes.append((draft, xy))
        # areas beside the outer pieces, kept where the element still passes the loader
        for outer in (LEFT, RIGHT):
            (i, k), r = pieces[0] if outer == LEFT else pieces[-1]
            ll = lanelets[i]
            along = r * row.sign
            side = outer if along > 0 else 1 - outer
            if ll.type not in ("driving", "bicycle") or any(
                n is not None for n in ll.neighbours[side]
            ):
                continue
            for area in by_linestring.get(ll.linestrings[side], ()):
                made = _area_lane(ll, k, side, along, area, row.id, succ)
                if made is None:
                    continue
                trial = [made, *lanes] if outer == LEFT else [*lanes, made]
                if _fault([(xy, d.width) for d, xy in trial]) is not None:
                    report.skip(
                        f"{area.subtype} area strip that does not fit beside its lanelet",
                        f"area {area.id} beside lanelet {ll.id}",
                    )
                    continue
                area.used = True
                lanes = trial
                break
        for index, (draft, xy) in enumerate(lanes):
            draft.index = index
            draft.lonlat = to_lonlat(projector, xy)
        # the seed lanelet first, so that the loader's messages name it
        seed_id = lanelets[row.seed[0]].id
        yield from sorted(
            (d for d, _ in lanes), key=lambda d: d.properties.get("lanelet") != seed_id
        )


def _area_lane(
    ll: _Lanelet, k: int, side: int, along: int, area: _Area, segment: str, succ: tuple[str, ...]
) -> tuple[LaneDraft, FloatArray] | None:
    """The lane that the strip of `area` beside piece k of `ll` on `side` makes (its centre
    line in metres along the reference), or None if the area is not found along it."""
    line = ll.lines[side]
    t0 = float(line.project(ll.center.interpolate(float(ll.stations[k]))))
    t1 = float(line.project(ll.center.interpolate(float(ll.stations[k + 1]))))
    if t1 - t0 < MIN_PIECE:
        return None
    n = max(5, math.ceil((t1 - t0) / _STEP))
    depths = []
    for t in np.linspace(t0, t1, n + 2)[1:-1]:
        p = np.asarray(line.interpolate(t).coords[0])
        ahead = np.asarray(line.interpolate(min(t + 0.5, line.length)).coords[0])
        behind = np.asarray(line.interpolate(max(t - 0.5, 0.0)).coords[0])
        tangent = ahead - behind
        norm = math.hypot(*tangent)
        if norm == 0.0:
            continue
        tx, ty = tangent / norm
        normal = np.array([-ty, tx]) if side == LEFT else np.array([ty, -tx])
        start = p + 0.02 * normal
        hit = LineString([start, p + _RAY * normal]).intersection(area.polygon)
        for part in getattr(hit, "geoms", [hit]):
            if (
                isinstance(part, LineString)
                and not part.is_empty
                and part.distance(Point(start)) < 0.05
            ):
                depths.append(part.length + 0.02)
                break
    if len(depths) < _AREA_COVER * n:
        return None
    lane_type, cap = AREA_LANES[area.subtype]
    width = min(float(np.median(depths)), cap)
    if width < _AREA_MIN_WIDTH:
        return None
    # the mitred parallel of the bound (the loader's own notion of a lateral offset)
    strip = dedupe(np.asarray(substring(line, t0, t1).coords, dtype=np.float64), _VERTEX_GAP)
    try:
        frame = Frame(strip)
    except MapError:
        return None
    xy = frame.p + (-width / 2.0 if side == LEFT else width / 2.0) * frame.m
    if not LineString(xy).is_simple:
        return None
    xy = xy if along > 0 else xy[::-1]
    direction: Direction = "both" if lane_type == "sidewalk" else _direction(ll, along)
    props = {"area": area.id, "subtype": area.subtype, "beside_lanelet": ll.id}
    draft = LaneDraft(segment, 0, lane_type, width, direction, xy, f"area {area.id}", succ, props)
    return draft, xy
