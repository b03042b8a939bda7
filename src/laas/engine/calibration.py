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
violators algorithm (`scipy.optimize.isotonic_regression`), taken as the lower quartile
of such fits to the dev runs resampled with replacement, and thinned to knots that move
g by at most 0.005 (`scripts/fit_calibration.py`, which prints this table: all 40 dev
seeds of every family at both sigma_pos, 320 runs, 354,558 answers; ECE 0.028 -> 0.004
at sigma_pos 1 and 0.040 -> 0.008 at 2.5 there). The answers of one run share its road,
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
    (0.1475, 0.1030),
    (0.1490, 0.1093),
    (0.1500, 0.1163),
    (0.1505, 0.1250),
    (0.1545, 0.1303),
    (0.1620, 0.1355),
    (0.1630, 0.1536),
    (0.1635, 0.1814),
    (0.1640, 0.1937),
    (0.1645, 0.2215),
    (0.1655, 0.2338),
    (0.1660, 0.2411),
    (0.1675, 0.2612),
    (0.1860, 0.2668),
    (0.1935, 0.2719),
    (0.2145, 0.2770),
    (0.2150, 0.2911),
    (0.2160, 0.2971),
    (0.2165, 0.3093),
    (0.2210, 0.3192),
    (0.2290, 0.3257),
    (0.2300, 0.3312),
    (0.2385, 0.3386),
    (0.2390, 0.3457),
    (0.2395, 0.3599),
    (0.2400, 0.3678),
    (0.2495, 0.3732),
    (0.2785, 0.3783),
    (0.3240, 0.3852),
    (0.3250, 0.3938),
    (0.3260, 0.3997),
    (0.3275, 0.4171),
    (0.3300, 0.4234),
    (0.3330, 0.4297),
    (0.3390, 0.4352),
    (0.3445, 0.4407),
    (0.3595, 0.4465),
    (0.3650, 0.4550),
    (0.3745, 0.4698),
    (0.3750, 0.4770),
    (0.3760, 0.4854),
    (0.3775, 0.4917),
    (0.3810, 0.4985),
    (0.3855, 0.5037),
    (0.4475, 0.5099),
    (0.4930, 0.5182),
    (0.4960, 0.5234),
    (0.4985, 0.5294),
    (0.4995, 0.5388),
    (0.5010, 0.5443),
    (0.5040, 0.5500),
    (0.5060, 0.5587),
    (0.5120, 0.5638),
    (0.5300, 0.5695),
    (0.5390, 0.5756),
    (0.5475, 0.5813),
    (0.5505, 0.5903),
    (0.5595, 0.5954),
    (0.5755, 0.6048),
    (0.5765, 0.6131),
    (0.5865, 0.6184),
    (0.5950, 0.6259),
    (0.5965, 0.6334),
    (0.6030, 0.6418),
    (0.6355, 0.6468),
    (0.6390, 0.6526),
    (0.6395, 0.6621),
    (0.6410, 0.6683),
    (0.6420, 0.6788),
    (0.6450, 0.6934),
    (0.6515, 0.6984),
    (0.6550, 0.7037),
    (0.6575, 0.7168),
    (0.6830, 0.7228),
    (0.6865, 0.7299),
    (0.6900, 0.7349),
    (0.6910, 0.7406),
    (0.6970, 0.7458),
    (0.7115, 0.7528),
    (0.7145, 0.7585),
    (0.7220, 0.7651),
    (0.7250, 0.7708),
    (0.7285, 0.7780),
    (0.7340, 0.7845),
    (0.7405, 0.7936),
    (0.7780, 0.8003),
    (0.7795, 0.8054),
    (0.7830, 0.8112),
    (0.7870, 0.8164),
    (0.7945, 0.8244),
    (0.8030, 0.8301),
    (0.8085, 0.8409),
    (0.8115, 0.8460),
    (0.8170, 0.8549),
    (0.8220, 0.8636),
    (0.8275, 0.8722),
    (0.8335, 0.8778),
    (0.8465, 0.8831),
    (0.8635, 0.8885),
    (0.8660, 0.8942),
    (0.8745, 0.9064),
    (0.8800, 0.9122),
    (0.8830, 0.9177),
    (0.8870, 0.9266),
    (0.8955, 0.9317),
    (0.9020, 0.9378),
    (0.9095, 0.9429),
    (0.9175, 0.9480),
    (0.9195, 0.9594),
    (0.9210, 0.9652),
    (0.9280, 0.9706),
    (0.9320, 0.9760),
    (0.9445, 0.9812),
    (0.9605, 0.9881),
    (0.9720, 0.9932),
    (0.9855, 0.9983),
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
