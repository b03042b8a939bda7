"""A simulated scenario: its road users' plans, the GNSS error model, and its trace.

A scenario is a route (a chain of road elements) and a plan per user: a kind, a speed,
a start station on the route and the lanes it takes from which second on. Lane changes
are smooth: the lateral offset follows d(t) = o_a + (o_b - o_a) (1 - cos(pi u)) / 2 over
`change_time` seconds. The GNSS error model adds to the true position a common error
(the bias, the same for every receiver in the area, optionally drifting as a random
walk) and per-fix Gaussian noise on position, speed and heading (paper section V).

Optional features, all off by default (the built-in scenarios use none of them, and their
traces are what they always were):

- a user may enter late and leave early (`enter`, `leave`), stop for a while (`stops`:
  a cosine speed profile, peak deceleration `brake`), be parked (`speed` 0), drive at its
  own speed along its own lane, slowed for curves (`along_lane`, `_Motion`), send at its
  own rate (`rate`), and have a receiver of its own: a constant error (`bias`), a noise
  level (`noise_scale` times the model's sigma_pos) and a reported accuracy
  (`accuracy_scale`);
- the error model may add heading noise that grows as speed falls (`heading_per_speed`),
  heavy-tailed outliers (`outlier_rate`), multipath jumps (`multipath_rate`), and lost
  fixes, singly (`dropout_rate`) or in gaps (`gap_rate`);
- a user may lie (`lie`, a `Lie`): its receiver reports a false path, its own path moved
  across and along the road or onto another lane, at once or growing slowly. The lie is a
  plausible drive (inside the area, on or near the road, speed and heading those of the
  false path) and draws no random numbers, so a trace with a liar has the same noise as
  the same trace without one, and the two can be compared fix by fix.

These draw from a second random stream (seeded by (seed, 1)), so the first stream, and with
it every trace of a scenario that uses none of them, is unchanged.

A user may instead drive a path of its own (`UserPlan.path`), for maps whose lane layout
changes and whose roads branch: a chain of (segment, lane) pieces, each driven along the
lane's centre line in its direction of travel (a `backward` lane against the segment's
coordinate order; a `both` lane forward unless the step says "backward"). The centre lines
are joined into one polyline in the map's UTM projection, and `start` and the distance
driven (`distance_driven`: speed, stops, enter and leave as above) are metres along it, so
the true position is continuous across element boundaries and through junctions. Where a
lane ends a little apart from where the next one starts (a lane that merges, the corner of
a junction) a straight chord joins them; its first half belongs to the piece before, its
second half to the piece after. The true segment and lane of a fix are those of the piece
it is on. Consecutive pieces must connect: the one is a successor of the other and their
facing ends are at most `PATH_SUCCESSOR_GAP` metres apart, or their facing ends are at most
`PATH_JOIN_GAP` metres apart. A path fixes the user's lanes and its direction, so it cannot
be combined with `lanes`, `reverse`, `along_lane` or a `lie`. A path draws no random
numbers: a user without one (every user of the built-in scenarios and families) is
simulated exactly as before. `laas.sim.roam` draws such paths on any map.

`laas.sim.kinematics` moves the users, `laas.sim.simulate` samples their fixes, and
`laas.sim.builtin` holds the built-in scenarios; `laas.sim.scenario` names them all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, model_validator

from laas.errors import ConfigError
from laas.models import GpsMeasurement

__all__ = [
    "EPOCH_MS",
    "PATH_JOIN_GAP",
    "PATH_SUCCESSOR_GAP",
    "ErrorModel",
    "Fixes",
    "Lie",
    "PathStep",
    "Scenario",
    "SimulatedFix",
    "Trace",
    "UserPlan",
    "Way",
    "braking_time",
]


EPOCH_MS = 1_700_000_000_000  # 2023-11-14T22:13:20Z, the scenario's t = 0

PATH_JOIN_GAP = 3.0
"""m: path pieces whose facing ends are this close connect, successors or not."""
PATH_SUCCESSOR_GAP = 15.0
"""m: a successor's lane may start this far from where the previous lane ends."""

Way = Literal["forward", "backward"]
"""The way a path piece is driven: along its segment's coordinate order, or against it."""
PathStep = tuple[str, int] | tuple[str, int, Way]
"""One piece of a path: (segment id, lane index), or with the way it is driven."""


