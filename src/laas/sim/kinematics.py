"""How simulated road users move: along a route of road elements or a path of lanes,
with smooth lane changes, stops, and speeds of their own in curves (`along_lane`); and
where a lying user says it is (`Lie`). The plans are `laas.sim.plan`'s.
"""

from __future__ import annotations

import bisect
import itertools
import math
from dataclasses import dataclass

import numpy as np

from laas.errors import ConfigError
from laas.map.hdmap import HdMap, Segment
from laas.sim.plan import PATH_JOIN_GAP, PATH_SUCCESSOR_GAP, Lie, PathStep, UserPlan, braking_time

__all__ = [
    "CURVE_ACCEL",
    "LATERAL_ACCEL",
    "LanePath",
    "Motion",
    "Route",
    "distance_driven",
    "false_position",
    "true_state",
]


class Route:
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


class LanePath:
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


def _cruising_time(plan: UserPlan, t: float) -> float:
    """Seconds at cruising speed that the distance driven from `enter` to t is worth.

    Around a stop reached at a and held for h seconds the speed is v (1 + cos(pi y / T)) / 2
    for y = t - (a - T) in [0, T], then 0, then v (1 - cos(pi y / T)) / 2 over the T seconds
    after a + h; each stop costs T + h seconds once passed.
    """
    tau = t - plan.enter
    ramp = braking_time(plan)
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


class Motion:
    """Each lane's geometry along a route, for users who drive at their own speed.

    On a 1 m grid of route stations s, per lane k: the stretch g_k(s) = dl_k/ds (metres of
    lane k per metre of station) and a speed limit from its curvature kappa_k,
    v_k(s) = sqrt(LATERAL_ACCEL / kappa_k(s)), lowered so that the speed never has to
    change faster than CURVE_ACCEL: v_k(s) <= sqrt(v_k(s')^2 + 2 CURVE_ACCEL |s - s'|).
    """

    def __init__(self, route: Route) -> None:
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

    def stations(self, route: Route, plan: UserPlan, end: float) -> tuple[np.ndarray, np.ndarray]:
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


def true_state(
    route: Route, plan: UserPlan, t: float, table: tuple[np.ndarray, np.ndarray] | None = None
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


def false_position(
    route: Route,
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
