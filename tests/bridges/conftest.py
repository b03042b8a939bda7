"""Fixtures of the bridge tests: the Hamburg car's fixes, and the paper's deployment."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from laas.run.deployment import LocalDeployment
from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate


@pytest.fixture(scope="module")
def car(hamburg_map: HdMap) -> list[GpsMeasurement]:
    """The Hamburg scenario's car, one fix a second (its timestamps: shift them)."""
    trace = simulate(hamburg_map, hamburg_scenario(), ErrorModel(), 0)
    return [f.measurement for f in trace.fixes if f.user == "car"]


@pytest.fixture(scope="module")
def deployment(hamburg_map: HdMap) -> Iterator[LocalDeployment]:
    """Three brokers (Mosquitto if installed), two cores and the worker, anonymous."""
    with LocalDeployment(hamburg_map) as d:
        yield d
