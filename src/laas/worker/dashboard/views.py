"""What the live map is drawn from, as JSON: the map's lanes, each answered fix, each
common-error area.

Everything leaves in WGS 84 (lon, lat), so the page needs no projection library: it
draws in a local plane around the map's centre. The map's frame is the UTM grid, so an
area's estimate b and its covariance P are drawn by their points, not their numbers:
the area's centre c, the tip c + b, and the 1-sigma ellipse around the tip,

    c + b + V diag(sqrt(l)) (cos t, sin t)',    P = V diag(l) V'   (eigendecomposition)

each projected back to WGS 84, which keeps the grid's rotation against true north (the
meridian convergence) right without the page knowing of it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from laas.map.hdmap import HdMap
from laas.worker.service import Observation

__all__ = ["AreaSnapshot", "area_views", "lanes_geojson", "observation_view"]

_DIGITS = 7  # decimal places of a degree: about 1 cm
_ELLIPSE_POINTS = 48


@dataclass(frozen=True, slots=True)
class AreaSnapshot:
    """One common-error area as the worker held it: centre c (2,), mean b (2,) and
    covariance P (2, 2), in the map's UTM frame (metres)."""

    centre: np.ndarray
    b: np.ndarray
    P: np.ndarray


def _lonlat(points: np.ndarray) -> list[list[float]]:
    return [[round(float(lon), _DIGITS), round(float(lat), _DIGITS)] for lon, lat in points]


def lanes_geojson(hdmap: HdMap) -> dict[str, Any]:
    """The map's lanes as a GeoJSON FeatureCollection (RFC 7946: WGS 84 lon/lat): one
    LineString per lane centre line, with `segment`, `lane` (0 = left-most), `type`,
    `width` (m) and `direction`; `bbox` is the map's extent and `name` its source."""
    features: list[dict[str, Any]] = []
    for segment in hdmap.segments.values():
        for lane in segment.lanes:
            xy = np.asarray(lane.centerline.coords, dtype=float)
            coords = _lonlat(hdmap.projection.to_wgs84_array(xy[:, 0], xy[:, 1]))
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": coords},
                    "properties": {
                        "segment": segment.id,
                        "lane": lane.index,
                        "type": lane.type,
                        "width": lane.width,
                        "direction": lane.direction,
                    },
                }
            )
    x0, y0, x1, y1 = hdmap.bounds
    corners = hdmap.projection.to_wgs84_array([x0, x0, x1, x1], [y0, y1, y0, y1])
    west, south = corners.min(axis=0)
    east, north = corners.max(axis=0)
    return {
        "type": "FeatureCollection",
        "name": hdmap.source,
        "bbox": [round(float(v), _DIGITS) for v in (west, south, east, north)],
        "features": features,
    }


def observation_view(seen: Observation) -> dict[str, Any]:
    """One answered fix: the pseudonym, the raw fix and the answer (lon, lat)."""
    fix, answer = seen.fix, seen.answer
    return {
        "pseudonym": seen.pseudonym,
        "timestamp": answer.timestamp,
        "raw": [round(fix.longitude, _DIGITS), round(fix.latitude, _DIGITS)],
        "position": [round(answer.longitude, _DIGITS), round(answer.latitude, _DIGITS)],
        "segment": answer.segment,
        "lane": answer.lane,
        "lane_type": answer.lane_type,
        "probability": round(answer.probability, 4),
        "accuracy_cross": round(answer.accuracy_cross, 3),
        "accuracy_along": round(answer.accuracy_along, 3),
    }


def area_views(hdmap: HdMap, areas: Sequence[AreaSnapshot]) -> list[dict[str, Any]]:
    """Each area (numbered as in the metrics): its centre and the tip c + b in lon/lat,
    b east and north (UTM grid, m), its 1-sigma across and along the road (the square
    roots of P's eigenvalues, as ``laas_common_error_sigma_metres``), the direction of
    the along axis (degrees counter-clockwise from grid east) and the ellipse (lon, lat)."""
    views = []
    t = np.linspace(0.0, 2.0 * math.pi, _ELLIPSE_POINTS, endpoint=False)
    for i, area in enumerate(areas):
        c, b = np.asarray(area.centre, float), np.asarray(area.b, float)
        low_high, v = np.linalg.eigh(np.asarray(area.P, float))  # ascending eigenvalues
        sigma = np.sqrt(np.clip(low_high, 0.0, None))
        tip = c + b
        ring = tip[:, None] + v @ (sigma[:, None] * np.vstack([np.cos(t), np.sin(t)]))  # (2, k)
        xs = np.concatenate([[c[0], tip[0]], ring[0]])
        ys = np.concatenate([[c[1], tip[1]], ring[1]])
        points = _lonlat(hdmap.projection.to_wgs84_array(xs, ys))
        views.append(
            {
                "area": i,
                "centre": points[0],
                "tip": points[1],
                "b": [round(float(b[0]), 3), round(float(b[1]), 3)],
                "sigma_across": round(float(sigma[0]), 3),
                "sigma_along": round(float(sigma[1]), 3),
                "along_degrees": round(math.degrees(math.atan2(v[1, 1], v[0, 1])), 2),
                "ellipse": points[2:],
            }
        )
    return views
