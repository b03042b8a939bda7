"""Road users roaming any map: random paths that follow successors and cross junctions.

``roam_scenario(hdmap, seed)`` draws a scenario on any lane map (imported or generated) in
which every user drives a path of its own (``UserPlan.path``, see :mod:`laas.sim.scenario`):
a chain of (segment, lane, way) pieces from successor to successor, taking a random branch
at every junction. The same (map, seed) gives the same scenario: every draw comes from one
generator seeded by (crc32("roam"), seed), in a fixed order (users one after the other, each
in the order below; the map's segments and lanes in file order). U(a, b) is uniform, "p" a
probability, D the scenario's duration.

Per user:
  kind      car, bicycle, pedestrian with weights (0.6, 0.25, 0.15), among the kinds whose
            lane type (driving, bicycle, sidewalk) the map has
  start     a lane of the kind's type, chosen with probability proportional to its length;
            its way the lane's direction (``both``: forward or backward with p 0.5); a point
            U(0, 1) of the lane's length along it in that way
  speed     cars U(5, 14) m/s, bicycles U(3, 7), pedestrians U(0.8, 1.8)
  time      enters late with p 0.3, at U(0, D / 2) s; stays to the end unless its path ends
  stop      a stop (a light, say) with p 0.25, held U(5, 20) s, if it fits in its time;
            braking and starting at peak 2.0 m/s^2 (cars), 1.5 (bicycles), 1.0 (pedestrians)
  path      from the start lane on, until it is long enough for the user's time on the map:
            the next segments are the current one's successors when the user drives forward
            and its predecessors (the segments that list it as a successor) when it drives
            backward. A next segment is a candidate when it has a lane of the user's type
            that may be driven in a way whose start is within ``PATH_SUCCESSOR_GAP`` m of
            where the current lane ends; the candidate's lane is the one (and the way, for a
            ``both`` lane) that starts nearest. One candidate is drawn uniformly (at a
            junction: any branch). No candidate: a dead end, and the path ends there.
  leave     where the path ends: 1 m before its end (``leave``, the bisection of
            ``distance_driven``). If less than 2 s of driving would remain after the start
            point, the user starts at the start of its first lane instead.
  receiver  a phase U(0, min(1, 1 / rate)) s floored to the millisecond; a constant bias of
            magnitude U(0, 1) m in a direction U(0, 360); noise_scale U(0.7, 1.4)

The GNSS error model is the scenario's (``errors``, the paper's by default). The scenario's
``route`` is empty (every user has a path) and its ``map`` is the map's ``source``.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from laas.errors import ConfigError
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap, Lane
from laas.sim.scenario import (
    PATH_SUCCESSOR_GAP,
    ErrorModel,
    PathStep,
    Scenario,
    UserPlan,
    Way,
    distance_driven,
    get_scenario,
)

__all__ = ["KINDS", "roam_scenario", "scenario_or_roam"]

KINDS: dict[str, str] = {"car": "driving", "bicycle": "bicycle", "pedestrian": "sidewalk"}
"""The kinds of road user and the lane type each drives."""

_WEIGHTS = {"car": 0.6, "bicycle": 0.25, "pedestrian": 0.15}
_SPEEDS = {"car": (5.0, 14.0), "bicycle": (3.0, 7.0), "pedestrian": (0.8, 1.8)}
_BRAKES = {"car": 2.0, "bicycle": 1.5, "pedestrian": 1.0}
_MARGIN = 1.0  # m left before the end of a path when the user leaves there
_STREAM = zlib.crc32(b"roam")

Step = tuple[str, int, Way]
_WAYS: dict[str, tuple[Way, ...]] = {
    "forward": ("forward",),
    "backward": ("backward",),
    "both": ("forward", "backward"),
}


def _ways(lane: Lane) -> tuple[Way, ...]:
    """The ways a lane may be driven."""
    return _WAYS[lane.direction]


def _ends(lane: Lane, way: Way) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) of a lane's centre line driven in `way`."""
    xy = np.asarray(lane.centerline.coords, dtype=np.float64)[:, :2]
    return (xy[-1], xy[0]) if way == "backward" else (xy[0], xy[-1])


class _Graph:
    """The map's lanes by type and its segments' predecessors."""

    def __init__(self, hdmap: HdMap) -> None:
        self.hdmap = hdmap
        self.by_type: dict[str, list[Lane]] = {}
        self.predecessors: dict[str, list[str]] = {s: [] for s in hdmap.segments}
        for segment in hdmap.segments.values():
            for lane in segment.lanes:
                self.by_type.setdefault(lane.type, []).append(lane)
            for succ in segment.successors:
                self.predecessors[succ].append(segment.id)

    def lane(self, step: Step) -> Lane:
        return self.hdmap.segments[step[0]].lanes[step[1]]

    def options(self, step: Step) -> list[tuple[float, Step]]:
        """(gap, next step) per next segment that continues `step` (see the docstring)."""
        segment = self.hdmap.segments[step[0]]
        lane = segment.lanes[step[1]]
        end = _ends(lane, step[2])[1]
        nexts = self.predecessors[segment.id] if step[2] == "backward" else segment.successors
        out: list[tuple[float, Step]] = []
        for seg_id in nexts:
            best: tuple[float, Step] | None = None
            for other in self.hdmap.segments[seg_id].lanes:
                if other.type != lane.type:
                    continue
                for way in _ways(other):
                    gap = float(np.hypot(*(_ends(other, way)[0] - end)))
                    if gap <= PATH_SUCCESSOR_GAP and (best is None or gap < best[0]):
                        best = (gap, (seg_id, other.index, way))
            if best is not None:
                out.append(best)
        return out


