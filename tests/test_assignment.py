"""The scalable joint lane search returns what exhaustive enumeration returns."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from laas.engine.assignment import best_assignment, enumerate_assignments


@settings(max_examples=400, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 6), lanes=st.integers(1, 5))
def test_sweep_equals_enumeration_on_random_cases(seed: int, n: int, lanes: int) -> None:
    rng = np.random.default_rng(seed)
    offsets = np.cumsum(rng.uniform(1.2, 3.6, lanes))[None, :] + rng.normal(0, 0.2, (n, lanes))
    d = rng.uniform(-4.0, 16.0, n)
    sigma = rng.uniform(0.15, 2.0, n)
    log_prior = np.log(rng.dirichlet(np.ones(lanes), size=n))
    mu, tau = float(rng.normal(0, 2)), float(rng.uniform(0.05, 12.0))
    fast = best_assignment(d, offsets, sigma, log_prior, mu, tau)
    slow = enumerate_assignments(d, offsets, sigma, log_prior, mu, tau)
    assert fast.cost == pytest.approx(slow.cost, abs=1e-8)
    # Same assignment unless two assignments tie (then the costs above agree).
    if not np.array_equal(fast.lanes, slow.lanes):
        others = enumerate_assignments(d, offsets, sigma, log_prior, mu, tau)
        assert others.cost == pytest.approx(fast.cost, abs=1e-8)
    assert fast.delta == pytest.approx(slow.delta, abs=1e-6) or not np.array_equal(
        fast.lanes, slow.lanes
    )
    np.testing.assert_allclose(fast.marginals.sum(axis=1), 1.0)


def test_group_shifted_by_a_common_error_is_placed_on_its_true_lanes() -> None:
    offsets = np.tile([0.0, 3.25, 5.975, 7.975], (3, 1))
    true = np.array([0, 2, 3])
    d = offsets[0, true] + 1.4  # everyone 1.4 m to the right of the truth
    result = best_assignment(d, offsets, np.full(3, 0.4), np.log(np.full((3, 4), 0.25)))
    assert result.lanes.tolist() == true.tolist()
    assert result.delta == pytest.approx(1.4, abs=0.05)


def test_hundred_users_are_solved_exactly() -> None:
    rng = np.random.default_rng(3)
    n = 100
    offsets = np.tile([0.0, 3.25, 6.5, 9.0], (n, 1))
    true = rng.integers(0, 4, n)
    d = offsets[0, true] + 2.0 + rng.normal(0, 0.3, n)
    result = best_assignment(d, offsets, np.full(n, 0.4), np.log(np.full((n, 4), 0.25)), 2.0, 0.5)
    assert (result.lanes == true).mean() > 0.97
    assert result.candidates <= n * 3 + 1


def test_shapes_are_checked() -> None:
    with pytest.raises(ValueError, match="shapes disagree"):
        best_assignment(np.zeros(2), np.zeros((3, 2)), np.ones(2), np.zeros((2, 2)))
