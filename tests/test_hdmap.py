"""The HD map: the Hamburg test road, segment frames, queries, and rejection of broken maps."""

from __future__ import annotations

import contextlib
import copy
import itertools
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from laas.errors import MapError
from laas.map.bundled import bundled_map
from laas.map.frame import Frame
from laas.map.geojson import read_geojson, read_geojson_file
from laas.map.hdmap import HdMap, Segment
from laas.map.mapgen import Curve, LaneSpec, Straight, local_to_lonlat, road_features, track

HAMBURG_IDS = ["messe-0", "messe-1", "messe-2", "messe-3", "messe-4"]
# d of the lane centres: 0, (3.25+3.25)/2, +(3.25+2.2)/2, +(2.2+1.8)/2
HAMBURG_OFFSETS = [0.0, 3.25, 5.975, 7.975]


def _heading_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


# --- the Hamburg map ------------------------------------------------------------------------


def test_hamburg_segments_and_lanes(hamburg_map: HdMap) -> None:
    assert list(hamburg_map.segments) == HAMBURG_IDS
    assert hamburg_map.projection.epsg == 32632
    assert hamburg_map.source == str(bundled_map("messe-hamburg"))
    for k, seg in enumerate(hamburg_map.segments.values()):
        assert [lane.index for lane in seg.lanes] == [0, 1, 2, 3]
        assert [lane.type for lane in seg.lanes] == ["driving", "driving", "parking", "bicycle"]
        assert [lane.width for lane in seg.lanes] == [3.25, 3.25, 2.2, 1.8]
        assert {lane.direction for lane in seg.lanes} == {"forward"}
        assert all(lane.segment == seg.id for lane in seg.lanes)
        assert seg.lanes[0].properties == {"road": "messe"}  # extra properties are kept
        assert seg.successors == ((HAMBURG_IDS[k + 1],) if k + 1 < len(HAMBURG_IDS) else ())
        assert seg.reference.equals(seg.lanes[0].centerline)
        assert 60.0 <= seg.length <= 150.0
    total = sum(seg.length for seg in hamburg_map.segments.values())
    assert 560.0 < total < 640.0


def test_hamburg_is_near_messe(hamburg_map: HdMap) -> None:
    x0, y0, x1, y1 = hamburg_map.bounds
    lon, lat = hamburg_map.projection.to_wgs84((x0 + x1) / 2, (y0 + y1) / 2)
    assert abs(lat - 53.561) < 0.005
    assert abs(lon - 9.980) < 0.008


def test_hamburg_area_is_the_lane_surface(hamburg_map: HdMap) -> None:
    for seg in hamburg_map.segments.values():
        assert seg.area.geom_type == "Polygon"
        expected = sum(lane.width * lane.centerline.length for lane in seg.lanes)
        assert seg.area.area == pytest.approx(expected, rel=0.002)
        for x, y in seg.reference.coords:  # the ends lie on the flat caps
            assert seg.area.distance(shapely.Point(x, y)) < 1e-3
        assert seg.area.contains(seg.reference.interpolate(0.5, normalized=True))


def test_headings_follow_the_road(hamburg_map: HdMap) -> None:
    segs = hamburg_map.segments
    for sid in ("messe-0", "messe-1"):
        assert _heading_diff(segs[sid].heading(10.0), 30.0) < 0.05
    for sid in ("messe-3", "messe-4"):
        assert _heading_diff(segs[sid].heading(50.0), 60.0) < 0.05
    curve = segs["messe-2"]
    assert _heading_diff(curve.heading(0.0), 30.0) < 1.0
    assert _heading_diff(curve.heading(curve.length / 2), 45.0) < 1.0
    assert _heading_diff(curve.heading(curve.length), 60.0) < 1.0
    # a right-hand curve: heading increases steadily
    stations = np.linspace(0.0, curve.length, 40)
    headings = [curve.heading(float(s)) for s in stations]
    steps = [(b - a + 180.0) % 360.0 - 180.0 for a, b in itertools.pairwise(headings)]
    assert all(-1e-9 <= step < 5.0 for step in steps)
    for s in stations:
        assert 0.0 <= curve.heading(float(s)) < 360.0
        t = curve.tangent(float(s))
        assert float(np.hypot(*t)) == pytest.approx(1.0)
        h = math.radians(curve.heading(float(s)))
        np.testing.assert_allclose(t, [math.sin(h), math.cos(h)], atol=1e-12)


