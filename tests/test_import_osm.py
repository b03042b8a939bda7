"""The OpenStreetMap importer: lane layouts from tags, lane-centre geometry, topology,
bounding-box extracts and bad input on hand-made .osm files (tests/data/osm/), and the
real Helsinki extract (maps/samples/osm/Helsinki.osm.pbf, ODbL)."""

from __future__ import annotations

import math
import time
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely
from shapely import LineString, Point

from laas.errors import ConfigError, MapError
from laas.map.frame import sharpest_turn
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import Lane
from laas.map.importers import import_map
from laas.map.importers.common import ImportReport, ImportResult
from laas.map.importers.osm import import_osm, lane_layout, parse_width

DATA = Path(__file__).parent / "data" / "osm"
TAGS = DATA / "tags.osm"
JUNCTION = DATA / "junction.osm"
HELSINKI = Path(__file__).parents[1] / "maps" / "samples" / "osm" / "Helsinki.osm.pbf"

BAD_TAG = "tag value not usable, default used: lanes"
LOST = "connection lost: two road elements start at the same node"

# way id -> lanes left to right: (type, direction, width m, centre offset from the way m,
# the lane property that tells its kind or None)
EXPECTED: dict[int, list[tuple[str, str, float, float, Any]]] = {
    101: [("driving", "backward", 3.0, -1.5, None), ("driving", "forward", 3.0, 1.5, None)],
    102: [
        ("driving", "backward", 3.0, -4.5, None),
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "forward", 3.0, 1.5, None),
        ("driving", "forward", 3.0, 4.5, None),
    ],
    103: [
        ("driving", "backward", 3.25, -3.25, None),
        ("driving", "forward", 3.25, 0.0, None),
        ("driving", "forward", 3.25, 3.25, None),
    ],
    104: [
        ("driving", "backward", 3.25, -3.25, None),
        ("driving", "backward", 3.25, 0.0, None),
        ("driving", "forward", 3.25, 3.25, None),
    ],
    105: [("driving", "forward", 3.0, 0.0, None)],
    # oneway=-1: node order kept, lanes backward; the cycle lane on the travel's right
    106: [
        ("bicycle", "backward", 1.5, -3.75, "lane"),
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "backward", 3.0, 1.5, None),
    ],
    # width=10 minus 2 x 2.2 m parking: driving lanes of 2.8 m
    107: [
        ("parking", "backward", 2.2, -3.9, "parallel"),
        ("driving", "backward", 2.8, -1.4, None),
        ("driving", "forward", 2.8, 1.4, None),
        ("parking", "forward", 2.2, 3.9, "parallel"),
    ],
    # the brief's example
    108: [
        ("sidewalk", "both", 2.0, -5.5, None),
        ("bicycle", "backward", 1.5, -3.75, "lane"),
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "forward", 3.0, 1.5, None),
        ("bicycle", "forward", 1.5, 3.75, "lane"),
        ("sidewalk", "both", 2.0, 5.5, None),
    ],
    109: [
        ("bicycle", "backward", 1.5, -3.75, "lane"),
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "forward", 3.0, 1.5, None),
        ("parking", "forward", 4.5, 5.25, "diagonal"),
        ("bicycle", "forward", 2.0, 8.5, "track"),
        ("sidewalk", "both", 1.5, 10.25, None),
    ],
    110: [
        ("sidewalk", "both", 1.5, -4.25, None),
        ("bicycle", "forward", 2.0, -2.5, "track"),
        ("driving", "forward", 3.0, 0.0, None),
        ("bicycle", "forward", 2.0, 2.5, "track"),
    ],
    111: [
        ("sidewalk", "both", 1.5, -3.75, None),
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "forward", 3.0, 1.5, None),
    ],
    112: [("driving", "backward", 3.0, -1.5, None), ("driving", "forward", 3.0, 1.5, None)],
    113: [
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "forward", 3.0, 1.5, None),
        ("sidewalk", "both", 1.5, 3.75, None),
    ],
    # lanes=4 busway=lane: the outer lanes become bus lanes
    114: [
        ("driving", "backward", 3.25, -4.875, "bus"),
        ("driving", "backward", 3.25, -1.625, None),
        ("driving", "forward", 3.25, 1.625, None),
        ("driving", "forward", 3.25, 4.875, "bus"),
    ],
    # no lanes tag: the bus lane is added
    115: [
        ("driving", "backward", 3.0, -3.0, None),
        ("driving", "forward", 3.0, 0.0, None),
        ("driving", "forward", 3.0, 3.0, "bus"),
    ],
    116: [("bicycle", "both", 2.0, 0.0, None)],
    117: [("bicycle", "forward", 2.0, 0.0, None)],
    118: [("sidewalk", "both", 2.0, 0.0, None)],
    119: [("sidewalk", "both", 2.0, 0.0, None)],
    120: [("sidewalk", "both", 6.0, 0.0, None)],
    121: [("driving", "backward", 3.0, -1.5, None), ("driving", "forward", 3.0, 1.5, None)],
    122: [
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "forward", 3.0, 1.5, None),
        ("parking", "forward", 5.0, 5.5, "perpendicular"),
    ],
    123: [("driving", "both", 3.0, 0.0, None)],
    124: [("driving", "forward", 3.5, -1.75, None), ("driving", "forward", 3.5, 1.75, None)],
    125: [("bicycle", "backward", 1.5, -2.25, "lane"), ("driving", "forward", 3.0, 0.0, None)],
    126: [
        ("driving", "backward", 3.0, -1.5, None),
        ("driving", "forward", 3.0, 1.5, None),
        ("bicycle", "both", 2.0, 4.0, "track"),
    ],
    # curved; width=7; sidewalk:both=yes overridden on the left by sidewalk:left=separate
    127: [
        ("driving", "backward", 3.5, -1.75, None),
        ("driving", "forward", 3.5, 1.75, None),
        ("sidewalk", "both", 1.5, 4.25, None),
    ],
    128: [
        ("parking", "forward", 2.2, -4.35, "parallel"),
        ("driving", "forward", 3.25, -1.625, None),
        ("driving", "forward", 3.25, 1.625, "bus"),
        ("parking", "forward", 2.2, 4.35, "parallel"),
    ],
}


