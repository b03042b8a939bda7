"""Lane accuracy on random roads: the `ci` suite (dev seeds 0-7 of each family, sigma_pos 1
and 2.5) must not fall below what the engine measured when these thresholds were set.

The thresholds sit a little below the figures `laas evaluate --suite ci` printed then (in
the comments), so that a regression fails here and a change of the model that moves them
is a decision, recorded by moving them. The held-out suite is never run here.
"""

from __future__ import annotations

import pytest

from laas.sim.suite import Summary, get_suite, run_suite, summarize

# What `laas evaluate --suite ci` printed when these were set (commit of the fitted
# constants): default mode's median lane accuracy 0.904 at sigma_pos 1 and 0.862 at 2.5;
# 3 of 48 runs more than 0.05 below paper mode.
ACC_MEDIAN_1 = 0.88
ACC_MEDIAN_25 = 0.83
BELOW_PAPER = 4


@pytest.fixture(scope="module")
def overall() -> dict[float, Summary]:
    rows = run_suite(get_suite("ci"), workers=2)
    assert all(m.error is None for r in rows for m in r.methods.values())
    return {s.sigma_pos: s for s in summarize(rows) if s.family == "all"}


def test_default_mode_keeps_its_lane_accuracy_on_random_roads(
    overall: dict[float, Summary],
) -> None:
    one, two = overall[1.0], overall[2.5]
    assert one.accuracy_median["default"] >= ACC_MEDIAN_1, one.accuracy_median
    assert two.accuracy_median["default"] >= ACC_MEDIAN_25, two.accuracy_median
    for s in (one, two):
        assert s.accuracy_median["default"] > s.accuracy_median["paper"] + 0.2
        assert s.aed_median["default"] < s.aed_median["paper"]


def test_default_mode_rarely_falls_below_paper_mode(overall: dict[float, Summary]) -> None:
    assert sum(s.default_below_paper for s in overall.values()) <= BELOW_PAPER


def test_the_oracle_shows_what_the_common_error_is_worth(overall: dict[float, Summary]) -> None:
    assert overall[1.0].accuracy_median["oracle"] >= 0.9