def test_lane_offsets_match_widths(hamburg_map: HdMap) -> None:
    for seg in hamburg_map.segments.values():
        for s in np.linspace(-5.0, seg.length + 5.0, 23):
            offsets = seg.lane_offsets(float(s))
            assert offsets.shape == (4,)
            assert offsets[0] == 0.0
            np.testing.assert_allclose(offsets, HAMBURG_OFFSETS, atol=0.005)
        assert seg.lateral_bounds(seg.length / 2) == pytest.approx((-1.625, 8.875), abs=0.005)


def test_lane_centre_lines_have_constant_offset_in_the_frame(hamburg_map: HdMap) -> None:
    # also on the curve: lanes are mitred offset curves, and d = const is such a curve
    for seg in hamburg_map.segments.values():
        for lane, expected in zip(seg.lanes, HAMBURG_OFFSETS, strict=True):
            sd = seg.frame_array(np.asarray(lane.centerline.coords))
            np.testing.assert_allclose(sd[:, 1], expected, atol=0.005)
            assert sd[0, 0] == pytest.approx(0.0, abs=0.01)
            assert sd[-1, 0] == pytest.approx(seg.length, abs=0.01)


def test_locate_points_on_every_lane(hamburg_map: HdMap) -> None:
    for seg in hamburg_map.segments.values():
        for s in np.linspace(1.0, seg.length - 1.0, 9):
            for k, d in enumerate(seg.lane_offsets(float(s))):
                x, y = seg.point(float(s), float(d))
                found = hamburg_map.locate(x, y)
                assert found is not None and found.id == seg.id, (seg.id, s, k)


def test_locate_outside_the_road(hamburg_map: HdMap) -> None:
    seg = hamburg_map.segments["messe-1"]
    x, y = seg.point(70.0, 8.875 + 5.0)  # 5 m right of the bicycle lane's edge
    assert not seg.area.intersects(shapely.Point(x, y))
    found = hamburg_map.locate(x, y)
    assert found is not None and found.id == "messe-1"
    assert hamburg_map.locate(x, y, max_distance=4.0) is None
    _, _, x1, y1 = hamburg_map.bounds
    assert hamburg_map.locate(x1 + 100.0, y1 + 100.0) is None
    assert hamburg_map.locate(0.0, 0.0) is None


def test_locate_at_a_seam_is_deterministic(hamburg_map: HdMap) -> None:
    a, b = hamburg_map.segments["messe-0"], hamburg_map.segments["messe-1"]
    x, y = a.point(a.length, 3.0)
    assert b.frame(x, y)[0] == pytest.approx(0.0, abs=0.01)
    first = hamburg_map.locate(x, y)
    assert first is not None and first.id in ("messe-0", "messe-1")
    assert all(hamburg_map.locate(x, y) is first for _ in range(5))
    # just past the seam, the point is inside messe-1 only
    inside = hamburg_map.locate(*a.point(a.length + 0.5, 3.0))
    assert inside is not None and inside.id == "messe-1"


def test_segments_near(hamburg_map: HdMap) -> None:
    seg = hamburg_map.segments["messe-2"]
    x, y = seg.point(seg.length / 2, 3.0)
    near = hamburg_map.segments_near(x, y, 1.0)
    assert [s.id for s in near] == ["messe-2"]
    wide = hamburg_map.segments_near(x, y, 200.0)
    assert wide[0].id == "messe-2"
    assert {s.id for s in wide} == set(HAMBURG_IDS)
    assert hamburg_map.segments_near(0.0, 0.0, 100.0) == []


