"""Scenario families and suites: reproducible draws, valid maps, the written distributions,
the simulator's optional features, the oracle and the smoke suite."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
from collections import Counter
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from laas.cli import main
from laas.config import EngineConfig
from laas.evaluation.score import score
from laas.evaluation.suite import METHODS, format_report, get_suite, oracle_answers, run_suite
from laas.map.geojson import read_geojson, read_geojson_file
from laas.map.hdmap import HdMap
from laas.sim.family import FAMILIES, FamilyCase, Road, build_case, get_family
from laas.sim.scenario import (
    EPOCH_MS,
    ErrorModel,
    Trace,
    UserPlan,
    hamburg_scenario,
    simulate,
    simulate_with,
)

SEEDS = range(12)
WIDTHS = {
    "driving": (2.75, 3.75),
    "bicycle": (1.5, 2.2),
    "parking": (2.0, 2.6),
    "sidewalk": (1.5, 4.0),
}
SPEEDS = {"bicycle": (3.0, 8.0), "pedestrian": (0.8, 2.0)}


def _road(case: FamilyCase) -> Road:
    """A drawn family's road (map families have none)."""
    assert case.road is not None
    return case.road


@pytest.fixture(scope="module")
def cases() -> list[FamilyCase]:
    return [build_case(f, s) for f in FAMILIES for s in SEEDS]


def _fingerprint(trace: Trace) -> str:
    h = hashlib.sha256()
    for f in trace.fixes:
        h.update(repr((f.user, f.measurement.model_dump(), f.true_e, f.true_n, f.lane)).encode())
    return h.hexdigest()


def _case_hash(family: str, seed: int) -> str:
    case = build_case(family, seed)
    trace = simulate(case.hdmap, case.scenario, case.scenario.errors, seed)
    text = json.dumps(case.geojson) + case.scenario.model_dump_json()
    return hashlib.sha256(text.encode()).hexdigest() + _fingerprint(trace)


# --- reproducibility --------------------------------------------------------------------


def test_same_family_and_seed_give_the_same_map_scenario_and_trace() -> None:
    a, b = build_case("urban", 7), build_case("urban", 7)
    assert json.dumps(a.geojson) == json.dumps(b.geojson)
    assert a.scenario == b.scenario
    ta = simulate(a.hdmap, a.scenario, a.scenario.errors, 7)
    tb = simulate(b.hdmap, b.scenario, b.scenario.errors, 7)
    assert ta.fixes == tb.fixes
    other = build_case("urban", 8)
    assert json.dumps(other.geojson) != json.dumps(a.geojson)
    assert build_case("shared", 7).scenario != a.scenario


def test_a_worker_process_draws_the_same_case() -> None:
    with ProcessPoolExecutor(max_workers=1) as pool:
        there = pool.submit(_case_hash, "arterial", 3).result()
    assert there == _case_hash("arterial", 3)


def test_unknown_family_and_negative_seed_are_refused() -> None:
    from laas.errors import ConfigError

    with pytest.raises(ConfigError, match="urban"):
        get_family("suburban")
    with pytest.raises(ConfigError):
        build_case("urban", -1)


# --- the maps ---------------------------------------------------------------------------


def test_generated_maps_load_and_chain_their_elements(cases: list[FamilyCase]) -> None:
    zones, hemispheres = set(), set()
    for case in cases:
        again = read_geojson(case.geojson)  # the reader validates every lane
        assert set(again.segments) == set(case.scenario.route)
        route = case.scenario.route
        for here, there in itertools.pairwise(route):
            assert case.hdmap.segments[here].successors == (there,)
            end = case.hdmap.segments[here].reference.coords[-1]
            start = case.hdmap.segments[there].reference.coords[0]
            assert math.dist(end, start) < 0.01  # the elements join up
        assert case.hdmap.segments[route[-1]].successors == ()
        lon, lat = _road(case).origin
        assert -56.0 <= lat <= 70.0 and -177.0 <= lon <= 177.0
        zones.add(case.hdmap.projection.zone)
        hemispheres.add(case.hdmap.projection.south)
    assert len(zones) > 10 and hemispheres == {True, False}


def test_cross_sections_follow_the_written_rules(cases: list[FamilyCase]) -> None:
    corners = 0
    for case in cases:
        lanes = _road(case).lanes
        assert 2 <= len(lanes) <= get_family(case.family).max_lanes <= 8
        types = [lane.type for lane in lanes]
        assert "driving" in types
        for k, lane in enumerate(lanes):
            lo, hi = WIDTHS[lane.type]
            assert lo - 1e-9 <= lane.width <= hi + 1e-9
            if lane.type == "sidewalk":
                assert lane.direction == "both"
                assert k in (0, len(lanes) - 1)  # at the edges
            if lane.type == "parking":  # parking is never at the edge of a sidewalked road
                assert any(t == "driving" for t in types)
        driving = {lane.width for lane in lanes if lane.type == "driving"}
        assert len(driving) == 1  # one width per road
        directions = {lane.direction for lane in lanes if lane.type == "driving"}
        assert directions == ({"forward", "backward"} if _road(case).two_way else {"forward"}) or (
            directions == {"both"}
        )
        corners += sum(1 for p in _road(case).pieces if abs(getattr(p, "angle", 0.0)) == 90.0)
        for seg in case.hdmap.segments.values():
            assert [lane.type for lane in seg.lanes] == types
    assert corners > 0


