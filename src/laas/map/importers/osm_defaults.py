"""The OpenStreetMap importer's defaults: what a way is when its tags do not say.

Every number here is used only where a way lacks the tag (or has a value the importer
cannot read); ``docs/maps/osm.md`` prints these tables. Sources:

- **osm2streets** (a-b-street/osm2streets, ``osm2streets/src/lanes/mod.rs``,
  ``LaneSpec::typical_lane_widths``; ``classic.rs`` for lane counts): driving lane 10 ft
  = 3.05 m "typical", 12 ft = 3.66 m "highway"; bicycle lane 2.0 m "standard", 1.5 m
  "absolute minimum" (UK LTN 1/20 table 5-2); parking 7 ft = 2.13 m; sidewalk 1.5 m
  (6 ft = 1.83 m "wide"); one driving lane per direction without a ``lanes`` tag, an odd
  ``lanes`` count gives the extra lane to the forward direction.
- **SUMO netconvert** (eclipse-sumo/sumo): its OSM typemap
  ``data/typemap/osmNetconvert.typ.xml`` (2 lanes for motorway and trunk, 1 for the
  others; ``oneway`` implied on motorway and motorway_link; ``width="2"`` for cycleway,
  footway, path and pedestrian), its default lane width (``SUMO_const_laneWidth`` 3.2 m),
  ``--default.sidewalk-width`` 2.0 m, and ``osmNetconvertBicycle.typ.xml``
  (``cycleway.lane`` 1.25 m, ``cycleway.track`` 1.5 m).
- **Issue 12** of LaaS sets the ranges: driving lane 3.0–3.5 m by road class, cycle lane
  1.5 m, sidewalk 1.5–2.0 m, parking 2.0–2.5 m.

Where the sources differ the value is chosen inside the issue's range, nearest to the
source that models the same thing (driving lanes: 3.5 m on motorways and trunk roads,
between SUMO's 3.2 m and osm2streets' 3.66 m; 3.25 m on primary and secondary roads, near
SUMO's 3.2 m; 3.0 m on smaller streets, osm2streets' 10 ft). Diagonal and perpendicular
parking are LaaS's own estimates (the depth of a stall, about a car length); neither
source models them separately.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = [
    "BICYCLE_LANE_WIDTH",
    "BICYCLE_TRACK_WIDTH",
    "DRIVING_WIDTH_RANGE",
    "MAX_LANES",
    "PARKING_WIDTHS",
    "PATH_WIDTH_RANGE",
    "ROAD_CLASSES",
    "SKIPPED_HIGHWAYS",
    "RoadClass",
]

Kind = Literal["road", "cycle", "foot"]


@dataclass(frozen=True)
class RoadClass:
    """What a ``highway=*`` value is without further tags.

    `kind`: ``road`` (driving lanes, with cycle lanes, parking and sidewalks from tags),
    ``cycle`` (one bicycle lane) or ``foot`` (one sidewalk lane). `width`: one driving lane
    (road) or the way's one lane (cycle, foot), metres. `lanes`: driving lanes per
    direction without a ``lanes`` tag. `oneway`: oneway is implied. `single_track`: a
    two-way way without lane tags has ONE driving lane for both directions. `sidewalk`:
    width of a sidewalk tagged on the road.
    """

    kind: Kind
    width: float
    lanes: int = 1
    oneway: bool = False
    single_track: bool = False
    sidewalk: float = 1.5


ROAD_CLASSES: dict[str, RoadClass] = {
    "motorway": RoadClass("road", 3.5, lanes=2, oneway=True, sidewalk=2.0),
    "motorway_link": RoadClass("road", 3.5, oneway=True, sidewalk=2.0),
    "trunk": RoadClass("road", 3.5, lanes=2, sidewalk=2.0),
    "trunk_link": RoadClass("road", 3.5, sidewalk=2.0),
    "primary": RoadClass("road", 3.25, sidewalk=2.0),
    "primary_link": RoadClass("road", 3.25, sidewalk=2.0),
    "secondary": RoadClass("road", 3.25, sidewalk=2.0),
    "secondary_link": RoadClass("road", 3.25, sidewalk=2.0),
    "tertiary": RoadClass("road", 3.0, sidewalk=2.0),
    "tertiary_link": RoadClass("road", 3.0, sidewalk=2.0),
    "unclassified": RoadClass("road", 3.0),
    "residential": RoadClass("road", 3.0),
    "living_street": RoadClass("road", 3.0),
    "road": RoadClass("road", 3.0),
    "busway": RoadClass("road", 3.25),
    "service": RoadClass("road", 3.0, single_track=True),
    "track": RoadClass("road", 3.0, single_track=True),
    "cycleway": RoadClass("cycle", 2.0),
    "footway": RoadClass("foot", 2.0),
    "path": RoadClass("foot", 2.0),
    "pedestrian": RoadClass("foot", 2.0),
    "bridleway": RoadClass("foot", 2.0),
}
"""The ``highway=*`` values imported; every other value is left out and counted."""

SKIPPED_HIGHWAYS: tuple[str, ...] = (
    "steps",
    "corridor",
    "elevator",
    "platform",
    "construction",
    "proposed",
    "planned",
    "abandoned",
    "disused",
    "raceway",
)
"""Well-known values that are not imported (documented; any unknown value is skipped too):
stairs and indoor corridors are no lanes, platforms are stops, and roads under
construction, proposed or abandoned carry no traffic."""

BICYCLE_LANE_WIDTH = 1.5  # cycleway=lane: issue 12; osm2streets' absolute minimum
BICYCLE_TRACK_WIDTH = 2.0  # cycleway=track: osm2streets' standard (LTN 1/20)

PARKING_WIDTHS: dict[str, float] = {
    "parallel": 2.2,  # osm2streets 7 ft = 2.13 m; issue 12: 2.0-2.5 m
    "diagonal": 4.5,  # LaaS estimate: depth of an angled stall
    "perpendicular": 5.0,  # LaaS estimate: a car length
}

DRIVING_WIDTH_RANGE = (2.0, 5.5)
"""A driving lane scaled from a ``width`` tag must come out inside this range (metres);
otherwise the tag is reported and the default width is used."""

PATH_WIDTH_RANGE = (0.3, 30.0)
"""Accepted ``width`` of a cycleway or footway (its one lane), metres."""

MAX_LANES = 12
"""A ``lanes`` value above this is reported as not understood."""
