"""Map generator: polylines, lane layout, splitting, and the committed Hamburg map."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from laas.map.geo import UtmProjection
from laas.map.geojson import read_geojson
from laas.map.mapgen import (
    Curve,
    LaneSpec,
    Straight,
    arc,
    feature_collection,
    local_to_lonlat,
    road_features,
    road_features_utm,
    track,
)

ROOT = Path(__file__).resolve().parent.parent


def test_track_straight_then_left_curve() -> None:
    pts = track((10.0, 20.0), 0.0, [Straight(100.0), Curve(radius=50.0, angle=-90.0)], step=2.0)
    assert pts[0] == (10.0, 20.0)
    assert pts[1] == pytest.approx((10.0, 120.0))
    assert pts[-1] == pytest.approx((-40.0, 170.0))
    # every curve point is on the circle around (-40, 120), at most 2 m apart
    for x, y in pts[1:]:
        assert math.hypot(x + 40.0, y - 120.0) == pytest.approx(50.0)
    gaps = np.hypot(*np.diff(np.asarray(pts[1:]), axis=0).T)
    assert gaps.max() <= 2.0 + 1e-9


def test_track_right_curve_keeps_heading() -> None:
    pts = track((0.0, 0.0), 90.0, [Curve(20.0, 180.0), Straight(10.0)])
    # east, U-turn to the right (clockwise) ends 40 m south heading west
    assert pts[-2] == pytest.approx((0.0, -40.0), abs=1e-9)
    assert pts[-1] == pytest.approx((-10.0, -40.0), abs=1e-9)


def test_arc_directions() -> None:
    cw = arc((0.0, 0.0), 10.0, 0.0, 90.0, clockwise=True, step=1.0)
    assert cw[0] == pytest.approx((0.0, 10.0))
    assert cw[-1] == pytest.approx((10.0, 0.0))
    ccw = arc((0.0, 0.0), 10.0, 0.0, 90.0, clockwise=False, step=1.0)
    assert ccw[-1] == pytest.approx((10.0, 0.0))
    half = 10.0 / math.sqrt(2.0)  # the long way round: bearing 225 degrees halfway
    assert ccw[len(ccw) // 2] == pytest.approx((-half, -half), abs=0.2)
    assert len(ccw) > 2 * len(cw)


@pytest.mark.parametrize(
    "parts", [[Straight(0.0)], [Curve(0.0, 10.0)], [Curve(10.0, 0.0)]], ids=["len", "r", "angle"]
)
def test_track_rejects_degenerate_parts(parts: list[Straight | Curve]) -> None:
    with pytest.raises(ValueError):
        track((0.0, 0.0), 0.0, parts)


def test_local_to_lonlat() -> None:
    ll = local_to_lonlat([(0.0, 0.0), (0.0, 100.0), (100.0, 0.0)], 9.98, 53.56)
    assert ll[0] == pytest.approx((9.98, 53.56), abs=1e-9)
    proj = UtmProjection.for_location(9.98, 53.56)
    o = np.array(proj.to_utm(*ll[0]))
    assert np.array(proj.to_utm(*ll[1])) - o == pytest.approx([0.0, 100.0], abs=1e-6)
    assert np.array(proj.to_utm(*ll[2])) - o == pytest.approx([100.0, 0.0], abs=1e-6)


def _road(**kwargs: object) -> dict[str, object]:
    ref = local_to_lonlat(
        track((0.0, 0.0), 45.0, [Straight(50.0), Curve(30.0, -60.0)]), 2.35, 48.85
    )
    lanes = [
        LaneSpec("bicycle", 2.0, "backward"),
        LaneSpec("driving", 3.0),
        LaneSpec("parking", 2.5),
    ]
    return road_features("p", ref, lanes, **kwargs)  # type: ignore[arg-type]


def test_road_features_layout() -> None:
    data = _road(split_at=(25.0, 50.0))
    feats = data["features"]
    assert isinstance(feats, list) and len(feats) == 9
    props = [f["properties"] for f in feats]
    assert [(p["segment"], p["lane"]) for p in props] == [
        (f"p-{i}", k) for i in range(3) for k in range(3)
    ]
    assert [p["successors"] for p in props[::3]] == [["p-1"], ["p-2"], []]
    assert props[0]["type"] == "bicycle" and props[0]["direction"] == "backward"
    assert all(p["road"] == "p" for p in props)
    for f in feats:  # rounded to 8 decimals
        for lon, lat in f["geometry"]["coordinates"]:
            assert round(lon, 8) == lon and round(lat, 8) == lat
    m = read_geojson(data)
    assert [s.id for s in m.segments.values()] == ["p-0", "p-1", "p-2"]
    assert m.segments["p-0"].length == pytest.approx(25.0, abs=0.01)
    for seg in m.segments.values():
        np.testing.assert_allclose(seg.lane_offsets(seg.length / 2), [0.0, 2.5, 5.25], atol=0.005)


def test_reference_is_center() -> None:
    left = read_geojson(_road())
    center = read_geojson(_road(reference_is="center"))
    a, b = left.segments["p-0"], center.segments["p-0"]
    # the whole road moves left by half its width (7.5 / 2); offsets between lanes stay
    np.testing.assert_allclose(a.lane_offsets(10.0), b.lane_offsets(10.0), atol=0.005)
    x, y = b.point(10.0, 0.0)
    _, d = a.frame(x, y)
    assert d == pytest.approx(-3.75, abs=0.01)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"split_at": (30.0, 20.0)}, "increasing"),
        ({"split_at": (0.0,)}, "inside"),
        ({"split_at": (500.0,)}, "inside"),
        ({"reference_is": "right_edge"}, "reference_is"),
    ],
)
def test_road_features_rejects_bad_arguments(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _road(**kwargs)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (("road", 0.0, "forward"), "lane type"),
        (("driving", 0.0, "forward"), "width"),
        (("driving", math.nan, "forward"), "width"),
        (("driving", 3.0, "sideways"), "direction"),
    ],
)
def test_lane_spec_validation(args: tuple[str, float, str], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        LaneSpec(*args)  # type: ignore[arg-type]


def test_utm_variant_and_merge() -> None:
    proj = UtmProjection.for_location(151.2, -33.87)
    x0, y0 = proj.to_utm(151.2, -33.87)
    a = road_features_utm("a", [(x0, y0), (x0 + 100.0, y0)], proj, [LaneSpec("driving", 3.5)])
    b = road_features_utm(
        "b", [(x0 + 100.0, y0), (x0 + 100.0, y0 - 80.0)], proj, [LaneSpec("driving", 3.5)]
    )
    a["features"][0]["properties"]["successors"] = ["b-0"]
    m = read_geojson(feature_collection(a, b))
    assert list(m.segments) == ["a-0", "b-0"]
    assert m.segments["a-0"].successors == ("b-0",)
    assert m.segments["a-0"].heading(1.0) == pytest.approx(90.0, abs=0.01)
    assert m.segments["b-0"].heading(1.0) == pytest.approx(180.0, abs=0.01)


@settings(max_examples=25, deadline=None)
@given(
    widths=st.lists(st.floats(0.8, 4.5), min_size=1, max_size=6),
    bearing=st.floats(0.0, 360.0, exclude_max=True),
    radius=st.floats(40.0, 300.0),
    turn=st.floats(-90.0, 90.0).filter(lambda a: abs(a) > 1.0),
    lon=st.floats(-170.0, 170.0),
    lat=st.floats(-70.0, 70.0),
)
def test_generated_maps_load_anywhere(
    widths: list[float], bearing: float, radius: float, turn: float, lon: float, lat: float
) -> None:
    local = track((0.0, 0.0), bearing, [Straight(60.0), Curve(radius, turn), Straight(60.0)])
    curve = radius * math.radians(abs(turn))
    lanes = [LaneSpec("driving", w) for w in widths]
    data = road_features(
        "g", local_to_lonlat(local, lon, lat), lanes, split_at=(60.0, 60.0 + curve)
    )
    m = read_geojson(data)
    expected = np.concatenate(([0.0], np.cumsum((np.array(widths[:-1]) + widths[1:]) / 2)))
    for seg in m.segments.values():
        np.testing.assert_allclose(seg.lane_offsets(seg.length / 2), expected, atol=0.01)
        x, y = seg.point(seg.length / 2, float(expected[-1]))
        found = m.locate(x, y)
        assert found is not None and found.id == seg.id


def test_hamburg_file_is_generated_by_the_script() -> None:
    out = subprocess.run(
        [sys.executable, str(ROOT / "maps" / "make_messe_hamburg.py")],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    committed = (ROOT / "maps" / "messe-hamburg.geojson").read_text(encoding="utf-8")
    assert out == committed, (
        "regenerate: python maps/make_messe_hamburg.py > maps/messe-hamburg.geojson"
    )
    data = json.loads(out)
    assert data["type"] == "FeatureCollection"
    assert len(data["features"]) == 5 * 4