class ErrorModel(BaseModel):
    """GNSS errors: a common bias (m east, m north) plus per-fix noise, and the optional
    receiver effects of the module docstring (each off at its default)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    bias_east: float = -8.0
    bias_north: float = 8.0
    bias_drift: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0, description="random walk of the common bias, m/sqrt(s)"
    )
    sigma_pos: Annotated[float, Field(ge=0.0)] = 1.0
    sigma_vel: Annotated[float, Field(ge=0.0)] = 0.25
    sigma_heading: Annotated[float, Field(ge=0.0)] = Field(default=0.05, description="degrees")
    heading_per_speed: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0,
        description=(
            "heading noise that grows as speed v falls, degrees * m/s: "
            "sigma_h = sigma_heading + k / max(v, 0.1), at most 180 degrees"
        ),
    )
    outlier_rate: Annotated[float, Field(ge=0.0, le=1.0)] = Field(
        default=0.0, description="share of fixes whose noise is outlier_scale * Student-t"
    )
    outlier_scale: Annotated[float, Field(ge=0.0)] = Field(
        default=10.0, description="scale of the outliers' Student-t per axis, m"
    )
    outlier_dof: Annotated[float, Field(gt=0.0)] = Field(
        default=3.0, description="degrees of freedom of the outliers' Student-t"
    )
    multipath_rate: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0, description="multipath jumps per second per receiver (Poisson)"
    )
    multipath_offset: Annotated[float, Field(ge=0.0)] = Field(
        default=4.0, description="size of a jump: U(0.5, 1) times this, any direction, m"
    )
    multipath_duration: Annotated[float, Field(gt=0.0)] = Field(
        default=4.0, description="length of a jump: U(0.5, 1.5) times this, s"
    )
    dropout_rate: Annotated[float, Field(ge=0.0, lt=1.0)] = Field(
        default=0.0, description="share of fixes lost one by one"
    )
    gap_rate: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0, description="gaps (runs of lost fixes) per second per receiver (Poisson)"
    )
    gap_duration: Annotated[float, Field(gt=0.0)] = Field(
        default=4.0, description="length of a gap: U(0.5, 1.5) times this, s"
    )
    accuracy_jitter: Annotated[float, Field(ge=0.0)] = Field(
        default=0.25, description="log-normal spread of a reported accuracy about its level"
    )


class Lie(BaseModel):
    """A participant that lies: what its receiver reports is a false path.

    The false path is the user's own path with its station moved `along` metres ahead and
    its lateral offset moved `across` metres to the right of its direction of travel, plus
    the lateral step to the lane `lanes` lanes to its right (negative: left; clipped to the
    road) at every moment, following the user's own lane changes. From `start` on (the
    user's own clock) the lie is f(t) times that displacement, f growing linearly from 0
    to 1 over `ramp` seconds (0: at once), so a slowly growing drift is a long ramp. Speed
    and heading are those of the false path, and the common error, noise and receiver
    effects are added to it as to an honest fix.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    across: float = Field(default=0.0, description="m to the right of the direction of travel")
    along: float = Field(default=0.0, description="m ahead along the direction of travel")
    lanes: int = Field(default=0, description="lanes to the right of the true lane (< 0: left)")
    start: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0, description="when the lie begins, s of the user's own clock"
    )
    ramp: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0, description="seconds over which the lie grows to its full size (0: at once)"
    )

    def factor(self, t: float) -> float:
        """f(t): the share of the lie at time t, 0 before `start`, 1 after `ramp`."""
        if t < self.start:
            return 0.0
        if self.ramp <= 0.0:
            return 1.0
        return min(1.0, (t - self.start) / self.ramp)