def _kind(props: Any) -> Any:
    """The property that tells a lane's kind: bus lane, cycleway kind, parking orientation."""
    if props.get("bus_lane"):
        return "bus"
    return props.get("cycleway") or props.get("parking")


def _osm_lines(path: Path) -> dict[int, np.ndarray]:
    """Each way's node coordinates (lon, lat), read from the XML without osmium."""
    root = ET.parse(path).getroot()
    nodes = {
        int(n.get("id", "")): (float(n.get("lon", "")), float(n.get("lat", "")))
        for n in root.iter("node")
    }
    return {
        int(w.get("id", "")): np.array([nodes[int(nd.get("ref", ""))] for nd in w.iter("nd")])
        for w in root.iter("way")
    }


def _lanes(result: ImportResult) -> list[Lane]:
    return [lane for seg in result.hdmap.segments.values() for lane in seg.lanes]


@pytest.fixture(scope="module")
def tags_map() -> ImportResult:
    return import_osm(TAGS)


@pytest.fixture(scope="module")
def junction_map() -> ImportResult:
    return import_osm(JUNCTION)


# ----------------------------------------------------------------------------------------------
# Lanes from tags
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("way", sorted(EXPECTED))
def test_lane_layout_per_tag_case(tags_map: ImportResult, way: int) -> None:
    seg = tags_map.hdmap.segments[f"way{way}-0"]
    got = [
        (lane.type, lane.direction, round(lane.width, 3), _kind(lane.properties))
        for lane in seg.lanes
    ]
    want = [(t, d, w, k) for t, d, w, _, k in EXPECTED[way]]
    assert got == want
    for lane in seg.lanes:
        assert lane.properties["osm_way"] == way
        assert lane.properties["highway"] in (
            "residential",
            "primary",
            "secondary",
            "tertiary",
            "cycleway",
            "footway",
            "path",
            "pedestrian",
            "service",
            "motorway",
        )
        assert lane.properties["origin"] == f"way {way}"


