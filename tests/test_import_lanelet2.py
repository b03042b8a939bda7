"""The Lanelet2 importer (laas.map.importers.lanelet2) on Lanelet2's Karlsruhe example map
(maps/samples/lanelet2/mapping_example.osm, BSD-3-Clause) and on small hand-made maps
(tests/data/lanelet2/, written by make_inputs.py there):

side_by_side.osm      1001 (left) and 1002 (right), eastbound, sharing a bound
opposite.osm          2001 eastbound, 2002 westbound, sharing their left bound (inverted)
neighbour_change.osm  3001 with left neighbour 3002, then 3003; 3004 on its right throughout
subtypes.osm          bus lane 4001 + road 4002 with a parking area (4100) and a walkway
                      area (4101) beside them; walkways 4003-4005; crosswalk 4006, rail
                      4007, unknown subtype 4008
successors.osm        5001 -> 5002 -> {5003, 5004} (a junction); a two-way road in two
                      elements, 5101/5102 then 5103/5104
repairs.osm           8001 with a 90 degree corner; 8101 widening from 2 to 10 m beside 8102
broken.osm            6001 fine; 6002 with a missing node; 6003 without right bound; 6004
                      0.3 m long; a stop line with a missing node
broken_only.osm       7001 without right bound
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path
from typing import Any

import lanelet2
import numpy as np
import pytest
from lanelet2.core import BasicPoint3d
from lanelet2.io import Origin
from lanelet2.projection import UtmProjector
from shapely import LineString, Point

from laas.errors import ConfigError, MapError
from laas.map.geo import UtmProjection
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap, Segment
from laas.map.importers import import_map
from laas.map.importers.common import ImportResult
from laas.map.importers.lanelet2 import import_lanelet2, to_lonlat

ROOT = Path(__file__).parents[1]
KARLSRUHE = ROOT / "maps" / "samples" / "lanelet2" / "mapping_example.osm"
DATA = Path(__file__).parent / "data" / "lanelet2"
REJECTED = "road element rejected by the loader"


@pytest.fixture(scope="module")
def karlsruhe() -> tuple[ImportResult, float]:
    start = time.perf_counter()
    result = import_lanelet2(KARLSRUHE)
    return result, time.perf_counter() - start


def _imp(name: str, **options: Any) -> ImportResult:
    return import_lanelet2(DATA / name, **options)


def _lanelet_lanes(hdmap: HdMap) -> dict[int, list[tuple[Segment, int]]]:
    """lanelet id -> [(segment, lane index)] of the lanes made from it."""
    out: dict[int, list[tuple[Segment, int]]] = {}
    for seg in hdmap.segments.values():
        for lane in seg.lanes:
            if "lanelet" in lane.properties:
                out.setdefault(lane.properties["lanelet"], []).append((seg, lane.index))
    return out


def _only_segment(hdmap: HdMap, lanelet: int) -> Segment:
    (seg, _), *rest = _lanelet_lanes(hdmap)[lanelet]
    assert not rest
    return seg


def _file_nodes(path: Path) -> dict[int, tuple[float, float]]:
    """node id -> (lat, lon) as written in the file."""
    return {
        int(e.get("id", "0")): (float(e.get("lat", "nan")), float(e.get("lon", "nan")))
        for e in ET.parse(path).getroot().iter("node")
    }


# ----------------------------------------------------------------------------------------------
# Karlsruhe
# ----------------------------------------------------------------------------------------------


def test_karlsruhe_imports_with_few_rejections(karlsruhe: tuple[ImportResult, float]) -> None:
    result, seconds = karlsruhe
    m = result.hdmap
    # printed, not bounded (docs/maps/lanelet2.md quotes about 1.3 s on one core)
    print(f"\nKarlsruhe imported in {seconds:.2f} s")
    assert len(m.segments) == 279
    by_type = Counter(lane.type for seg in m.segments.values() for lane in seg.lanes)
    assert by_type == {"driving": 358, "sidewalk": 55, "parking": 44, "bicycle": 14}
    assert Counter(len(seg.lanes) for seg in m.segments.values()) == {1: 149, 2: 76, 3: 46, 4: 8}
    skipped = result.report.skipped
    assert skipped[REJECTED] == 1  # lanelet 50348: 1.3 m long, 8.5 m wide, a near duplicate
    assert "lanelet 50348" in result.report.examples[REJECTED][0]
    assert skipped["crosswalk lanelet (crosses roads)"] == 8
    assert skipped["rail lanelet (no lane type for rails)"] == 2
    assert skipped["connection lost: two road elements start at the same place"] <= 1
    # every road, highway, bicycle and walkway lanelet is in the map, but the rejected one
    kept = _lanelet_lanes(m)
    assert len(kept) == 371 - 8 - 2 - 1
    directions = Counter(lane.direction for seg in m.segments.values() for lane in seg.lanes)
    assert directions["backward"] > 0 and directions["both"] > 0


def test_karlsruhe_written_map_loads_strictly(
    karlsruhe: tuple[ImportResult, float], tmp_path: Path
) -> None:
    result, _ = karlsruhe
    out = tmp_path / "karlsruhe.geojson"
    result.write(out)
    loaded = read_geojson_file(out)
    assert list(loaded.segments) == list(result.hdmap.segments)
    for seg in loaded.segments.values():
        assert seg.successors == result.hdmap.segments[seg.id].successors


def test_karlsruhe_centres_are_lanelet2s_centre_lines(
    karlsruhe: tuple[ImportResult, float],
) -> None:
    """Each lane made from a lanelet lies on Lanelet2's own centre line of it (computed here
    with another origin and projected back to lat/lon), and the pieces of a lanelet add up
    to its whole centre line."""
    result, _ = karlsruhe
    projector = UtmProjector(Origin(48.99, 8.41))
    lmap = lanelet2.io.load(str(KARLSRUHE), projector)
    utm = UtmProjection.for_location(8.42, 49.0)
    reference: dict[int, LineString] = {}
    for ll in lmap.laneletLayer:
        xy = np.array([(p.x, p.y) for p in ll.centerline])
        lonlat = to_lonlat(projector, xy)
        reference[ll.id] = LineString(utm.to_utm_array(lonlat[:, 0], lonlat[:, 1]))
    worst = 0.0
    covered: Counter[int] = Counter()
    for feature in result.geojson["features"]:
        lid = feature["properties"].get("lanelet")
        if lid is None:
            continue
        c = np.array(feature["geometry"]["coordinates"])
        line = LineString(utm.to_utm_array(c[:, 0], c[:, 1]))
        for s in np.linspace(0.0, line.length, 25):
            worst = max(worst, reference[lid].distance(line.interpolate(s)))
        covered[lid] += line.length
    assert len(covered) == 360
    assert worst < 0.1, f"a lane centre is {worst:.3f} m off Lanelet2's centre line"
    for lid, length in covered.items():
        assert length == pytest.approx(reference[lid].length, abs=0.2), lid


def test_karlsruhe_successors_follow_lanelet2s_routing_graph(
    karlsruhe: tuple[ImportResult, float],
) -> None:
    """Where Lanelet2's routing graph (German vehicle rules) has lanelet B following A, the
    element holding A's end and the one holding B's start are linked, one as the other's
    successor; all but the one connection reported lost."""
    result, _ = karlsruhe
    m = result.hdmap
    lmap = lanelet2.io.load(str(KARLSRUHE), UtmProjector(Origin(49.0, 8.42)))
    rules = lanelet2.traffic_rules.create(
        lanelet2.traffic_rules.Locations.Germany, lanelet2.traffic_rules.Participants.Vehicle
    )
    graph = lanelet2.routing.RoutingGraph(lmap, rules)
    lanes = _lanelet_lanes(m)

    back = UtmProjector(Origin(49.0, 8.42))

    def holding(lid: int, end: bool) -> Segment:
        """The element whose lane from lanelet `lid` is nearest to its travel end (start)."""
        ll = lmap.laneletLayer[lid]
        p = ll.centerline[-1] if end else ll.centerline[0]
        g = back.reverse(BasicPoint3d(p.x, p.y, 0.0))
        here = Point(*m.projection.to_utm(g.lon, g.lat))
        return min(
            (seg for seg, _ in lanes[lid]),
            key=lambda seg: min(
                lane.centerline.distance(here)
                for lane in seg.lanes
                if lane.properties.get("lanelet") == lid
            ),
        )

    pairs = missing = 0
    for ll in lmap.laneletLayer:
        if ll.id not in lanes:
            continue
        for nxt in graph.following(ll):
            if nxt.id not in lanes:
                continue
            pairs += 1
            a, b = holding(ll.id, True), holding(nxt.id, False)
            if b.id not in a.successors and a.id not in b.successors:
                missing += 1
    assert pairs > 300
    assert (
        missing
        <= result.report.skipped["connection lost: two road elements start at the same place"]
    )


def test_karlsruhe_nodes_survive_the_projection() -> None:
    """Lat/lon -> Lanelet2's plane -> to_lonlat gives back every node of the file."""
    projector = UtmProjector(Origin(49.02, 8.40))
    lmap = lanelet2.io.load(str(KARLSRUHE), projector)
    nodes = _file_nodes(KARLSRUHE)
    points = list(lmap.pointLayer)
    lonlat = to_lonlat(projector, np.array([(p.x, p.y) for p in points]))
    expected = np.array([(nodes[p.id][1], nodes[p.id][0]) for p in points])
    assert len(points) == len(nodes) == 2258
    assert np.abs(lonlat - expected).max() < 1e-9


