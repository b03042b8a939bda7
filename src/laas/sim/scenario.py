"""Simulated road users with ground truth, for evaluation and the demo.

A scenario is a route (a chain of road elements) and a plan per user: a kind, a speed,
a start station on the route and the lanes it takes from which second on. Lane changes
are smooth: the lateral offset follows d(t) = o_a + (o_b - o_a) (1 - cos(pi u)) / 2 over
`change_time` seconds. The GNSS error model adds to the true position a common error
(the bias, the same for every receiver in the area, optionally drifting as a random
walk) and per-fix Gaussian noise on position, speed and heading (paper section V).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from laas.errors import ConfigError
from laas.map.bundled import bundled_map
from laas.map.hdmap import HdMap, Segment
from laas.models import GpsMeasurement

__all__ = [
    "SCENARIOS",
    "ErrorModel",
    "Scenario",
    "SimulatedFix",
    "Trace",
    "UserPlan",
    "get_scenario",
    "hamburg_scenario",
    "melbourne_scenario",
    "simulate",
    "simulate_with",
]


EPOCH_MS = 1_700_000_000_000  # 2023-11-14T22:13:20Z, the scenario's t = 0


class ErrorModel(BaseModel):
    """GNSS errors: a common bias (m east, m north) plus per-fix Gaussian noise."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    bias_east: float = -8.0
    bias_north: float = 8.0
    bias_drift: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0, description="random walk of the common bias, m/sqrt(s)"
    )
    sigma_pos: Annotated[float, Field(ge=0.0)] = 1.0
    sigma_vel: Annotated[float, Field(ge=0.0)] = 0.25
    sigma_heading: Annotated[float, Field(ge=0.0)] = Field(default=0.05, description="degrees")


class UserPlan(BaseModel):
    """One road user's drive: lanes[k] = (from second, lane index)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    user: str
    kind: str
    speed: Annotated[float, Field(gt=0.0)]
    start: Annotated[float, Field(ge=0.0)] = Field(description="start station on the route, m")
    lanes: tuple[tuple[float, int], ...]
    change_time: Annotated[float, Field(gt=0.0)] = 3.0
    phase: Annotated[float, Field(ge=0.0, lt=1.0)] = Field(
        default=0.0, description="offset of this receiver's fixes within the period, s"
    )
    reverse: bool = Field(default=False, description="drive the route backwards from `start`")


class Scenario(BaseModel):
    """Users on a route of a map, sampled at `rate` Hz for `duration` seconds."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    map: str = Field(description="path of the GeoJSON map")
    route: tuple[str, ...] = Field(description="segment ids, in driving order")
    users: tuple[UserPlan, ...]
    duration: Annotated[float, Field(gt=0.0)]
    rate: Annotated[float, Field(gt=0.0)] = 1.0
    errors: ErrorModel = Field(default_factory=ErrorModel, description="the GNSS error model")


@dataclass(frozen=True, slots=True)
class SimulatedFix:
    """One measurement and the truth behind it."""

    user: str
    kind: str
    measurement: GpsMeasurement
    true_e: float
    true_n: float
    true_heading: float  # degrees
    segment: str
    lane: int


@dataclass(frozen=True)
class Trace:
    """All fixes of a simulated run, in time order."""

    scenario: Scenario
    errors: ErrorModel
    seed: int
    fixes: tuple[SimulatedFix, ...]


class _Route:
    """Stations along a chain of segments."""

    def __init__(self, hdmap: HdMap, route: tuple[str, ...]) -> None:
        missing = [s for s in route if s not in hdmap.segments]
        if missing:
            raise ConfigError(f"route names segments the map does not have: {missing}")
        self.segments: list[Segment] = [hdmap.segments[s] for s in route]
        lengths = [s.length for s in self.segments]
        self.starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self.length = float(sum(lengths))

    def locate(self, station: float) -> tuple[Segment, float]:
        k = int(np.searchsorted(self.starts, station, side="right")) - 1
        k = min(max(k, 0), len(self.segments) - 1)
        return self.segments[k], station - float(self.starts[k])


