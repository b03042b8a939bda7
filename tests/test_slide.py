"""The slide: one user's lane change must not move the common error, and the group, a lane over.

The road and users of the failure that issue 10 reports: four lanes (driving, driving,
bicycle, sidewalk), a long straight and a 75 degree curve in UTM zone 17, two cars, two
cyclists and a pedestrian with small receiver biases, a common error of 6-12 m in a random
direction that drifts, sigma_pos 1 m. A car and a cyclist change lanes and back; everybody
else keeps theirs. The engine before the joint estimate placed these users right 0.89 of the
time on seeds 0-5 (0.75 at worst); the thresholds sit below what it does now (0.93, 0.86).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from laas import EngineConfig, HdMap
from laas.evaluation.score import answer_trace
from laas.map.geojson import read_geojson
from laas.map.mapgen import Curve, LaneSpec, Straight, local_to_lonlat, road_features, track
from laas.sim.scenario import ErrorModel, Scenario, UserPlan, simulate

LANES = (
    LaneSpec("driving", 3.25, "forward"),
    LaneSpec("driving", 3.25, "forward"),
    LaneSpec("bicycle", 1.8, "forward"),
    LaneSpec("sidewalk", 2.5, "both"),
)
USERS = (
    UserPlan(user="car-a", kind="car", speed=9.0, start=200.0, lanes=((0, 0),), bias=(0.3, -0.4)),
    UserPlan(
        user="car-b",
        kind="car",
        speed=9.5,
        start=170.0,
        lanes=((0, 1), (25, 0), (40, 1)),
        phase=0.2,
        bias=(-0.5, 0.2),
    ),
    UserPlan(
        user="bike-a", kind="cyclist", speed=5.0, start=150.0, lanes=((0, 2),), bias=(0.6, 0.3)
    ),
    UserPlan(
        user="bike-b",
        kind="cyclist",
        speed=6.0,
        start=120.0,
        lanes=((0, 2), (50, 1), (60, 2)),
        bias=(-0.2, -0.6),
    ),
    UserPlan(
        user="walker", kind="pedestrian", speed=1.4, start=160.0, lanes=((0, 3),), bias=(0.4, 0.4)
    ),
)


@pytest.fixture(scope="module")
def road() -> HdMap:
    local = track((0.0, 0.0), 35.0, [Straight(700.0), Curve(40.0, 75.0), Straight(300.0)])
    curve = 40.0 * math.radians(75.0)
    data = road_features(
        "toronto", local_to_lonlat(local, -79.38, 43.65), LANES, split_at=(700.0, 700.0 + curve)
    )
    return read_geojson(data, source="toronto")


def _lane_accuracy(road: HdMap, seed: int) -> float:
    rng = np.random.default_rng(seed + 100)
    angle, size = rng.uniform(0.0, 2.0 * math.pi), rng.uniform(6.0, 12.0)
    errors = ErrorModel(
        bias_east=size * math.cos(angle),
        bias_north=size * math.sin(angle),
        bias_drift=0.1,
        sigma_pos=1.0,
        heading_per_speed=8.0,
    )
    scenario = Scenario(
        name="slide", map="toronto", route=tuple(road.segments), users=USERS, duration=80.0
    )
    trace = simulate(road, scenario, errors, seed)
    answers = answer_trace(road, trace, EngineConfig(sigma_pos=1.0, sigma_heading=0.05))
    return float(
        np.mean(
            [a is not None and a.lane == f.lane for f, a in zip(trace.fixes, answers, strict=True)]
        )
    )


def test_a_lane_change_does_not_slide_the_group(road: HdMap) -> None:
    accuracy = [_lane_accuracy(road, seed) for seed in range(6)]
    assert min(accuracy) >= 0.8, accuracy
    assert float(np.mean(accuracy)) >= 0.9, accuracy
