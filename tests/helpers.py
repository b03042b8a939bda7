"""Domain helpers for the tests: small maps built anywhere, fixes placed on lanes."""

from __future__ import annotations

import math
from typing import Any

from laas.map.geojson import read_geojson
from laas.map.hdmap import HdMap, Segment
from laas.map.mapgen import Curve, LaneSpec, Straight, local_to_lonlat, road_features, track
from laas.models import GpsMeasurement

T0 = 1_800_000_000_000


def small_map_data(
    origin: tuple[float, float] = (151.2070, -33.8700),
    bearing: float = 100.0,
    lanes: tuple[LaneSpec, ...] = (
        LaneSpec("sidewalk", 2.0, "both"),
        LaneSpec("driving", 3.0, "backward"),
        LaneSpec("driving", 3.0, "forward"),
        LaneSpec("bicycle", 1.5, "forward"),
    ),
    turn: float = 40.0,
) -> dict[str, Any]:
    """GeoJSON of a road: 150 m straight, a curve, 150 m straight; three segments (Sydney)."""
    local = track((0.0, 0.0), bearing, [Straight(150.0), Curve(60.0, turn), Straight(150.0)])
    curve = 60.0 * abs(math.radians(turn))
    return road_features(
        "r", local_to_lonlat(local, *origin), lanes, split_at=(150.0, 150.0 + curve)
    )


def small_map(**kwargs: Any) -> HdMap:
    """The map of `small_map_data`, loaded."""
    return read_geojson(small_map_data(**kwargs), source="small-map")


def fix_on(
    hdmap: HdMap,
    segment: Segment,
    s: float,
    lane: int,
    t_ms: int,
    *,
    bias: tuple[float, float] = (0.0, 0.0),
    lateral: float = 0.0,
    speed: float = 5.0,
    heading_offset: float = 0.0,
) -> GpsMeasurement:
    """A fix at station s on `lane` of `segment` (plus an error), heading along the road."""
    d = float(segment.lane_offsets(s)[lane]) + lateral
    e, n = segment.point(s, d)
    lon, lat = hdmap.projection.to_wgs84(e + bias[0], n + bias[1])
    return GpsMeasurement(
        timestamp=t_ms,
        latitude=lat,
        longitude=lon,
        altitude=0.0,
        heading=(segment.heading(s) + heading_offset) % 360.0,
        speed=speed,
    )


class Clock:
    """A clock a test sets by hand (seconds); call it to read it."""

    def __init__(self, now: float = 1_700_000_000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now