def _lateral(plan: UserPlan, t: float, offsets: np.ndarray) -> tuple[float, int]:
    """(d, true lane) at time t: smooth changes between the planned lanes."""
    lanes = sorted(plan.lanes)
    current = lanes[0][1]
    for k, (since, lane) in enumerate(lanes):
        if t < since:
            break
        previous = lanes[k - 1][1] if k else lane
        u = (t - since) / plan.change_time
        if u < 1.0 and k:
            d = (
                offsets[previous]
                + (offsets[lane] - offsets[previous]) * (1.0 - math.cos(math.pi * u)) / 2.0
            )
            nearest = int(np.argmin(np.abs(offsets - d)))
            return float(d), nearest
        current = lane
    return float(offsets[current]), current


def _true_state(
    route: _Route, plan: UserPlan, t: float
) -> tuple[float, float, str, int, Segment, float]:
    station = plan.start + (-plan.speed if plan.reverse else plan.speed) * t
    if not 0.0 <= station <= route.length:
        raise ConfigError(
            f"user {plan.user!r} runs off the end of the route at t={t:.1f} s; "
            "shorten the scenario or slow the user down"
        )
    segment, s = route.locate(station)
    offsets = segment.lane_offsets(s)
    if max(lane for _, lane in plan.lanes) >= len(offsets):
        raise ConfigError(f"user {plan.user!r} plans a lane that segment {segment.id} lacks")
    d, lane = _lateral(plan, t, offsets)
    e, n = segment.point(s, d)
    return e, n, segment.id, lane, segment, s


def simulate(hdmap: HdMap, scenario: Scenario, errors: ErrorModel, seed: int) -> Trace:
    """Sample every user's fixes with errors drawn from `seed` (reproducible)."""
    rng = np.random.default_rng(seed)
    route = _Route(hdmap, scenario.route)
    x0, y0, _x1, _y1 = hdmap.bounds
    convergence = hdmap.projection.convergence(*hdmap.projection.to_wgs84(x0, y0))
    period = 1.0 / scenario.rate
    steps = round(scenario.duration * scenario.rate) + 1
    times = sorted({round(k * period + p.phase, 6) for k in range(steps) for p in scenario.users})
    bias = np.array([errors.bias_east, errors.bias_north], dtype=float)
    last_t = 0.0
    fixes: list[SimulatedFix] = []
    plans = sorted(scenario.users, key=lambda p: p.phase)
    for t in times:
        if errors.bias_drift > 0.0 and t > last_t:
            bias = bias + rng.normal(0.0, errors.bias_drift * math.sqrt(t - last_t), 2)
        last_t = t
        for plan in plans:
            local = t - plan.phase
            if abs(local / period - round(local / period)) > 1e-6 or local < -1e-9:
                continue
            if local > scenario.duration + 1e-9:
                continue
            e, n, seg_id, lane, _, _ = _true_state(route, plan, local)
            e2, n2, *_ = _true_state(route, plan, min(local + 0.1, scenario.duration))
            e0, n0, *_ = _true_state(route, plan, max(local - 0.1, 0.0))
            heading = math.degrees(math.atan2(e2 - e0, n2 - n0)) % 360.0
            speed = math.hypot(e2 - e0, n2 - n0) / (
                min(local + 0.1, scenario.duration) - max(local - 0.1, 0.0)
            )
            me = e + bias[0] + rng.normal(0.0, errors.sigma_pos)
            mn = n + bias[1] + rng.normal(0.0, errors.sigma_pos)
            lon, lat = hdmap.projection.to_wgs84(me, mn)
            measurement = GpsMeasurement(
                timestamp=EPOCH_MS + round(t * 1000.0),
                latitude=lat,
                longitude=lon,
                altitude=10.0,
                # the receiver reports a true bearing: grid bearing + convergence
                heading=(heading + convergence + rng.normal(0.0, errors.sigma_heading)) % 360.0,
                speed=max(0.0, speed + rng.normal(0.0, errors.sigma_vel)),
            )
            fixes.append(
                SimulatedFix(plan.user, plan.kind, measurement, e, n, heading, seg_id, lane)
            )
    return Trace(scenario=scenario, errors=errors, seed=seed, fixes=tuple(fixes))


