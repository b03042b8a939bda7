"""Lane accuracy and integrity on random roads: the `ci` suite (dev seeds 0-5 of each
family, sigma_pos 1 and 2.5) must not fall below what the engine measured when these
thresholds were set.

The thresholds sit a little below the figures `laas evaluate --suite ci` printed then (in
the comments), so that a regression fails here and a change of the model that moves them
is a decision, recorded by moving them. These are in-sample checks: the `ci` suite is
dev seeds, which the calibration was fitted on, so they guard against regressions and
are not the claims. The claims (README, docs/evaluation.md) come from the held-out
suite (`laas evaluate --suite heldout`), which is never run here.
"""

from __future__ import annotations

import pytest

from laas.evaluation.suite import Summary, summarize
from tests.ci_suite import CiSuite

# What `laas evaluate --suite ci` printed when these were set (the lane evidence from the
# fix itself, P(on the element) in the probability, integrity scored by (segment, lane)
# id, the calibration refitted on all of dev; the families with receivers whose course is
# the road's): default mode's median lane accuracy 0.904 at sigma_pos 1 and 0.832 at 2.5
# (the landed engine on the same traces: 0.871 and 0.808); 1 + 1 of 48 runs more than
# 0.05 below paper mode.
ACC_MEDIAN_1 = 0.89
ACC_MEDIAN_25 = 0.82
BELOW_PAPER = 3
# Integrity, every answer pooled: said >= 0.9 and wrong 2.49 % (sigma_pos 1) and 2.00 %
# (2.5) of all answers (the landed engine: 4.41 % and 3.40 %); ECE 0.027 and 0.019 (0.060
# and 0.053; seeds 0-5 are among dev's hardest: on all 40 dev seeds the calibration leaves
# 0.005 and 0.005); 2 + 0 of 48 runs with an AED above the raw fixes'; errors across the
# road within twice accuracy_cross 0.97 and 0.97.
WRONG_90 = 0.027
ECE = 0.03
WORSE_THAN_RAW = 2
CROSS_2 = 0.93


@pytest.fixture(scope="module")
def overall(ci_suite: CiSuite) -> dict[float, Summary]:
    rows = ci_suite.rows
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


def test_default_mode_is_rarely_confident_and_wrong(overall: dict[float, Summary]) -> None:
    for s in overall.values():
        g = s.integrity["default"]
        assert g.wrong_90 <= WRONG_90, (s.sigma_pos, g.wrong_90)
        assert g.ece <= ECE, (s.sigma_pos, g.ece)
        assert g.cross_2 >= CROSS_2, (s.sigma_pos, g.cross_2)


def test_default_mode_is_rarely_further_from_the_truth_than_the_raw_fixes(
    overall: dict[float, Summary],
) -> None:
    assert sum(s.worse_than_raw["default"] for s in overall.values()) <= WORSE_THAN_RAW
