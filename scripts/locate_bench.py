"""Microseconds per `HdMap.locate` on a lane map, and its load time.

    .venv/bin/python scripts/locate_bench.py maps/helsinki.geojson [--points 2000]

Points on lanes: the middle of every lane's centre line, cycled; random points: uniform
in the map's bounds (some fall outside every road element). One process, wall clock.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from laas.map.summary import load_timed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map")
    parser.add_argument("--points", type=int, default=2000)
    a = parser.parse_args()
    hdmap, load_s = load_timed(a.map)
    lanes = [lane for seg in hdmap.segments.values() for lane in seg.lanes]
    picked = [lanes[k % len(lanes)] for k in range(a.points)]
    middles = [lane.centerline.interpolate(0.5, normalized=True) for lane in picked]
    on_xy = [(p.x, p.y) for p in middles]
    x0, y0, x1, y1 = hdmap.bounds
    rng = np.random.default_rng(0)
    rand_xy = list(zip(rng.uniform(x0, x1, a.points), rng.uniform(y0, y1, a.points), strict=True))
    print(f"{a.map}: {len(hdmap.segments)} road elements, {len(lanes)} lanes, load {load_s:.2f} s")
    for name, points in (("on lanes", on_xy), ("random in bounds", rand_xy)):
        start = time.perf_counter()
        found = sum(hdmap.locate(float(x), float(y)) is not None for x, y in points)
        took = time.perf_counter() - start
        print(
            f"locate, {name}: {took / len(points) * 1e6:.1f} us per call, "
            f"{found}/{len(points)} found"
        )


if __name__ == "__main__":
    main()
