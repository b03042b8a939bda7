"""Privacy against the service itself: how many pseudonym changes a tracker undoes, and
what each rotation strategy costs in accuracy (`laas privacy`).

A run draws road users roaming a map (`laas.sim.roam`) for a while, simulates their
fixes, and plays each rotation strategy of the LDM (`ldm.wire.rotation`) over them exactly as
the core and the participant library would: the same `next_rotation` times the core's
``rotate`` notices, the same `Rotator` decides the participant's own changes and its
silence, from the speed its receiver reports. What comes out is the service's view, one
(pseudonym, time, position, velocity) per input sent, which the attacker
(`laas.evaluation.linker`) joins. Against the truth (which user each pseudonym was) a run
reports

    changes    pseudonym changes inside trips (an old pseudonym, then a new one)
    re-linked  the share of changes the attacker joined to the right old pseudonym
    followed   the share of trips whose every change it joined (a trip without a change
               is followed: the service saw it whole)
    pieces     per trip, 1 + its changes left unjoined; and, of the trips longer than
               5 min, the share with at least 3 pieces (the C-ITS aim: 95 %)

and, with ``accuracy``, the lane accuracy of every fix's answer: the engine's (driven as
the worker drives it: the service's inputs in time order under their pseudonyms, silent
pseudonyms forgotten after the engine's ``track_timeout``), or, for a fix not sent
because the participant kept quiet, the participant's own answer (`laas.deadreckon`: its
last correction applied to the fix, on the lane map; a plan with ``own_map`` False keeps
the last answered lane instead); against the same run without rotation, overall and in
the 30 s around each change.
"""

from __future__ import annotations

import functools
import math
import random
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from laas.config import EngineConfig
from laas.deadreckon import dead_reckon
from laas.engine import Engine
from laas.errors import ConfigError
from laas.evaluation.linker import Observation, link
from laas.evaluation.score import judge
from laas.map.bundled import bundled_map
from laas.map.geo import UtmProjection
from laas.map.geojson import read_geojson, read_geojson_file
from laas.map.hdmap import HdMap
from laas.map.mapgen import Curve, LaneSpec, Straight, road_features_utm, track
from laas.models import CorrectedPosition, GpsMeasurement
from laas.sim.family import FAMILIES, MAP_FAMILIES, build_case
from laas.sim.roam import roam_scenario
from laas.sim.scenario import Trace, simulate
from ldm.client.rotation import Rotator
from ldm.config import CoreConfig
from ldm.core.rotation import next_rotation
from ldm.wire.rotation import RotationPolicy

__all__ = [
    "DEFAULT_STRATEGY",
    "STRATEGIES",
    "Plan",
    "PrivacyRow",
    "format_privacy",
    "privacy_rows",
    "privacy_run",
    "privacy_trace",
    "service_view",
    "target_check",
]

LONG_TRIP = 300.0  # s: the C-ITS aim counts trips longer than 5 min
AROUND = 15.0  # s either side of a change: the 30 s window whose accuracy is reported
ATTACKERS = (2.0, 0.5)  # m/s^2 the tracker allows for (`laas.evaluation.linker`); the one that
#                         re-links more counts: a loose gate for turns, a tight one for crowds


@dataclass(frozen=True)
class Plan:
    """One strategy as a deployment would set it: the core's policy and period, and
    whether the participants hold the lane map for their own answers while silent."""

    name: str
    policy: RotationPolicy | None  # None: no rotation at all (the accuracy baseline)
    period: float = 120.0
    own_map: bool = True  # False: a silent participant keeps its last answered lane

    @property
    def rekey_interval(self) -> float:
        """The core's rule for this period (`CoreConfig.rekey_interval`)."""
        return CoreConfig(name="x", cluster="mqtt://x", rotation_period=self.period).rekey_interval