def test_lane_point(hamburg_map: HdMap) -> None:
    seg = hamburg_map.segments["messe-2"]
    x, y = seg.point(50.0, 4.0)
    for k, lane in enumerate(seg.lanes):
        px, py = seg.lane_point(k, x, y)
        assert lane.centerline.distance(shapely.Point(px, py)) < 1e-6
        s, d = seg.frame(px, py)
        assert s == pytest.approx(50.0, abs=0.2)
        assert d == pytest.approx(HAMBURG_OFFSETS[k], abs=0.01)
    with pytest.raises(IndexError):
        seg.lane_point(4, x, y)


def test_frame_signs_and_extrapolation(hamburg_map: HdMap) -> None:
    seg = hamburg_map.segments["messe-0"]  # straight, bearing 30 degrees
    x0, y0 = seg.reference.coords[0]
    east = (math.cos(math.radians(30.0)), -math.sin(math.radians(30.0)))  # right of travel
    s, d = seg.frame(x0 + 2.0 * east[0], y0 + 2.0 * east[1])
    assert (s, d) == pytest.approx((0.0, 2.0), abs=1e-3)
    t = seg.tangent(0.0)
    s, d = seg.frame(x0 - 10.0 * t[0], y0 - 10.0 * t[1])
    assert (s, d) == pytest.approx((-10.0, 0.0), abs=1e-3)
    xe, ye = seg.reference.coords[-1]
    s, d = seg.frame(xe + 7.0 * t[0] - 1.0 * east[0], ye + 7.0 * t[1] - 1.0 * east[1])
    assert (s, d) == pytest.approx((seg.length + 7.0, -1.0), abs=1e-3)


@settings(max_examples=300, deadline=None)
@given(
    k=st.integers(0, len(HAMBURG_IDS) - 1),
    frac=st.floats(-0.3, 1.3),
    d=st.floats(-15.0, 15.0),
)
def test_frame_point_round_trip(hamburg_map: HdMap, k: int, frac: float, d: float) -> None:
    seg = hamburg_map.segments[HAMBURG_IDS[k]]
    s = frac * seg.length
    x, y = seg.point(s, d)
    s2, d2 = seg.frame(x, y)
    assert s2 == pytest.approx(s, abs=1e-6)
    assert d2 == pytest.approx(d, abs=1e-6)
    assert seg.point(s2, d2) == pytest.approx((x, y), abs=1e-6)


@settings(max_examples=50, deadline=None)
@given(
    k=st.integers(0, len(HAMBURG_IDS) - 1),
    pts=st.lists(st.tuples(st.floats(-400, 400), st.floats(-400, 400)), min_size=1, max_size=40),
)
def test_frame_array_matches_frame(
    hamburg_map: HdMap, k: int, pts: list[tuple[float, float]]
) -> None:
    seg = hamburg_map.segments[HAMBURG_IDS[k]]
    cx, cy = seg.point(seg.length / 2, 0.0)
    xy = np.asarray(pts) + np.array([cx, cy])
    out = seg.frame_array(xy)
    assert out.shape == (len(pts), 2)
    for row, (x, y) in zip(out, xy, strict=True):
        assert tuple(row) == pytest.approx(seg.frame(float(x), float(y)), abs=1e-6)


def test_frame_distance_matches_geometry_near_the_road(hamburg_map: HdMap) -> None:
    # near the reference, |d| is the Euclidean distance to it (to mitre-join precision)
    rng = np.random.default_rng(7)
    for seg in hamburg_map.segments.values():
        for _ in range(50):
            x, y = seg.point(rng.uniform(0, seg.length), rng.uniform(-10, 10))
            _, d = seg.frame(x, y)
            assert abs(d) == pytest.approx(seg.reference.distance(shapely.Point(x, y)), abs=0.01)


