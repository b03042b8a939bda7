"""Simulated road users with ground truth, for evaluation and the demo: the names of
`laas.sim.plan` (what a scenario is), `laas.sim.kinematics` (how its users move),
`laas.sim.simulate` (a run's fixes) and `laas.sim.builtin` (the built-in scenarios), in
one place.
"""

from laas.sim.builtin import SCENARIOS, get_scenario, hamburg_scenario, melbourne_scenario
from laas.sim.kinematics import distance_driven
from laas.sim.plan import (
    EPOCH_MS,
    PATH_JOIN_GAP,
    PATH_SUCCESSOR_GAP,
    ErrorModel,
    Lie,
    PathStep,
    Scenario,
    SimulatedFix,
    Trace,
    UserPlan,
    Way,
)
from laas.sim.simulate import simulate, simulate_with

__all__ = [
    "EPOCH_MS",
    "PATH_JOIN_GAP",
    "PATH_SUCCESSOR_GAP",
    "SCENARIOS",
    "ErrorModel",
    "Lie",
    "PathStep",
    "Scenario",
    "SimulatedFix",
    "Trace",
    "UserPlan",
    "Way",
    "distance_driven",
    "get_scenario",
    "hamburg_scenario",
    "melbourne_scenario",
    "simulate",
    "simulate_with",
]
