"""Which road element (`laas.engine.elements`): elements beside the answered one share the
user by their lanes' likelihood; a road alone, one that crosses, or one joined at a seam
takes nothing from it."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from laas.engine.elements import element_share
from laas.map.geojson import read_geojson
from laas.map.hdmap import HdMap, Segment
from laas.map.mapgen import LaneSpec, Straight, local_to_lonlat, road_features, track

ORIGIN = (151.2070, -33.8700)
CYCLE = (LaneSpec("bicycle", 2.0, "both"),)
FOOT = (LaneSpec("sidewalk", 2.0, "both"),)


def _map(*roads: tuple[str, tuple[float, float], float, tuple[LaneSpec, ...]]) -> HdMap:
    """Straight roads of 100 m: (id, start in local metres, bearing, lanes)."""
    features: list[dict[str, Any]] = []
    for road_id, start, bearing, lanes in roads:
        local = track(start, bearing, [Straight(100.0)])
        data = road_features(road_id, local_to_lonlat(local, *ORIGIN), lanes)
        features += data["features"]
    return read_geojson({"type": "FeatureCollection", "features": features}, source="test")


def _share(hdmap: HdMap, segment: Segment, lateral: float, velocity: tuple[float, float]) -> float:
    """element_share for a user at station 50 m, `lateral` m from lane 0's centre, known
    to 0.6 m (1 sigma) across the road."""
    x, y = segment.point(50.0, float(segment.lane_offsets(50.0)[0]) + lateral)
    v = np.array(velocity)
    return element_share(hdmap, segment, np.array([x, y]), 0.6**2, v, float(np.hypot(*v)), 0.25**2)


def _segment(hdmap: HdMap, prefix: str) -> Segment:
    return next(s for k, s in hdmap.segments.items() if k.startswith(prefix))


def test_a_road_alone_keeps_the_user() -> None:
    hdmap = _map(("c", (0.0, 0.0), 90.0, CYCLE))
    cycle = _segment(hdmap, "c")
    assert hdmap.beside(cycle.id) == ()
    assert _share(hdmap, cycle, 0.0, (4.0, 0.0)) == 1.0


def test_a_footway_a_metre_and_a_half_beside_shares_the_user_by_distance() -> None:
    """A cycle track with a footway whose centre line is 2.5 m away (its edge 0.5 m): a
    user on the cycle track's centre is more likely there, one halfway between is
    either, and one on the footway's side belongs to the footway."""
    hdmap = _map(("c", (0.0, 0.0), 90.0, CYCLE), ("f", (0.0, -2.5), 90.0, FOOT))
    cycle, foot = _segment(hdmap, "c"), _segment(hdmap, "f")
    assert hdmap.beside(cycle.id) == (foot,)
    v = (1.2, 0.0)  # walking pace: both lane types fit it
    centre, halfway = _share(hdmap, cycle, 0.0, v), _share(hdmap, cycle, 1.25, v)
    beyond = _share(hdmap, cycle, 2.0, v)
    assert 0.95 < centre < 1.0  # the footway's lane centre is 2.5 m = 3 sigma away
    assert math.isclose(halfway, 0.5, abs_tol=0.05)
    assert beyond < 0.3
    assert centre > halfway > beyond


def test_a_road_that_crosses_takes_nothing_from_a_user_driving_along() -> None:
    hdmap = _map(
        ("a", (0.0, 0.0), 90.0, (LaneSpec("driving", 3.5, "both"),)),
        ("x", (50.0, 50.0), 180.0, (LaneSpec("driving", 3.5, "both"),)),
    )
    along, across = _segment(hdmap, "a"), _segment(hdmap, "x")
    assert hdmap.beside(along.id) == (across,)
    assert _share(hdmap, along, 0.0, (10.0, 0.0)) > 0.999  # 10 m/s along "a"
    # the same place, driving along "x" instead: "x" takes it
    assert _share(hdmap, along, 0.0, (0.0, -10.0)) < 0.001


def test_an_element_joined_at_a_seam_is_not_beside() -> None:
    """The three elements of one road (split where it curves) join end to start: the
    seam is `Engine._on_element`'s business, not theirs."""
    from .helpers import small_map

    hdmap = small_map()
    for segment in hdmap.segments.values():
        assert hdmap.beside(segment.id) == ()