def test_non_finite_inputs_are_rejected(hamburg_map: HdMap) -> None:
    seg = hamburg_map.segments["messe-0"]
    with pytest.raises(ValueError):
        seg.frame(math.nan, 0.0)
    with pytest.raises(ValueError):
        seg.point(math.inf, 0.0)
    with pytest.raises(ValueError):
        seg.lane_offsets(math.nan)


def test_frame_array_rejects_bad_shapes(hamburg_map: HdMap) -> None:
    seg = hamburg_map.segments["messe-0"]
    assert seg.frame_array(np.zeros((0, 2))).shape == (0, 2)
    assert seg.frame_array([1.0, 2.0]).shape == (1, 2)
    with pytest.raises(ValueError):
        seg.frame_array(np.zeros((3, 3)))


# --- another place: Sydney, left-hand traffic, a backward lane, centre reference -------------


@pytest.fixture(scope="module")
def sydney() -> HdMap:
    lanes = [
        LaneSpec("sidewalk", 2.5, "both"),
        LaneSpec("driving", 3.5, "forward"),
        LaneSpec("driving", 3.3, "backward"),
        LaneSpec("bicycle", 1.5, "backward", properties={"surface": "green"}),
    ]
    local = track((0.0, 0.0), 170.0, [Straight(80.0), Curve(40.0, 50.0), Straight(60.0)])
    ref = local_to_lonlat(local, 151.2070, -33.8700)  # George Street, southwards, right curve
    data = road_features(
        "george", ref, lanes, split_at=(80.0, 80.0 + 40.0 * math.radians(50)), reference_is="center"
    )
    return read_geojson(data, source="sydney")


def test_another_place_loads_and_works(sydney: HdMap) -> None:
    assert sydney.projection.epsg == 32756
    assert sydney.source == "sydney"
    assert list(sydney.segments) == ["george-0", "george-1", "george-2"]
    seg = sydney.segments["george-1"]
    assert [lane.direction for lane in seg.lanes] == ["both", "forward", "backward", "backward"]
    assert seg.lanes[3].properties == {"road": "george", "surface": "green"}
    np.testing.assert_allclose(seg.lane_offsets(seg.length / 2), [0.0, 3.0, 6.4, 8.8], atol=0.005)
    # a right-hand curve of 50 degrees starting at bearing 170
    assert _heading_diff(seg.heading(0.0), 170.0) < 1.5
    assert _heading_diff(seg.heading(seg.length), 220.0) < 1.5
    assert _heading_diff(sydney.segments["george-2"].heading(1.0), 220.0) < 0.05
    # lane 0 (the sidewalk) is on the outside of a right curve: its reference is the longest
    assert seg.length > seg.lanes[3].centerline.length
    for s in np.linspace(1.0, seg.length - 1.0, 7):
        for k, d in enumerate(seg.lane_offsets(float(s))):
            x, y = seg.point(float(s), float(d))
            found = sydney.locate(x, y)
            assert found is not None and found.id == "george-1", (s, k)
            assert seg.frame(x, y) == pytest.approx((s, d), abs=1e-6)


# --- broken maps ----------------------------------------------------------------------------


def _base() -> dict[str, Any]:
    """Two segments of three 3 m lanes: features 0-2 are r-0 lanes 0-2, 3-5 are r-1."""
    ref = local_to_lonlat(track((0.0, 0.0), 60.0, [Straight(120.0)]), 9.98, 53.56)
    lanes = [LaneSpec("driving", 3.0), LaneSpec("driving", 3.0), LaneSpec("sidewalk", 3.0)]
    return road_features("r", ref, lanes, split_at=(60.0,))


def test_base_map_is_valid() -> None:
    m = read_geojson(_base())
    assert list(m.segments) == ["r-0", "r-1"]


