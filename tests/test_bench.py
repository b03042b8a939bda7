"""`laas bench` end to end on the embedded broker: a few participants, a few seconds.

A functional test, not a timed one: it checks that every stage ran and the report is
sane, never how fast anything was.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest

from laas.errors import ConfigError
from laas.map.hdmap import HdMap
from laas.run.bench import (
    ROTATION_OFF,
    STAGES,
    BenchConfig,
    bench_scenario,
    format_loads,
    format_report,
    run_bench,
    run_loads,
)
from laas.sim.scenario import ErrorModel, simulate
from ldm.local.pytest_plugin import need_mosquitto


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_bench_runs_end_to_end_on_the_embedded_broker(hamburg_map: HdMap) -> None:
    lines: list[str] = []
    config = BenchConfig(
        participants=4,
        rate=2.0,
        duration=2.0,
        brokers="embedded",
        rotation_period=20.0,
        processes=2,
        privacy_speedup=50.0,
    )
    scenario = bench_scenario(4, rate=2.0, duration=2.0, spread=config.spread)
    fixes = len(simulate(hamburg_map, scenario, ErrorModel(), seed=0).fixes)
    report = run_bench(config, progress=lines.append)

    assert report.brokers == "embedded-process"
    assert report.processes == 2
    assert report.sent == fixes >= 4 * 2 * 2
    assert report.answered == report.sent, report.errors
    assert report.error_replies == report.lost == 0
    assert report.ldm.n == report.answered
    assert 0 < report.ldm.p50 <= report.ldm.p95 <= report.ldm.p99 <= report.ldm.max
    assert report.bare.n > 0 and report.bare.p50 > 0
    assert report.overhead > 0 and math.isfinite(report.overhead)
    assert report.throughput > 0
    assert report.worker_answered == report.sent
    # Every stage timed for every fix, joined by correlation id across the processes,
    # and the stages of one trip add up to no more than the round trips measured.
    assert [name for name, _, _ in STAGES] == list(report.stages)
    for name, lat in report.stages.items():
        assert lat.n == report.sent, name
        assert lat.p50 <= lat.p99 <= lat.max, name
    assert sum(lat.mean for lat in report.stages.values()) <= report.ldm.mean
    cpu = report.cpu_per_1000()
    assert all(0 < v < 1000 for v in cpu.values()), cpu

    rotating, fixed = report.privacy
    assert rotating.rotation_period == 20.0 and fixed.rotation_period == ROTATION_OFF
    assert rotating.rotations > 0  # 100 s of scenario at one rotation per 20 s
    assert fixed.rotations == 0
    for run in report.privacy:
        assert run.answered == run.fixes == 303
    # The Hamburg scenario through the deployment: what the README quotes for it (lane
    # accuracy 0.970 without rotation, less with it: a rotated pseudonym is a new track),
    # less a margin for the live worker's batches, which depend on timing.
    print(f"\nprivacy runs: accuracy {rotating.accuracy:.3f} rotating, {fixed.accuracy:.3f} not")
    assert fixed.accuracy >= 0.93, fixed
    assert rotating.accuracy <= fixed.accuracy + 0.01, (rotating, fixed)

    text = format_report(report)
    assert "LDM: fix -> corrected position" in text and "bare MQTT echo" in text
    assert f"answered     {report.sent}/{report.sent} (100.0 %)" in text
    assert "rotation every 20 s" in text and "rotation off" in text
    assert json.loads(json.dumps(report.as_dict()))["share_answered"] == 1.0
    assert any("sessions open" in line for line in lines)
    assert "queue wait in the worker" in text and "CPU s per 1,000 fixes" in text


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_bench_reports_the_aligned_and_the_spread_load_together() -> None:
    """`laas bench --both`: the load on the whole second, then spread over it, each on
    its own deployment, every fix answered in both, one row each in one report."""
    config = BenchConfig(
        participants=4, rate=2.0, duration=2.0, brokers="embedded", processes=1, privacy=False
    )
    aligned, spread = run_loads(replace(config, spread=True))
    assert (aligned.spread, spread.spread) == (False, True)
    for report in (aligned, spread):
        assert report.sent >= 4 * 2 * 2 and report.answered == report.sent, report.errors
    text = format_loads([aligned, spread])
    answered = [line.split("  ")[0] for line in text.splitlines() if "100.0 %" in line]
    assert answered == ["on the whole second", "spread over the second"], text
    cpu = text.split("CPU s per 1,000 fixes", 1)[1].splitlines()[1:3]
    assert [line.split("  ")[0] for line in cpu] == answered, text


def test_bench_participants_stay_on_the_road(hamburg_map: HdMap) -> None:
    scenario = bench_scenario(50, rate=1.0, duration=300.0, seed=3)
    trace = simulate(hamburg_map, scenario, ErrorModel(), seed=3)  # raises if one drives off
    assert len({f.user for f in trace.fixes}) == 50
    assert len(trace.fixes) >= 50 * 300
    assert {f.lane for f in trace.fixes if f.kind == "bicycle"} == {3}


def test_users_whose_phases_lie_a_microsecond_apart_each_get_one_fix_a_period(
    hamburg_map: HdMap,
) -> None:
    """Phases drawn for 1,000 bench users lie as close as a microsecond: each user still
    has one fix per period (the simulator gave two users each fix twice, and the worker
    refused every second one as not newer: 38 error replies in a 1,000-user bench)."""
    scenario = bench_scenario(2, rate=1.0, duration=5.0, seed=0, spread=True)
    a, b = scenario.users
    close = (a.model_copy(update={"phase": 0.2959102}), b.model_copy(update={"phase": 0.2959108}))
    apart = simulate(hamburg_map, scenario, ErrorModel(), seed=0)  # phases drawn far apart
    trace = simulate(hamburg_map, scenario.model_copy(update={"users": close}), ErrorModel(), 0)
    for user in (a.user, b.user):
        stamps = [f.measurement.timestamp for f in trace.fixes if f.user == user]
        alone = [f for f in apart.fixes if f.user == user]
        assert len(stamps) == len(alone) == 5, (user, stamps)  # 5 s at 1 Hz
        assert stamps == sorted(set(stamps)), (user, stamps)


@pytest.mark.parametrize(
    "bad",
    [{"participants": 0}, {"rate": 0.0}, {"duration": -1.0}, {"rotation_period": 0.0}],
)
def test_bench_config_refuses_nonsense(bad: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        BenchConfig(**bad)  # type: ignore[arg-type]


@pytest.mark.slow
@pytest.mark.mosquitto
@pytest.mark.timeout(120)
def test_bench_load_generator_answers_every_fix_of_200_participants() -> None:
    """200 participants, each its own connection and session, on the shared client loop
    of two processes (paced ramp, fixes on the whole second), on Mosquitto brokers that
    `run_bench` starts on free ports: every fix is answered."""
    need_mosquitto()
    lines: list[str] = []
    config = BenchConfig(
        participants=200,
        rate=1.0,
        duration=5.0,
        brokers="mosquitto",
        processes=2,
        connect_rate=400.0,
        privacy=False,
    )
    report = run_bench(config, progress=lines.append)

    assert report.brokers == "mosquitto"
    assert report.participants == 200 and not report.spread
    assert report.sent >= 200 * 5
    assert report.answered == report.sent, report.errors
    assert report.error_replies == report.lost == 0
    assert report.worker_answered == report.sent
    assert report.ldm.n == report.answered and report.ldm.p50 <= report.ldm.p99
    assert report.privacy == []
    assert any(line.startswith("  ramp: ") for line in lines)
    assert sum("sessions open after" in line for line in lines) == 2


def test_bench_with_two_regional_workers_answers_every_fix() -> None:
    """`laas bench --workers 2`: two worker processes, each serving a strip of the map;
    each participant routes its fixes by position, and every fix is answered."""
    config = BenchConfig(
        participants=8,
        rate=2.0,
        duration=3.0,
        brokers="embedded",
        processes=2,
        privacy=False,
        workers=2,
    )
    report = run_bench(config)
    assert report.workers == 2
    assert report.answered == report.sent >= 8 * 2 * 3, report.errors
    assert report.worker_answered == report.sent
    assert "2 regional laas workers" in format_report(report)