def simulate_with(
    hdmap: HdMap, scenario: Scenario, seed: int, *, sigma_pos: float, sigma_vel: float
) -> Trace:
    """`simulate` with the scenario's own error model at these receiver sigmas."""
    errors = scenario.errors.model_copy(update={"sigma_pos": sigma_pos, "sigma_vel": sigma_vel})
    return simulate(hdmap, scenario, errors, seed)


def hamburg_scenario() -> Scenario:
    """The paper's section V scenario on `maps/messe-hamburg.geojson`.

    A car and two cyclists ride together for 100 s at 1 Hz (303 fixes). The car keeps
    lane 0 and changes to lane 1 near the end; cyclist 1 starts on the parking lane 2,
    takes lane 1 after 20 s and the bicycle lane 3 after another 40 s; cyclist 2 starts
    on lane 3, takes lane 1 after 60 s and lane 0 near the end.
    """
    return Scenario(
        name="messe-hamburg",
        map=str(bundled_map("messe-hamburg")),
        route=("messe-0", "messe-1", "messe-2", "messe-3", "messe-4"),
        duration=100.0,
        rate=1.0,
        users=(
            UserPlan(user="car", kind="car", speed=5.4, start=25.0, lanes=((0, 0), (88, 1))),
            UserPlan(
                user="cyclist-1",
                kind="bicycle",
                speed=5.0,
                start=40.0,
                lanes=((0, 2), (20, 1), (60, 3)),
                phase=0.2,
            ),
            UserPlan(
                user="cyclist-2",
                kind="bicycle",
                speed=4.9,
                start=50.0,
                lanes=((0, 3), (60, 1), (90, 0)),
                change_time=4.0,
                phase=0.4,
            ),
        ),
    )


def melbourne_scenario() -> Scenario:
    """A second, different scenario: a two-way street corner in Melbourne.

    Seven road users of three kinds on `maps/melbourne-corner.geojson` for 120 s at 1 Hz:
    two cars and a cyclist along the map's reference direction (the cyclist swings into
    the driving lane and back), a car and a cyclist against it, and a pedestrian on each
    sidewalk, one each way. The common error is (+4 m E, -7 m N) and drifts as a random
    walk of 0.05 m/sqrt(s).
    """
    return Scenario(
        name="melbourne-corner",
        map=str(bundled_map("melbourne-corner")),
        route=("corner-0", "corner-1", "corner-2", "corner-3", "corner-4"),
        duration=120.0,
        rate=1.0,
        errors=ErrorModel(bias_east=4.0, bias_north=-7.0, bias_drift=0.05),
        users=(
            UserPlan(user="car-1", kind="car", speed=3.8, start=10.0, lanes=((0, 3),)),
            UserPlan(
                user="car-2",
                kind="car",
                speed=3.6,
                start=500.0,
                lanes=((0, 2),),
                reverse=True,
                phase=0.1,
            ),
            UserPlan(user="car-3", kind="car", speed=3.5, start=40.0, lanes=((0, 3),), phase=0.2),
            UserPlan(
                user="bike-1",
                kind="bicycle",
                speed=3.6,
                start=28.0,
                lanes=((0, 4), (45, 3), (75, 4)),
                phase=0.3,
            ),
            UserPlan(
                user="bike-2",
                kind="bicycle",
                speed=3.4,
                start=480.0,
                lanes=((0, 1),),
                reverse=True,
                phase=0.5,
            ),
            UserPlan(
                user="walker-1",
                kind="pedestrian",
                speed=1.4,
                start=170.0,
                lanes=((0, 5),),
                phase=0.6,
            ),
            UserPlan(
                user="walker-2",
                kind="pedestrian",
                speed=1.3,
                start=330.0,
                lanes=((0, 0),),
                reverse=True,
                phase=0.8,
            ),
        ),
    )


SCENARIOS = {"messe-hamburg": hamburg_scenario, "melbourne-corner": melbourne_scenario}
"""The built-in scenarios by name."""


def get_scenario(name: str) -> Scenario:
    """A built-in scenario by name; the error lists the names there are."""
    try:
        return SCENARIOS[name]()
    except KeyError:
        raise ConfigError(
            f"unknown scenario {name!r}; choose one of {', '.join(sorted(SCENARIOS))}"
        ) from None
