"""`laas bench-filter`: the lane filter's time per update against the users in a segment.

One straight four-lane road element, N users on random lanes sharing a common error,
every user reporting once a second. For each N it times, on this process's one core:

- paper mode, one engine step (Kalman, map lookup, the joint hypothesis filter over
  L^N hypotheses), until L^N passes `paper_limit`, where enumeration is impractical;
- default mode, one engine step (the common error kept uncertain by a fast drift, so the
  grid posterior stays wide). Its cost does not grow with N: each fix updates its own
  user's lane table and the area's grid, never the other users';
- default mode in batches: the N fixes of each second handed to the engine together, as
  the live worker takes a crowd's epoch (`Engine.process_many`), the time per fix.

Medians over the timed steps; the first steps are warm-up and not timed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from laas.config import EngineConfig, Mode
from laas.engine.engine import Engine
from laas.map.geojson import read_geojson
from laas.map.hdmap import HdMap
from laas.map.mapgen import LaneSpec, local_to_lonlat, road_features
from laas.models import GpsMeasurement

__all__ = ["GROUP_SIZES", "FilterRow", "bench_filter", "format_filter_table", "group_sizes"]

_LANES = (
    LaneSpec("driving", 3.25),
    LaneSpec("driving", 3.25),
    LaneSpec("parking", 2.2),
    LaneSpec("bicycle", 1.8),
)


GROUP_SIZES = (1, 2, 3, 4, 6, 8, 10, 20, 50, 100, 200)
"""The users in a segment `laas bench-filter` times, up to its ``--max-users``."""


def group_sizes(max_users: int) -> list[int]:
    """The sizes of `GROUP_SIZES` up to `max_users`."""
    return [n for n in GROUP_SIZES if n <= max_users]


@dataclass(frozen=True)
class FilterRow:
    """Median milliseconds per update for N users in one segment (None: not run)."""

    users: int
    hypotheses: float  # L^N
    paper_ms: float | None
    default_ms: float
    batched_ms: float  # default mode, the N fixes of a second as one batch, per fix

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def _road() -> HdMap:
    reference = local_to_lonlat([(0.0, 0.0), (0.0, 1000.0)], 13.4050, 52.5200)  # Berlin
    return read_geojson(road_features("bench", reference, _LANES), source="bench road")


def _time_engine(hdmap: HdMap, n: int, mode: Mode, steps: int, seed: int, batch: bool) -> float:
    rng = np.random.default_rng(seed)
    seg = hdmap.segments["bench-0"]
    engine = Engine(hdmap, EngineConfig(mode=mode, bias_drift=5.0))
    stations = rng.uniform(50.0, 900.0, n)
    lanes = rng.integers(0, len(_LANES), n)
    times: list[float] = []
    for k in range(steps + 3):
        fixes = []
        for i in range(n):
            s = stations[i] + 5.0 * k
            e, north = seg.point(s, float(seg.lane_offsets(s)[lanes[i]]))
            lon, lat = hdmap.projection.to_wgs84(
                e - 8.0 + rng.normal(0, 1.0), north + 8.0 + rng.normal(0, 1.0)
            )
            m = GpsMeasurement(
                timestamp=1_700_000_000_000 + 1000 * k + i,
                latitude=lat,
                longitude=lon,
                heading=seg.heading(s),
                speed=5.0,
            )
            fixes.append((f"u{i}", m))
        if batch:
            start = time.perf_counter()
            engine.process_many(fixes)
            if k >= 3:
                times.append((time.perf_counter() - start) / n)
            continue
        for fix in fixes:
            start = time.perf_counter()
            engine.process(*fix)
            if k >= 3:
                times.append(time.perf_counter() - start)
    return 1000.0 * float(np.median(times))


def bench_filter(
    counts: Sequence[int] = (1, 2, 3, 4, 6, 8, 10, 20, 50, 100),
    *,
    steps: int = 10,
    paper_limit: int = 4**8,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
) -> list[FilterRow]:
    """Time both modes for every N in `counts`."""
    hdmap = _road()
    lanes = len(_LANES)
    rows = []
    for n in counts:
        if progress is not None:
            progress(n)
        hyp = float(lanes) ** n
        paper = _time_engine(hdmap, n, "paper", steps, seed, False) if hyp <= paper_limit else None
        default = _time_engine(hdmap, n, "default", steps, seed, False)
        batched = _time_engine(hdmap, n, "default", steps, seed, True)
        rows.append(FilterRow(n, hyp, paper, default, batched))
    return rows


def format_filter_table(rows: Sequence[FilterRow]) -> str:
    """The table `laas bench-filter` prints."""

    def ms(v: float | None) -> str:
        return f"{v:10.3f}" if v is not None else f"{'-':>10}"

    head = f"{'users':>6}{'L^N':>10}  {'paper':>10}{'default':>10}{'batched':>10}"
    lines = [
        "lane filter, median ms per update (one core); '-' = impractical, not run",
        head,
        "-" * len(head),
    ]
    for r in rows:
        lines.append(
            f"{r.users:>6}{r.hypotheses:>10.3g}  "
            f"{ms(r.paper_ms)}{ms(r.default_ms)}{ms(r.batched_ms)}"
        )
    lines.append("paper, default: one whole engine step (Kalman, map, lane filter), per fix")
    lines.append("batched: default mode, each second's N fixes as one batch, per fix")
    return "\n".join(lines)
