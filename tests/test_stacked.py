"""The default mode's stacked arithmetic (`laas.engine.stacked`) against the equations
of its module docstring written out in numpy, and its two ways of computing the evidence
against each other."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from laas.engine import stacked

_U = 120  # cells of the u-grid


def _inputs(n: int, h: int, lanes: int, seed: int) -> tuple[Any, ...]:
    """alpha, T, F, d, u, lo, o, s, w, eps, pi, s_mp; some users' spans run past the grid."""
    rng = np.random.default_rng(seed)
    alpha = rng.random((n, h, lanes))
    alpha /= alpha.sum(axis=2, keepdims=True)
    return (
        alpha,
        rng.random((n, lanes, lanes)),
        rng.random((n, lanes)),
        rng.normal(0.0, 3.0, n),
        np.linspace(-6.0, 6.0, _U),
        rng.integers(0, _U, n),
        np.sort(rng.uniform(-5.0, 5.0, (n, lanes)), axis=1),
        rng.uniform(0.5, 4.0, n),
        rng.uniform(0.05, 1.0, n),
        1e-3,
        0.05,
        3.0,
    )


def _cells(lo: np.ndarray, h: int) -> np.ndarray:
    """Each user's cells lo..lo + h, past the grid its last cell."""
    out: np.ndarray = np.minimum(lo[:, None] + np.arange(h), _U - 1)
    return out


@pytest.mark.parametrize(("n", "h", "lanes"), [(1, 30, 3), (1, 400, 4), (12, 150, 5)])
def test_the_evidence_cell_by_cell_is_the_evidence_in_arrays(n: int, h: int, lanes: int) -> None:
    args = _inputs(n, h, lanes, seed=n * h)
    cells = stacked._evidence_cells(*args)
    arrays = stacked._evidence_arrays(*args)
    for a, b in zip(cells, arrays, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)
    # the dispatcher takes one of them, and its answer is theirs
    for a, b in zip(stacked.evidence(*args), arrays, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)


def test_the_evidence_is_the_docstrings_prediction_times_likelihood() -> None:
    args = _inputs(2, 20, 3, seed=5)
    alpha, transition, fit, d, u, lo, offsets, sigma, weight, eps, pi, wide = args
    joint, log_c = stacked.evidence(*args)
    cells = _cells(lo, 20)
    for i in range(2):
        s, s_w = sigma[i], np.hypot(sigma[i], wide)
        r = d[i] - u[cells[i]][:, None] - offsets[i][None, :]
        normal = (1 - pi) * np.exp(-0.5 * (r / s) ** 2) / (s * np.sqrt(2 * np.pi))
        broad = pi * np.exp(-0.5 * (r / s_w) ** 2) / (s_w * np.sqrt(2 * np.pi))
        a = (alpha[i] @ transition[i]) * fit[i]
        unnormalised = a * (eps + normal + broad) ** weight[i]
        c = unnormalised.sum(axis=1)
        np.testing.assert_allclose(log_c[i], np.log(c), rtol=1e-12)
        np.testing.assert_allclose(joint[i], unnormalised / c[:, None], rtol=1e-12)


def test_lanes_and_conditionals_are_the_moments_of_the_posterior_given_the_lane() -> None:
    rng = np.random.default_rng(7)
    n, h, lanes = 3, 40, 4
    moments = rng.random((2, _U, 6))  # two normals
    moments[1, :, :] = 0.0  # the second holds no mass of the posterior: not held
    group = np.array([0, 0, 1])
    lo = np.array([3, 100, 10])  # the second user's span runs past the grid
    alpha = rng.random((n, h, lanes))
    marginal, lane, mean, cov, held = stacked.lanes_and_conditionals(
        moments, group, lo, alpha, 0.01
    )
    assert held.tolist() == [True, True, False]
    cells = _cells(lo, h)
    for i in range(2):
        m = moments[group[i]][cells[i]]
        p = m[:, 0] @ alpha[i]
        np.testing.assert_allclose(marginal[i], p / p.sum(), rtol=1e-12)
        assert lane[i] == int(np.argmax(p))
        g = alpha[i, :, lane[i]]
        sums = g @ m / (g @ m[:, 0])
        e, nn = sums[1], sums[2]
        np.testing.assert_allclose(mean[i], [e, nn], rtol=1e-12)
        expected = [
            [sums[3] - e * e + 0.01, sums[4] - e * nn],
            [sums[4] - e * nn, sums[5] - nn * nn + 0.01],
        ]
        np.testing.assert_allclose(cov[i], expected, rtol=1e-10, atol=1e-12)
