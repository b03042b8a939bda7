"""The common error's posterior forgets old evidence at the rate it states (issue 22)."""

from __future__ import annotations

import math

import numpy as np

from laas.engine.common_error import CommonError

PRIOR = 10.0  # m
TAU = 30.0  # s


def _told(memory: float | None, cap: float | None = None) -> CommonError:
    """An area that no longer drifts, told once that u = b_east = 2 m, within 0.5 m."""
    area = CommonError(np.zeros(2), PRIOR, 0.0, 0.3, cap, memory)
    area.predict(0.0)
    area.update(np.array([1.0, 0.0]), -0.5 * ((area.u.values - 2.0) / 0.5) ** 2, "a")
    return area


def test_evidence_fades_as_e_to_the_minus_its_age_over_tau() -> None:
    """log p = lam (evidence + prior) + (1 - lam) prior: the evidence's precision 1 / 0.5^2
    counts with weight lam = e^(-t / tau), and the mean shrinks towards the prior's 0."""
    for t in (10.0, 30.0, 45.0):
        area = _told(TAU)
        area.predict(t)
        lam = math.exp(-t / TAU)
        precision = lam / 0.25 + 1.0 / PRIOR**2
        expected_var = 1.0 / precision + area.cell_var
        expected_mean = (lam / 0.25) * 2.0 / precision
        assert math.isclose(float(area.P[0, 0]), expected_var, rel_tol=0.03), t
        assert math.isclose(float(area.b[0]), expected_mean, rel_tol=0.01), t


def test_fading_in_steps_is_fading_at_once() -> None:
    """lam(a) lam(b) = lam(a + b); only the floor of the cells the window dropped, set
    again at each step, tells them apart (by 1e-4 or less)."""
    once, steps = _told(TAU), _told(TAU)
    once.predict(45.0)
    for k in range(1, 46):
        steps.predict(float(k))
    assert np.allclose(once.b, steps.b, rtol=1e-4, atol=1e-4)
    assert np.allclose(once.P, steps.P, rtol=1e-4)


def test_without_a_memory_evidence_is_kept() -> None:
    area = _told(None)
    before = area.P.copy()
    area.predict(90.0)
    assert np.allclose(area.P, before)
    assert abs(float(area.b[0]) - 2.0) < 0.01


def test_cells_the_window_dropped_come_back_as_the_evidence_fades() -> None:
    """Evidence within 0.1 m shrinks the window to |b_e - 2| < 0.9 m and two 0.3 m cells
    more (40 nats), where no posterior has a variance above 1.5^2. Faded for 6 tau, it
    holds e^-6 of that evidence, a variance of 1 / (e^-6 / 0.01 + 1 / 100) = 3.9 m^2: the
    posterior has to widen past the window it had."""
    area = CommonError(np.zeros(2), PRIOR, 0.0, 0.3, None, TAU)
    area.predict(0.0)
    area.update(np.array([1.0, 0.0]), -0.5 * ((area.u.values - 2.0) / 0.1) ** 2, "a")
    assert float(area.P[0, 0]) < 0.03
    area.predict(6 * TAU)
    assert float(area.P[0, 0]) > 3.0


def test_a_robust_area_keeps_its_evidence() -> None:
    """The one-liar term log(1 + S) is computed beside the whole of every record."""
    area = _told(TAU, cap=16.0)
    area.update(np.array([1.0, 0.0]), -0.5 * ((area.u.values - 2.2) / 0.5) ** 2, "b")
    before = area.P.copy()
    area.predict(60.0)
    assert area.memory is None
    assert np.allclose(area.P, before)


def test_evidence_shared_late_counts_as_faded_as_if_it_had_come_here() -> None:
    """A neighbour's evidence of time 0, taken at 30 s, counts as this area's own evidence
    of time 0 would by then (and, taken by an area that has no time yet, from time 0)."""
    here = _told(TAU)
    here.predict(TAU)
    source = CommonError(np.zeros(2), PRIOR, 0.0, 0.3, None, TAU)
    source.record()
    source.predict(0.0)
    source.update(np.array([1.0, 0.0]), -0.5 * ((source.u.values - 2.0) / 0.5) ** 2)
    shared = source.shared()
    assert shared is not None and shared[2] == 0.0
    late = CommonError(np.zeros(2), PRIOR, 0.0, 0.3, None, TAU)
    late.predict(TAU)
    late.take_shared(*shared)
    fresh = CommonError(np.zeros(2), PRIOR, 0.0, 0.3, None, TAU)
    fresh.take_shared(*shared)
    fresh.predict(TAU)
    for area in (late, fresh):
        assert np.allclose(area.b, here.b, atol=0.02)
        assert np.allclose(area.P, here.P, rtol=0.05)