def _plan(
    name: str,
    strategy: str,
    period: float,
    silence: float = 0.0,
    longest: float | None = None,
    own_map: bool = True,
) -> Plan:
    policy = {"strategy": strategy, "silence": silence, "silence_max": longest}
    return Plan(name, RotationPolicy.model_validate(policy), period, own_map)


STRATEGIES: dict[str, Plan] = {
    p.name: p
    for p in (
        Plan("none", None),
        _plan("periodic", "periodic", 120.0),
        _plan("periodic-15", "periodic", 15.0),
        _plan("distance", "distance", 360.0),
        _plan("epoch", "epoch", 120.0),
        _plan("stop", "stop", 360.0),
        _plan("epoch+silent15", "epoch", 120.0, 15.0),
        _plan("epoch+silent30", "epoch", 120.0, 30.0),
        _plan("epoch+silent60", "epoch", 120.0, 60.0),
        _plan("periodic+silent30-90", "periodic", 120.0, 30.0, 90.0),
        _plan("distance+silent30-90", "distance", 360.0, 30.0, 90.0),
        _plan("stop+silent30-90", "stop", 360.0, 30.0, 90.0),
        _plan("epoch180+silent60-90", "epoch", 180.0, 60.0, 90.0),
        _plan("epoch+silent30-90/no-map", "epoch", 120.0, 30.0, 90.0, own_map=False),
        _plan("epoch+silent30-90", "epoch", 120.0, 30.0, 90.0),
    )
}
"""The strategies `laas privacy` compares (``distance`` and ``stop``: the core's period is
their backstop, 6 min as C-ITS's longest; ``/no-map``: the participants answer themselves
without the lane map, on their last answered lane)."""

DEFAULT_STRATEGY = "epoch+silent30-90"
"""The LaaS deployment's default (docs/security.md): within 0.02 of lane accuracy on every
place measured; ``epoch+silent60`` re-links less against this module's straight-line
tracker, but more against one that predicts along the road, as a service with the map
can, and there silences of random length do better."""


def _sim_rng(seed: int, user: str) -> random.Random:
    return random.Random(zlib.crc32(f"{seed}/{user}".encode()))


def service_view(trace: Trace, plan: Plan, seed: int = 0) -> list[str | None]:
    """The pseudonym each fix is sent under (None: not sent, the participant was silent),
    as the core and the participant library decide it (module docstring)."""
    if plan.policy is None:
        return [f.user for f in trace.fixes]
    out: list[str | None] = [None] * len(trace.fixes)
    by_user: dict[str, list[int]] = {}
    for i, fix in enumerate(trace.fixes):
        by_user.setdefault(fix.user, []).append(i)
    policy, period, rekey = plan.policy, plan.period, plan.rekey_interval
    for user, idx in by_user.items():
        t0 = trace.fixes[idx[0]].measurement.timestamp / 1000.0
        rotator = Rotator(policy, rekey, t0, _sim_rng(seed, user))
        key = 0  # the participant's current key; a pseudonym per key the core has seen
        seen = -1  # the key of the core's current pseudonym
        created = -math.inf  # the core's current pseudonym, made at its first input
        core_next = math.inf  # when the core's next ``rotate`` notice goes
        last_t: float | None = None
        for i in idx:
            m = trace.fixes[i].measurement
            t = m.timestamp / 1000.0
            while t >= core_next:  # the core's tick sent ``rotate``; the library obeys
                notice, core_next = core_next, next_rotation(policy.strategy, period, core_next)
                if rotator.may_change(notice):
                    key += 1
                    rotator.changed(notice)
            if last_t is not None and rotator.moved(m.speed * (t - last_t), m.speed, t):
                key += 1
                rotator.changed(t)
            last_t = t
            if rotator.silent(t):
                continue
            if key != seen:  # the core's `_pseudonym_for`: a new key, a new pseudonym
                if seen >= 0 and t - created < rekey:
                    raise AssertionError(f"{user}: the core would refuse key {key} at {t}")
                seen, created = key, t
                core_next = next_rotation(policy.strategy, period, t)
            rotator.used(t)
            out[i] = f"{user}#{key}"
    return out