Mutation = Callable[[dict[str, Any]], Any]


def _props(i: int, **changes: Any) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        data["features"][i]["properties"].update(changes)

    return mutate


def _drop(i: int, key: str) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        del data["features"][i]["properties"][key]

    return mutate


def _geometry(i: int, geometry: Any) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        data["features"][i]["geometry"] = geometry

    return mutate


def _coords(i: int, f: Callable[[list[list[float]]], Any]) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        geom = data["features"][i]["geometry"]
        geom["coordinates"] = f(geom["coordinates"])

    return mutate


def _swap_geometry(i: int, j: int) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        data["features"][i]["geometry"] = copy.deepcopy(data["features"][j]["geometry"])

    return mutate


def _replace(value: Any) -> Mutation:
    return lambda data: value


def _half(coords: list[list[float]]) -> list[list[float]]:
    (x0, y0), (x1, y1) = coords[0], coords[-1]
    return [[x0, y0], [(x0 + x1) / 2, (y0 + y1) / 2]]


def _bowtie(coords: list[list[float]]) -> list[list[float]]:
    (x0, y0), (x1, y1) = coords[0], coords[-1]
    return [[x0, y0], [x1, y1], [x1, y0], [x0, y1]]


def _v_shape(coords: list[list[float]]) -> list[list[float]]:
    (x0, y0), (x1, y1) = coords[0], coords[-1]
    return [[x0, y0], [x1, y1], [x0, y1 + (y1 - y0)]]


def _features(mutate: Callable[[list[Any]], Any]) -> Mutation:
    def apply(data: dict[str, Any]) -> None:
        mutate(data["features"])

    return apply