def _path(
    rng: np.random.Generator, graph: _Graph, first: Step, need: float
) -> tuple[list[Step], float]:
    """Steps from `first` on until the path is `need` metres long or ends; and its length."""
    steps = [first]
    length = graph.lane(first).centerline.length
    while length < need:
        options = graph.options(steps[-1])
        if not options:
            break
        gap, step = options[int(rng.integers(0, len(options)))] if len(options) > 1 else options[0]
        steps.append(step)
        length += gap + graph.lane(step).centerline.length
    return steps, length


def _leave(plan: UserPlan, room: float, end: float) -> float:
    """The last time (ms rounded down) at which the user has driven at most `room` metres."""
    lo, hi = plan.enter, end
    for _ in range(60):
        mid = (lo + hi) / 2.0
        lo, hi = (mid, hi) if distance_driven(plan, mid) <= room else (lo, mid)
    return max(math.floor(lo * 1000.0) / 1000.0, plan.enter + 0.001)


def roam_scenario(
    hdmap: HdMap,
    seed: int,
    users: int = 10,
    duration: float = 120.0,
    rate: float = 1.0,
    name: str | None = None,
    errors: ErrorModel | None = None,
) -> Scenario:
    """Draw `users` road users roaming `hdmap` for `duration` s (see the module docstring)."""
    if seed < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    if users < 1:
        raise ConfigError(f"a roaming scenario needs at least one user, got {users}")
    if not (0.0 < duration < math.inf and 0.0 < rate < math.inf):
        raise ConfigError(
            f"duration and rate must be finite and > 0, got {duration} s and {rate} Hz"
        )
    graph = _Graph(hdmap)
    kinds = [k for k in KINDS if graph.by_type.get(KINDS[k])]
    if not kinds:
        raise ConfigError(
            f"{hdmap.source}: the map has no driving, bicycle or sidewalk lane, so no road "
            "user can roam on it"
        )
    weights = np.array([_WEIGHTS[k] for k in kinds])
    rng = np.random.default_rng([_STREAM, seed])
    plans = tuple(
        _draw_user(rng, graph, i, kinds, weights / weights.sum(), duration, rate)
        for i in range(users)
    )
    return Scenario(
        name=name if name is not None else f"roam-{Path(hdmap.source).stem}-{seed}",
        map=hdmap.source,
        route=(),
        users=plans,
        duration=duration,
        rate=rate,
        errors=errors if errors is not None else ErrorModel(),
    )


def scenario_or_roam(
    scenario: str,
    map_path: str | Path | None = None,
    seed: int = 0,
    users: int = 10,
    duration: float = 120.0,
) -> tuple[Scenario, HdMap]:
    """The built-in scenario `scenario` and its map; or, given `map_path`, `users` road
    users roaming that lane map (GeoJSON) for `duration` s, drawn with `seed`."""
    if map_path is not None:
        hdmap = read_geojson_file(map_path)
        return roam_scenario(hdmap, seed, users=users, duration=duration), hdmap
    chosen = get_scenario(scenario)
    return chosen, read_geojson_file(chosen.map)


def _draw_user(
    rng: np.random.Generator,
    graph: _Graph,
    i: int,
    kinds: Sequence[str],
    weights: np.ndarray,
    duration: float,
    rate: float,
) -> UserPlan:
    kind = kinds[int(rng.choice(len(kinds), p=weights))]
    lanes = graph.by_type[KINDS[kind]]
    lengths = np.array([lane.centerline.length for lane in lanes])
    lane = lanes[int(rng.choice(len(lanes), p=lengths / lengths.sum()))]
    ways = _ways(lane)
    way = ways[int(rng.integers(0, 2))] if len(ways) > 1 else ways[0]
    start = float(rng.uniform(0.0, 1.0)) * lane.centerline.length
    speed = float(rng.uniform(*_SPEEDS[kind]))
    enter = round(float(rng.uniform(0.0, duration / 2.0)), 3) if rng.random() < 0.3 else 0.0
    brake = _BRAKES[kind]
    stops: tuple[tuple[float, float], ...] = ()
    if rng.random() < 0.25:
        ramp = math.pi * speed / (2.0 * brake)
        held = float(rng.uniform(5.0, 20.0))
        lo, hi = enter + ramp + 1.0, duration - held - ramp - 1.0
        if hi > lo:
            stops = ((round(float(rng.uniform(lo, hi)), 3), round(held, 3)),)
    first: Step = (lane.segment, lane.index, way)
    plan = UserPlan(
        user=f"{kind}-{i}",
        kind=kind,
        speed=speed,
        start=0.0,
        path=(first,),
        enter=enter,
        stops=stops,
        brake=brake,
    )
    driven = distance_driven(plan, duration)
    steps, length = _path(rng, graph, first, start + driven + _MARGIN)
    margin = min(_MARGIN, length / 2.0)
    if length - margin - start < 2.0 * speed:  # too little left: start at the lane's start
        start = 0.0
    leave = None
    if start + driven > length - margin:
        leave = _leave(plan, length - margin - start, duration)
    phase = math.floor(float(rng.uniform(0.0, min(1.0, 1.0 / rate))) * 999.0) / 1000.0
    size, angle = float(rng.uniform(0.0, 1.0)), math.radians(float(rng.uniform(0.0, 360.0)))
    path: tuple[PathStep, ...] = tuple(steps)
    return UserPlan.model_validate(
        {
            **plan.model_dump(),
            "start": start,
            "path": path,
            "leave": leave,
            "phase": phase,
            "bias": (size * math.sin(angle), size * math.cos(angle)),
            "noise_scale": float(rng.uniform(0.7, 1.4)),
        }
    )