def observations(hdmap: HdMap, trace: Trace, view: Sequence[str | None]) -> list[Observation]:
    """What the service sees of each input sent: pseudonym, time, position, velocity."""
    proj = hdmap.projection
    out = []
    for fix, p in zip(trace.fixes, view, strict=True):
        if p is None:
            continue
        m = fix.measurement
        e, n = proj.to_utm(m.longitude, m.latitude)
        h = math.radians(m.heading)
        out.append(
            Observation(p, m.timestamp / 1000.0, e, n, m.speed * math.sin(h), m.speed * math.cos(h))
        )
    return out


def _answers(
    hdmap: HdMap,
    trace: Trace,
    view: Sequence[str | None],
    config: EngineConfig,
    own_map: bool = True,
) -> list[CorrectedPosition | None]:
    """Every fix's answer: the engine's under the fix's pseudonym, or the participant's
    own (`laas.deadreckon`; on the lane map if `own_map`)."""
    mine = hdmap if own_map else None
    engine = Engine(hdmap, config)
    out: list[CorrectedPosition | None] = []
    last: dict[str, tuple[CorrectedPosition, GpsMeasurement]] = {}
    next_expiry = -math.inf
    for fix, p in zip(trace.fixes, view, strict=True):
        m = fix.measurement
        if m.timestamp >= next_expiry:  # the worker's housekeeping, once a second
            engine.expire(m.timestamp)
            next_expiry = m.timestamp + 1000
        if p is None:
            held = last.get(fix.user)
            out.append(None if held is None else dead_reckon(held[0], held[1], m, mine))
            continue
        answer = engine.process(p, m)
        out.append(answer)
        if answer is not None:
            last[fix.user] = (answer, m)
    return out


@dataclass(frozen=True)
class PrivacyRow:
    """One strategy on one run (module docstring)."""

    place: str
    users: int
    seed: int
    density: float  # users on the map on average, per km^2 of the map's bounding box
    on_map: float  # users on the map at a change, on average
    strategy: str
    changes: int
    relinked: float  # share of changes (nan without changes)
    followed: float  # share of trips
    pieces: float  # median pieces per trip
    long_trips: int  # trips longer than LONG_TRIP
    three_pieces: float  # share of those with >= 3 pieces (nan without any)
    accuracy: float = math.nan
    accuracy_cost: float = math.nan  # against no rotation, all fixes
    around_cost: float = math.nan  # lane accuracy lost in the 30 s around the changes
    around_aed: float = math.nan  # AED added there, m

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def _area_km2(hdmap: HdMap) -> float:
    x0, y0, x1, y1 = hdmap.bounds
    return max((x1 - x0) * (y1 - y0), 1e4) / 1e6  # at least 100 m x 100 m


RING = (1000.0, 600.0, 40.0)  # m: the ring road's box and corner radius, about 0.6 km^2
RING_CUT = 150.0  # m: its road elements' length, like the families' (60-250 m)


def ring_map() -> HdMap:
    """``ring``: a closed two-way ring road (a driving, a bicycle lane and a sidewalk each
    way) round a 1.0 x 0.6 km box, so that road users keep driving it for as long as a
    run lasts (on the other maps most trips end at the map's edge within minutes)."""
    width, height, radius = RING
    parts: list[Straight | Curve] = []
    for side in (width, height, width, height):
        parts += [Straight(side - 2 * radius), Curve(radius, 90.0)]
    reference = track((0.0, 0.0), 90.0, parts)[:-1]  # the last point is the first again
    reference.append(reference[0])
    lanes = [
        LaneSpec("sidewalk", 2.5, "both"),
        LaneSpec("bicycle", 1.8, "backward"),
        LaneSpec("driving", 3.25, "backward"),
        LaneSpec("driving", 3.25, "forward"),
        LaneSpec("bicycle", 1.8, "forward"),
        LaneSpec("sidewalk", 2.5, "both"),
    ]
    length = 2 * (width + height) - 8 * radius + 2 * math.pi * radius
    cuts = list(np.arange(RING_CUT, length - RING_CUT / 2, RING_CUT))
    origin = (10.0, 53.55)  # lon, lat: anywhere will do
    projection = UtmProjection.for_location(*origin)
    ox, oy = projection.to_utm(*origin)
    geojson = road_features_utm(
        "ring", [(x + ox, y + oy) for x, y in reference], projection, lanes, cuts, "center"
    )
    last = f"ring-{len(cuts)}"
    for feature in geojson["features"]:  # close the ring: the last element leads to the first
        if feature["properties"]["segment"] == last:
            feature["properties"]["successors"] = ["ring-0"]
    return read_geojson(geojson, source="ring")


