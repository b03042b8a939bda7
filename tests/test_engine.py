"""The engine end to end on a map that is not Hamburg, in both modes."""

from __future__ import annotations

import numpy as np
import pytest

from laas.config import EngineConfig, Mode
from laas.engine.engine import Engine
from laas.map.geojson import read_geojson
from laas.map.hdmap import HdMap
from laas.map.mapgen import LaneSpec, local_to_lonlat, road_features
from laas.models import GpsMeasurement

from .helpers import T0, fix_on, small_map


@pytest.fixture(scope="module")
def sydney() -> HdMap:
    return small_map()


@pytest.mark.parametrize("mode", ["default", "paper"])
def test_group_with_a_common_error_is_placed_on_its_true_lanes(sydney: HdMap, mode: Mode) -> None:
    seg = sydney.segments["r-0"]
    rng = np.random.default_rng(1)
    engine = Engine(sydney, EngineConfig(mode=mode, sigma_pos=0.3))
    # A pedestrian on the sidewalk, a car forward, a cyclist on the bicycle lane; the
    # common error pushes everyone 1.2 m across the road and 2 m along it.
    lanes = {"walker": 0, "car": 2, "bike": 3}
    speeds = {"walker": 1.4, "car": 6.0, "bike": 5.0}
    starts = {"walker": 60.0, "car": 40.0, "bike": 50.0}
    seen: dict[str, list[int | None]] = {u: [] for u in lanes}
    for k in range(12):
        for j, (user, lane) in enumerate(lanes.items()):
            s = starts[user] + speeds[user] * k
            t = seg.tangent(s)
            bias = 1.2 * np.array([t[1], -t[0]]) + 2.0 * t  # across (to the right) and along
            m = fix_on(
                sydney,
                seg,
                s,
                lane,
                T0 + k * 1000 + j * 10,
                bias=(float(bias[0] + rng.normal(0, 0.2)), float(bias[1] + rng.normal(0, 0.2))),
                speed=speeds[user],
            )
            answer = engine.process(user, m)
            assert answer is not None and answer.segment == "r-0"
            seen[user].append(answer.lane)
    for user, lane in lanes.items():
        assert seen[user][-6:] == [lane] * 6, (user, seen[user])
    assert engine.stats.answered == 36


def test_default_mode_learns_the_common_error_across_two_road_directions() -> None:
    hdmap = small_map(turn=90.0)
    engine = Engine(hdmap, EngineConfig(sigma_pos=0.3))
    bias = np.array([3.0, -2.0])
    route = [("r-0", s) for s in np.arange(5.0, 150.0, 6.0)]
    route += [("r-1", s) for s in np.arange(2.0, hdmap.segments["r-1"].length, 6.0)]
    route += [("r-2", s) for s in np.arange(2.0, 150.0, 6.0)]
    errors, widest = [], []
    for k, (sid, s) in enumerate(route):
        seg = hdmap.segments[sid]
        for j, lane in enumerate((2, 3)):  # the forward driving and bicycle lanes
            m = fix_on(hdmap, seg, float(s), lane, T0 + k * 1000 + j, bias=(3.0, -2.0), speed=6.0)
            engine.process(f"u{lane}", m)
        area = engine.common_errors()[0]
        errors.append(area.b - bias)
        widest.append(float(np.sqrt(np.linalg.eigvalsh(area.P)[-1])))
    # Along the first straight only the cross-road part is known; after the corner, both.
    sids = [sid for sid, _ in route]
    on_r1, on_r2 = sids.index("r-1"), sids.index("r-2")
    assert widest[on_r1 - 2] > 9.0  # r-0 taught only its own cross-road part (its last
    # fix, at the corner, starts to teach the rest)
    assert np.hypot(*errors[-1]) < 0.5
    assert min(widest[on_r2:]) < 0.7
    # r-2 teaches only its own cross-road part; what r-0 and the corner taught about the
    # rest fades over evidence_memory (30 s), and the covariance says so: 0.6 m after the
    # corner, 1.0 m 25 s later (0.66 m if nothing faded)
    assert widest[-1] < 1.2


def test_off_map_duplicates_and_stale_fixes(sydney: HdMap) -> None:
    engine = Engine(sydney)
    seg = sydney.segments["r-0"]
    first = fix_on(sydney, seg, 20.0, 2, T0)
    assert engine.process("a", first) is not None
    assert engine.process("a", first) is None
    assert engine.process("a", fix_on(sydney, seg, 20.0, 2, T0 - 500)) is None
    assert (engine.stats.duplicate, engine.stats.out_of_order) == (1, 1)
    far = GpsMeasurement(
        timestamp=T0 + 1000, latitude=-33.0, longitude=151.0, heading=0.0, speed=0.0
    )
    answer = engine.process("b", far)
    assert answer is not None and answer.segment is None and answer.lane is None
    assert engine.stats.off_map == 1


def test_expiry_and_forget_free_the_state(sydney: HdMap) -> None:
    engine = Engine(sydney, EngineConfig(track_timeout=5.0))
    seg = sydney.segments["r-0"]
    engine.process("a", fix_on(sydney, seg, 20.0, 2, T0))
    engine.process("b", fix_on(sydney, seg, 30.0, 3, T0 + 4000))
    assert engine.users == 2
    assert engine.expire(T0 + 6000) == ["a"]
    engine.forget("b")
    assert engine.users == 0


def test_distant_users_get_common_errors_of_their_own_areas() -> None:
    from laas.engine.common_error import CommonErrorField

    field = CommonErrorField(2_000.0, 10.0, 0.05, 0.5)
    here = field.at(np.array([500_000.0, 5_900_000.0]))
    assert field.at(np.array([500_900.0, 5_900_300.0])) is here  # within size / 2
    there = field.at(np.array([503_000.0, 5_900_000.0]))
    assert there is not here
    assert field.at(np.array([502_400.0, 5_900_100.0])) is there  # nearest centre wins
    assert len(field.areas) == 2


def test_a_fast_car_is_not_placed_on_a_footway_beside_its_road() -> None:
    """A footway drawn as its own element 6 m beside a road (as OpenStreetMap draws
    them): a car's first fixes, 6 m off towards the footway, fall on the footway, and the
    common error is not known yet. A car at 12 m/s fits the road's lanes, not the footway,
    so the engine places it on the road (where taking the footway would also have pulled
    the common error 6 m the wrong way)."""
    origin = (10.0, 53.5)
    road = road_features(
        "road",
        local_to_lonlat([(0.0, 0.0), (300.0, 0.0)], *origin),
        (LaneSpec("driving", 3.25, "backward"), LaneSpec("driving", 3.25, "forward")),
    )
    foot = road_features(
        "foot",
        local_to_lonlat([(0.0, -10.0), (300.0, -10.0)], *origin),
        (LaneSpec("sidewalk", 2.0, "both"),),
    )
    hdmap = read_geojson(
        {"type": "FeatureCollection", "features": road["features"] + foot["features"]}
    )
    lane = hdmap.segments["road-0"]
    answers = []
    for mode in ("default", "paper"):
        engine = Engine(hdmap, EngineConfig(mode=mode))
        answers.append(
            [
                engine.process(
                    "car",
                    fix_on(hdmap, lane, 20.0 + 12.0 * k, 1, T0 + 1000 * k, lateral=6.0, speed=12.0),
                )
                for k in range(5)
            ]
        )
    default, paper = answers
    assert all(a is not None and a.segment == "road-0" for a in default)
    assert paper[0] is not None and paper[0].segment == "foot-0"  # paper mode: as located