# --- the users --------------------------------------------------------------------------


def _allowed(direction: str, reverse: bool) -> bool:
    return direction == "both" or direction == ("backward" if reverse else "forward")


def test_users_keep_to_lanes_of_their_kind_and_direction(cases: list[FamilyCase]) -> None:
    kinds: Counter[str] = Counter()
    parked = 0
    for case in cases:
        spec = get_family(case.family)
        users = case.scenario.users
        assert spec.users[0] <= len(users) <= spec.users[1]
        assert 60.0 <= case.scenario.duration <= 120.0
        for p in users:
            kinds[p.kind] += 1
            lanes = _road(case).lanes
            allowed = {
                "car": {"parking"} if p.speed == 0.0 else {"driving"},
                "bicycle": {"bicycle", "driving"},
                "pedestrian": {"sidewalk"},
            }[p.kind]
            for _, k in p.lanes:
                assert lanes[k].type in allowed, (case.family, case.seed, p)
                if p.speed > 0.0:
                    assert _allowed(lanes[k].direction, p.reverse), (case.family, case.seed, p)
            if p.speed == 0.0:
                parked += 1
                assert p.kind == "car" and len(p.lanes) == 1
            elif p.kind == "car":
                assert spec.car_speed[0] <= p.speed <= spec.car_speed[1]
            else:
                assert SPEEDS[p.kind][0] <= p.speed <= SPEEDS[p.kind][1]
            assert p.rate in (1.0, 2.0, 5.0, 10.0)
            assert 0.0 <= p.enter < (p.leave or case.scenario.duration) <= case.scenario.duration
            assert math.hypot(*p.bias) <= 1.0
            assert 0.7 <= p.noise_scale <= 1.4
    assert set(kinds) == {"car", "bicycle", "pedestrian"} and parked > 0


def test_cars_change_lanes_at_the_written_rate(cases: list[FamilyCase]) -> None:
    """One change per 20-60 s where the road allows one (an overtake counts two)."""
    changes, seconds = 0, 0.0
    for case in cases:
        lanes = _road(case).lanes
        for p in case.scenario.users:
            if p.kind != "car" or p.speed == 0.0:
                continue
            k = p.lanes[0][1]
            sides = [j for j in (k - 1, k + 1) if 0 <= j < len(lanes)]
            if not any(
                lanes[j].type == "driving" and _allowed(lanes[j].direction, p.reverse)
                for j in sides
            ):
                continue
            leave = p.leave or case.scenario.duration
            changes += sum(1 for t, _ in p.lanes[1:] if t < leave)
            seconds += leave - p.enter
    per_minute = changes / seconds * 60.0
    assert 1.0 <= per_minute <= 4.5, per_minute


def test_drawn_errors_lie_in_their_ranges(cases: list[FamilyCase]) -> None:
    for case in cases:
        e = case.scenario.errors
        assert math.hypot(e.bias_east, e.bias_north) <= 15.0
        assert 0.0 <= e.bias_drift <= 0.2
        assert 0.5 <= e.sigma_pos <= 4.0
        assert 0.0 <= e.outlier_rate <= 0.03 and 0.0 <= e.dropout_rate <= 0.05
        assert e.heading_per_speed > 0.0
    reporting = [p.accuracy_scale is not None for c in cases for p in c.scenario.users]
    assert 0.3 < np.mean(reporting) < 0.7


# --- the simulator's features -----------------------------------------------------------


