"""Regions: one map served by several workers, each for its own strip of it.

`split` cuts the map's bounds into ``count`` strips across its longer side, of equal
width. Each worker serves a region of `laas` as a service of its own name
(``laas-2of3``) and announces its coverage: its strip grown by ``overlap`` metres into
each neighbour (and by ``margin`` outwards, so fixes just off the map still find a
worker), as a polygon of longitude and latitude. A participant sends each fix to the
worker whose coverage holds it and stays with that worker while it is inside
(`ldm.client.routing.RoutedSession`): so a road user crossing a border is handed over once
it is ``overlap`` metres past it, and the new worker has been estimating the common
error of that side from its own users all along.

Hand-over (`laas.worker.service`): while a user's fix lies past its worker's border
(in the overlap, outside its ``strip``), the worker adds the user's state to the
answer, sealed with the region key (`laas.engine.handover`); the participant hands the
latest to the next worker with its first fix there (`ldm.client.routing.RoutedSession`), which
goes on with the user's track and lane table. And each worker sends the others its own
users' evidence about the common error of its areas (a sealed note, every
``share_every`` seconds), which those whose coverage holds an area fold into theirs, so
the common error on either side of a border is estimated from every user near it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from laas.errors import ConfigError
from laas.map.hdmap import HdMap

__all__ = ["Region", "parse_region", "split"]

_DENSIFY = 8  # points per edge: UTM straight lines are not quite straight in degrees


@dataclass(frozen=True)
class Region:
    """Strip `index` (0-based) of `count`: its UTM box and its announced coverage."""

    index: int
    count: int
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 in the map's UTM frame, m
    coverage: list[tuple[float, float]]  # (lon, lat) ring, the box grown by the overlap
    strip: tuple[float, float, float, float] | None = None  # the box without the overlap

    @property
    def name(self) -> str:
        """The service name of this region's worker: ``laas-2of3``."""
        return f"laas-{self.index + 1}of{self.count}"


def split(
    hdmap: HdMap, count: int, overlap: float = 150.0, margin: float = 10_000.0
) -> list[Region]:
    """The map cut into `count` strips across its longer side (module docstring)."""
    if count < 1:
        raise ConfigError(f"a map is served by at least one region, not {count}")
    if overlap < 0 or margin < 0:
        raise ConfigError("overlap and margin are distances in metres, not negative")
    x0, y0, x1, y1 = hdmap.bounds
    along_x = (x1 - x0) >= (y1 - y0)
    lo, hi = (x0, x1) if along_x else (y0, y1)
    width = (hi - lo) / count
    regions = []
    for k in range(count):
        a = lo + k * width - (overlap if k > 0 else margin)
        b = lo + (k + 1) * width + (overlap if k < count - 1 else margin)
        box = (a, y0 - margin, b, y1 + margin) if along_x else (x0 - margin, a, x1 + margin, b)
        a = lo + k * width if k > 0 else a
        b = lo + (k + 1) * width if k < count - 1 else b
        strip = (a, box[1], b, box[3]) if along_x else (box[0], a, box[2], b)
        regions.append(Region(k, count, box, _ring(hdmap, box), strip))
    return regions


def _ring(hdmap: HdMap, box: tuple[float, float, float, float]) -> list[tuple[float, float]]:
    """The box's outline in (lon, lat), each edge densified."""
    x0, y0, x1, y1 = box
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    xs: list[float] = []
    ys: list[float] = []
    for (ax, ay), (bx, by) in zip(corners, corners[1:] + corners[:1], strict=True):
        for i in range(_DENSIFY):
            f = i / _DENSIFY
            xs.append(ax + f * (bx - ax))
            ys.append(ay + f * (by - ay))
    lonlat = hdmap.projection.to_wgs84_array(xs, ys)
    return [(float(lon), float(lat)) for lon, lat in lonlat]


def parse_region(text: str) -> tuple[int, int]:
    """``K/N`` (1-based) -> (K - 1, N); a clear error otherwise."""
    found = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
    if found is None or not 1 <= int(found[1]) <= int(found[2]):
        raise ConfigError(f"--region {text!r}: give K/N with 1 <= K <= N, e.g. 2/3")
    return int(found[1]) - 1, int(found[2])
