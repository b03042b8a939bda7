"""Users on paths of their own (`UserPlan.path`) and roaming any map (`laas.sim.roam`):
continuous truth on the named lanes, successors followed through a junction, seeded draws,
broken paths refused, and the engine answering a roaming trace."""

from __future__ import annotations

import itertools
import math
from collections import Counter
from typing import Any

import pytest
from shapely import LineString, Point

from laas.config import EngineConfig
from laas.errors import ConfigError
from laas.map.bundled import bundled_map
from laas.map.geo import UtmProjection
from laas.map.geojson import read_geojson, read_geojson_file
from laas.map.hdmap import HdMap
from laas.map.mapgen import (
    Curve,
    LaneSpec,
    Straight,
    feature_collection,
    local_to_lonlat,
    road_features,
    road_features_utm,
    track,
)
from laas.sim.replay import replay
from laas.sim.roam import roam_scenario, scenario_or_roam
from laas.sim.scenario import Lie, Scenario, Trace, UserPlan, simulate
from laas.sim.trace import TraceLine

ORIGIN = (8.4037, 49.0069)  # Karlsruhe


def junction_map() -> HdMap:
    """Road a (two elements, 5 lanes) ends at a junction: road b goes on straight with 4
    lanes (a's right driving lane merges, a sidewalk instead of the bicycle lane), road c
    turns right through a corner element. Both ways: a backward driving lane, sidewalks."""
    proj = UtmProjection.for_location(*ORIGIN)
    ox, oy = proj.to_utm(*ORIGIN)
    walk = LaneSpec("sidewalk", 2.0, "both")
    back = LaneSpec("driving", 3.25, "backward")
    fwd = LaneSpec("driving", 3.25, "forward")
    bike = LaneSpec("bicycle", 1.8, "forward")

    def road(name: str, y0: float, parts: Any, lanes: Any, split: Any = ()) -> dict[str, Any]:
        local = track((0.0, y0), 0.0, parts)
        return road_features_utm(name, [(x + ox, y + oy) for x, y in local], proj, lanes, split)

    a = road("a", 0.0, [Straight(150.0)], [walk, back, fwd, fwd, bike], (75.0,))
    b = road("b", 150.0, [Straight(120.0)], [walk, back, fwd, walk])
    corner = 25.0 * math.pi / 2.0
    c = road(
        "c", 150.0, [Curve(25.0, 90.0), Straight(100.0)], [walk, back, fwd, fwd, bike], (corner,)
    )
    fc = feature_collection(a, b, c)
    for feature in fc["features"]:
        if feature["properties"]["segment"] == "a-1":
            feature["properties"]["successors"] = ["b-0", "c-0"]
    return read_geojson(fc, source="junction")


@pytest.fixture(scope="module")
def maps(hamburg_map: HdMap) -> dict[str, HdMap]:
    return {
        "hamburg": hamburg_map,
        "melbourne": read_geojson_file(bundled_map("melbourne-corner")),
        "junction": junction_map(),
    }


@pytest.fixture(scope="module")
def runs(maps: dict[str, HdMap]) -> list[tuple[HdMap, Trace]]:
    out = []
    for hdmap in maps.values():
        for seed in range(3):
            scenario = roam_scenario(hdmap, seed, users=12, duration=90.0)
            out.append((hdmap, simulate(hdmap, scenario, scenario.errors, seed)))
    return out


def _ends(hdmap: HdMap, step: Any) -> tuple[tuple[float, float], tuple[float, float]]:
    """(start, end) of a path step's centre line in its way."""
    coords = list(hdmap.segments[step[0]].lanes[step[1]].centerline.coords)
    if step[2] == "backward":
        coords.reverse()
    return coords[0][:2], coords[-1][:2]


def _chords(hdmap: HdMap, plan: UserPlan) -> list[LineString]:
    """The straight joins of a path where a lane does not start where the one before ends."""
    assert plan.path is not None
    out = []
    for a, b in itertools.pairwise(plan.path):
        end, start = _ends(hdmap, a)[1], _ends(hdmap, b)[0]
        if math.dist(end, start) > 0.5:
            out.append(LineString([end, start]))
    return out


# --- the truth ---------------------------------------------------------------------------


def test_roaming_truth_is_continuous(runs: list[tuple[HdMap, Trace]]) -> None:
    for _hdmap, trace in runs:
        plans = {p.user: p for p in trace.scenario.users}
        by_user: dict[str, list[Any]] = {}
        for fix in trace.fixes:
            by_user.setdefault(fix.user, []).append(fix)
        for user, fixes in by_user.items():
            for f0, f1 in itertools.pairwise(fixes):
                dt = (f1.measurement.timestamp - f0.measurement.timestamp) / 1000.0
                step = math.hypot(f1.true_e - f0.true_e, f1.true_n - f0.true_n)
                assert step <= plans[user].speed * dt + 0.01, (user, f0, f1)


