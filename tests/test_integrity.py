"""Integrity: lanes scored by geometry, the confidence figures, the calibration map, and
the engine's answers against them on a drawn road."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from laas.engine.calibration import KNOTS, calibrate
from laas.evaluation.integrity import IntegrityTally, lane_holds, run_interval
from laas.evaluation.score import score
from laas.evaluation.suite import simulate_case
from laas.models import CorrectedPosition
from laas.sim.family import MAP_FAMILIES, build_case
from laas.sim.scenario import Trace


def _truth_answers(case_map, trace: Trace) -> list[CorrectedPosition | None]:
    """Every fix answered with its own truth: segment, lane and position."""
    proj = case_map.projection
    out: list[CorrectedPosition | None] = []
    for f in trace.fixes:
        lon, lat = proj.to_wgs84(f.true_e, f.true_n)
        out.append(
            CorrectedPosition(
                timestamp=f.measurement.timestamp,
                latitude=lat,
                longitude=lon,
                segment=f.segment,
                lane=f.lane,
                lane_type=case_map.segments[f.segment].lanes[f.lane].type,
                probability=1.0,
                accuracy=0.1,
                accuracy_cross=0.1,
                accuracy_along=0.1,
            )
        )
    return out


@pytest.mark.parametrize("family", ["urban", "edge", *MAP_FAMILIES])
def test_a_perfect_answer_scores_one_on_every_map(family: str) -> None:
    case, trace = simulate_case(family, 0, 1.0)
    result = score(case.hdmap, trace, _truth_answers(case.hdmap, trace))
    assert result.accuracy == 1.0 and result.accuracy_id == 1.0
    assert result.integrity.wrong_90 == 0
    assert result.aed < 1e-6


def test_the_true_position_lies_in_its_own_lane_and_not_beside_it() -> None:
    case, trace = simulate_case("edge", 3, 1.0)
    hdmap = case.hdmap
    own = beside = 0
    for f in trace.fixes:
        own += lane_holds(hdmap, f.segment, f.lane, f.true_e, f.true_n)
        lanes = len(hdmap.segments[f.segment].lanes)
        other = f.lane + 1 if f.lane + 1 < lanes else f.lane - 1
        beside += lane_holds(hdmap, f.segment, other, f.true_e, f.true_n)
    n = len(trace.fixes)
    # only a lane change puts the truth across its lane's edge for a moment
    assert own >= 0.97 * n
    assert beside <= 0.03 * n
    assert not lane_holds(hdmap, "no-such-segment", 0, 0.0, 0.0)


def test_the_id_score_stays_beside_the_geometric_one() -> None:
    """An answer on the next element of the same lane is right by geometry, not by id."""
    case, trace = simulate_case("edge", 1, 1.0)
    hdmap = case.hdmap
    answers = _truth_answers(hdmap, trace)
    moved = 0
    for i, (f, a) in enumerate(zip(trace.fixes, answers, strict=True)):
        seg = hdmap.segments[f.segment]
        s, _ = seg.frame(f.true_e, f.true_n)
        nxt = seg.successors[0] if seg.successors else None
        if a is not None and nxt is not None and seg.length - s < 0.5:
            answers[i] = a.model_copy(update={"segment": nxt})
            moved += 1
    assert moved > 0
    result = score(hdmap, trace, answers)
    assert result.accuracy == 1.0
    assert result.accuracy_id == pytest.approx(1.0 - moved / len(trace.fixes))


def test_the_tally_counts_confident_and_wrong_answers_and_the_calibration_error() -> None:
    tally = IntegrityTally()
    for p, right in [(0.95, True)] * 8 + [(0.95, False)] * 2 + [(0.55, True)] * 5:
        tally.add_answer(p, right)
    tally.add_errors(
        np.array([0.1, 0.5, 3.0]), np.array([0.0, 2.0, 9.0]), np.full(3, 0.4), np.full(3, 1.5)
    )
    both = (tally + tally).summary()
    assert both.answers == 30
    assert both.wrong_90 == pytest.approx(4 / 30)
    assert both.said_90 == pytest.approx(20 / 30)
    # bins: 0.95 said, 0.8 right (10 answers); 0.55 said, 1.0 right (5)
    assert both.ece == pytest.approx((10 * 0.15 + 5 * 0.45) / 15)
    assert [both.cross_1, both.cross_2] == pytest.approx([1 / 3, 2 / 3])
    assert [both.along_1, both.along_2] == pytest.approx([1 / 3, 2 / 3])
    assert math.isnan(IntegrityTally().summary().ece)


def test_the_interval_over_runs_is_wide_when_one_run_holds_the_wrong_answers() -> None:
    """The same pooled share (1 %), spread over every run or held by one run of 20: the
    first is as sure as its runs agree, the second could be 0 on another sample."""
    spread = [IntegrityTally(answers=100, wrong_90=1) for _ in range(20)]
    one = [IntegrityTally(answers=100, wrong_90=20 if k == 0 else 0) for k in range(20)]
    assert IntegrityTally.total(spread).summary().wrong_90 == pytest.approx(0.01)
    assert IntegrityTally.total(one).summary().wrong_90 == pytest.approx(0.01)
    assert run_interval(spread) == pytest.approx((0.01, 0.01))
    lo, hi = run_interval(one)
    assert lo == 0.0  # a third of the resamples lack the one run: (19/20)^20 = 0.36
    assert 0.02 <= hi <= 0.04  # its copies in a resample: Binomial(20, 1/20), 95th percentile 3
    assert all(math.isnan(x) for x in run_interval([IntegrityTally()]))


def test_the_calibration_map_is_monotone_and_keeps_probabilities_probabilities() -> None:
    xs = [x for x, _ in KNOTS]
    ys = [y for _, y in KNOTS]
    assert xs[0] == 0.0 and xs[-1] == 1.0
    assert all(a <= b for a, b in itertools.pairwise(xs))
    assert all(a <= b for a, b in itertools.pairwise(ys))
    assert all(0.0 <= y <= 1.0 for y in ys)
    grid = np.linspace(0.0, 1.0, 101)
    g = [calibrate(float(p)) for p in grid]
    assert all(a <= b + 1e-12 for a, b in itertools.pairwise(g))


def test_one_user_alone_is_not_sure_of_its_lane_and_its_accuracy_says_so() -> None:
    """A single pedestrian between two sidewalks: the common error across the road is
    unobservable, so the answers say so (a low probability, a wide accuracy across)."""
    case = build_case("urban", 1)
    assert len(case.scenario.users) == 1
    from laas.engine import Engine
    from laas.evaluation.suite import engine_config

    _, trace = simulate_case("urban", 1, 1.0)
    engine = Engine(case.hdmap, engine_config("default", 1.0))
    answers = [engine.process(f.user, f.measurement) for f in trace.fixes]
    placed = [a for a in answers if a is not None and a.lane is not None]
    assert placed
    assert max(a.probability for a in placed) < 0.9
    assert min(a.accuracy_cross for a in placed) > 1.0