@functools.lru_cache(maxsize=4)
def _map(place: str) -> HdMap:
    if place == "ring":
        return ring_map()
    return read_geojson_file(bundled_map(MAP_FAMILIES.get(place, place)))


def privacy_trace(place: str, users: int, duration: float, seed: int) -> tuple[HdMap, Trace]:
    """Users roaming `place` (a real map's name, or a road family's: a road drawn from
    it) for `duration` s, and their simulated fixes."""
    if place in FAMILIES:
        hdmap = build_case(place, seed).hdmap
    else:
        try:
            hdmap = _map(place)
        except Exception as exc:
            raise ConfigError(
                f"unknown place {place!r}: give a road family ({', '.join(FAMILIES)}) or a "
                f"bundled map (e.g. {', '.join(MAP_FAMILIES)}, messe-hamburg): {exc}"
            ) from None
    scenario = roam_scenario(hdmap, seed, users=users, duration=duration)
    return hdmap, simulate(hdmap, scenario, scenario.errors, seed)


def _trips(trace: Trace) -> dict[str, tuple[float, float]]:
    spans: dict[str, tuple[float, float]] = {}
    for fix in trace.fixes:
        t = fix.measurement.timestamp / 1000.0
        lo, hi = spans.get(fix.user, (t, t))
        spans[fix.user] = (min(lo, t), max(hi, t))
    return spans


def privacy_run(
    place: str,
    users: int,
    duration: float,
    seed: int,
    strategies: Sequence[str],
    accuracy: bool = False,
    config: EngineConfig | None = None,
) -> list[PrivacyRow]:
    """Every strategy on one drawn run (module docstring)."""
    hdmap, trace = privacy_trace(place, users, duration, seed)
    config = config or EngineConfig()
    spans = _trips(trace)
    area = _area_km2(hdmap)
    density = sum(hi - lo for lo, hi in spans.values()) / max(duration, 1e-9) / area
    scores0: tuple[np.ndarray, np.ndarray] | None = None  # the baseline: no rotation
    if accuracy:
        unrotated = service_view(trace, STRATEGIES["none"])
        scores0 = _scores(hdmap, trace, _answers(hdmap, trace, unrotated, config))
    rows = []
    for name in strategies:
        plan = STRATEGIES[name]
        view = service_view(trace, plan, seed)
        seen = observations(hdmap, trace, view)
        changes = max(
            (_changes(trace, view, link(seen, accel)) for accel in ATTACKERS),
            key=lambda cs: sum(ok for *_, ok in cs),
        )
        unjoined = {u: 0 for u in spans}
        for u, _, ok in changes:
            unjoined[u] += not ok
        pieces = [1 + unjoined[u] for u in spans]
        long = [u for u, (lo, hi) in spans.items() if hi - lo > LONG_TRIP]
        on_map = [sum(lo <= t <= hi for lo, hi in spans.values()) for _, t, _ in changes]
        row = PrivacyRow(
            place=place,
            users=users,
            seed=seed,
            density=density,
            on_map=float(np.mean(on_map)) if on_map else math.nan,
            strategy=name,
            changes=len(changes),
            relinked=float(np.mean([ok for *_, ok in changes])) if changes else math.nan,
            followed=float(np.mean([unjoined[u] == 0 for u in spans])),
            pieces=float(np.median(pieces)),
            long_trips=len(long),
            three_pieces=float(np.mean([1 + unjoined[u] >= 3 for u in long])) if long else math.nan,
        )
        if scores0 is not None:
            right, err = _scores(hdmap, trace, _answers(hdmap, trace, view, config, plan.own_map))
            near = _near(trace, [(u, t) for u, t, _ in changes])
            row = _with_accuracy(row, right, err, *scores0, near)
        rows.append(row)
    return rows


