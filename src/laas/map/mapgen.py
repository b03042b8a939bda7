"""Build lane-level GeoJSON maps from a road description (reference line + lane layout).

Used by the scenario simulator, the tests and the map scripts in ``maps/``. A road is a reference
polyline (its left edge or its centre line) and a list of lanes from left to right; every lane's
centre line is a parallel (mitred) offset curve of the reference, and the road is cut into
segments at given stations. The result is a GeoJSON FeatureCollection dict in the format of
``maps/README.md`` that :func:`laas.map.geojson.read_geojson` loads.

Polylines can be drawn in a local metric frame (metres east and north of an origin) with
:func:`track` (straights and circular curves) or :func:`arc`, then placed on Earth with
:func:`local_to_lonlat`. Bearings are degrees clockwise from (UTM grid) north.

    >>> pts = track((0.0, 0.0), 0.0, [Straight(100.0), Curve(radius=50.0, angle=-90.0)])
    >>> [round(c, 6) for c in pts[-1]]
    [-50.0, 150.0]
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import shapely
from shapely import LineString
from shapely.ops import substring

from laas.map.geo import UtmProjection
from laas.map.hdmap import DIRECTIONS, LANE_TYPES, Direction, LaneType

__all__ = [
    "Curve",
    "LaneSpec",
    "Straight",
    "arc",
    "feature_collection",
    "local_to_lonlat",
    "road_features",
    "road_features_utm",
    "track",
]

Point2 = tuple[float, float]


@dataclass(frozen=True)
class LaneSpec:
    """One lane of a road, as seen from the left edge looking along the reference direction."""

    type: LaneType
    width: float
    direction: Direction = "forward"
    properties: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.type not in LANE_TYPES:
            raise ValueError(f"unknown lane type {self.type!r}")
        if self.direction not in DIRECTIONS:
            raise ValueError(f"unknown direction {self.direction!r}")
        if not (math.isfinite(self.width) and self.width > 0.0):
            raise ValueError(f"lane width must be > 0 metres, got {self.width}")


@dataclass(frozen=True)
class Straight:
    """A straight piece of ``length`` metres."""

    length: float


@dataclass(frozen=True)
class Curve:
    """A circular curve of ``radius`` metres turning by ``angle`` degrees (< 0 left, > 0 right)."""

    radius: float
    angle: float


def _unit(bearing_deg: float) -> Point2:
    b = math.radians(bearing_deg)
    return math.sin(b), math.cos(b)  # (east, north)


def arc(
    center: Point2,
    radius: float,
    start_bearing: float,
    end_bearing: float,
    *,
    clockwise: bool,
    step: float = 1.0,
) -> list[Point2]:
    """Points on a circle from ``start_bearing`` to ``end_bearing`` (bearings of the radius
    vector seen from ``center``), clockwise or counter-clockwise, at most ``step`` metres apart.
    Both end points are included."""
    if not radius > 0.0 or not step > 0.0:
        raise ValueError("radius and step must be > 0")
    sweep = (end_bearing - start_bearing) % 360.0
    if not clockwise:
        sweep = -((start_bearing - end_bearing) % 360.0)
    n = max(1, math.ceil(abs(math.radians(sweep)) * radius / step))
    out = []
    for k in range(n + 1):
        ex, ny = _unit(start_bearing + sweep * k / n)
        out.append((center[0] + radius * ex, center[1] + radius * ny))
    return out


def track(
    start: Point2, bearing: float, parts: Sequence[Straight | Curve], step: float = 1.0
) -> list[Point2]:
    """A polyline in a local metric frame from ``start`` heading ``bearing``, made of straights
    and tangent circular curves; curves are sampled at most ``step`` metres apart."""
    pts: list[Point2] = [(float(start[0]), float(start[1]))]
    heading = float(bearing)
    for part in parts:
        x, y = pts[-1]
        if isinstance(part, Straight):
            if not part.length > 0.0:
                raise ValueError(f"straight length must be > 0, got {part.length}")
            ex, ny = _unit(heading)
            pts.append((x + part.length * ex, y + part.length * ny))
        else:
            if not part.radius > 0.0 or part.angle == 0.0:
                raise ValueError(f"curve needs radius > 0 and angle != 0, got {part}")
            right = part.angle > 0.0
            to_center = heading + (90.0 if right else -90.0)
            ex, ny = _unit(to_center)
            center = (x + part.radius * ex, y + part.radius * ny)
            start_b = (to_center + 180.0) % 360.0  # bearing of the current point from the centre
            pts.extend(
                arc(center, part.radius, start_b, start_b + part.angle, clockwise=right, step=step)[
                    1:
                ]
            )
            heading = (heading + part.angle) % 360.0
    return pts


def local_to_lonlat(points: Sequence[Point2], origin_lon: float, origin_lat: float) -> list[Point2]:
    """Place local (east, north) metres on Earth: the origin's UTM zone, offset from its UTM
    coordinates (so local bearings are UTM grid bearings)."""
    proj = UtmProjection.for_location(origin_lon, origin_lat)
    ox, oy = proj.to_utm(origin_lon, origin_lat)
    xy = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    ll = proj.to_wgs84_array(xy[:, 0] + ox, xy[:, 1] + oy)
    return [(float(lon), float(lat)) for lon, lat in ll]


def _lane_offsets(lanes: Sequence[LaneSpec], reference_is: str) -> list[float]:
    """Right-positive offset of each lane centre from the reference line."""
    offsets, edge = [], 0.0
    for lane in lanes:
        offsets.append(edge + lane.width / 2.0)
        edge += lane.width
    if reference_is == "center":
        offsets = [o - edge / 2.0 for o in offsets]
    elif reference_is != "left_edge":
        raise ValueError(f"reference_is must be 'left_edge' or 'center', got {reference_is!r}")
    return offsets


def road_features_utm(
    road_id: str,
    reference_utm: Sequence[Point2],
    projection: UtmProjection,
    lanes: Sequence[LaneSpec],
    split_at: Sequence[float] = (),
    reference_is: Literal["left_edge", "center"] = "left_edge",
    *,
    decimals: int = 8,
) -> dict[str, Any]:
    """Like :func:`road_features`, with the reference already in ``projection``'s UTM metres."""
    if not road_id:
        raise ValueError("road_id must not be empty")
    if not lanes:
        raise ValueError("a road needs at least one lane")
    pts = np.asarray(reference_utm, dtype=np.float64).reshape(-1, 2)
    keep = np.ones(len(pts), dtype=bool)  # drop vertices within 1 mm of the previous one
    keep[1:] = np.hypot(*(pts[1:] - pts[:-1]).T) > 1e-3
    ref = LineString(pts[keep])
    if ref.length <= 0.0 or not ref.is_simple:
        raise ValueError("the reference line must have length and must not cross itself")
    cuts = [float(s) for s in split_at]
    if any(b <= a for a, b in itertools.pairwise(cuts)):
        raise ValueError(f"split_at must be strictly increasing, got {cuts}")
    if cuts and not (cuts[0] > 0.0 and cuts[-1] < ref.length):
        raise ValueError(f"split_at must lie inside (0, {ref.length:.1f}) m, got {cuts}")
    # snap cuts onto reference vertices closer than a millimetre (e.g. where a curve starts), so
    # no segment ends with a sliver of the next piece
    vertex_s = np.asarray(shapely.line_locate_point(ref, shapely.points(ref.coords)))
    for k, cut in enumerate(cuts):
        nearest = float(vertex_s[np.argmin(np.abs(vertex_s - cut))])
        if abs(nearest - cut) < 1e-3:
            cuts[k] = nearest
    stations = [0.0, *cuts, ref.length]
    offsets = _lane_offsets(lanes, reference_is)
    ids = [f"{road_id}-{i}" for i in range(len(stations) - 1)]

    features: list[dict[str, Any]] = []
    for i, seg_id in enumerate(ids):
        piece = substring(ref, stations[i], stations[i + 1])
        for k, (lane, off) in enumerate(zip(lanes, offsets, strict=True)):
            # shapely: positive distance offsets to the LEFT, and keeps the line's direction
            line = (
                piece
                if off == 0.0
                else shapely.offset_curve(piece, -off, join_style="mitre", mitre_limit=10.0)
            )
            if not isinstance(line, LineString) or line.is_empty:
                raise ValueError(
                    f"lane {k} of {seg_id} collapses (offset {off} m too large for the curvature)"
                )
            coords = np.asarray(line.coords, dtype=np.float64)[:, :2]
            lonlat = projection.to_wgs84_array(coords[:, 0], coords[:, 1])
            props: dict[str, Any] = {
                "segment": seg_id,
                "lane": k,
                "type": lane.type,
                "width": lane.width,
                "direction": lane.direction,
                "successors": [ids[i + 1]] if i + 1 < len(ids) else [],
                "road": road_id,
                **dict(lane.properties),
            }
            features.append(
                {
                    "type": "Feature",
                    "properties": props,
                    "geometry": {
                        "type": "LineString",
                        "coordinates": [
                            [round(float(lon), decimals), round(float(lat), decimals)]
                            for lon, lat in lonlat
                        ],
                    },
                }
            )
    return {"type": "FeatureCollection", "features": features}