def test_roaming_truth_lies_on_the_named_lane(runs: list[tuple[HdMap, Trace]]) -> None:
    chord_fixes = 0
    for hdmap, trace in runs:
        chords = {p.user: _chords(hdmap, p) for p in trace.scenario.users}
        for fix in trace.fixes:
            point = Point(fix.true_e, fix.true_n)
            segment = hdmap.segments[fix.segment]
            assert segment.area.distance(point) < 0.05, fix
            gap = segment.lanes[fix.lane].centerline.distance(point)
            if gap >= 0.5:  # only on the join of two lanes that do not meet, nearer its lane
                chord = next(c for c in chords[fix.user] if c.distance(point) < 1e-6)
                assert gap <= chord.length / 2.0 + 1e-6, fix
                chord_fixes += 1
    assert chord_fixes < 0.05 * sum(len(t.fixes) for _, t in runs)


def test_roaming_users_follow_successors(runs: list[tuple[HdMap, Trace]]) -> None:
    crossings: Counter[tuple[str, str]] = Counter()
    for hdmap, trace in runs:
        for plan in trace.scenario.users:
            assert plan.path is not None
            for a, b in itertools.pairwise(plan.path):
                assert len(a) == len(b) == 3  # roaming paths name every way
                assert a[2] == b[2]  # these maps need no turn of the way
                if a[2] == "forward":
                    assert b[0] in hdmap.segments[a[0]].successors
                else:
                    assert a[0] in hdmap.segments[b[0]].successors
                crossings[(a[0], b[0])] += 1
            # the fixes visit the path's pieces in its order
            seen = [
                k
                for k, _ in itertools.groupby(f.segment for f in trace.fixes if f.user == plan.user)
            ]
            pieces = iter(step[0] for step in plan.path)
            assert all(any(s == p for p in pieces) for s in seen), (plan.path, seen)
        types = {lane.type for s in hdmap.segments.values() for lane in s.lanes}
        kinds = {p.kind for p in trace.scenario.users}
        assert ("pedestrian" in kinds) <= ("sidewalk" in types)
    # through the junction both ways, into both branches, and backwards on Melbourne
    for pair in [("a-1", "b-0"), ("a-1", "c-0"), ("c-0", "a-1"), ("corner-1", "corner-0")]:
        assert crossings[pair] > 0, pair


def test_roaming_is_seeded(maps: dict[str, HdMap]) -> None:
    hdmap = maps["junction"]
    a, b = roam_scenario(hdmap, 4), roam_scenario(hdmap, 4)
    assert a == b
    assert simulate(hdmap, a, a.errors, 1).fixes == simulate(hdmap, b, b.errors, 1).fixes
    assert roam_scenario(hdmap, 5) != a
    assert a.map == hdmap.source and a.route == () and a.name == "roam-junction-4"
    assert roam_scenario(maps["hamburg"], 0).map == str(bundled_map("messe-hamburg"))


def test_a_map_with_no_lane_to_roam_is_refused() -> None:
    local = track((0.0, 0.0), 0.0, [Straight(100.0)])
    lanes = [LaneSpec("parking", 2.2)]
    hdmap = read_geojson(road_features("p", local_to_lonlat(local, *ORIGIN), lanes))
    with pytest.raises(ConfigError, match="no driving, bicycle or sidewalk lane"):
        roam_scenario(hdmap, 0)


# --- paths by hand -----------------------------------------------------------------------


def _one(hdmap: HdMap, **plan: Any) -> Trace:
    user = UserPlan.model_validate({"user": "u", "kind": "car", "speed": 8.0, "start": 0.0, **plan})
    scenario = Scenario(name="p", map=hdmap.source, route=(), users=(user,), duration=30.0)
    return simulate(hdmap, scenario, scenario.errors, 0)


