"""A scenario run: every user's fixes, sampled with errors from a seed (paper section V).

The true position comes from `laas.sim.kinematics`; the error model (`ErrorModel`) adds
the common error, the receiver's own noise and the optional features' events, drawn
from a second random stream (seeded by (seed, 1)) so that the first stream, and with it
every trace of a scenario that uses none of them, is unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from laas.sim.kinematics import LanePath, Motion, Route, distance_driven, false_position, true_state
from laas.sim.plan import EPOCH_MS, ErrorModel, Scenario, SimulatedFix, Trace, UserPlan

__all__ = ["simulate", "simulate_with"]


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
    route = Route(hdmap, scenario.route)
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
    paths = {p.user: LanePath(hdmap, p) for p in scenario.users if p.path is not None}
    motion = Motion(route) if any(p.along_lane for p in scenario.users) else None
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
                # one of this user's own times, as `times` rounded it: two users whose
                # phases lie within a microsecond of each other each keep their own (a
                # tolerance on t - phase took both, and gave each user two fixes of
                # the same millisecond)
                local = t - plan.phase
                k = round(local / period)
                if k < 0 or round(k * period + plan.phase, 6) != t:
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
                e, n, seg_id, lane, segment, s = true_state(route, plan, local, table)
                e2, n2, *_ = true_state(route, plan, hi, table)
                e0, n0, *_ = true_state(route, plan, lo, table)
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
            if plan.course_from_road:
                rep_heading = facing
            lying = plan.lie is not None and plan.lie.factor(local) > 0.0
            if plan.lie is not None and lying:
                rep_e, rep_n = false_position(route, plan, plan.lie, local, table)
                f2 = false_position(route, plan, plan.lie, hi, table)
                f0 = false_position(route, plan, plan.lie, lo, table)
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
