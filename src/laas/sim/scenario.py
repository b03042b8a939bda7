"""Simulated road users with ground truth, for evaluation and the demo.

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
"""

from __future__ import annotations

import bisect
import itertools
import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from laas.errors import ConfigError
from laas.map.bundled import bundled_map
from laas.map.hdmap import HdMap, Segment
from laas.models import GpsMeasurement

__all__ = [
    "PATH_JOIN_GAP",
    "PATH_SUCCESSOR_GAP",
    "SCENARIOS",
    "ErrorModel",
    "Lie",
    "PathStep",
    "Scenario",
    "SimulatedFix",
    "Trace",
    "UserPlan",
    "Way",
    "distance_driven",
    "get_scenario",
    "hamburg_scenario",
    "melbourne_scenario",
    "simulate",
    "simulate_with",
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
        ramp = _ramp(self)
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


@dataclass(frozen=True)
class _Piece:
    """One piece of a path: a lane's centre line in its direction of travel."""

    segment: Segment
    lane: int
    backward: bool
    xy: np.ndarray  # (n, 2) UTM, in the direction of travel


def _piece(hdmap: HdMap, plan: UserPlan, k: int, step: PathStep) -> _Piece:
    """Path step k of a user, checked against the map."""
    seg_id, lane = step[0], step[1]
    way = step[2] if len(step) == 3 else None
    segment = hdmap.segments.get(seg_id)
    if segment is None:
        raise ConfigError(
            f"user {plan.user!r}: path step {k} names segment {seg_id!r}, which the map lacks"
        )
    if not 0 <= lane < len(segment.lanes):
        raise ConfigError(
            f"user {plan.user!r}: path step {k} names lane {lane} of segment {seg_id!r}, "
            f"which has {len(segment.lanes)} lanes"
        )
    direction = segment.lanes[lane].direction
    if way is None:
        backward = direction == "backward"
    elif direction in ("both", way):
        backward = way == "backward"
    else:
        raise ConfigError(
            f"user {plan.user!r}: path step {k} drives lane {lane} of segment {seg_id!r} "
            f"{way}, but the lane runs {direction}"
        )
    xy = np.asarray(segment.lanes[lane].centerline.coords, dtype=np.float64)[:, :2]
    return _Piece(segment, lane, backward, xy[::-1] if backward else xy)


def _describe(piece: _Piece) -> str:
    way = "backward" if piece.backward else "forward"
    return f"({piece.segment.id!r}, lane {piece.lane}, {way})"


class _Path:
    """A user's path (`UserPlan.path`) as one polyline: its pieces' centre lines in order,
    joined by straight chords where a piece does not start where the one before ends."""

    def __init__(self, hdmap: HdMap, plan: UserPlan) -> None:
        assert plan.path is not None
        self.user = plan.user
        self.pieces = [_piece(hdmap, plan, k, step) for k, step in enumerate(plan.path)]
        parts: list[np.ndarray] = [self.pieces[0].xy]
        count = len(self.pieces[0].xy)
        ends = [(0, count - 1)]  # (first, last) vertex index of each piece
        for k, (a, b) in enumerate(itertools.pairwise(self.pieces)):
            gap = float(np.hypot(*(b.xy[0] - a.xy[-1])))
            linked = b.segment.id in a.segment.successors or a.segment.id in b.segment.successors
            if gap > PATH_JOIN_GAP and not (linked and gap <= PATH_SUCCESSOR_GAP):
                raise ConfigError(
                    f"user {plan.user!r}: path step {k + 1} {_describe(b)} does not connect "
                    f"to step {k} {_describe(a)}: it starts {gap:.1f} m from where that ends "
                    f"(at most {PATH_JOIN_GAP:g} m, or {PATH_SUCCESSOR_GAP:g} m from a "
                    "successor or predecessor)"
                )
            xy = b.xy[1:] if gap < 1e-6 else b.xy
            parts.append(xy)
            ends.append((count - (1 if gap < 1e-6 else 0), count + len(xy) - 1))
            count += len(xy)
        xy = np.concatenate(parts)
        dist = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        # piece k owns the path from the middle of the chord before it to that after it
        self.owner_from = [0.0] + [
            float(dist[a[1]] + dist[b[0]]) / 2.0 for a, b in itertools.pairwise(ends)
        ]
        keep = np.concatenate([[True], np.diff(dist) > 1e-9])  # no zero-length edges
        self.xy = xy[keep]
        self.dist = dist[keep]
        self.length = float(self.dist[-1])

    def state(self, x: float, t: float) -> tuple[float, float, str, int]:
        """(e, n, segment id, lane) of the point x metres along the path (at time t)."""
        if not -1e-6 <= x <= self.length + 1e-6:
            raise ConfigError(
                f"user {self.user!r} runs off the end of its path ({self.length:.1f} m) at "
                f"t={t:.1f} s; shorten the scenario, slow the user down or let it leave"
            )
        e = float(np.interp(x, self.dist, self.xy[:, 0]))
        n = float(np.interp(x, self.dist, self.xy[:, 1]))
        piece = self.pieces[bisect.bisect_right(self.owner_from, x) - 1]
        return e, n, piece.segment.id, piece.lane

    def heading(self, x: float) -> float:
        """Grid bearing of the path at x metres along it, degrees."""
        i = int(np.searchsorted(self.dist, x, side="right")) - 1
        i = min(max(i, 0), len(self.dist) - 2)
        de, dn = self.xy[i + 1] - self.xy[i]
        return math.degrees(math.atan2(de, dn)) % 360.0


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


def _ramp(plan: UserPlan) -> float:
    """Seconds to brake from (or speed up to) the cruising speed: T = pi v / (2 brake)."""
    return math.pi * plan.speed / (2.0 * plan.brake)


def _cruising_time(plan: UserPlan, t: float) -> float:
    """Seconds at cruising speed that the distance driven from `enter` to t is worth.

    Around a stop reached at a and held for h seconds the speed is v (1 + cos(pi y / T)) / 2
    for y = t - (a - T) in [0, T], then 0, then v (1 - cos(pi y / T)) / 2 over the T seconds
    after a + h; each stop costs T + h seconds once passed.
    """
    tau = t - plan.enter
    ramp = _ramp(plan)
    if not plan.stops or ramp <= 0.0:
        return tau
    lost = 0.0
    for at, held in plan.stops:
        x = t - (at - ramp)
        if x <= 0.0:
            break
        if x <= ramp:
            lost += (x - ramp / math.pi * math.sin(math.pi * x / ramp)) / 2.0
        elif x <= ramp + held:
            lost += ramp / 2.0 + (x - ramp)
        elif x <= 2.0 * ramp + held:
            y = x - ramp - held
            lost += ramp / 2.0 + held + (y + ramp / math.pi * math.sin(math.pi * y / ramp)) / 2.0
        else:
            lost += ramp + held
    return tau - lost


def distance_driven(plan: UserPlan, t: float) -> float:
    """Metres the user has driven from `enter` to its time t (stops and ramps included)."""
    return plan.speed * _cruising_time(plan, t)


LATERAL_ACCEL = 2.5  # m/s^2: most lateral acceleration of an `along_lane` user in a curve
CURVE_ACCEL = 1.5  # m/s^2: how fast it slows down for a curve and speeds up after it
_STEP = 0.1  # s, time step of an `along_lane` user's stations


class _Motion:
    """Each lane's geometry along a route, for users who drive at their own speed.

    On a 1 m grid of route stations s, per lane k: the stretch g_k(s) = dl_k/ds (metres of
    lane k per metre of station) and a speed limit from its curvature kappa_k,
    v_k(s) = sqrt(LATERAL_ACCEL / kappa_k(s)), lowered so that the speed never has to
    change faster than CURVE_ACCEL: v_k(s) <= sqrt(v_k(s')^2 + 2 CURVE_ACCEL |s - s'|).
    """

    def __init__(self, route: _Route) -> None:
        counts = {len(seg.lanes) for seg in route.segments}
        if len(counts) != 1:
            raise ConfigError("users who drive `along_lane` need a route of one lane count")
        lanes = counts.pop()
        self.grid = np.arange(0.0, route.length + 1.0, 1.0)
        self.g = np.ones((lanes, len(self.grid)))
        self.vmax = np.full((lanes, len(self.grid)), 100.0)
        for k in range(lanes):
            s_all, l_all, kappa_all = [], [], []
            length = 0.0
            for seg, s0 in zip(route.segments, route.starts, strict=True):
                xy = np.asarray(seg.lanes[k].centerline.coords, dtype=np.float64)[:, :2]
                chords = np.hypot(*np.diff(xy, axis=0).T)
                angles = np.arctan2(*np.diff(xy, axis=0).T[::-1])
                turn = np.abs((np.diff(angles) + math.pi) % (2.0 * math.pi) - math.pi)
                kappa = np.zeros(len(xy))
                kappa[1:-1] = turn / np.maximum((chords[:-1] + chords[1:]) / 2.0, 1e-6)
                s_all.append(seg.frame_array(xy)[:, 0] + s0)
                l_all.append(length + np.concatenate([[0.0], np.cumsum(chords)]))
                kappa_all.append(kappa)
                length += float(chords.sum())
            s, lk, kappa = (np.concatenate(a) for a in (s_all, l_all, kappa_all))
            order = np.argsort(s, kind="stable")
            on_grid = np.interp(self.grid, s[order], lk[order])
            self.g[k] = np.maximum(np.gradient(on_grid, self.grid), 0.05)
            curv = np.interp(self.grid, s[order], kappa[order])
            v = np.sqrt(LATERAL_ACCEL / np.maximum(curv, LATERAL_ACCEL / 100.0**2))
            for i in range(len(v) - 2, -1, -1):
                v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * CURVE_ACCEL))
            for i in range(1, len(v)):
                v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2.0 * CURVE_ACCEL))
            self.vmax[k] = v

    def at(self, station: float, d: float, offsets: np.ndarray) -> tuple[float, float]:
        """(stretch, speed limit) at a station for lateral offset d, between two lanes
        by linear blend of the stretch and the lower of the limits."""
        i = min(max(round(station), 0), len(self.grid) - 1)
        b = min(max(bisect.bisect_left(offsets.tolist(), d), 1), len(offsets) - 1)
        a = max(b - 1, 0)
        span = float(offsets[b] - offsets[a])
        w = min(max((d - float(offsets[a])) / span, 0.0), 1.0) if span > 0.0 else 0.0
        g = (1.0 - w) * self.g[a, i] + w * self.g[b, i]
        vmax = (
            self.vmax[a, i]
            if w <= 0.0
            else self.vmax[b, i]
            if w >= 1.0
            else min(self.vmax[a, i], self.vmax[b, i])
        )
        return float(g), float(vmax)

    def stations(self, route: _Route, plan: UserPlan, end: float) -> tuple[np.ndarray, np.ndarray]:
        """(times, stations) of an `along_lane` user every _STEP s from `enter` past `end`:
        ds = +-min(dD / dt, v_max) dt / g, D the planned distance (`distance_driven`).
        The blend between lanes takes each segment's lane offsets at its middle."""
        times = np.arange(plan.enter, end + 2.0 * _STEP, _STEP)
        planned = np.diff([distance_driven(plan, float(t)) for t in times], append=0.0)
        stations = np.empty_like(times)
        middles: dict[str, np.ndarray] = {}
        s = plan.start
        sign = -1.0 if plan.reverse else 1.0
        for j, t in enumerate(times):
            stations[j] = s
            if planned[j] <= 0.0:
                continue
            segment, _ = route.locate(s)
            offsets = middles.get(segment.id)
            if offsets is None:
                offsets = middles[segment.id] = segment.lane_offsets(segment.length / 2.0)
            d, _ = _lateral(plan, float(t) + _STEP / 2.0, offsets)
            g, vmax = self.at(s, d, offsets)
            s += sign * min(float(planned[j]), vmax * _STEP) / g
        return times, stations