def test_origin_does_not_change_the_coordinates(
    karlsruhe: tuple[ImportResult, float],
) -> None:
    result, _ = karlsruhe
    other = import_lanelet2(KARLSRUHE, origin=(49.05, 8.35))  # some 6 km away
    mine = {
        (f["properties"]["segment"], f["properties"]["lane"]): f for f in result.geojson["features"]
    }
    theirs = {
        (f["properties"]["segment"], f["properties"]["lane"]): f for f in other.geojson["features"]
    }
    assert mine.keys() == theirs.keys()
    worst = max(
        float(
            np.abs(
                np.array(mine[k]["geometry"]["coordinates"])
                - np.array(theirs[k]["geometry"]["coordinates"])
            ).max()
        )
        for k in mine
    )
    assert worst < 1e-7


# ----------------------------------------------------------------------------------------------
# Hand-made maps
# ----------------------------------------------------------------------------------------------


def test_side_by_side_lanelets_form_one_element() -> None:
    m = _imp("side_by_side.osm").hdmap
    assert list(m.segments) == ["ll1001"]
    seg = m.segments["ll1001"]
    assert [lane.properties["lanelet"] for lane in seg.lanes] == [1001, 1002]
    assert [lane.direction for lane in seg.lanes] == ["forward", "forward"]
    assert [lane.width for lane in seg.lanes] == pytest.approx([3.5, 3.5], abs=0.01)
    assert seg.lane_offsets(20.0)[1] == pytest.approx(3.5, abs=0.01)
    assert seg.heading(20.0) == pytest.approx(90.0, abs=0.5)  # east
    assert seg.length == pytest.approx(40.0, abs=0.01)