class UserPlan(BaseModel):
    """One road user's drive: lanes[k] = (from second, lane index) on the scenario's route,
    or its own `path` of (segment, lane) pieces (see the module docstring).

    Times (lanes, enter, leave, stops) are the user's own clock, t - phase.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    user: str
    kind: str
    speed: Annotated[float, Field(ge=0.0)] = Field(description="cruising speed, m/s; 0: parked")
    start: Annotated[float, Field(ge=0.0)] = Field(
        description="station on the route at `enter` (with a `path`: metres along it), m"
    )
    lanes: tuple[tuple[float, int], ...] = Field(
        default=(), description="(from second, lane index) on the route; none with a `path`"
    )
    change_time: Annotated[float, Field(gt=0.0)] = 3.0
    phase: Annotated[float, Field(ge=0.0, lt=1.0)] = Field(
        default=0.0, description="offset of this receiver's fixes within the period, s"
    )
    reverse: bool = Field(default=False, description="drive the route backwards from `start`")
    along_lane: bool = Field(
        default=False,
        description=(
            "`speed` is along the user's own path, slowed for curves (see `_Motion`); "
            "else it is the rate of the route's station, lane 0's length"
        ),
    )
    enter: Annotated[float, Field(ge=0.0)] = Field(
        default=0.0, description="when the user appears (its first fix), s"
    )
    leave: Annotated[float, Field(gt=0.0)] | None = Field(
        default=None, description="when the user sends its last fix, s (None: the end)"
    )
    stops: tuple[tuple[float, float], ...] = Field(
        default=(),
        description="(when the speed reaches 0, for how long it stays 0) per stop, s",
    )
    brake: Annotated[float, Field(gt=0.0)] = Field(
        default=1.5,
        description=(
            "peak deceleration and acceleration around a stop, m/s^2: the speed follows "
            "a half cosine over pi v / (2 brake) seconds"
        ),
    )
    rate: Annotated[float, Field(gt=0.0, le=50.0)] | None = Field(
        default=None, description="this receiver's fix rate, Hz (None: the scenario's)"
    )
    bias: tuple[float, float] = Field(
        default=(0.0, 0.0), description="this receiver's own constant error, (m E, m N)"
    )
    noise_scale: Annotated[float, Field(gt=0.0)] = Field(
        default=1.0, description="this receiver's position noise in units of sigma_pos"
    )
    accuracy_scale: Annotated[float, Field(gt=0.0)] | None = Field(
        default=None,
        description=(
            "the receiver reports accuracy = scale * sqrt(2) * its sigma per axis * "
            "log-normal jitter, rounded to 0.1 m: the horizontal radius, as GpsMeasurement "
            "defines it (None: it reports none)"
        ),
    )
    course_from_road: bool = Field(
        default=False,
        description=(
            "the receiver reports the road's direction as its course (a smoothed or "
            "map-matched course, a phone's fused bearing), so a lane change does not show "
            "in it; else the course of its true motion"
        ),
    )
    lie: Lie | None = Field(
        default=None, description="this participant reports a false path (None: it does not)"
    )
    path: tuple[PathStep, ...] | None = Field(
        default=None,
        description=(
            "(segment, lane[, way]) pieces driven in order along their centre lines, instead "
            "of the route (None: the route and `lanes`)"
        ),
    )

    @model_validator(mode="after")
    def _check_path(self) -> UserPlan:
        if self.path is None:
            if not self.lanes:
                raise ConfigError(f"user {self.user!r} needs `lanes` on the route, or a `path`")
            return self
        if not self.path:
            raise ConfigError(f"user {self.user!r}: its path is empty")
        clash = [
            name
            for name, used in (
                ("lanes", bool(self.lanes)),
                ("reverse", self.reverse),
                ("along_lane", self.along_lane),
                ("lie", self.lie is not None),
            )
            if used
        ]
        if clash:
            raise ConfigError(
                f"user {self.user!r} drives a path, so it cannot have {', '.join(clash)}: "
                "the path gives its lanes and its way (a step's third element), and a path "
                "user drives its lanes' centre lines with no along_lane and no lie"
            )
        return self

    @model_validator(mode="after")
    def _check_times(self) -> UserPlan:
        period = 1.0 / self.rate if self.rate is not None else None
        if period is not None and self.phase >= period:
            raise ValueError(f"phase {self.phase} must be below the period {period:g} s")
        if self.leave is not None and self.leave <= self.enter:
            raise ValueError(f"leave ({self.leave}) must come after enter ({self.enter})")
        ramp = braking_time(self)
        last = self.enter
        for at, stopped in self.stops:
            if stopped < 0.0 or at - ramp < last - 1e-9:
                raise ValueError(
                    f"stop at {at} s: stops must not overlap, start after `enter` and last >= 0 s"
                )
            last = at + stopped + ramp
        return self


class Scenario(BaseModel):
    """Users on a route of a map (or on paths of their own), sampled at `rate` Hz for
    `duration` seconds."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    map: str = Field(
        description="path of the GeoJSON map (generated maps: a name, see laas.sim.family)"
    )
    route: tuple[str, ...] = Field(
        description="segment ids, in driving order (may be empty when every user has a path)"
    )
    users: tuple[UserPlan, ...]
    duration: Annotated[float, Field(gt=0.0)]
    rate: Annotated[float, Field(gt=0.0)] = 1.0
    errors: ErrorModel = Field(default_factory=ErrorModel, description="the GNSS error model")

    @model_validator(mode="after")
    def _check_route(self) -> Scenario:
        if not self.route:
            routed = [p.user for p in self.users if p.path is None]
            if routed:
                raise ConfigError(
                    f"scenario {self.name!r} has no route for users without a path: {routed}"
                )
        return self


@dataclass(frozen=True, slots=True)
class SimulatedFix:
    """One measurement and the truth behind it, with the true errors an oracle may use."""

    user: str
    kind: str
    measurement: GpsMeasurement
    true_e: float
    true_n: float
    true_heading: float  # degrees
    segment: str
    lane: int
    common_e: float = 0.0  # the common error at this fix, m east
    common_n: float = 0.0  # and m north
    receiver_e: float = 0.0  # the receiver's own constant error, m east
    receiver_n: float = 0.0  # and m north
    lie: bool = False  # the measurement reports a false path (`UserPlan.lie`)


class Fixes(Protocol):
    """What answering and scoring a run read of it: its fixes, each with its truth."""

    @property
    def fixes(self) -> Sequence[SimulatedFix]: ...


@dataclass(frozen=True)
class Trace:
    """All fixes of a simulated run, in time order."""

    scenario: Scenario
    errors: ErrorModel
    seed: int
    fixes: tuple[SimulatedFix, ...]


def braking_time(plan: UserPlan) -> float:
    """Seconds to brake from (or speed up to) the cruising speed: T = pi v / (2 brake)."""
    return math.pi * plan.speed / (2.0 * plan.brake)
