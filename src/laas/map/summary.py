"""What a lane map holds, in figures: `laas map info`."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap

__all__ = ["MapSummary", "load_timed", "summarise"]


@dataclass(frozen=True)
class MapSummary:
    """Segments, lanes by type, lane length by type (m), bounds (lon/lat), UTM zone."""

    source: str
    segments: int
    lanes: dict[str, int]
    length_m: dict[str, float]
    directions: dict[str, int]
    successors: int
    bounds_lonlat: tuple[float, float, float, float]
    utm: str
    load_s: float | None = None

    def lines(self) -> list[str]:
        w, s, e, n = self.bounds_lonlat
        out = [
            f"map      {self.source}",
            f"segments {self.segments} ({self.successors} successor links)",
            f"lanes    {sum(self.lanes.values())}: "
            + ", ".join(f"{k} {v}" for k, v in sorted(self.lanes.items())),
            f"length   {sum(self.length_m.values()) / 1000:.2f} km of lane centre line: "
            + ", ".join(f"{k} {v / 1000:.2f} km" for k, v in sorted(self.length_m.items())),
            "travel   " + ", ".join(f"{k} {v}" for k, v in sorted(self.directions.items())),
            f"bounds   lon {w:.6f} .. {e:.6f}, lat {s:.6f} .. {n:.6f}",
            f"utm      {self.utm}",
        ]
        if self.load_s is not None:
            out.append(f"load     {self.load_s * 1000:.0f} ms")
        return out

    def as_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "segments": self.segments,
            "lanes": self.lanes,
            "length_m": {k: round(v, 1) for k, v in self.length_m.items()},
            "directions": self.directions,
            "successors": self.successors,
            "bounds_lonlat": list(self.bounds_lonlat),
            "utm": self.utm,
            "load_s": self.load_s,
        }


def load_timed(path: str | Path) -> tuple[HdMap, float]:
    """Load a map; the map and the seconds the load took (wall clock)."""
    start = time.perf_counter()
    hdmap = read_geojson_file(path)
    return hdmap, time.perf_counter() - start


def summarise(hdmap: HdMap, load_s: float | None = None) -> MapSummary:
    """The figures of `hdmap`."""
    lanes: Counter[str] = Counter()
    length: Counter[str] = Counter()
    directions: Counter[str] = Counter()
    links = 0
    for segment in hdmap.segments.values():
        links += len(segment.successors)
        for lane in segment.lanes:
            lanes[lane.type] += 1
            length[lane.type] += lane.centerline.length
            directions[lane.direction] += 1
    x0, y0, x1, y1 = hdmap.bounds
    proj = hdmap.projection
    corners = [proj.to_wgs84(x, y) for x, y in ((x0, y0), (x0, y1), (x1, y0), (x1, y1))]
    lons = [c[0] for c in corners]
    lats = [c[1] for c in corners]
    hemisphere = "S" if proj.south else "N"
    return MapSummary(
        source=hdmap.source,
        segments=len(hdmap.segments),
        lanes=dict(lanes),
        length_m=dict(length),
        directions=dict(directions),
        successors=links,
        bounds_lonlat=(min(lons), min(lats), max(lons), max(lats)),
        utm=f"zone {proj.zone}{hemisphere} (EPSG:{proj.epsg})",
        load_s=load_s,
    )
