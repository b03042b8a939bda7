"""Compile the engine's arithmetic before the first fix that counts (`laas.engine.jit`).

The compiled functions are built on their first call: some seconds on a fresh install
(then kept in numba's cache), some tenths of a second in each new process after. A
worker that did this on its first real fix would answer it seconds late, so it first
drives a short synthetic crowd through an engine of its own: three users driving one
road element of the map for 20 simulated seconds, one fix at a time and in a batch,
which takes every compiled function down the paths that live fixes take. The engine is
then thrown away; nothing of it reaches the worker's own. The users cross from the
element into the next, so a lane table is carried over too (`cooperative._reproject`).
A paper-mode worker's crowd goes through a default-mode engine as well: its own uses
only the Kalman step, and the warm-up builds every function either way.

    .venv/bin/python -m laas.engine.warm     # fill the cache (`scripts/test` does)
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from laas.config import EngineConfig
from laas.engine.engine import Engine
from laas.engine.jit import COMPILED
from laas.engine.stacked import _evidence_cells
from laas.engine.tracking import _product, multipath_weight
from laas.map.hdmap import HdMap, Segment
from laas.models import GpsMeasurement

__all__ = ["warm_up"]

log = logging.getLogger(__name__)

_USERS = 3
_SECONDS = 20
_SPEED = 8.0  # m/s
_T0 = 1_700_000_000_000  # ms: any time; the engine keeps none of it


def warm_up(hdmap: HdMap | None = None, config: EngineConfig | None = None) -> float:
    """Drive a short synthetic crowd through a throw-away engine on `hdmap` (None: a
    bundled map), so every compiled function is built or loaded; the seconds it took."""
    started = time.perf_counter()
    if hdmap is None:
        from laas.map.bundled import bundled_map
        from laas.map.geojson import read_geojson_file

        hdmap = read_geojson_file(bundled_map("messe-hamburg"))

    def rank(e: Segment) -> tuple[bool, bool, float]:
        return (bool(e.successors), len(e.lanes) > 1, e.length)

    segment = max(hdmap.segments.values(), key=rank)
    following = next((hdmap.segments[e] for e in segment.successors if e in hdmap.segments), None)
    fixes = _fixes(hdmap, segment, following)
    configs = [config or EngineConfig()]
    if configs[0].mode != "default":
        configs.append(EngineConfig())
    for c in configs if fixes else []:
        one = Engine(hdmap, c)
        for fix in fixes[:_SECONDS]:  # one fix at a time
            one.process(*fix)
        many = Engine(hdmap, c)
        for k in range(0, len(fixes), _USERS):  # every user's fix of a second together
            many.process_many(fixes[k : k + _USERS])
    # what the crowd may not reach: the evidence of few cells (a settled posterior's
    # narrow span), and the multipath weight and the 4 x 4 product on their own (inside
    # the Kalman step they are compiled as part of `_kalman`)
    cube, row = np.ones((1, 2, 2)), np.ones(1)
    _evidence_cells(
        cube,
        cube,
        np.ones((1, 2)),
        row,
        row,
        np.zeros(1, dtype=np.intp),
        np.ones((1, 2)),
        row,
        row,
        1e-3,
        0.05,
        3.0,
    )
    multipath_weight(1.0, 0.0, 1.0, 0.0, 0.0, 0.05)
    square = np.eye(4)
    _product(square, square, np.empty((4, 4)), True)
    missing = [f.__name__ for f in COMPILED if not f.signatures]
    if missing:
        log.warning("laas.engine.warm: compiled on the first fix instead: %s", ", ".join(missing))
    return time.perf_counter() - started


def _fixes(
    hdmap: HdMap, segment: Segment, following: Segment | None
) -> list[tuple[str, GpsMeasurement]]:
    """Each second, a fix of each user driving `segment` on a lane of its own, into
    `following` at half time if there is one, in order of time; empty if the element
    is too short to drive for a second."""
    if segment.length < _SPEED:
        return []
    projection = hdmap.projection
    out = []
    start = segment.length - _SPEED * _SECONDS / 2 if following is not None else 0.0
    for second in range(_SECONDS):
        s = max(start, 0.0) + second * _SPEED
        on = segment
        if following is not None and s > segment.length:
            on, s = following, min(s - segment.length, following.length)
        s %= max(on.length, 1.0)
        t_e, t_n = on.tangent(s).tolist()
        lon, lat = projection.to_wgs84(*on.point(s))
        bearing = math.degrees(math.atan2(t_e, t_n)) + projection.convergence(lon, lat)
        heading = min(bearing % 360.0, 359.999)  # x % 360 of a tiny negative x is 360.0
        offsets = on.lane_offsets(s).tolist()
        for user in range(_USERS):
            x, y = on.point(s, offsets[user % len(offsets)])
            lon, lat = projection.to_wgs84(x, y)
            measurement = GpsMeasurement(
                timestamp=_T0 + 1000 * second,
                latitude=lat,
                longitude=lon,
                heading=heading,
                speed=_SPEED,
                accuracy=2.0,
            )
            out.append((f"warm-{user}", measurement))
    return out


if __name__ == "__main__":
    print(f"laas: the engine's compiled arithmetic ready in {warm_up():.1f} s")