def test_known_node_survives() -> None:
    """Lanelet 1001's centre line starts halfway between the first nodes of its bounds
    (3.5 m apart, so the midpoint in lat/lon is the midpoint on the ground to 1e-12 deg)."""
    path = DATA / "side_by_side.osm"
    nodes = _file_nodes(path)
    root = ET.parse(path).getroot()
    ways = {
        int(w.get("id", "0")): [int(n.get("ref", "0")) for n in w.iter("nd")]
        for w in root.iter("way")
    }
    rel = next(r for r in root.iter("relation") if r.get("id") == "1001")
    firsts = [nodes[ways[int(m.get("ref", "0"))][0]] for m in rel.iter("member")]
    lat, lon = np.mean(firsts, axis=0)
    for origin in (None, (48.9, 8.3)):
        result = _imp("side_by_side.osm", origin=origin)
        feature = next(
            f for f in result.geojson["features"] if f["properties"].get("lanelet") == 1001
        )
        first = feature["geometry"]["coordinates"][0]
        assert abs(first[0] - lon) < 1e-7 and abs(first[1] - lat) < 1e-7


def test_opposite_lanelet_is_backward_with_reversed_centre_line() -> None:
    m = _imp("opposite.osm").hdmap
    seg = _only_segment(m, 2001)
    # reference: 2001's direction (east); lane 0 is the north lane, 2002, running west
    assert [lane.properties["lanelet"] for lane in seg.lanes] == [2002, 2001]
    assert [lane.direction for lane in seg.lanes] == ["backward", "forward"]
    for lane in seg.lanes:
        xs = np.asarray(lane.centerline.coords)[:, 0]
        assert xs[-1] > xs[0] + 39.0  # coordinates follow the reference, eastwards
    assert seg.lane_offsets(20.0)[1] == pytest.approx(3.5, abs=0.01)