def test_lane_centres_lie_at_the_expected_offsets(tags_map: ImportResult) -> None:
    """Every lane centre, sampled every metre, is |d| from the way's line (UTM) within
    0.1 m, on the right side for d > 0; the curved way 127 included."""
    hdmap = tags_map.hdmap
    lines = _osm_lines(TAGS)
    worst = 0.0
    for way, lanes in EXPECTED.items():
        ll = lines[way]
        xy = hdmap.projection.to_utm_array(ll[:, 0], ll[:, 1])
        ref = LineString(xy)
        seg = hdmap.segments[f"way{way}-0"]
        for lane, (_, _, _, offset, _) in zip(seg.lanes, lanes, strict=True):
            centre = lane.centerline
            for s in np.arange(0.5, centre.length - 0.5, 1.0):
                p = centre.interpolate(s)
                dist = float(ref.distance(p))
                worst = max(worst, abs(dist - abs(offset)))
                if abs(offset) > 0.5:
                    at = min(max(float(ref.project(p)), 0.5), ref.length - 0.5)
                    a, b = ref.interpolate(at - 0.5), ref.interpolate(at + 0.5)
                    cross = (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x)
                    assert (cross < 0) == (offset > 0), (way, lane.index)  # right = clockwise
    print(f"largest deviation of a lane centre from its offset: {worst * 1000:.1f} mm")
    assert worst < 0.1


def test_lane_spacing_in_the_loaded_frame(tags_map: ImportResult) -> None:
    """The loader's own frame on lane 0 sees the lanes at the layout's spacing."""
    for way, lanes in EXPECTED.items():
        seg = tags_map.hdmap.segments[f"way{way}-0"]
        want = np.array([off for _, _, _, off, _ in lanes])
        for s in (0.25 * seg.length, 0.5 * seg.length, 0.75 * seg.length):
            got = seg.lane_offsets(s)
            assert np.allclose(got, want - want[0], atol=0.1), (way, s, got)


def test_reversed_oneway_mirrors_the_oneway() -> None:
    """oneway=-1 is the oneway=yes layout seen from the other end."""
    tags = {"highway": "residential", "lanes": "2", "cycleway": "lane", "sidewalk": "right"}
    fwd = lane_layout({**tags, "oneway": "yes"})
    back = lane_layout({**tags, "oneway": "-1", "sidewalk": "left"})
    assert [(x.type, x.width) for x in back.lanes] == [(x.type, x.width) for x in fwd.lanes][::-1]
    assert {x.direction for x in back.lanes if x.type != "sidewalk"} == {"backward"}
    assert back.offsets == tuple(-o for o in fwd.offsets[::-1])


def test_left_hand_traffic_by_driving_side_tag() -> None:
    layout = lane_layout({"highway": "residential", "driving_side": "left", "cycleway": "lane"})
    assert [(x.type, x.direction) for x in layout.lanes] == [
        ("bicycle", "forward"),
        ("driving", "forward"),
        ("driving", "backward"),
        ("bicycle", "backward"),
    ]


@pytest.mark.parametrize(
    ("tags", "want"),
    [
        # lanes = forward + backward + both_ways (the OSM wiki); a both_ways lane is one
        # centre lane for both directions (a shared turn lane)
        ({"lanes": "2", "lanes:both_ways": "1"}, ["both", "centre"]),  # a through lane
        ({"lanes": "3", "lanes:both_ways": "1"}, ["backward", "centre", "forward"]),
        ({"lanes": "5", "lanes:both_ways": "1"}, ["backward"] * 2 + ["centre"] + ["forward"] * 2),
        ({"lanes": "1", "lanes:both_ways": "1"}, ["both"]),  # the one lane is all there is
        ({"lanes": "2", "lanes:both_ways": "2"}, ["both", "centre"]),
        (
            {"lanes:forward": "1", "lanes:backward": "1", "lanes:both_ways": "1"},
            ["backward", "centre", "forward"],
        ),
        ({"lanes:both_ways": "1"}, ["backward", "centre", "forward"]),  # a lane each way
        ({"highway": "service", "lanes:both_ways": "1"}, ["both"]),  # a single track
    ],
)
def test_both_ways_lanes_count_in_lanes(tags: dict[str, str], want: list[str]) -> None:
    layout = lane_layout({"highway": "residential", **tags})
    got = ["centre" if dict(x.properties).get("centre_lane") else x.direction for x in layout.lanes]
    assert got == want
    assert {x.type for x in layout.lanes} == {"driving"}
    if "lanes" in tags:
        assert len(layout.lanes) == int(tags["lanes"])


