"""The lane probability, calibrated: what the model says mapped to how often it is right.

The lane filter's probability P(l*) is the posterior of its model: Gaussian receivers
whose errors are independent from fix to fix once `evidence_interval` is allowed for, a
common error that drifts as a random walk. Real receivers break that model in ways it
cannot see in one answer (multipath that looks like a lane change, a lasting bias on a
narrow lane), so the posterior is not exactly the rate at which its answers are right.
A monotone map g, fitted once on the development suite, takes the one to the other:

    P_reported = g(P(l*)),   g non-decreasing, piecewise linear between `KNOTS`

g is the isotonic regression of "the answered lane holds the true position" on P(l*)
over every answer of `laas evaluate --suite dev` (both sigma_pos), by the pool-adjacent-
violators algorithm (`scipy.optimize.isotonic_regression`), thinned to knots that move g
by at most 0.005 (`scripts/fit_calibration.py --seeds 20`, which prints this table:
dev seeds 0-19 of urban, arterial and shared at both sigma_pos, 164,634 answers; ECE
0.025 -> 0.006 there). Being monotone, g never changes which lane is answered, only what
is said of it. The held-out suite is never used to fit it; `laas evaluate --suite
heldout` shows how it holds there.
"""

from __future__ import annotations

import numpy as np

__all__ = ["KNOTS", "calibrate"]

KNOTS: tuple[tuple[float, float], ...] = (
    (0.0000, 0.0000),
    (0.1475, 0.1667),
    (0.1667, 0.2500),
    (0.1669, 0.3034),
    (0.2212, 0.3302),
    (0.2381, 0.4000),
    (0.2393, 0.4217),
    (0.2538, 0.4664),
    (0.2708, 0.4778),
    (0.2773, 0.5056),
    (0.3085, 0.5172),
    (0.3114, 0.5259),
    (0.3389, 0.5449),
    (0.3607, 0.5818),
    (0.5712, 0.6158),
    (0.5881, 0.6271),
    (0.6362, 0.6601),
    (0.6377, 0.6706),
    (0.6411, 0.6990),
    (0.6452, 0.7105),
    (0.6471, 0.7214),
    (0.6833, 0.7267),
    (0.6913, 0.7474),
    (0.7052, 0.7537),
    (0.7409, 0.7848),
    (0.7462, 0.7913),
    (0.7665, 0.8081),
    (0.7675, 0.8359),
    (0.8229, 0.8439),
    (0.8418, 0.8588),
    (0.8541, 0.8885),
    (0.8597, 0.8951),
    (0.8740, 0.9061),
    (0.8949, 0.9170),
    (0.8961, 0.9224),
    (0.9140, 0.9424),
    (0.9218, 0.9479),
    (0.9274, 0.9530),
    (0.9345, 0.9586),
    (0.9477, 0.9636),
    (0.9547, 0.9717),
    (0.9640, 0.9783),
    (0.9680, 0.9835),
    (0.9771, 0.9892),
    (0.9879, 0.9959),
    (1.0000, 1.0000),
)
"""(P(l*), P_reported) knots of g; fitted by scripts/fit_calibration.py on the dev suite."""

_X = np.array([k[0] for k in KNOTS])
_Y = np.array([k[1] for k in KNOTS])


def calibrate(probability: float) -> float:
    """g(P(l*)): the reported lane probability.

    >>> calibrate(0.0), calibrate(1.0)
    (0.0, 1.0)
    """
    return float(np.interp(probability, _X, _Y))