def test_neighbour_change_cuts_the_element() -> None:
    result = _imp("neighbour_change.osm")
    m = result.hdmap
    assert list(m.segments) == ["ll3001-0", "ll3001-1"]
    first, second = m.segments["ll3001-0"], m.segments["ll3001-1"]
    assert [lane.properties["lanelet"] for lane in first.lanes] == [3002, 3001, 3004]
    assert [lane.properties["lanelet"] for lane in second.lanes] == [3003, 3001, 3004]
    for seg in (first, second):
        assert seg.length == pytest.approx(50.0, abs=0.05)
        for lane in seg.lanes:  # every lane is cut at the same station, x = 50 m
            assert lane.centerline.length == pytest.approx(50.0, abs=0.05)
    assert first.successors == ("ll3001-1",)
    assert second.successors == ()
    assert not result.report.skipped


def test_subtypes_bus_lane_walkways_and_areas() -> None:
    result = _imp("subtypes.osm")
    m = result.hdmap
    road = _only_segment(m, 4001)
    kinds = [
        (lane.type, lane.direction, dict(lane.properties).get("subtype")) for lane in road.lanes
    ]
    assert kinds == [
        ("sidewalk", "both", "walkway"),  # walkway area 4101, north of the road
        ("driving", "forward", "road"),
        ("driving", "forward", "bus_lane"),
        ("parking", "forward", "parking"),  # parking area 4100, south of the bus lane
    ]
    assert road.lanes[0].properties["area"] == 4101
    assert road.lanes[3].properties["area"] == 4100
    assert [lane.width for lane in road.lanes] == pytest.approx([2.0, 3.5, 3.5, 2.5], abs=0.02)
    offsets = road.lane_offsets(20.0)
    assert offsets[1:] == pytest.approx([2.75, 6.25, 9.25], abs=0.02)
    walk = {lid: _only_segment(m, lid).lanes[0] for lid in (4003, 4004, 4005)}
    assert {lid: (lane.type, lane.direction) for lid, lane in walk.items()} == {
        4003: ("sidewalk", "both"),  # pedestrians walk both ways by default
        4004: ("sidewalk", "both"),  # one_way is for vehicles
        4005: ("sidewalk", "forward"),  # one_way:pedestrian=yes
    }
    skipped = result.report.skipped
    assert skipped["crosswalk lanelet (crosses roads)"] == 1
    assert skipped["rail lanelet (no lane type for rails)"] == 1
    assert result.report.examples["lanelet of unknown subtype 'hovercraft'"] == ["lanelet 4008"]


def test_successors_from_shared_end_points_and_junctions() -> None:
    result = _imp("successors.osm")
    m = result.hdmap
    s1, s2 = _only_segment(m, 5001), _only_segment(m, 5002)
    straight, turn = _only_segment(m, 5003), _only_segment(m, 5004)
    assert s1.successors == (s2.id,)
    assert set(s2.successors) == {straight.id, turn.id}
    # the two junction lanelets overlap: one element each, flagged
    assert len(straight.lanes) == len(turn.lanes) == 1
    assert straight.lanes[0].properties["junction"] is True
    assert turn.lanes[0].properties["junction"] is True
    assert "junction" not in s1.lanes[0].properties
    # the turn ends heading south
    assert turn.heading(turn.length) == pytest.approx(180.0, abs=6.0)