def test_a_path_crosses_a_junction_and_a_merge(maps: dict[str, HdMap]) -> None:
    hdmap = maps["junction"]
    trace = _one(hdmap, start=72.0, leave=15.0, path=(("a-0", 3), ("a-1", 3), ("b-0", 2)))
    assert [k for k, _ in itertools.groupby((f.segment, f.lane) for f in trace.fixes)] == [
        ("a-0", 3),
        ("a-1", 3),
        ("b-0", 2),
    ]
    # lane 3 of a merges into lane 2 of b across a 3.25 m chord on the elements' shared end:
    # at t = 10 s the car is 152 m along, 2 m into it, past its middle, so on b's lane 2
    on_chord = trace.fixes[10]
    end = hdmap.segments["a-1"].lanes[3].centerline.coords[-1]
    start = hdmap.segments["b-0"].lanes[2].centerline.coords[0]
    assert (on_chord.segment, on_chord.lane) == ("b-0", 2)
    assert math.dist(end, (on_chord.true_e, on_chord.true_n)) == pytest.approx(2.0, abs=0.01)
    assert math.dist(start, (on_chord.true_e, on_chord.true_n)) == pytest.approx(1.25, abs=0.01)
    last = trace.fixes[-1]
    assert (
        hdmap.segments["b-0"].lanes[2].centerline.distance(Point(last.true_e, last.true_n)) < 1e-6
    )
    # and back the other way on the backward lane, round the corner
    trace = _one(hdmap, path=(("c-1", 1), ("c-0", 1), ("a-1", 1), ("a-0", 1)))
    seen = [k for k, _ in itertools.groupby(f.segment for f in trace.fixes)]
    assert seen == ["c-1", "c-0", "a-1", "a-0"]
    assert 170.0 < trace.fixes[-1].true_heading < 190.0  # southwards at the end


def test_a_broken_path_is_refused(maps: dict[str, HdMap]) -> None:
    hdmap = maps["junction"]
    with pytest.raises(ConfigError, match=r"user 'u'.*'b-0'.*'a-0'"):
        _one(hdmap, path=(("a-0", 2), ("b-0", 2)))
    with pytest.raises(ConfigError, match=r"'c-0', lane 2, forward.*'b-0', lane 2, forward"):
        _one(hdmap, path=(("b-0", 2), ("c-0", 2)))
    with pytest.raises(ConfigError, match="runs backward"):
        _one(hdmap, path=(("a-0", 1, "forward"),))
    with pytest.raises(ConfigError, match="'x-0'"):
        _one(hdmap, path=(("x-0", 1),))
    with pytest.raises(ConfigError, match="has 4 lanes"):
        _one(hdmap, path=(("b-0", 4),))
    with pytest.raises(ConfigError, match="runs off the end of its path"):
        _one(hdmap, path=(("b-0", 2),))


@pytest.mark.parametrize(
    "extra",
    [{"lanes": ((0.0, 1),)}, {"reverse": True}, {"along_lane": True}, {"lie": Lie(across=3.0)}],
)
def test_a_path_refuses_what_it_cannot_do(extra: dict[str, Any]) -> None:
    with pytest.raises(ConfigError, match=f"drives a path, so it cannot have {next(iter(extra))}"):
        UserPlan(user="u", kind="car", speed=5.0, start=0.0, path=(("a-0", 2),), **extra)
    with pytest.raises(ConfigError, match="needs `lanes`"):
        UserPlan(user="u", kind="car", speed=5.0, start=0.0)
    with pytest.raises(ConfigError, match="no route"):
        user = UserPlan(user="u", kind="car", speed=5.0, start=0.0, lanes=((0.0, 0),))
        Scenario(name="p", map="m", route=(), users=(user,), duration=10.0)


# --- the engine on a roaming trace -------------------------------------------------------


def test_replay_answers_a_roaming_trace_on_its_lanes(maps: dict[str, HdMap]) -> None:
    hdmap = maps["hamburg"]
    scenario = roam_scenario(hdmap, 1, users=10, duration=100.0)
    trace = simulate(hdmap, scenario, scenario.errors, 1)
    lines = [TraceLine(k, f.user, f.measurement) for k, f in enumerate(trace.fixes, start=1)]
    results = list(replay(hdmap, lines, EngineConfig()))
    assert [r.line for r in results] == [line.line for line in lines]  # every fix answered
    right = sum(
        r.answer.segment == f.segment and r.answer.lane == f.lane
        for r, f in zip(results, trace.fixes, strict=True)
    )
    chance = 1.0 / 4.0  # four lanes on every element
    assert right / len(results) > max(0.8, 3.0 * chance)


def test_scenario_or_roam_is_the_built_in_scenario_or_users_roaming_the_map() -> None:
    """What `laas scenario`, `plot`, `regions` and `simulate` run: `--scenario`, or with
    `--map` users roaming that map."""
    builtin, hdmap = scenario_or_roam("messe-hamburg", seed=3)
    assert builtin.name == "messe-hamburg" and hdmap.source == builtin.map
    path = bundled_map("messe-hamburg")
    roaming, hdmap = scenario_or_roam("messe-hamburg", path, seed=3, users=4, duration=30.0)
    assert roaming.name == "roam-messe-hamburg-3" and len(roaming.users) == 4
    assert roaming == roam_scenario(read_geojson_file(path), 3, users=4, duration=30.0)