def test_more_both_ways_lanes_than_lanes_is_counted() -> None:
    report = ImportReport("test")
    layout = lane_layout(
        {"highway": "residential", "lanes": "1", "lanes:both_ways": "2"}, "way 9", report
    )
    assert [x.direction for x in layout.lanes] == ["both"]  # `lanes` is kept
    kind = "tag value not usable, default used: lanes:both_ways"
    assert report.skipped == {kind: 1} and report.examples[kind] == ["way 9: lanes:both_ways='2'"]


def test_narrow_two_way_road_becomes_one_lane() -> None:
    """width=3 on a two-way street without lane tags: one lane for both directions."""
    layout = lane_layout({"highway": "residential", "width": "3"})
    assert [(x.type, x.direction, x.width) for x in layout.lanes] == [("driving", "both", 3.0)]


def test_parse_width() -> None:
    assert parse_width("3.5") == 3.5
    assert parse_width("7 m") == 7.0
    assert parse_width("12'") == pytest.approx(3.6576)
    assert parse_width("12'6\"") == pytest.approx(3.81)
    assert parse_width("wide") is None
    assert parse_width("2,5") is None


def test_bad_tag_is_counted_and_the_default_used(tags_map: ImportResult) -> None:
    report = tags_map.report
    assert report.skipped[BAD_TAG] == 1
    assert report.examples[BAD_TAG] == ["way 121: lanes='abc'"]
    assert len(tags_map.hdmap.segments["way121-0"].lanes) == 2  # the residential default


def test_unused_ways_are_counted_by_kind(tags_map: ImportResult) -> None:
    skipped = tags_map.report.skipped
    assert skipped["highway=steps"] == 1
    assert skipped["highway=construction"] == 1
    assert skipped["highway=proposed"] == 1
    assert skipped["area=yes (a surface, not a road)"] == 1
    assert "road element rejected by the loader" not in skipped
    assert len(tags_map.hdmap.segments) == len(EXPECTED)


def test_written_map_loads_strictly(tags_map: ImportResult, tmp_path: Path) -> None:
    out = tmp_path / "tags.geojson"
    tags_map.write(out)
    loaded = read_geojson_file(out)
    assert set(loaded.segments) == set(tags_map.hdmap.segments)
    lane = loaded.segments["way108-0"].lanes[4]
    assert (lane.type, lane.direction, lane.properties["cycleway"]) == (
        "bicycle",
        "forward",
        "lane",
    )


# ----------------------------------------------------------------------------------------------
# Topology
# ----------------------------------------------------------------------------------------------


def test_ways_split_at_intersections_with_successors(junction_map: ImportResult) -> None:
    segs = junction_map.hdmap.segments
    succ = {sid: set(seg.successors) for sid, seg in segs.items()}
    # the main street is cut at the crossroads C, the cross street too
    assert {"way301-0", "way301-1", "way303-0", "way303-1"} <= set(segs)
    assert math.isclose(segs["way301-0"].length, 100.0, abs_tol=0.1)
    assert succ["way304-0"] == {"way301-0"}  # ends where the main street starts
    # the pieces that end at C name every other piece at C, however it is drawn: the ones
    # that start there and the ones that end there too (met head on)
    at_c = {"way301-0", "way301-1", "way303-0", "way303-1", "way305-0"}
    for ending in ("way301-0", "way303-0", "way305-0"):  # the footway ends at C
        assert succ[ending] == at_c - {ending}
    assert succ["way301-1"] == {"way302-0"}  # the layout changes at node 3
    assert succ["way302-0"] == succ["way303-1"] == set()
    # way301-1 and way303-1 both start at C and cannot name each other; no way that ends
    # at C can be turned round to change that (both run through C)
    lost = junction_map.report.examples[LOST]
    assert junction_map.report.skipped[LOST] == 2 and lost[0] == "node 2 (ways 301, 303)"
    assert not any(lane.properties.get("osm_reversed") for lane in _lanes(junction_map))
    assert len(segs["way301-1"].lanes) == 4 and len(segs["way302-0"].lanes) == 4
    assert [x.type for x in segs["way301-1"].lanes] == [
        "sidewalk",
        "driving",
        "driving",
        "sidewalk",
    ]
    assert [x.type for x in segs["way302-0"].lanes] == ["driving"] * 4