BROKEN: list[tuple[str, Mutation, list[str]]] = [
    # (case id, mutation, substrings the message must contain)
    ("not a collection", _replace({"type": "Feature"}), ["not a GeoJSON FeatureCollection"]),
    ("a list", _replace([]), ["not a GeoJSON FeatureCollection"]),
    ("no features list", _replace({"type": "FeatureCollection"}), ["no 'features' list"]),
    ("empty", _replace({"type": "FeatureCollection", "features": []}), ["no features"]),
    ("feature not object", _features(lambda f: f.__setitem__(2, 7)), ["feature 2", "object"]),
    ("feature type", _features(lambda f: f[1].__setitem__("type", "Point")), ["feature 1"]),
    ("no properties", _features(lambda f: f[4].pop("properties")), ["feature 4", "properties"]),
    ("no segment", _drop(1, "segment"), ["feature 1", "'segment'"]),
    ("segment int", _props(1, segment=5), ["feature 1", "'segment'"]),
    ("no lane", _drop(1, "lane"), ["feature 1", "segment 'r-0'", "'lane'"]),
    ("lane str", _props(1, lane="1"), ["feature 1", "segment 'r-0'", "'lane'"]),
    ("lane bool", _props(1, lane=True), ["feature 1", "'lane'"]),
    ("lane float", _props(1, lane=1.0), ["feature 1", "'lane'"]),
    ("lane negative", _props(1, lane=-1), ["feature 1", ">= 0"]),
    ("no type", _drop(4, "type"), ["feature 4", "segment 'r-1', lane 1", "'type'"]),
    ("unknown type", _props(4, type="highway"), ["feature 4", "lane 1", "unknown lane type"]),
    ("width zero", _props(4, width=0), ["feature 4", "lane 1", "'width'", "> 0"]),
    ("width negative", _props(4, width=-3.0), ["feature 4", "'width'"]),
    ("width str", _props(4, width="3"), ["feature 4", "'width'", "number"]),
    ("width nan", _props(4, width=math.nan), ["feature 4", "'width'"]),
    ("no direction", _drop(5, "direction"), ["feature 5", "lane 2", "'direction'"]),
    ("unknown direction", _props(5, direction="north"), ["feature 5", "unknown direction"]),
    ("successors str", _props(0, successors="r-1"), ["feature 0", "'successors'"]),
    ("successors int", _props(0, successors=[1]), ["feature 0", "'successors'"]),
    ("unknown successor", _props(2, successors=["r-9"]), ["feature 2", "lane 2", "'r-9'"]),
    (
        "duplicate",
        _props(4, lane=0),
        ["feature 4", "segment 'r-1', lane 0", "duplicate", "feature 3"],
    ),
    ("no geometry", _geometry(3, None), ["feature 3", "segment 'r-1', lane 0", "geometry"]),
    (
        "point",
        _geometry(3, {"type": "Point", "coordinates": [9.98, 53.56]}),
        ["feature 3", "LineString"],
    ),
    (
        "multiline",
        _geometry(3, {"type": "MultiLineString", "coordinates": []}),
        ["feature 3", "LineString"],
    ),
    ("coordinates missing", _geometry(3, {"type": "LineString"}), ["feature 3", "coordinates"]),
    ("empty line", _coords(3, lambda c: []), ["feature 3", "at least 2 points"]),
    ("one point", _coords(3, lambda c: c[:1]), ["feature 3", "at least 2 points"]),
    ("identical points", _coords(3, lambda c: [c[0], c[0], c[0]]), ["feature 3", "distinct"]),
    ("non-numeric", _coords(3, lambda c: [c[0], ["9.98", "53.56"]]), ["feature 3", "coordinate 1"]),
    ("bool coordinate", _coords(3, lambda c: [c[0], [True, 53.5]]), ["feature 3", "coordinate 1"]),
    ("lat/lon swapped", _coords(3, lambda c: [[y, x] for x, y in c]), ["segment 'r-1'"]),
    ("lat too large", _coords(3, lambda c: [c[0], [9.98, 95.0]]), ["feature 3", "range"]),
    ("lon too large", _coords(3, lambda c: [c[0], [200.0, 53.56]]), ["feature 3", "range"]),
    ("self-intersecting", _coords(3, _bowtie), ["feature 3", "intersects itself"]),
    ("closed", _coords(3, lambda c: [*c, c[0]]), ["feature 3", "closed"]),
    (
        "lanes not contiguous",
        _props(2, lane=3),
        ["feature 2", "segment 'r-0', lane 3", "contiguous", "missing [2]"],
    ),
    (
        "lanes not from 0",
        _features(lambda f: [f[k]["properties"].update(lane=k + 1) for k in (0, 1, 2)]),
        ["segment 'r-0'", "contiguous"],
    ),
    ("lane too far", _swap_geometry(1, 2), ["feature 1", "segment 'r-0', lane 1", "side by side"]),
    ("width inconsistent", _props(1, width=8.0), ["feature 1", "lane 1", "side by side"]),
    (
        "lanes numbered right to left",
        _features(lambda f: [f[0]["properties"].update(lane=2), f[2]["properties"].update(lane=0)]),
        ["segment 'r-0'", "not to the right"],
    ),
    (
        "lane reversed",
        _coords(4, lambda c: c[::-1]),
        ["feature 4", "segment 'r-1', lane 1", "against the segment's reference"],
    ),
    ("lane half length", _coords(4, _half), ["feature 4", "lane 1", "covers stations"]),
    ("lane elsewhere", _swap_geometry(4, 1), ["feature 4", "segment 'r-1', lane 1"]),
    ("sharp turn", _coords(0, _v_shape), ["feature 0", "segment 'r-0', lane 0", "turns by"]),
]


@pytest.mark.parametrize(
    ("mutate", "expected"), [pytest.param(m, e, id=name) for name, m, e in BROKEN]
)
def test_broken_maps_are_rejected(mutate: Mutation, expected: list[str]) -> None:
    data = _base()
    replaced = mutate(data)
    if replaced is not None:
        data = replaced
    with pytest.raises(MapError) as info:
        read_geojson(data, source="broken.geojson")
    message = str(info.value)
    assert message.startswith("broken.geojson: ")
    for part in expected:
        assert part in message, message


