"""Generate maps/messe-hamburg.geojson, the paper's four-lane test road near Messe Hamburg.

    python maps/make_messe_hamburg.py > maps/messe-hamburg.geojson

Deterministic: the same output on every run. The road runs north-north-east (bearing 30 degrees)
for 280 m, turns right by 30 degrees on a 150 m radius (measured at the road's left edge), then
runs 220 m north-east (bearing 60). Lanes, left to right: two forward driving lanes, a parking
lane and a bicycle lane. Cut into five segments: two straights, the curve, two straights.

Why this orientation: the paper's common error is (-8 m east, +8 m north), and its paper-mode
results (Table I: AED 2.75 m, RMSE_y > RMSE_x) leave about 2.7 m of it along the road, which
only a road running some 75 degrees off the error's direction (bearing ~30 or ~60 degrees)
does. The paper does not publish its road; this is the road its own figures imply.
"""

from __future__ import annotations

import json
import math
import sys

from laas.map.mapgen import Curve, LaneSpec, Straight, local_to_lonlat, road_features, track

ORIGIN = (9.9760, 53.5585)  # lon, lat of the road's left edge at the start (St. Pauli, Messe)
FIRST, RADIUS, TURN, LAST = 280.0, 150.0, 30.0, 220.0
CURVE_LENGTH = RADIUS * math.radians(abs(TURN))
SPLIT_AT = (FIRST / 2, FIRST, FIRST + CURVE_LENGTH, FIRST + CURVE_LENGTH + LAST / 2)
LANES = (
    LaneSpec("driving", 3.25, "forward"),
    LaneSpec("driving", 3.25, "forward"),
    LaneSpec("parking", 2.2, "forward"),
    LaneSpec("bicycle", 1.8, "forward"),
)


def build() -> dict[str, object]:
    local = track((0.0, 0.0), 30.0, [Straight(FIRST), Curve(RADIUS, TURN), Straight(LAST)])
    reference = local_to_lonlat(local, *ORIGIN)
    fc = road_features("messe", reference, LANES, split_at=SPLIT_AT)
    fc["name"] = "messe-hamburg"
    return fc


if __name__ == "__main__":
    json.dump(build(), sys.stdout, indent=1)
    sys.stdout.write("\n")
