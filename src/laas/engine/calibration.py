"""The lane probability, calibrated: what the model says mapped to how often it is right.

The lane filter's probability P(l*) is the posterior of its model: Gaussian receivers
whose errors are independent from fix to fix once `evidence_interval` is allowed for, a
common error that drifts as a random walk, its evidence faded over `evidence_memory`.
Real receivers break that model in ways it cannot see in one answer (multipath that looks
like a lane change, a lasting bias on a narrow lane), so the posterior is not exactly the
rate at which its answers are right.
A monotone map g, fitted once on the development suite, takes the one to the other:

    P_reported = g(P(l*)),   g non-decreasing, piecewise linear between `KNOTS`

g is the isotonic regression of "the answered lane holds the true position" on P(l*)
over every answer of `laas evaluate --suite dev` (both sigma_pos), by the pool-adjacent-
violators algorithm (`scipy.optimize.isotonic_regression`), taken as the lower quartile
of such fits to the dev runs resampled with replacement, and thinned to knots that move
g by at most 0.005 (`scripts/fit_calibration.py`, which prints this table: all 40 dev
seeds of every family at both sigma_pos, 320 runs, 354,558 answers; ECE 0.040 -> 0.003
at sigma_pos 1 and 0.058 -> 0.007 at 2.5 there). The answers of one run share its road,
users and errors, so the runs are the samples; where they disagree the lower quartile
says a little less, the side integrity asks for (the script's docstring gives the check
on halves of dev). Being monotone, g never changes which lane is answered, only what is
said of it. The held-out suite is never used to fit it; `laas evaluate --suite heldout`
shows how it holds there.
"""

from __future__ import annotations

import numpy as np

__all__ = ["KNOTS", "calibrate"]

KNOTS: tuple[tuple[float, float], ...] = (
    (0.0000, 0.0000),
    (0.1475, 0.0866),
    (0.1500, 0.0951),
    (0.1505, 0.1043),
    (0.1550, 0.1096),
    (0.1590, 0.1202),
    (0.1610, 0.1275),
    (0.1615, 0.1417),
    (0.1625, 0.1667),
    (0.1630, 0.2222),
    (0.1635, 0.2568),
    (0.1645, 0.2624),
    (0.1680, 0.2675),
    (0.1860, 0.2742),
    (0.2120, 0.2802),
    (0.2145, 0.2921),
    (0.2150, 0.2995),
    (0.2165, 0.3097),
    (0.2175, 0.3202),
    (0.2260, 0.3395),
    (0.2325, 0.3543),
    (0.2380, 0.3598),
    (0.2395, 0.3811),
    (0.2400, 0.3930),
    (0.2445, 0.3983),
    (0.2485, 0.4071),
    (0.2570, 0.4140),
    (0.2585, 0.4355),
    (0.2770, 0.4418),
    (0.2900, 0.4498),
    (0.3095, 0.4550),
    (0.3100, 0.4622),
    (0.3205, 0.4701),
    (0.3220, 0.4759),
    (0.3235, 0.4824),
    (0.3540, 0.4897),
    (0.3645, 0.4951),
    (0.3840, 0.5006),
    (0.4090, 0.5064),
    (0.4105, 0.5130),
    (0.4110, 0.5205),
    (0.4135, 0.5259),
    (0.4450, 0.5327),
    (0.4535, 0.5412),
    (0.4620, 0.5522),
    (0.4655, 0.5586),
    (0.4825, 0.5646),
    (0.5140, 0.5726),
    (0.5205, 0.5777),
    (0.5400, 0.5833),
    (0.5415, 0.5917),
    (0.5445, 0.5978),
    (0.5465, 0.6054),
    (0.5470, 0.6145),
    (0.5485, 0.6203),
    (0.5515, 0.6254),
    (0.5585, 0.6304),
    (0.5600, 0.6391),
    (0.5730, 0.6462),
    (0.5745, 0.6512),
    (0.5750, 0.6611),
    (0.5775, 0.6697),
    (0.5825, 0.6755),
    (0.5855, 0.6931),
    (0.5935, 0.6991),
    (0.6110, 0.7099),
    (0.6235, 0.7151),
    (0.6330, 0.7206),
    (0.6345, 0.7257),
    (0.6410, 0.7325),
    (0.6440, 0.7379),
    (0.6685, 0.7433),
    (0.6920, 0.7493),
    (0.6995, 0.7547),
    (0.7010, 0.7631),
    (0.7025, 0.7691),
    (0.7050, 0.7789),
    (0.7125, 0.7852),
    (0.7165, 0.7944),
    (0.7315, 0.7995),
    (0.7330, 0.8046),
    (0.7340, 0.8120),
    (0.7345, 0.8178),
    (0.7385, 0.8250),
    (0.7410, 0.8303),
    (0.7595, 0.8364),
    (0.7770, 0.8418),
    (0.7930, 0.8476),
    (0.7950, 0.8536),
    (0.7975, 0.8604),
    (0.8025, 0.8671),
    (0.8085, 0.8727),
    (0.8155, 0.8784),
    (0.8245, 0.8868),
    (0.8275, 0.8921),
    (0.8460, 0.8987),
    (0.8495, 0.9047),
    (0.8660, 0.9104),
    (0.8795, 0.9167),
    (0.8805, 0.9218),
    (0.8815, 0.9289),
    (0.8860, 0.9340),
    (0.8885, 0.9395),
    (0.8950, 0.9447),
    (0.9020, 0.9498),
    (0.9085, 0.9549),
    (0.9160, 0.9670),
    (0.9230, 0.9725),
    (0.9370, 0.9777),
    (0.9490, 0.9831),
    (0.9540, 0.9884),
    (0.9650, 0.9938),
    (0.9855, 0.9988),
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
