"""Write the small hand-made Lanelet2 maps of this folder (run from the repository root:
``python tests/data/lanelet2/make_inputs.py``).

Geometry is drawn in metres (x east, y north) on the UTM grid around 49.0 N, 8.4 E and
written as lat/lon with 10 decimals. Lanelet2 finds a lanelet's direction from which
bound is on its left. Every file is described in ``tests/test_import_lanelet2.py``.
"""

from __future__ import annotations

import math
from pathlib import Path

from laas.map.geo import UtmProjection

HERE = Path(__file__).resolve().parent
BASE_LON, BASE_LAT = 8.4, 49.0
_PROJ = UtmProjection.for_location(BASE_LON, BASE_LAT)
_E0, _N0 = _PROJ.to_utm(BASE_LON, BASE_LAT)

Pt = tuple[float, float]


class Osm:
    """A Lanelet2 OSM file under construction; nodes at equal positions are shared."""

    def __init__(self) -> None:
        self.nodes: dict[Pt, int] = {}
        self.ways: list[tuple[int, list[int], dict[str, str]]] = []
        self.relations: list[tuple[int, list[tuple[str, int]], dict[str, str]]] = []
        self._next_way = 100_000

    def node(self, p: Pt) -> int:
        key = (round(p[0], 4), round(p[1], 4))
        if key not in self.nodes:
            self.nodes[key] = len(self.nodes) + 1
        return self.nodes[key]

    def way(self, points: list[Pt], kind: str = "line_thin", missing: int | None = None) -> int:
        """A linestring; `missing` adds a reference to a node id that is not in the file."""
        self._next_way += 1
        refs = [self.node(p) for p in points]
        if missing is not None:
            refs.insert(1, missing)
        self.ways.append((self._next_way, refs, {"type": kind}))
        return self._next_way

    def lanelet(self, rid: int, left: int | None, right: int | None, **tags: str) -> None:
        members = [(role, w) for role, w in (("left", left), ("right", right)) if w is not None]
        self.relations.append((rid, members, {"type": "lanelet", **tags}))

    def area(self, rid: int, outer: list[int], **tags: str) -> None:
        members = [("outer", w) for w in outer]
        self.relations.append((rid, members, {"type": "multipolygon", **tags}))

    def write(self, name: str) -> None:
        lines = ["<?xml version='1.0' encoding='UTF-8'?>", "<osm version='0.6' generator='laas'>"]
        for (x, y), nid in self.nodes.items():
            lon, lat = _PROJ.to_wgs84(_E0 + x, _N0 + y)
            lines.append(f"  <node id='{nid}' version='1' lat='{lat:.10f}' lon='{lon:.10f}' />")
        for wid, refs, tags in self.ways:
            lines.append(f"  <way id='{wid}' version='1'>")
            lines += [f"    <nd ref='{r}' />" for r in refs]
            lines += [f"    <tag k='{k}' v='{v}' />" for k, v in tags.items()]
            lines.append("  </way>")
        for rid, members, tags in self.relations:
            lines.append(f"  <relation id='{rid}' version='1'>")
            lines += [f"    <member type='way' ref='{w}' role='{role}' />" for role, w in members]
            lines += [f"    <tag k='{k}' v='{v}' />" for k, v in tags.items()]
            lines.append("  </relation>")
        lines.append("</osm>")
        (HERE / name).write_text("\n".join(lines) + "\n", encoding="utf-8")


def xs(x0: float, x1: float, step: float = 10.0) -> list[float]:
    n = max(1, round((x1 - x0) / step))
    return [x0 + (x1 - x0) * k / n for k in range(n + 1)]


def hline(o: Osm, y: float, x0: float, x1: float, kind: str = "line_thin") -> int:
    """A straight bound at height y from x0 to x1 (west to east when x0 < x1)."""
    return o.way([(x, y) for x in xs(min(x0, x1), max(x0, x1))], kind)


def side_by_side() -> None:
    """Lanelets 1001 (left) and 1002 (right), eastbound, 3.5 m each, sharing a bound."""
    o = Osm()
    top, mid, bottom = hline(o, 7.0, 0, 40), hline(o, 3.5, 0, 40), hline(o, 0.0, 0, 40)
    o.lanelet(1001, top, mid, subtype="road", one_way="yes")
    o.lanelet(1002, mid, bottom, subtype="road", one_way="yes")
    o.write("side_by_side.osm")


def opposite() -> None:
    """A two-way road: 2001 eastbound (south half), 2002 westbound (north half); both have
    the middle linestring as their left bound, 2002 inverted."""
    o = Osm()
    top, mid, bottom = hline(o, 7.0, 0, 40), hline(o, 3.5, 0, 40), hline(o, 0.0, 0, 40)
    o.lanelet(2001, mid, bottom, subtype="road", one_way="yes")
    o.lanelet(2002, mid, top, subtype="road")  # one_way unset: the default, yes
    o.write("opposite.osm")


def neighbour_change() -> None:
    """3001 runs 100 m east; its left neighbour is 3002 for the first 50 m, 3003 for the
    rest (their right bounds are separate linestrings over 3001's left bound's nodes); 3004
    runs along its right side all the way."""
    o = Osm()
    mid = o.way([(x, 3.5) for x in xs(0, 100, 25)])
    first = o.way([(x, 3.5) for x in xs(0, 50, 25)])
    second = o.way([(x, 3.5) for x in xs(50, 100, 25)])
    top1, top2 = hline(o, 7.0, 0, 50), hline(o, 7.0, 50, 100)
    bottom = o.way([(x, 0.0) for x in xs(0, 100, 25)])
    low = o.way([(x, -3.5) for x in xs(0, 100, 25)])
    o.lanelet(3001, mid, bottom, subtype="road")
    o.lanelet(3002, top1, first, subtype="road")
    o.lanelet(3003, top2, second, subtype="road")
    o.lanelet(3004, bottom, low, subtype="road")
    o.write("neighbour_change.osm")