def _station(plan: UserPlan, t: float, table: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """The user's station on the route at its time t."""
    if table is not None:
        return float(np.interp(t, table[0], table[1]))
    return plan.start + (-plan.speed if plan.reverse else plan.speed) * _cruising_time(plan, t)


def _true_state(
    route: _Route, plan: UserPlan, t: float, table: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[float, float, str, int, Segment, float]:
    station = _station(plan, t, table)
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


def _false_position(
    route: _Route,
    plan: UserPlan,
    lie: Lie,
    t: float,
    table: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[float, float]:
    """Where a lying user says it is at its time t (see `Lie`): station s + f sign along,
    lateral offset d + f ((d_k - d) + sign across), with sign -1 for a user driving against
    the reference and d_k its offset had it driven `lanes` lanes to its right."""
    f = lie.factor(t)
    sign = -1.0 if plan.reverse else 1.0
    station = _station(plan, t, table)
    station = min(max(station + f * sign * lie.along, 0.0), route.length)
    segment, s = route.locate(station)
    offsets = segment.lane_offsets(s)
    d, _ = _lateral(plan, t, offsets)
    shift = d
    if lie.lanes:
        step = lie.lanes if not plan.reverse else -lie.lanes
        last = len(offsets) - 1
        moved = tuple((since, min(max(k + step, 0), last)) for since, k in plan.lanes)
        shift, _ = _lateral(plan.model_copy(update={"lanes": moved}), t, offsets)
    e, n = segment.point(s, d + f * ((shift - d) + sign * lie.across))
    return e, n


def _events(
    rng: np.random.Generator, rate: float, mean: float, start: float, end: float
) -> list[tuple[float, float]]:
    """(from, to) of a Poisson process of events of length U(0.5, 1.5) * mean."""
    out: list[tuple[float, float]] = []
    t = start
    while rate > 0.0:
        t += float(rng.exponential(1.0 / rate))
        if t > end:
            break
        out.append((t, t + float(rng.uniform(0.5, 1.5)) * mean))
    return out


@dataclass(frozen=True)
class _Receiver:
    """A user's receiver events, drawn once from the second stream."""

    multipath: list[tuple[float, float, float, float]]  # (from, to, m east, m north)
    gaps: list[tuple[float, float]]

    @classmethod
    def draw(
        cls, rng: np.random.Generator, errors: ErrorModel, start: float, end: float
    ) -> _Receiver:
        jumps = []
        for a, b in _events(rng, errors.multipath_rate, errors.multipath_duration, start, end):
            size = float(rng.uniform(0.5, 1.0)) * errors.multipath_offset
            angle = float(rng.uniform(0.0, 2.0 * math.pi))
            jumps.append((a, b, size * math.sin(angle), size * math.cos(angle)))
        gaps = _events(rng, errors.gap_rate, errors.gap_duration, start, end)
        return cls(jumps, gaps)

    def offset(self, t: float) -> tuple[float, float]:
        for a, b, de, dn in self.multipath:
            if a <= t < b:
                return de, dn
        return 0.0, 0.0

    def in_gap(self, t: float) -> bool:
        return any(a <= t < b for a, b in self.gaps)


def _own_times(scenario: Scenario) -> dict[str, dict[float, float]]:
    """Users with a rate of their own: {user: {scenario time: own time}} of their fixes."""
    out: dict[str, dict[float, float]] = {}
    for p in scenario.users:
        if p.rate is not None:
            steps = math.floor(scenario.duration * p.rate + 1e-9) + 1
            out[p.user] = {round(k / p.rate + p.phase, 6): k / p.rate for k in range(steps)}
    return out


def simulate(hdmap: HdMap, scenario: Scenario, errors: ErrorModel, seed: int) -> Trace:
    """Sample every user's fixes with errors drawn from `seed` (reproducible)."""
    rng = np.random.default_rng(seed)
    extra = np.random.default_rng([seed, 1])  # the optional features' own stream
    route = _Route(hdmap, scenario.route)
    x0, y0, _x1, _y1 = hdmap.bounds
    convergence = hdmap.projection.convergence(*hdmap.projection.to_wgs84(x0, y0))
    period = 1.0 / scenario.rate
    steps = round(scenario.duration * scenario.rate) + 1
    own = _own_times(scenario)
    times = sorted(
        {
            round(k * period + p.phase, 6)
            for k in range(steps)
            for p in scenario.users
            if p.rate is None
        }.union(*(set(d) for d in own.values()))
    )
    receivers = {
        p.user: _Receiver.draw(
            extra, errors, p.enter, scenario.duration if p.leave is None else p.leave
        )
        for p in scenario.users
    }
    paths = {p.user: _Path(hdmap, p) for p in scenario.users if p.path is not None}
    motion = _Motion(route) if any(p.along_lane for p in scenario.users) else None
    tables = {
        p.user: motion.stations(route, p, scenario.duration if p.leave is None else p.leave)
        for p in scenario.users
        if motion is not None and p.along_lane
    }
    bias = np.array([errors.bias_east, errors.bias_north], dtype=float)
    last_t = 0.0
    fixes: list[SimulatedFix] = []
    plans = sorted(scenario.users, key=lambda p: p.phase)
    shared = [p for p in plans if p.rate is None]  # at the scenario's rate: tested at each t
    due: dict[float, list[UserPlan]] = {}  # at rates of their own: listed by time
    for p in plans:
        for t in own.get(p.user, ()):
            due.setdefault(t, []).append(p)
    for t in times:
        if errors.bias_drift > 0.0 and t > last_t:
            bias = bias + rng.normal(0.0, errors.bias_drift * math.sqrt(t - last_t), 2)
        last_t = t
        mine = due.get(t)
        for plan in shared if mine is None else sorted([*shared, *mine], key=lambda p: p.phase):
            end = scenario.duration if plan.leave is None else plan.leave
            if plan.rate is None:
                local = t - plan.phase
                if abs(local / period - round(local / period)) > 1e-6 or local < -1e-9:
                    continue
            else:
                local = own[plan.user][t]
            if local > end + 1e-9 or local < plan.enter - 1e-9:
                continue
            receiver = receivers[plan.user]
            if errors.dropout_rate > 0.0 and extra.random() < errors.dropout_rate:
                continue
            if receiver.in_gap(local):
                continue
            table = tables.get(plan.user)
            path = paths.get(plan.user)
            hi, lo = min(local + 0.1, end), max(local - 0.1, plan.enter)
            if path is None:
                e, n, seg_id, lane, segment, s = _true_state(route, plan, local, table)
                e2, n2, *_ = _true_state(route, plan, hi, table)
                e0, n0, *_ = _true_state(route, plan, lo, table)
                facing = (segment.heading(s) + (180.0 if plan.reverse else 0.0)) % 360.0
            else:
                x = plan.start + distance_driven(plan, local)
                e, n, seg_id, lane = path.state(x, local)
                e2, n2, *_ = path.state(plan.start + distance_driven(plan, hi), hi)
                e0, n0, *_ = path.state(plan.start + distance_driven(plan, lo), lo)
                facing = path.heading(x)
            if math.hypot(e2 - e0, n2 - n0) > 1e-9:
                heading = math.degrees(math.atan2(e2 - e0, n2 - n0)) % 360.0
            else:  # standing still: the way it faces
                heading = facing
            speed = math.hypot(e2 - e0, n2 - n0) / (hi - lo)
            # what the receiver reports: the true path, or a liar's false one with the
            # false path's own heading and speed
            rep_e, rep_n, rep_heading, rep_speed = e, n, heading, speed
            lying = plan.lie is not None and plan.lie.factor(local) > 0.0
            if plan.lie is not None and lying:
                rep_e, rep_n = _false_position(route, plan, plan.lie, local, table)
                f2 = _false_position(route, plan, plan.lie, hi, table)
                f0 = _false_position(route, plan, plan.lie, lo, table)
                if math.hypot(f2[0] - f0[0], f2[1] - f0[1]) > 1e-9:
                    rep_heading = math.degrees(math.atan2(f2[0] - f0[0], f2[1] - f0[1])) % 360.0
                rep_speed = math.hypot(f2[0] - f0[0], f2[1] - f0[1]) / (hi - lo)
            sigma = errors.sigma_pos * plan.noise_scale
            me = rep_e + bias[0] + rng.normal(0.0, sigma)
            mn = rep_n + bias[1] + rng.normal(0.0, sigma)
            if errors.outlier_rate > 0.0 and extra.random() < errors.outlier_rate:
                me = (
                    rep_e
                    + bias[0]
                    + errors.outlier_scale * float(extra.standard_t(errors.outlier_dof))
                )
                mn = (
                    rep_n
                    + bias[1]
                    + errors.outlier_scale * float(extra.standard_t(errors.outlier_dof))
                )
            jump = receiver.offset(local)
            me += plan.bias[0] + jump[0]
            mn += plan.bias[1] + jump[1]
            sigma_h = errors.sigma_heading
            if errors.heading_per_speed > 0.0:
                sigma_h = min(180.0, sigma_h + errors.heading_per_speed / max(rep_speed, 0.1))
            accuracy = None
            if plan.accuracy_scale is not None:
                level = plan.accuracy_scale * math.sqrt(2.0) * sigma
                jitter = math.exp(float(extra.normal(0.0, errors.accuracy_jitter)))
                accuracy = max(0.1, round(level * jitter, 1))
            lon, lat = hdmap.projection.to_wgs84(me, mn)
            reported = (rep_heading + convergence + rng.normal(0.0, sigma_h)) % 360.0
            measurement = GpsMeasurement(
                timestamp=EPOCH_MS + round(t * 1000.0),
                latitude=lat,
                longitude=lon,
                altitude=10.0,
                # the receiver reports a true bearing: grid bearing + convergence
                heading=reported if reported < 360.0 else 0.0,
                speed=max(0.0, rep_speed + rng.normal(0.0, errors.sigma_vel)),
                accuracy=accuracy,
            )
            fixes.append(
                SimulatedFix(
                    plan.user,
                    plan.kind,
                    measurement,
                    e,
                    n,
                    heading,
                    seg_id,
                    lane,
                    float(bias[0]),
                    float(bias[1]),
                    plan.bias[0],
                    plan.bias[1],
                    lying,
                )
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