def test_two_way_road_elements_point_the_same_way() -> None:
    """The second element's first lanelet (5103) runs west, yet the element is oriented east
    like the first one, so that it is the first one's successor; its westbound lane is
    backward."""
    result = _imp("successors.osm")
    m = result.hdmap
    first, second = _only_segment(m, 5101), _only_segment(m, 5103)
    assert second.id == "ll5103"
    assert first.successors == (second.id,)
    assert [lane.properties["lanelet"] for lane in first.lanes] == [5102, 5101]
    assert [lane.properties["lanelet"] for lane in second.lanes] == [5103, 5104]
    assert [lane.direction for lane in second.lanes] == ["backward", "forward"]
    assert second.heading(10.0) == pytest.approx(90.0, abs=0.5)
    assert "connection lost: two road elements start at the same place" not in (
        result.report.skipped
    )


def test_rows_are_cut_to_pass_the_loader() -> None:
    """A corner sharper than the loader's 60 degrees becomes a cut; lanes that drift apart
    (a lane widening from 2 to 10 m) are cut in the middle: nothing is rejected."""
    result = _imp("repairs.osm")
    assert not result.report.skipped
    m = result.hdmap
    corner = [m.segments["ll8001-0"], m.segments["ll8001-1"]]
    assert corner[0].successors == ("ll8001-1",)
    for seg in corner:
        assert seg.length == pytest.approx(21.75, abs=0.05)  # cut at the corner
    assert [seg.heading(10.0) for seg in corner] == pytest.approx([90.0, 180.0], abs=0.5)
    wide = [m.segments["ll8101-0"], m.segments["ll8101-1"]]
    assert wide[0].successors == ("ll8101-1",)
    assert [seg.lanes[0].width for seg in wide] == pytest.approx([4.0, 8.0], abs=0.05)
    assert [seg.lanes[1].width for seg in wide] == pytest.approx([3.0, 3.0], abs=0.01)


def test_broken_lanelets_are_counted_by_id() -> None:
    result = _imp("broken.osm")
    assert list(result.hdmap.segments) == ["ll6001"]
    report = result.report
    kind = "lanelet with a missing or broken bound"
    assert report.skipped[kind] == 2
    named = report.examples[kind]
    assert named[0].startswith("lanelet 6002: ") and "nonexisting points" in named[0]
    assert named[1].startswith("lanelet 6003: ") and "right border" in named[1]
    assert report.examples["degenerate lanelet"] == ["lanelet 6004: centre line shorter than 0.5 m"]
    # a broken way that no lanelet uses is counted on its own
    (stop_line,) = report.examples["primitive the Lanelet2 parser could not read"]
    assert "nonexisting points" in stop_line


def test_nothing_usable_is_a_map_error_naming_the_lanelet() -> None:
    with pytest.raises(MapError, match=r"broken_only\.osm: no lanelet .*lanelet 7001"):
        _imp("broken_only.osm")


def test_unreadable_input_is_a_map_error(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="cannot read"):
        import_lanelet2(tmp_path / "missing.osm")
    bad = tmp_path / "bad.osm"
    bad.write_text("<osm><node id='1' lat='49'", encoding="utf-8")
    with pytest.raises(MapError, match=r"bad\.osm: not an OSM XML file"):
        import_lanelet2(bad)
    with pytest.raises(MapError, match="cannot read"):
        import_lanelet2(bad, origin=(49.0, 8.4))  # Lanelet2's own parser says so too


def test_bad_origin_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="origin"):
        _imp("side_by_side.osm", origin=(95.0, 8.4))


def test_import_map_dispatches_to_lanelet2(tmp_path: Path) -> None:
    result = import_map("lanelet2", DATA / "opposite.osm", origin=(49.0, 8.4))
    out = tmp_path / "opposite.geojson"
    result.write(out)
    assert list(read_geojson_file(out).segments) == ["ll2001"]
