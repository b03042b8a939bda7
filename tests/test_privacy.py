"""The tracker on the service side against the rotation strategies (`laas privacy`)."""

from __future__ import annotations

import math

from laas.deadreckon import dead_reckon
from laas.evaluation.privacy import (
    DEFAULT_STRATEGY,
    STRATEGIES,
    privacy_run,
    privacy_trace,
    service_view,
)
from laas.evaluation.score import judge, score
from laas.map.bundled import bundled_map
from laas.map.geojson import read_geojson_file
from laas.models import CorrectedPosition, GpsMeasurement
from laas.run.deployment import LocalDeployment
from laas.run.participants import run_participants
from laas.sim.scenario import get_scenario, simulate
from ldm import CoreConfig, RotationPolicy

DEFAULT_BOUND = 0.5
"""The issue's bound on the share of changes re-linked where 10-49 users share an area:
the default must stay below it on the ring with 50 users (about 47 on it at a change) for
300 s, where today's periodic change is re-linked every time. Measured: 0.305 (seed 0)."""


def test_the_tracker_links_todays_periodic_change() -> None:
    (row,) = privacy_run("ring", 10, 300.0, 0, ["periodic"])
    assert row.changes >= 10
    assert row.relinked >= 0.9 and row.followed >= 0.9


def test_the_default_stays_below_its_bound_where_periodic_is_linked() -> None:
    rows = {
        r.strategy: r for r in privacy_run("ring", 50, 300.0, 0, ["periodic", DEFAULT_STRATEGY])
    }
    assert rows["periodic"].relinked >= 0.9
    default = rows[DEFAULT_STRATEGY]
    assert 10 <= default.on_map < 50 and default.changes >= 50
    assert default.relinked < DEFAULT_BOUND
    assert default.followed < 0.5 * rows["periodic"].followed


def test_the_service_view_keeps_the_cores_rules_and_the_silence() -> None:
    _, trace = privacy_trace("ring", 8, 200.0, 1)
    times = [f.measurement.timestamp / 1000.0 for f in trace.fixes]
    for name, plan in STRATEGIES.items():
        view = service_view(trace, plan, 1)  # raises if the core would refuse a key
        if plan.policy is None:
            assert view == [f.user for f in trace.fixes]
            continue
        CoreConfig(  # a core takes the plan (its idle_timeout above the longest silence)
            name="c",
            cluster="mqtt://c",
            rotation_period=plan.period,
            rotation=plan.policy,
            idle_timeout=plan.policy.longest_silence + 30.0,
        )
        last: dict[str, tuple[str, float]] = {}
        for fix, p, t in zip(trace.fixes, view, times, strict=True):
            if p is None:
                continue
            before = last.get(fix.user)
            if before is not None and before[0] != p:
                # a change: the user kept quiet for the silence, within one fix interval
                gap = t - before[1]
                longest = plan.policy.longest_silence
                assert plan.policy.silence <= gap <= longest + 1.001, (name, gap)
                if plan.policy.strategy == "epoch":  # just after a multiple of the period
                    early = (math.floor(before[1] / plan.period) + 1) * plan.period - before[1]
                    assert early <= 1.001, (name, before[1], early)
            last[fix.user] = (p, t)


def test_a_silent_participant_dead_reckons_with_its_last_correction() -> None:
    fix = GpsMeasurement(timestamp=1000, latitude=53.5, longitude=10.0, heading=90.0, speed=10.0)
    later = fix.model_copy(update={"timestamp": 6000, "longitude": 10.0007})
    answer = CorrectedPosition(
        timestamp=1000,
        latitude=53.50002,
        longitude=9.99995,
        segment="s",
        lane=1,
        lane_type="driving",
        probability=0.9,
        accuracy=1.0,
        accuracy_cross=0.3,
        accuracy_along=1.0,
    )
    own = dead_reckon(answer, fix, later)
    assert own.timestamp == 6000 and (own.segment, own.lane) == ("s", 1)
    assert math.isclose(own.latitude, 53.50002) and math.isclose(own.longitude, 10.00065)


def test_a_silent_participant_with_the_map_follows_its_lane_through_junctions() -> None:
    """Helsinki's users answer themselves for up to 60 s from one exact answer (the truth):
    on the map's lanes nearly always right, where the last lane alone is often wrong."""
    hdmap, trace = privacy_trace("helsinki", 20, 300.0, 0)
    held: dict[str, tuple[CorrectedPosition, GpsMeasurement]] = {}
    right: dict[bool, list[bool]] = {True: [], False: []}
    for fix in trace.fixes:
        m = fix.measurement
        last = held.get(fix.user)
        if last is None or m.timestamp - last[1].timestamp > 60_000:
            lon, lat = hdmap.projection.to_wgs84(fix.true_e, fix.true_n)
            lane = hdmap.segments[fix.segment].lanes[fix.lane]
            answer = CorrectedPosition(
                timestamp=m.timestamp,
                latitude=lat,
                longitude=lon,
                segment=fix.segment,
                lane=fix.lane,
                lane_type=lane.type,
                probability=1.0,
                accuracy=1.0,
                accuracy_cross=0.3,
                accuracy_along=1.0,
            )
            held[fix.user] = (answer, m)
            continue
        for on_map in (True, False):
            own = dead_reckon(*last, m, hdmap if on_map else None)
            right[on_map].append(judge(hdmap, fix, own)[3])
    assert len(right[True]) > 1000
    with_map, without = sum(right[True]) / len(right[True]), sum(right[False]) / len(right[False])
    assert with_map > 0.95 and without < 0.8, (with_map, without)


def test_live_participants_keep_quiet_and_answer_themselves() -> None:
    """The Hamburg users through the three-broker deployment under epochs with silence:
    every fix answered (the silent ones by the participant itself), no key refused."""
    hdmap = read_geojson_file(bundled_map("messe-hamburg"))
    scenario = get_scenario("messe-hamburg")
    trace = simulate(hdmap, scenario, scenario.errors, 0)
    policy = RotationPolicy(strategy="epoch", silence=0.3, silence_max=0.8)
    with LocalDeployment(hdmap, rotation_period=2.0, rotation=policy) as deployment:
        run = run_participants(
            deployment.user_url, trace, speedup=10.0, hdmap=hdmap, **deployment.trust
        )
        stats = deployment.cores["user"].stats
    assert run.answered == len(trace.fixes) and not run.errors
    assert run.silent > 0 and stats.rotations >= 3 and stats.rejected_rekey == 0
    assert score(hdmap, trace, run.answers).accuracy > 0.8
