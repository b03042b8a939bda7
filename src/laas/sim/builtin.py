"""The built-in scenarios: the paper's Hamburg test road and a Melbourne corner."""

from __future__ import annotations

from laas.errors import ConfigError
from laas.map.bundled import bundled_map
from laas.sim.plan import ErrorModel, Scenario, UserPlan

__all__ = ["SCENARIOS", "get_scenario", "hamburg_scenario", "melbourne_scenario"]


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
