"""A foreign set (`laas.sim.foreign`): recorded roads read back as traces and scored as a suite.

The set is made here from the project's own simulator, written as `laas scenario` writes
a run, so the test needs no folder outside the repository.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from laas.errors import ConfigError, TraceError
from laas.evaluation.suite import foreign_suite, get_suite, run_suite
from laas.map.bundled import bundled_map
from laas.map.geojson import read_geojson_file
from laas.sim.foreign import find_roads, load_road
from laas.sim.plan import SimulatedFix
from laas.sim.scenario import Trace, get_scenario, simulate_with
from laas.sim.truth import write_run


def _write_set(root: Path) -> Trace:
    scenario = get_scenario("messe-hamburg")
    hdmap = read_geojson_file(scenario.map)
    trace = simulate_with(hdmap, scenario, 3, sigma_pos=1.0, sigma_vel=0.25)
    road = root / "sigma1" / "7"
    write_run(trace, hdmap.projection.epsg, road)
    shutil.copy(bundled_map("messe-hamburg"), road / "map.geojson")
    return trace


def test_a_recorded_road_reads_back_with_its_truth_and_the_oracles_common_error(tmp_path):
    trace = _write_set(tmp_path)
    (road,) = find_roads(tmp_path)
    assert (road.road, road.sigma_pos) == (7, 1.0)
    _, foreign = load_road(road)
    assert len(foreign.fixes) == len(trace.fixes)
    by_key = {(f.user, f.measurement.timestamp): f for f in trace.fixes}
    drawn = np.array(
        [
            (f.common_e, f.common_n, *_true(by_key[(f.user, f.measurement.timestamp)]))
            for f in foreign.fixes
        ]
    )
    read = np.array([(f.common_e, f.common_n, f.true_e, f.true_n) for f in foreign.fixes])
    assert np.allclose(read[:, 2:], drawn[:, 2:], atol=1e-6)  # the truth, as written
    # the oracle's estimate of the common error: the mean fix error within 5 s, within a
    # metre of the error the simulator drew, where the drawn error is several metres
    miss = np.hypot(*(read[:, :2] - drawn[:, :2]).T)
    assert np.hypot(*drawn[:, :2].T).mean() > 3.0
    assert np.median(miss) < 1.0


def _true(fix: SimulatedFix) -> tuple[float, float]:
    return fix.true_e, fix.true_n


def test_the_foreign_suite_scores_a_road_three_ways(tmp_path):
    _write_set(tmp_path)
    suite = get_suite("foreign", tmp_path)
    assert suite.jobs() == [("foreign", 7, 1.0)]
    (row,) = run_suite(suite, workers=1)
    assert row.users == 3 and row.fixes > 100
    assert {m: s.error for m, s in row.methods.items()} == {
        "default": None,
        "paper": None,
        "oracle": None,
    }
    # the Hamburg scenario's three users: default mode finds their lanes
    assert row.methods["default"].accuracy_id > 0.9
    assert row.methods["default"].integrity.answers == row.methods["default"].answered


def test_a_missing_or_empty_set_is_refused_by_name(tmp_path):
    with pytest.raises(TraceError, match="no such folder"):
        foreign_suite(tmp_path / "nowhere")
    with pytest.raises(TraceError, match="no roads found"):
        foreign_suite(tmp_path)
    with pytest.raises(ConfigError, match="--foreign DIR"):
        get_suite("foreign", None)
