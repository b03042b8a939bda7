"""The lane filters on constructed cases: the paper's joint hypotheses and the transitions."""

from __future__ import annotations

import numpy as np
import pytest

from laas.engine.paper import JointHypothesisFilter
from laas.engine.transition import direction_likelihood, lane_transition

OFFSETS = np.array([0.0, 3.25, 5.975, 7.975])
NORMAL = np.array([1.0, 0.0])  # the road runs north; lanes increase to the east


def _placed(d: float) -> np.ndarray:
    """(L, 2): a user at lateral d placed on each lane (at northing 0)."""
    placed: np.ndarray = np.outer(OFFSETS - d, NORMAL) + np.array([d, 0.0])
    return placed


def test_joint_filter_picks_the_hypothesis_matching_relative_positions() -> None:
    jf = JointHypothesisFilter(4, 1 << 20)
    stay = lane_transition(OFFSETS, 0.0, 1.0, 0.01, 0.45)
    ones = np.ones(4)
    # True lanes 0 and 3, both fixes shifted 1 m to the west by a common error.
    positions = {"a": np.array([OFFSETS[0] - 1.0, 0.0]), "b": np.array([OFFSETS[3] - 1.0, 5.0])}
    for u in positions:
        jf.add(u)
    assert jf.hypotheses == 16
    for _ in range(3):
        for u in ("a", "b"):
            placed = {v: _placed(p[0]) + np.array([0, p[1]]) for v, p in positions.items()}
            lane, prob = jf.step(u, stay, ones, placed, positions, {"a": 0.3, "b": 0.3})
    winner = np.unravel_index(int(np.argmax(jf.belief)), jf.belief.shape)
    assert tuple(int(x) for x in winner) == (0, 3)
    assert lane == 3 and prob > 0.9


def test_users_joining_and_leaving_keep_what_is_known() -> None:
    jf = JointHypothesisFilter(3, 1 << 20)
    jf.add("a", np.array([0.8, 0.1, 0.1]))
    jf.add("b")
    np.testing.assert_allclose(jf.marginal("a"), [0.8, 0.1, 0.1])
    out = jf.remove("b")
    np.testing.assert_allclose(out, [1 / 3] * 3)
    np.testing.assert_allclose(jf.marginal("a"), [0.8, 0.1, 0.1])
    assert jf.users == ["a"]


def test_users_past_the_hypothesis_cap_are_solo() -> None:
    jf = JointHypothesisFilter(4, 4**3)
    for u in "abcd":
        jf.add(u)
    assert jf.users == ["a", "b", "c"] and "d" in jf.solo
    assert jf.hypotheses == 64


def test_heading_across_the_lanes_predicts_a_lane_change_to_that_side() -> None:
    aligned = lane_transition(OFFSETS, 0.0, 1.0, 0.01, 0.45)
    assert aligned[1, 1] > 0.97
    rightwards = lane_transition(OFFSETS, 1.2, 1.0, 0.01, 0.45)  # 1.2 m/s to the right
    assert rightwards[1, 2] > 0.4 > rightwards[1, 0]
    leftwards = lane_transition(OFFSETS, -1.2, 1.0, 0.01, 0.45)
    assert leftwards[1, 0] > 0.3 > leftwards[1, 2]
    np.testing.assert_allclose(rightwards.sum(axis=1), 1.0)
    # The prediction moves belief toward the heading's side.
    belief = np.array([0.0, 1.0, 0.0, 0.0]) @ rightwards
    assert belief[2] > 0.4 and belief[0] < 0.02


def test_prediction_on_a_lane_change_in_the_joint_filter() -> None:
    jf = JointHypothesisFilter(4, 1 << 20)
    jf.add("a", np.array([0.0, 1.0, 0.0, 0.0]))
    turn = lane_transition(OFFSETS, 2.0, 1.0, 0.01, 0.45)
    lane, prob = jf.step("a", turn, np.ones(4), {}, {}, {})
    assert jf.marginal("a")[2] == pytest.approx(0.45, abs=0.01)
    assert lane == 1 and prob == pytest.approx(0.55 - 0.01, abs=0.02)


def test_wrong_way_lanes_are_unlikely_for_moving_users_only() -> None:
    dirs = ("backward", "forward", "both")
    np.testing.assert_allclose(direction_likelihood(dirs, 8.0), [0.05, 1.0, 1.0])
    np.testing.assert_allclose(direction_likelihood(dirs, -8.0), [1.0, 0.05, 1.0])
    np.testing.assert_allclose(direction_likelihood(dirs, 0.5), [1.0, 1.0, 1.0])
