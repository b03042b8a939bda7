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
dev seeds 0-11 of every family at both sigma_pos, 113,512 answers; ECE 0.025 -> 0.006
there, the share said >= 0.9 and wrong 1.00 % -> 1.32 %). Being monotone, g never
changes which lane is answered, only what is said of it. The held-out suite is never used
to fit it; `laas evaluate --suite heldout` shows how it holds there.
"""

from __future__ import annotations

import numpy as np

__all__ = ["KNOTS", "calibrate"]

KNOTS: tuple[tuple[float, float], ...] = (
    (0.0000, 0.0000),
    (0.1500, 0.1410),
    (0.1667, 0.2500),
    (0.1669, 0.3036),
    (0.2223, 0.3412),
    (0.3304, 0.3743),
    (0.3368, 0.4126),
    (0.3673, 0.4737),
    (0.3779, 0.5000),
    (0.3780, 0.5139),
    (0.3795, 0.5633),
    (0.5190, 0.6001),
    (0.5712, 0.6296),
    (0.6361, 0.6667),
    (0.6380, 0.7079),
    (0.6806, 0.7292),
    (0.6913, 0.7358),
    (0.7462, 0.7495),
    (0.7665, 0.7727),
    (0.7668, 0.7778),
    (0.7673, 0.8115),
    (0.8229, 0.8332),
    (0.8386, 0.8398),
    (0.8418, 0.8542),
    (0.8540, 0.8808),
    (0.8615, 0.8962),
    (0.8740, 0.9025),
    (0.8905, 0.9077),
    (0.8930, 0.9213),
    (0.9097, 0.9333),
    (0.9189, 0.9387),
    (0.9217, 0.9501),
    (0.9375, 0.9621),
    (0.9537, 0.9683),
    (0.9547, 0.9745),
    (0.9640, 0.9848),
    (0.9738, 0.9898),
    (0.9827, 0.9950),
    (0.9888, 1.0000),
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
