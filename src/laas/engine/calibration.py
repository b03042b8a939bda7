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
by at most 0.005 (`scripts/fit_calibration.py --seeds 12`, which prints this table:
dev seeds 0-11 of every family at both sigma_pos, 113,512 answers; ECE 0.032 -> 0.006
there, the share said >= 0.9 and wrong 0.80 % -> 1.16 %; refitted at stop 31 for its
model). Being monotone, g never
changes which lane is answered, only what is said of it. The held-out suite is never used
to fit it; `laas evaluate --suite heldout` shows how it holds there.
"""

from __future__ import annotations

import numpy as np

__all__ = ["KNOTS", "calibrate"]

KNOTS: tuple[tuple[float, float], ...] = (
    (0.0000, 0.0000),
    (0.1500, 0.1096),
    (0.1645, 0.2517),
    (0.2210, 0.3259),
    (0.3249, 0.3617),
    (0.3282, 0.4409),
    (0.3329, 0.4684),
    (0.3742, 0.4762),
    (0.3757, 0.4889),
    (0.3772, 0.5000),
    (0.3773, 0.5412),
    (0.3788, 0.5505),
    (0.3806, 0.5679),
    (0.5266, 0.5833),
    (0.5270, 0.5959),
    (0.5300, 0.6232),
    (0.5308, 0.6416),
    (0.6391, 0.6885),
    (0.6413, 0.6984),
    (0.6439, 0.7057),
    (0.6793, 0.7143),
    (0.6821, 0.7232),
    (0.6907, 0.7434),
    (0.6927, 0.7492),
    (0.6967, 0.7625),
    (0.7690, 0.7972),
    (0.7784, 0.8095),
    (0.7800, 0.8173),
    (0.7936, 0.8394),
    (0.8036, 0.8503),
    (0.8266, 0.8708),
    (0.8370, 0.8833),
    (0.8609, 0.8944),
    (0.8658, 0.8998),
    (0.8700, 0.9070),
    (0.9014, 0.9185),
    (0.9193, 0.9439),
    (0.9207, 0.9528),
    (0.9309, 0.9676),
    (0.9328, 0.9754),
    (0.9442, 0.9809),
    (0.9638, 0.9873),
    (0.9740, 0.9923),
    (0.9853, 0.9979),
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