def subtypes() -> None:
    """A road (4002, north) beside a bus lane (4001, south), a parking area (4100) along the
    bus lane's outer bound and a walkway area (4101) along the road's; walkways 4003 (no
    one_way), 4004 (one_way=yes), 4005 (one_way:pedestrian=yes); a crosswalk (4006), a rail
    (4007) and a lanelet of unknown subtype (4008) elsewhere."""
    o = Osm()
    top, mid, bottom = hline(o, 7.0, 0, 40), hline(o, 3.5, 0, 40), hline(o, 0.0, 0, 40, "curbstone")
    o.lanelet(4001, mid, bottom, subtype="bus_lane", one_way="yes")
    o.lanelet(4002, top, mid, subtype="road", one_way="yes")
    park = o.way([(40.0, 0.0), (40.0, -2.5), (0.0, -2.5), (0.0, 0.0)], "curbstone")
    o.area(4100, [bottom, park], subtype="parking")
    walk = o.way([(40.0, 7.0), (40.0, 9.0), (0.0, 9.0), (0.0, 7.0)], "curbstone")
    o.area(4101, [top, walk], subtype="walkway")
    for k, (rid, tags) in enumerate(
        [
            (4003, {}),
            (4004, {"one_way": "yes"}),
            (4005, {"one_way:pedestrian": "yes"}),
            (4006, {"subtype": "crosswalk"}),
            (4007, {"subtype": "rail"}),
            (4008, {"subtype": "hovercraft"}),
        ]
    ):
        y = 30.0 + 10.0 * k
        tags = {"subtype": "walkway", **tags}
        o.lanelet(rid, hline(o, y + 2.0, 0, 30), hline(o, y, 0, 30), **tags)
    o.write("subtypes.osm")


def successors() -> None:
    """5001 -> 5002 (shared end points), then 5003 straight on and 5004 turning right: they
    start at the same stop line and overlap (a junction). Further north a two-way road in
    two elements: 5101 (east) and 5102 (west), then 5103 (west) and 5104 (east); 5104
    follows 5101, 5102 follows 5103."""
    o = Osm()
    o.lanelet(5001, hline(o, 3.5, 0, 30), hline(o, 0.0, 0, 30), subtype="road")
    o.lanelet(5002, hline(o, 3.5, 30, 60), hline(o, 0.0, 30, 60), subtype="road")
    o.lanelet(5003, hline(o, 3.5, 60, 90), hline(o, 0.0, 60, 90), subtype="road")
    # right turn around (60, -10): left bound radius 13.5, right bound radius 10
    angles = [math.radians(90 - 10 * k) for k in range(10)]
    left = o.way([(60 + 13.5 * math.cos(a), -10 + 13.5 * math.sin(a)) for a in angles])
    right = o.way([(60 + 10.0 * math.cos(a), -10 + 10.0 * math.sin(a)) for a in angles])
    o.lanelet(5004, left, right, subtype="road")
    y = 40.0
    mid1, mid2 = hline(o, y + 3.5, 0, 30), hline(o, y + 3.5, 30, 60)
    o.lanelet(5101, mid1, hline(o, y, 0, 30), subtype="road")
    o.lanelet(5102, mid1, hline(o, y + 7.0, 0, 30), subtype="road")
    o.lanelet(5103, mid2, hline(o, y + 7.0, 30, 60), subtype="road")
    o.lanelet(5104, mid2, hline(o, y, 30, 60), subtype="road")
    o.write("successors.osm")


def repairs() -> None:
    """8001 turns right by 90 degrees at one corner (x = 20 m); 8101 widens from 2 m to
    10 m over 60 m beside 8102, 3 m wide throughout."""
    o = Osm()
    left = o.way([(0.0, 3.5), (23.5, 3.5), (23.5, -20.0)])
    right = o.way([(0.0, 0.0), (20.0, 0.0), (20.0, -20.0)])
    o.lanelet(8001, left, right, subtype="road")
    y = 30.0
    top = o.way([(x, y + 3.0 + 2.0 + 8.0 * x / 60.0) for x in xs(0, 60, 5)])
    mid, bottom = hline(o, y + 3.0, 0, 60), hline(o, y, 0, 60)
    o.lanelet(8101, top, mid, subtype="road")
    o.lanelet(8102, mid, bottom, subtype="road")
    o.write("repairs.osm")


def broken() -> None:
    """A good lanelet (6001); 6002 whose right bound references a node missing from the
    file; 6003 without a right bound; 6004 only 0.3 m long; a stop line (in no lanelet)
    with a missing node."""
    o = Osm()
    o.lanelet(6001, hline(o, 3.5, 0, 30), hline(o, 0.0, 0, 30), subtype="road")
    o.lanelet(6002, hline(o, 13.5, 0, 30), o.way([(0.0, 10.0), (30.0, 10.0)], missing=999_999))
    o.lanelet(6003, hline(o, 23.5, 0, 30), None, subtype="road")
    o.lanelet(6004, o.way([(0.0, 33.5), (0.3, 33.5)]), o.way([(0.0, 30.0), (0.3, 30.0)]))
    o.way([(0.0, 40.0), (5.0, 40.0)], "stop_line", missing=888_888)  # in no lanelet
    o.write("broken.osm")
    only = Osm()
    only.lanelet(7001, only.way([(0.0, 3.5), (30.0, 3.5)]), None, subtype="road")
    only.write("broken_only.osm")


if __name__ == "__main__":
    side_by_side()
    opposite()
    neighbour_change()
    subtypes()
    successors()
    repairs()
    broken()