def test_sharp_corner_is_split(junction_map: ImportResult) -> None:
    segs = junction_map.hdmap.segments
    assert set(segs["way306-0"].successors) == {"way306-1"}
    for sid in ("way306-0", "way306-1"):
        assert math.isclose(segs[sid].length, 100.0, abs_tol=0.1)
        turn, _ = sharpest_turn(np.asarray(segs[sid].reference.coords))
        assert turn < 1.0


def test_short_piece_is_left_out_and_bridged(junction_map: ImportResult) -> None:
    segs = junction_map.hdmap.segments
    assert "way307-1" not in segs  # the 0.5 m between the two crossings
    assert junction_map.report.skipped["piece shorter than 1 m between junctions"] == 1
    # through the short piece to node 32, and the crossings' pieces at both nodes
    assert set(segs["way307-0"].successors) == {
        "way307-2",
        "way308-0",
        "way308-1",
        "way309-0",
        "way309-1",
    }
    assert junction_map.report.examples[LOST][1] == "node 32 (ways 307, 309)"


def test_roundabout_and_loop_are_cut_into_open_pieces(junction_map: ImportResult) -> None:
    segs = junction_map.hdmap.segments
    # cut at node 49, where way 311 ends: the pieces ending there name each other
    assert set(segs["way310-0"].successors) == {"way310-1", "way311-0"}
    assert set(segs["way310-1"].successors) == {"way310-0"}
    assert set(segs["way311-0"].successors) == {"way310-0", "way310-1"}
    # junction=roundabout implies oneway: one forward lane
    assert [(x.type, x.direction) for x in segs["way310-0"].lanes] == [("driving", "forward")]
    assert set(segs["way312-0"].successors) == {"way312-1"}
    assert set(segs["way312-1"].successors) == {"way312-0"}
    assert not junction_map.report.skipped.get("road element rejected by the loader")


# ----------------------------------------------------------------------------------------------
# Bounding box
# ----------------------------------------------------------------------------------------------


def _box_around(path: Path, node: int, half: float = 0.0002) -> tuple[float, float, float, float]:
    root = ET.parse(path).getroot()
    n = next(x for x in root.iter("node") if x.get("id") == str(node))
    lon, lat = float(n.get("lon", "")), float(n.get("lat", ""))
    return lon - half, lat - half, lon + half, lat + half


def test_bbox_extract_keeps_ways_touching_it_cut_one_node_beyond() -> None:
    # a box around node 1 only (the main street's first node, the end of way 304)
    result = import_osm(JUNCTION, bbox=_box_around(JUNCTION, 1))
    segs = result.hdmap.segments
    assert set(segs) == {"way301-0", "way304-0"}
    assert math.isclose(segs["way301-0"].length, 100.0, abs_tol=0.1)  # cut at node 2
    assert set(segs["way304-0"].successors) == {"way301-0"}
    assert result.report.skipped["way outside the bbox"] == 10


def test_bbox_around_the_crossroads() -> None:
    result = import_osm(JUNCTION, bbox=_box_around(JUNCTION, 2))
    assert set(result.hdmap.segments) == {
        "way301-0",
        "way301-1",
        "way303-0",
        "way303-1",
        "way305-0",
    }


@pytest.mark.parametrize(
    "bbox", [(25.0, 60.0, 24.0, 61.0), (24.0, 60.0, 25.0, float("nan")), (1.0, 2.0, 3.0)]
)
def test_bad_bbox_is_refused(bbox: Any) -> None:
    with pytest.raises(ConfigError, match="bbox"):
        import_osm(JUNCTION, bbox=bbox)


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------