def test_a_drawn_trace_respects_each_users_plan() -> None:
    case = build_case("urban", 5)
    trace = simulate(case.hdmap, case.scenario, case.scenario.errors, 5)
    plans = {p.user: p for p in case.scenario.users}
    by_user: dict[str, list[float]] = {}
    for fix in trace.fixes:
        plan = plans[fix.user]
        t = (fix.measurement.timestamp - EPOCH_MS) / 1000.0 - plan.phase
        assert plan.enter - 1e-3 <= t <= (plan.leave or case.scenario.duration) + 1e-3
        assert (fix.measurement.accuracy is None) == (plan.accuracy_scale is None)
        assert (fix.receiver_e, fix.receiver_n) == plan.bias
        assert fix.lane in {lane for _, lane in plan.lanes}  # between two during a change
        by_user.setdefault(fix.user, []).append(t)
    for user, times in by_user.items():
        steps = np.diff(times) * (plans[user].rate or 1.0)  # whole periods (gaps drop some)
        assert np.allclose(steps, np.round(steps), atol=0.02) and (steps >= 0.99).all()
    ratios = [
        f.measurement.accuracy
        / (plans[f.user].accuracy_scale or 1.0)
        / (math.sqrt(2.0) * case.scenario.errors.sigma_pos * plans[f.user].noise_scale)
        for f in trace.fixes
        if f.measurement.accuracy is not None
    ]
    assert len(ratios) > 100 and 0.9 < float(np.median(ratios)) < 1.1  # the radius, jittered
    first = trace.fixes[0]
    errors = case.scenario.errors
    assert math.hypot(first.common_e - errors.bias_east, first.common_n - errors.bias_north) < 1.0


def test_stopped_and_parked_users_stand_still() -> None:
    plan = UserPlan(
        user="u",
        kind="car",
        speed=5.0,
        start=20.0,
        lanes=((0.0, 0),),
        stops=((30.0, 10.0),),
        brake=2.0,
        along_lane=True,
    )
    parked = UserPlan(user="p", kind="car", speed=0.0, start=100.0, lanes=((0.0, 2),))
    base = hamburg_scenario()
    hdmap = read_geojson_file(base.map)
    scenario = base.model_copy(update={"users": (plan, parked), "duration": 60.0})
    errors = ErrorModel(bias_east=0.0, bias_north=0.0, sigma_pos=0.0, sigma_vel=0.0)
    trace = simulate(hdmap, scenario, errors, 0)
    car = [f for f in trace.fixes if f.user == "u"]
    still = [f for f in car if 30.0 < (f.measurement.timestamp - EPOCH_MS) / 1000.0 < 40.0]
    assert len(still) == 9 and all(f.measurement.speed < 1e-6 for f in still)
    assert car[30].measurement.speed < 0.05 and car[40].measurement.speed < 0.05
    assert (
        math.dist((still[0].true_e, still[0].true_n), (still[-1].true_e, still[-1].true_n)) < 1e-6
    )
    # braking takes pi v / (2 brake) = 3.9 s at peak 2 m/s^2: half speed 2 s before the stop
    assert car[28].measurement.speed == pytest.approx(2.5, abs=0.3)
    assert car[10].measurement.speed == pytest.approx(5.0, abs=0.05)
    spots = {(round(f.true_e, 6), round(f.true_n, 6)) for f in trace.fixes if f.user == "p"}
    assert len(spots) == 1


def test_new_error_features_do_what_they_say() -> None:
    case = build_case("arterial", 4)
    quiet = ErrorModel(bias_east=0.0, bias_north=0.0, sigma_pos=1.0, sigma_vel=0.1)

    def errors_of(model: ErrorModel) -> tuple[np.ndarray, int]:
        trace = simulate(case.hdmap, case.scenario, model, 1)
        proj = case.hdmap.projection
        xy = np.array(
            [proj.to_utm(f.measurement.longitude, f.measurement.latitude) for f in trace.fixes]
        )
        true = np.array([(f.true_e + f.receiver_e, f.true_n + f.receiver_n) for f in trace.fixes])
        return np.hypot(*(xy - true).T), len(trace.fixes)

    base, n = errors_of(quiet)
    heavy, _ = errors_of(quiet.model_copy(update={"outlier_rate": 0.2, "outlier_scale": 10.0}))
    assert np.percentile(heavy, 95) > 3.0 * np.percentile(base, 95)
    _, kept = errors_of(quiet.model_copy(update={"dropout_rate": 0.5}))
    assert 0.4 < kept / n < 0.6
    _, gapped = errors_of(quiet.model_copy(update={"gap_rate": 0.1, "gap_duration": 5.0}))
    assert gapped < 0.9 * n
    jumpy, _ = errors_of(quiet.model_copy(update={"multipath_rate": 0.2, "multipath_offset": 6.0}))
    assert np.mean(jumpy > 4.0) > 0.2 > np.mean(base > 4.0)


def test_heading_noise_grows_as_speed_falls() -> None:
    base = hamburg_scenario()
    hdmap = read_geojson_file(base.map)
    slow = UserPlan(user="slow", kind="pedestrian", speed=1.0, start=30.0, lanes=((0.0, 3),))
    fast = UserPlan(user="fast", kind="car", speed=10.0, start=100.0, lanes=((0.0, 0),))
    scenario = base.model_copy(update={"users": (slow, fast), "duration": 40.0})
    errors = ErrorModel(sigma_heading=0.5, heading_per_speed=20.0)
    trace = simulate(hdmap, scenario, errors, 3)

    def spread(user: str) -> float:
        diffs = [
            (f.measurement.heading - f.true_heading + 180.0) % 360.0 - 180.0
            for f in trace.fixes
            if f.user == user
        ]
        return float(np.std(diffs))

    assert spread("slow") > 3.0 * spread("fast")  # 20.5 against 2.5 degrees


