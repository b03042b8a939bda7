"""Generate maps/melbourne-corner.geojson, the second evaluation road.

    python maps/make_melbourne_corner.py > maps/melbourne-corner.geojson

A two-way city street in Melbourne's CBD grid (southern hemisphere, UTM 55S) that turns a
right-angle corner: 240 m south-south-east (grid bearing 160), a 90-degree left turn on a
20 m radius (at the road's left edge, the inside of the turn), then 240 m east-north-east
(bearing 70). Six lanes, left to right looking along the reference direction: a sidewalk,
a backward bicycle lane, a backward driving lane, a forward driving lane, a forward bicycle
lane and a sidewalk. Deterministic.
"""

from __future__ import annotations

import json
import math
import sys

from laas.map.mapgen import Curve, LaneSpec, Straight, local_to_lonlat, road_features, track

ORIGIN = (144.9612, -37.8105)  # lon, lat of the road's left edge at the start
FIRST, RADIUS, TURN, LAST = 240.0, 20.0, -90.0, 240.0
CURVE_LENGTH = RADIUS * math.radians(abs(TURN))
SPLIT_AT = (120.0, FIRST, FIRST + CURVE_LENGTH, FIRST + CURVE_LENGTH + 120.0)
LANES = (
    LaneSpec("sidewalk", 2.5, "both"),
    LaneSpec("bicycle", 1.6, "backward"),
    LaneSpec("driving", 3.3, "backward"),
    LaneSpec("driving", 3.3, "forward"),
    LaneSpec("bicycle", 1.6, "forward"),
    LaneSpec("sidewalk", 2.5, "both"),
)


def build() -> dict[str, object]:
    local = track((0.0, 0.0), 160.0, [Straight(FIRST), Curve(RADIUS, TURN), Straight(LAST)])
    fc = road_features("corner", local_to_lonlat(local, *ORIGIN), LANES, split_at=SPLIT_AT)
    fc["name"] = "melbourne-corner"
    return fc


if __name__ == "__main__":
    json.dump(build(), sys.stdout, indent=1)
    sys.stdout.write("\n")