def test_invalid_json_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.geojson"
    path.write_text('{"type": "FeatureCollection",\n "features": [}', encoding="utf-8")
    with pytest.raises(MapError, match=r"bad\.geojson: invalid JSON at line 2"):
        read_geojson_file(path)


def test_missing_file_is_a_map_error(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="cannot read"):
        read_geojson_file(tmp_path / "nope.geojson")


def test_load_from_file_equals_from_geojson(tmp_path: Path) -> None:
    path = tmp_path / "r.geojson"
    path.write_text(json.dumps(_base()), encoding="utf-8")
    m = read_geojson_file(str(path))
    assert m.source == str(path)
    assert list(m.segments) == ["r-0", "r-1"]
    assert m.segments["r-0"].successors == ("r-1",)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4)
    ),
    max_leaves=12,
)


@settings(max_examples=200, deadline=None)
@given(
    key=st.sampled_from(["segment", "lane", "type", "width", "direction", "successors"]),
    value=json_values,
    feature=st.integers(0, 5),
)
def test_fuzzed_properties_raise_only_map_errors(key: str, value: Any, feature: int) -> None:
    data = _base()
    data["features"][feature]["properties"][key] = value
    try:
        read_geojson(data)
    except MapError as exc:
        assert f"feature {feature}" in str(exc) or "segment" in str(exc)


@settings(max_examples=200, deadline=None)
@given(
    value=json_values,
    where=st.sampled_from(["root", "features", "feature", "geometry", "coordinates", "position"]),
)
def test_fuzzed_structure_raises_only_map_errors(value: Any, where: str) -> None:
    data: Any = _base()
    if where == "root":
        data = value
    elif where == "features":
        data["features"] = value
    elif where == "feature":
        data["features"][3] = value
    elif where == "geometry":
        data["features"][3]["geometry"] = value
    elif where == "coordinates":
        data["features"][3]["geometry"]["coordinates"] = value
    else:
        data["features"][3]["geometry"]["coordinates"][1] = value
    with contextlib.suppress(MapError):
        read_geojson(data)


def test_segment_rejects_gaps_in_lane_indices(hamburg_map: HdMap) -> None:
    lanes = hamburg_map.segments["messe-0"].lanes
    with pytest.raises(MapError, match="contiguous"):
        Segment("messe-0", [lanes[0], lanes[2]])
    with pytest.raises(MapError, match="no lanes"):
        Segment("x", [])


@pytest.mark.parametrize("sweep", [200.0, 300.0])
def test_the_frame_of_a_reference_that_winds_past_a_half_turn(sweep: float) -> None:
    """Beyond about 180 degrees of turning the vertex normal lines are not in order along
    the reference, so bisecting over them found the wrong piece (310 of 400 points of a
    300-degree arc); every point of the curve d = const maps back to its (s, d)."""
    radius = 30.0
    angle = np.radians(np.arange(0.0, sweep + 0.5, 2.0))
    frame = Frame(np.column_stack((radius * np.sin(angle), radius - radius * np.cos(angle))))
    assert frame.winds
    rng = np.random.default_rng(1)
    s = rng.uniform(-5.0, frame.length + 5.0, 400)  # the extrapolated ends too
    d = rng.uniform(-5.0, 5.0, 400)
    xy = np.array([frame.point(float(a), float(b)) for a, b in zip(s, d, strict=True)])
    np.testing.assert_allclose(frame.frame_array(xy), np.column_stack((s, d)), atol=1e-6)
    for (x, y), a, b in zip(xy[:50], s[:50], d[:50], strict=True):
        assert frame.frame(float(x), float(y)) == pytest.approx((a, b), abs=1e-6)
    straight = Frame(np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 5.0]]))
    assert not straight.winds  # the bisection keeps the rest