def road_features(
    road_id: str,
    reference_lonlat: Sequence[Point2],
    lanes: Sequence[LaneSpec],
    split_at: Sequence[float] = (),
    reference_is: Literal["left_edge", "center"] = "left_edge",
    *,
    decimals: int = 8,
) -> dict[str, Any]:
    """A GeoJSON FeatureCollection for one road.

    ``reference_lonlat``: the road's left edge (or centre line) as (lon, lat), in the direction
    of travel of ``forward`` lanes. ``lanes``: left to right. ``split_at``: stations (metres
    along the reference) where the road is cut into segments ``<road_id>-0``, ``<road_id>-1``, ...
    each the successor of the one before. Coordinates are rounded to ``decimals`` places.
    """
    ll = np.asarray(reference_lonlat, dtype=np.float64).reshape(-1, 2)
    if len(ll) < 2:
        raise ValueError("the reference line needs at least 2 points")
    proj = UtmProjection.for_location(float(ll[:, 0].mean()), float(ll[:, 1].mean()))
    xy = proj.to_utm_array(ll[:, 0], ll[:, 1])
    return road_features_utm(
        road_id,
        [(float(x), float(y)) for x, y in xy],
        proj,
        lanes,
        split_at,
        reference_is,
        decimals=decimals,
    )


def feature_collection(*collections: Mapping[str, Any]) -> dict[str, Any]:
    """Merge several FeatureCollections (e.g. several roads) into one."""
    features: list[Any] = []
    for fc in collections:
        features.extend(fc["features"])
    return {"type": "FeatureCollection", "features": features}