def test_truncated_xml_is_a_map_error(tmp_path: Path) -> None:
    text = TAGS.read_text(encoding="utf-8")
    bad = tmp_path / "broken.osm"
    bad.write_text(text[: len(text) // 2], encoding="utf-8")
    with pytest.raises(MapError, match=r"broken\.osm: cannot read the OSM file \(XML parsing"):
        import_osm(bad)


def test_missing_file_and_no_roads(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="no such OSM file"):
        import_osm(tmp_path / "nothing.osm")
    empty = tmp_path / "empty.osm"
    empty.write_text(
        '<?xml version="1.0"?>\n<osm version="0.6"><node id="1" lat="60" lon="24"/>'
        '<way id="7"><nd ref="1"/><tag k="highway" v="steps"/></way></osm>\n',
        encoding="utf-8",
    )
    with pytest.raises(MapError, match="no lanes found"):
        import_osm(empty)


def _osm_file(path: Path, nodes: dict[int, tuple[float, float]], ways: list[Any]) -> Path:
    """A hand-made OSM file: nodes at (east, north) metres from 24.95 E, 60.25 N (a local
    approximation, fine for topology), ways as (id, node ids, tags)."""
    lat0, lon0 = 60.25, 24.95
    m_lat = 111_320.0
    m_lon = m_lat * math.cos(math.radians(lat0))
    text = ['<?xml version="1.0"?>', '<osm version="0.6">']
    for nid, (x, y) in nodes.items():
        text.append(f'<node id="{nid}" lat="{lat0 + y / m_lat:.8f}" lon="{lon0 + x / m_lon:.8f}"/>')
    for wid, refs, tags in ways:
        text.append(f'<way id="{wid}">')
        text += [f'<nd ref="{r}"/>' for r in refs]
        text += [f'<tag k="{k}" v="{v}"/>' for k, v in tags.items()]
        text.append("</way>")
    text.append("</osm>")
    path.write_text("\n".join(text) + "\n", encoding="utf-8")
    return path


HEAD_ON_NODES = {
    1: (0.0, 0.0),
    2: (100.0, 0.0),
    3: (200.0, 0.0),
    4: (300.0, 0.0),
    11: (0.0, 100.0),
    12: (100.0, 100.0),
    13: (200.0, 100.0),
}
ROAD = {"highway": "residential"}
HEAD_ON_WAYS = [
    (401, [1, 2], {**ROAD, "sidewalk": "right"}),
    (402, [3, 2], {**ROAD, "sidewalk": "right"}),  # drawn the other way: meets 401 head on
    (403, [3, 4], ROAD),  # starts where 402 starts
    (404, [11, 12], ROAD),
    (405, [13, 12], {**ROAD, "oneway": "yes"}),  # traffic from 13 into the two-way 404
]


def test_ways_drawn_head_on_are_turned_round_and_linked(tmp_path: Path) -> None:
    """A two-way road running on into ways drawn the other way: the middle way is turned
    round, so each follows the one before, and its lanes are the same lanes seen from
    the other end; a oneway turned round keeps its traffic's direction."""
    result = import_osm(_osm_file(tmp_path / "head_on.osm", HEAD_ON_NODES, HEAD_ON_WAYS))
    segs = result.hdmap.segments
    assert {sid: seg.successors for sid, seg in segs.items()} == {
        "way401-0": ("way402-0",),
        "way402-0": ("way403-0",),
        "way403-0": (),
        "way404-0": ("way405-0",),
        "way405-0": (),
    }
    turned = {sid for sid, seg in segs.items() if seg.lanes[0].properties.get("osm_reversed")}
    assert turned == {"way402-0", "way405-0"}
    assert LOST not in result.report.skipped
    assert "road element rejected by the loader" not in result.report.skipped

    # way 402 alone is not turned round: the same lanes, right to left, directions flipped,
    # and the same centre lines, reversed
    alone = import_osm(_osm_file(tmp_path / "alone.osm", HEAD_ON_NODES, HEAD_ON_WAYS[1:2]))
    drawn = alone.hdmap.segments["way402-0"].lanes
    lanes = segs["way402-0"].lanes
    assert [(x.type, x.direction) for x in drawn] == [
        ("driving", "backward"),
        ("driving", "forward"),
        ("sidewalk", "both"),
    ]
    flip = {"forward": "backward", "backward": "forward", "both": "both"}
    for lane, other in zip(lanes, drawn[::-1], strict=True):
        assert (lane.type, lane.width, lane.direction) == (
            other.type,
            other.width,
            flip[other.direction],
        )
        assert np.array_equal(
            np.asarray(lane.centerline.coords), np.asarray(other.centerline.coords)[::-1]
        )
    # the sidewalk stays north of the road (way 402's right, drawn westwards)
    assert lanes[0].centerline.centroid.y > lanes[1].centerline.centroid.y

    # the oneway's traffic still runs from node 13 into node 12
    (oneway,) = segs["way405-0"].lanes
    assert oneway.direction == "backward"
    xy = np.asarray(oneway.centerline.coords)
    travel_end = xy[0]  # a backward lane is driven against the reference
    lon, lat = result.hdmap.projection.to_wgs84(float(travel_end[0]), float(travel_end[1]))
    node12 = _osm_lines(tmp_path / "head_on.osm")[404][-1]
    assert math.dist((lon, lat), tuple(node12)) < 1e-6


def test_import_map_dispatches_to_osm() -> None:
    result = import_map("osm", JUNCTION)
    assert "way301-0" in result.hdmap.segments


# ----------------------------------------------------------------------------------------------
# Helsinki
# ----------------------------------------------------------------------------------------------

# The middle of the extract (about 670 m x 1000 m of its 1000 m x 1660 m): the whole file
# takes about twice as long (see docs/maps/osm.md for its figures).
HELSINKI_BOX = (24.938, 60.167, 24.950, 60.176)


def test_helsinki_imports_and_loads(tmp_path: Path) -> None:
    start = time.perf_counter()
    result = import_osm(HELSINKI, bbox=HELSINKI_BOX)
    took_import = time.perf_counter() - start
    out = tmp_path / "helsinki.geojson"
    result.write(out)
    start = time.perf_counter()
    hdmap = read_geojson_file(out)
    took_load = time.perf_counter() - start

    segs = hdmap.segments
    by_type = Counter(lane.type for seg in segs.values() for lane in seg.lanes)
    skipped = result.report.skipped
    print(
        f"Helsinki (bbox): {len(segs)} road elements, {dict(by_type)}; import "
        f"{took_import:.1f} s, load {took_load:.1f} s; left out {dict(skipped)}"
    )
    assert len(segs) > 1500
    assert by_type["driving"] > 800 and by_type["sidewalk"] > 800
    assert by_type["bicycle"] > 100 and by_type["parking"] > 50
    assert skipped["highway=steps"] > 10 and skipped["area=yes (a surface, not a road)"] > 10
    assert skipped["way outside the bbox"] > 500
    rejected = skipped.get("road element rejected by the loader", 0)
    assert rejected <= 0.01 * len(segs)
    # every road element has a successor or a predecessor somewhere (the network is joined)
    linked = {s for seg in segs.values() for s in seg.successors}
    linked |= {sid for sid, seg in segs.items() if seg.successors}
    assert len(linked) > 0.9 * len(segs)

    # locate: points on lane centres are found in their own segment (or one overlapping it)
    rng = np.random.default_rng(12)
    ids = sorted(segs)
    points = []
    for sid in rng.choice(ids, size=300, replace=False):
        lane = segs[sid].lanes[0]
        p = lane.centerline.interpolate(0.5, normalized=True)
        points.append((sid, p.x, p.y))
    start = time.perf_counter()
    found = [hdmap.locate(x, y) for _, x, y in points]
    per_locate = (time.perf_counter() - start) / len(points) * 1e6
    print(f"HdMap.locate: {per_locate:.0f} us per call")
    hits = 0
    for (sid, x, y), seg in zip(points, found, strict=True):
        assert seg is not None
        hits += seg.id == sid or bool(shapely.intersects(seg.area, segs[sid].area))
        assert seg.area.distance(Point(x, y)) < 1e-6
    assert hits == len(points)