def _changes(
    trace: Trace, view: Sequence[str | None], joins: dict[str, str]
) -> list[tuple[str, float, bool]]:
    """Each change of pseudonym: its user, time, and whether `joins` re-linked it."""
    changes = []
    last: dict[str, str] = {}
    for fix, p in zip(trace.fixes, view, strict=True):
        if p is None:
            continue
        old = last.get(fix.user)
        if old is not None and old != p:
            changes.append((fix.user, fix.measurement.timestamp / 1000.0, joins.get(p) == old))
        last[fix.user] = p
    return changes


def _scores(
    hdmap: HdMap, trace: Trace, answers: Sequence[CorrectedPosition | None]
) -> tuple[np.ndarray, np.ndarray]:
    """Per fix: the answered lane is right (as `laas.evaluation.score` counts it), and the error
    in m (nan unanswered)."""
    right = np.zeros(len(answers), dtype=bool)
    err = np.full(len(answers), np.nan)
    for i, (fix, a) in enumerate(zip(trace.fixes, answers, strict=True)):
        if a is not None:
            de, dn, _, right[i] = judge(hdmap, fix, a)
            err[i] = math.hypot(de, dn)
    return right, err


def _near(trace: Trace, changes: Sequence[tuple[str, float]]) -> np.ndarray:
    """The fixes of a changing user within AROUND s of its change."""
    by_user: dict[str, list[float]] = {}
    for u, t in changes:
        by_user.setdefault(u, []).append(t)
    near = np.zeros(len(trace.fixes), dtype=bool)
    for i, fix in enumerate(trace.fixes):
        t = fix.measurement.timestamp / 1000.0
        near[i] = any(abs(t - c) <= AROUND for c in by_user.get(fix.user, ()))
    return near


def _with_accuracy(
    row: PrivacyRow,
    right: np.ndarray,
    err: np.ndarray,
    right0: np.ndarray,
    err0: np.ndarray,
    near: np.ndarray,
) -> PrivacyRow:
    values = dict(accuracy=float(right.mean()), accuracy_cost=float(right0.mean() - right.mean()))
    if near.any():
        values["around_cost"] = float(right0[near].mean() - right[near].mean())
        values["around_aed"] = float(np.nanmean(err[near]) - np.nanmean(err0[near]))
    return PrivacyRow(**{**asdict(row), **values})


def privacy_rows(
    places: Sequence[str],
    users: Sequence[int],
    duration: float,
    seeds: Sequence[int],
    strategies: Sequence[str],
    accuracy_users: int | None,
) -> Iterator[PrivacyRow]:
    """`privacy_run` over places x user counts (and `accuracy_users`) x seeds; the
    accuracy too where the count is `accuracy_users`."""
    unknown = [s for s in strategies if s not in STRATEGIES]
    if unknown:
        raise ConfigError(f"unknown strategies {unknown}; choose from {', '.join(STRATEGIES)}")
    counts = sorted({*users, *([accuracy_users] if accuracy_users else [])})
    for place in places:
        for n in counts:
            for seed in seeds:
                yield from privacy_run(
                    place, n, duration, seed, strategies, accuracy=n == accuracy_users
                )