def test_the_builtin_scenarios_use_none_of_the_new_features() -> None:
    scenario = hamburg_scenario()
    hdmap = read_geojson_file(scenario.map)
    trace = simulate_with(hdmap, scenario, 0, sigma_pos=1.0, sigma_vel=0.25)
    assert len(trace.fixes) == 303
    assert all(f.measurement.accuracy is None for f in trace.fixes)
    assert {(f.common_e, f.common_n) for f in trace.fixes} == {(-8.0, 8.0)}
    assert {(f.receiver_e, f.receiver_n) for f in trace.fixes} == {(0.0, 0.0)}


# --- the oracle and the suites ----------------------------------------------------------


def _clean(case: FamilyCase) -> tuple[HdMap, Trace]:
    """The case's users with ideal receivers under a large, drifting common error."""
    users = tuple(
        p.model_copy(update={"bias": (0.0, 0.0), "noise_scale": 1.0, "course_from_road": False})
        for p in case.scenario.users
    )
    scenario = case.scenario.model_copy(update={"users": users})
    errors = ErrorModel(
        bias_east=9.0, bias_north=-7.0, bias_drift=0.1, sigma_pos=0.3, sigma_vel=0.1
    )
    return case.hdmap, simulate(case.hdmap, scenario, errors, 11)


def test_the_oracle_is_near_perfect_with_small_noise_and_no_outliers() -> None:
    hdmap, trace = _clean(build_case("arterial", 6))
    config = EngineConfig(sigma_pos=0.3, sigma_vel=0.1)
    result = score(hdmap, trace, oracle_answers(hdmap, trace, config))
    assert result.accuracy > 0.97 and result.aed < 0.5
    # the same oracle told a wrong common error (none) fails: the assertion above can fail
    blind = dataclasses.replace(
        trace, fixes=tuple(dataclasses.replace(f, common_e=0.0, common_n=0.0) for f in trace.fixes)
    )
    worse = score(hdmap, blind, oracle_answers(hdmap, blind, config))
    assert worse.accuracy < 0.5 and worse.aed > 5.0


@pytest.mark.slow
def test_the_smoke_suite_scores_every_run_three_ways() -> None:
    suite = get_suite("smoke")
    rows = run_suite(suite, workers=2)
    assert [(r.family, r.seed, r.sigma_pos) for r in rows] == suite.jobs()
    for row in rows:
        assert set(row.methods) == set(METHODS)
        for method in row.methods.values():
            assert method.error is None
            assert 0.0 <= method.accuracy <= 1.0 and method.answered > 0
            assert math.isfinite(method.aed)
    report = format_report(suite, rows)
    assert all(f in report for f in ("urban", "arterial", "shared", "oracle", "worst run"))
    json.dumps([r.as_dict() for r in rows])  # --json can print them


def test_evaluate_refuses_an_unknown_suite(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", "--suite", "nope"]) == 2
    assert "heldout" in capsys.readouterr().err


def test_a_suite_cut_down_runs_only_what_was_asked_and_the_calibration_moves_no_lane() -> None:
    suite = get_suite("smoke").subset(families=["urban"], seeds=1)
    assert suite.jobs() == [("urban", 1, 1.0)]
    raw = suite.subset(calibrated=False)
    assert "uncalibrated" in raw.description and suite.calibrated and not raw.calibrated
    (calibrated,) = run_suite(suite, workers=1)
    (uncalibrated,) = run_suite(raw, workers=1)
    said, plain = calibrated.methods["default"], uncalibrated.methods["default"]
    # the calibration map changes what is said of a lane, never the lane or the position
    assert said.accuracy == plain.accuracy and said.aed == plain.aed
    assert sum(said.integrity.prob) != pytest.approx(sum(plain.integrity.prob), abs=1e-6)
    assert calibrated.methods["paper"] == dataclasses.replace(
        uncalibrated.methods["paper"], seconds=calibrated.methods["paper"].seconds
    )


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--suite", "dev", "--families", "urban,town"], "no family town"),
        (["--suite", "ci", "--sigma-pos", "4"], "not 4"),
        (["--suite", "ci", "--seeds", "0"], "1 or more"),
        (["--seeds", "3"], "give --suite too"),
        (["--uncalibrated"], "--uncalibrated"),
    ],
)
def test_evaluate_refuses_a_cut_it_cannot_make(
    args: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["evaluate", *args]) == 2
    assert named in capsys.readouterr().err
