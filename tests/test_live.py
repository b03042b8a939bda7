"""LaaS end to end through the paper's three-broker deployment, against offline replay."""

from __future__ import annotations

import pytest

from laas.config import EngineConfig
from laas.errors import ConfigError
from laas.evaluation.score import answer_trace, score
from laas.map.bundled import bundled_map
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.run.deployment import LocalDeployment
from laas.run.participants import run_participants
from laas.sim.roam import roam_scenario
from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate
from ldm.local.brokers import BrokerKind
from ldm.local.pytest_plugin import broker_kind

from .helpers import small_map

__all__ = ["broker_kind"]

CONFIG = EngineConfig(sigma_pos=1.0, sigma_vel=0.25, sigma_heading=0.05)


@pytest.mark.parametrize(
    "rotation_period",
    [pytest.param(1e6, id="rotation-off"), pytest.param(120.0, id="rotation-default")],
)
def test_live_accuracy_matches_offline_replay(
    hamburg_map: HdMap, broker_kind: BrokerKind, rotation_period: float
) -> None:
    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    offline = score(hamburg_map, trace, answer_trace(hamburg_map, trace, CONFIG))
    with LocalDeployment(
        hamburg_map, CONFIG, brokers=broker_kind, rotation_period=rotation_period
    ) as deployment:
        live = run_participants(deployment.user_url, trace, speedup=20.0, **deployment.trust)
        assert deployment.service is not None
        assert deployment.service.stats.answered == len(trace.fixes)
    assert live.errors == []
    assert live.answered == len(trace.fixes)
    online = score(hamburg_map, trace, live.answers)
    # The same engine and the same batching rule (`laas.sim.batches`): measured
    # identical (0.9802 both, every run seen). The live worker's batches are what waited
    # in its queue, so a loaded machine may cut one differently: at most 3 of the 303
    # fixes on another lane.
    moved = abs(online.accuracy - offline.accuracy) * len(trace.fixes)
    assert moved <= 3.0 + 1e-9, (online.accuracy, offline.accuracy)
    assert online.accuracy > 0.9


def test_rotation_costs_little_accuracy(hamburg_map: HdMap) -> None:
    """Pseudonyms rotating every 1.5 s (30 s of the scenario at 20x): a rotated user is
    a new track to the worker, but the common error carries the group over."""
    scenario = hamburg_scenario()
    trace = simulate(hamburg_map, scenario, scenario.errors, seed=4)
    offline = score(hamburg_map, trace, answer_trace(hamburg_map, trace, CONFIG))
    with LocalDeployment(
        hamburg_map, CONFIG, brokers="embedded", rotation_period=1.5
    ) as deployment:
        live = run_participants(deployment.user_url, trace, speedup=20.0, **deployment.trust)
        assert deployment.cores["user"].stats.rotations > 0  # pseudonyms did rotate
    assert live.answered == len(trace.fixes), live.errors[:3]
    online = score(hamburg_map, trace, live.answers)
    # measured: no cost here (0.9802 both); the README quotes 0.029 for the bench's 20
    # users rotating every 10 s
    assert online.accuracy >= offline.accuracy - 0.03, (online.accuracy, offline.accuracy)


def test_a_worker_process_needs_a_map_file() -> None:
    with pytest.raises(ConfigError, match="is not one"):
        LocalDeployment(small_map(), worker_process=True)  # built in memory


@pytest.mark.parametrize("name", ["karlsruhe", "fabriksgatan"])
def test_the_live_worker_answers_on_imported_maps(name: str) -> None:
    """Users roaming a map imported from Lanelet2 (Karlsruhe) or OpenDRIVE (fabriksgatan),
    through the three-broker deployment, answered as offline replay answers them."""
    hdmap = read_geojson_file(bundled_map(name))
    errors = ErrorModel(bias_east=1.0, bias_north=-1.5, sigma_pos=1.0, sigma_vel=0.25)
    scenario = roam_scenario(hdmap, seed=2, users=6, duration=30.0, errors=errors)
    trace = simulate(hdmap, scenario, scenario.errors, seed=2)
    assert len(trace.fixes) > 40
    offline = score(hdmap, trace, answer_trace(hdmap, trace, CONFIG))
    with LocalDeployment(hdmap, CONFIG, brokers="embedded") as deployment:
        live = run_participants(deployment.user_url, trace, speedup=20.0, **deployment.trust)
    assert live.errors == [] and live.answered == len(trace.fixes)
    online = score(hdmap, trace, live.answers)
    # measured identical on a quiet machine; a loaded one cuts the live batches
    # differently (as above): at most 3 answers of the run on another lane (fabriksgatan's
    # 92 fixes: 2 answers, 0.022, in one run of the test command beside a busy core)
    moved = abs(online.accuracy - offline.accuracy) * len(trace.fixes)
    assert moved <= 3.0 + 1e-9, (online.accuracy, offline.accuracy, len(trace.fixes))