def _pct(x: float) -> str:
    return "     -" if math.isnan(x) else f"{100 * x:5.1f}%"


def _num(x: float, fmt: str) -> str:
    return "-" if math.isnan(x) else format(x, fmt)


def format_privacy(rows: Sequence[PrivacyRow]) -> str:
    """The rows as a table, one line per (place, users, seed, strategy)."""
    head = (
        f"{'place':<13}{'users':>6}{'seed':>5}{'/km2':>7}{'at chg':>7}  "
        f"{'strategy':<25}{'changes':>8}"
        f"{'re-linked':>10}{'followed':>9}{'pieces':>7}{'>5min':>6}{'>=3 pcs':>8}"
        f"{'acc':>7}{'cost':>7}{'cost30s':>8}{'AED30s':>7}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r.place:<13}{r.users:>6}{r.seed:>5}{r.density:>7.1f}{_num(r.on_map, '.0f'):>7}  "
            f"{r.strategy:<25}{r.changes:>8}{_pct(r.relinked):>10}{_pct(r.followed):>9}"
            f"{r.pieces:>7.1f}{r.long_trips:>6}{_pct(r.three_pieces):>8}"
            f"{_num(r.accuracy, '.3f'):>7}{_num(r.accuracy_cost, '+.3f'):>7}"
            f"{_num(r.around_cost, '+.3f'):>8}{_num(r.around_aed, '+.2f'):>7}"
        )
    return "\n".join(lines)


def target_check(rows: Sequence[PrivacyRow], strategy: str = DEFAULT_STRATEGY) -> str:
    """The issue's targets for `strategy`, each with the figure measured and whether it is
    met: re-linked < 10 % of changes with >= 50 users on the map, < 50 % with 10-49;
    >= 3 pieces for 95 % of trips over 5 min; lane accuracy cost <= 0.02."""
    mine = [r for r in rows if r.strategy == strategy]

    def share(rs: Sequence[PrivacyRow], field: str, weight: str) -> float:
        w: float = sum(getattr(r, weight) for r in rs if not math.isnan(getattr(r, field)))
        if w == 0:
            return math.nan
        total: float = sum(
            getattr(r, field) * getattr(r, weight) for r in rs if not math.isnan(getattr(r, field))
        )
        return float(total / w)

    crowd = [r for r in mine if r.on_map >= 50]
    some = [r for r in mine if 10 <= r.on_map < 50]
    costs = [r.accuracy_cost for r in mine if not math.isnan(r.accuracy_cost)]
    checks = [
        ("re-linked, >= 50 users on the map", share(crowd, "relinked", "changes"), "<", 0.10),
        ("re-linked, 10-49 users on the map", share(some, "relinked", "changes"), "<", 0.50),
        ("trips > 5 min with >= 3 pieces", share(mine, "three_pieces", "long_trips"), ">=", 0.95),
        ("lane accuracy cost", max(costs) if costs else math.nan, "<=", 0.02),
    ]
    lines = [f"targets for {strategy!r} (pooled over its runs above):"]
    for what, value, op, bound in checks:
        if math.isnan(value):
            lines.append(f"  {what}: not measured")
            continue
        met = value < bound if op == "<" else value >= bound if op == ">=" else value <= bound
        shown = f"{value:.3f}" if what.startswith("lane") else f"{100 * value:.1f} %"
        limit = f"{bound:.2f}" if what.startswith("lane") else f"{100 * bound:.0f} %"
        lines.append(f"  {what}: {shown} (target {op} {limit}) {'met' if met else 'MISSED'}")
    lone = [r for r in mine if r.on_map < 10]
    for band, rs in ((">= 50", crowd), ("10-49", some), ("< 10", lone)):
        value = share(rs, "three_pieces", "long_trips")
        if not math.isnan(value):  # where the pooled share comes from
            lines.append(
                f"  (trips > 5 min with >= 3 pieces, {band} on the map: {100 * value:.1f} %)"
            )
    return "\n".join(lines)
