"""The lane probability, calibrated: what the model says mapped to how often it is right.

The lane filter's probability P(l*) is the posterior of its model: Gaussian receivers
whose errors are independent from fix to fix once `evidence_interval` is allowed for, a
common error that drifts as a random walk, its evidence faded over `evidence_memory`.
Real receivers break that model in ways it cannot see in one answer (multipath that looks
like a lane change, a lasting bias on a narrow lane), so the posterior is not exactly the
rate at which its answers are right.
A monotone map g, fitted once on the development suite, takes the one to the other:

    P_reported = g(P(l*)),   g non-decreasing, piecewise linear between `KNOTS`

g is the isotonic regression of "the answer's (segment, lane) is the true one" on P over
every answer of `laas evaluate --suite dev` (both sigma_pos, in batches as the live
worker takes them; P is the lane's posterior times P(on the named element),
`Engine._on_element`), by the pool-adjacent-violators algorithm
(`scipy.optimize.isotonic_regression`), taken as the lower quartile of such fits to the
dev runs resampled with replacement, and thinned to knots that move g by at most 0.005
(`scripts/fit_calibration.py`, which prints this table: all 40 dev seeds of every family
at both sigma_pos, 320 runs, 354,558 answers; ECE 0.027 -> 0.005 at sigma_pos 1 and
0.033 -> 0.005 at 2.5 there). The answers of one run share its road, users and errors,
so the runs are the samples; where they disagree the lower quartile says a little less,
the side integrity asks for (the script's docstring gives the check on halves of dev).
Being monotone, g never changes which lane is answered, only what is said of it. The
held-out suite is never used to fit it; `laas evaluate --suite heldout` shows how it
holds there.
"""

from __future__ import annotations

from bisect import bisect_right

__all__ = ["KNOTS", "calibrate"]

KNOTS: tuple[tuple[float, float], ...] = (
    (0.0000, 0.0000),
    (0.0845, 0.0087),
    (0.0850, 0.0146),
    (0.0855, 0.0206),
    (0.0875, 0.0410),
    (0.0880, 0.0510),
    (0.0885, 0.0604),
    (0.0910, 0.0655),
    (0.0925, 0.0710),
    (0.1330, 0.0789),
    (0.1370, 0.0846),
    (0.1440, 0.0982),
    (0.1555, 0.1035),
    (0.1610, 0.1318),
    (0.1625, 0.1400),
    (0.1630, 0.2000),
    (0.1635, 0.2106),
    (0.1645, 0.2158),
    (0.1685, 0.2262),
    (0.1875, 0.2323),
    (0.1880, 0.2500),
    (0.1890, 0.2579),
    (0.1945, 0.2636),
    (0.2135, 0.2690),
    (0.2375, 0.2750),
    (0.2400, 0.2818),
    (0.2440, 0.2911),
    (0.2465, 0.2995),
    (0.2470, 0.3052),
    (0.2505, 0.3134),
    (0.2525, 0.3190),
    (0.2530, 0.3240),
    (0.2535, 0.3470),
    (0.2640, 0.3531),
    (0.2805, 0.3608),
    (0.2955, 0.3689),
    (0.2995, 0.3745),
    (0.3085, 0.3797),
    (0.3115, 0.3881),
    (0.3150, 0.3936),
    (0.3220, 0.4043),
    (0.3235, 0.4128),
    (0.3285, 0.4207),
    (0.3305, 0.4284),
    (0.3340, 0.4336),
    (0.3505, 0.4392),
    (0.3520, 0.4444),
    (0.3555, 0.4534),
    (0.3590, 0.4599),
    (0.3650, 0.4649),
    (0.4105, 0.4702),
    (0.4400, 0.4754),
    (0.4575, 0.4874),
    (0.4670, 0.4929),
    (0.4865, 0.4981),
    (0.5025, 0.5058),
    (0.5065, 0.5112),
    (0.5075, 0.5216),
    (0.5085, 0.5276),
    (0.5160, 0.5355),
    (0.5190, 0.5454),
    (0.5340, 0.5508),
    (0.5380, 0.5566),
    (0.5400, 0.5640),
    (0.5420, 0.5696),
    (0.5445, 0.5756),
    (0.5475, 0.5834),
    (0.5495, 0.5893),
    (0.5520, 0.5955),
    (0.5625, 0.6020),
    (0.5680, 0.6130),
    (0.5770, 0.6195),
    (0.6045, 0.6245),
    (0.6170, 0.6297),
    (0.6285, 0.6354),
    (0.6295, 0.6419),
    (0.6300, 0.6493),
    (0.6310, 0.6576),
    (0.6510, 0.6630),
    (0.6525, 0.6762),
    (0.6535, 0.6813),
    (0.6545, 0.6895),
    (0.6550, 0.6947),
    (0.6645, 0.7019),
    (0.6695, 0.7077),
    (0.6740, 0.7129),
    (0.6745, 0.7203),
    (0.6780, 0.7276),
    (0.6905, 0.7328),
    (0.6970, 0.7390),
    (0.7025, 0.7456),
    (0.7045, 0.7521),
    (0.7175, 0.7571),
    (0.7225, 0.7622),
    (0.7280, 0.7673),
    (0.7300, 0.7733),
    (0.7425, 0.7791),
    (0.7455, 0.7843),
    (0.7650, 0.7897),
    (0.7660, 0.8010),
    (0.7705, 0.8101),
    (0.7735, 0.8154),
    (0.7750, 0.8218),
    (0.7840, 0.8289),
    (0.7950, 0.8347),
    (0.8015, 0.8400),
    (0.8050, 0.8494),
    (0.8085, 0.8548),
    (0.8135, 0.8629),
    (0.8150, 0.8680),
    (0.8215, 0.8735),
    (0.8275, 0.8786),
    (0.8360, 0.8837),
    (0.8365, 0.8897),
    (0.8410, 0.8956),
    (0.8430, 0.9032),
    (0.8660, 0.9083),
    (0.8700, 0.9159),
    (0.8730, 0.9216),
    (0.8810, 0.9268),
    (0.8950, 0.9321),
    (0.9010, 0.9372),
    (0.9115, 0.9431),
    (0.9225, 0.9535),
    (0.9285, 0.9587),
    (0.9395, 0.9641),
    (0.9500, 0.9694),
    (0.9520, 0.9764),
    (0.9590, 0.9816),
    (0.9650, 0.9874),
    (0.9790, 0.9926),
    (0.9955, 0.9978),
    (1.0000, 1.0000),
)
"""(P(l*), P_reported) knots of g; fitted by scripts/fit_calibration.py on the dev suite."""

_X = [k[0] for k in KNOTS]
_Y = [k[1] for k in KNOTS]


def calibrate(probability: float) -> float:
    """g(P(l*)): the reported lane probability, linear between the knots (as
    `numpy.interp`, in plain floats: its call costs more than one value's arithmetic).

    >>> calibrate(0.0), calibrate(1.0)
    (0.0, 1.0)
    >>> import numpy as np
    >>> bool(calibrate(0.9) == float(np.interp(0.9, _X, _Y)))
    True
    """
    p = float(probability)
    if not p < _X[-1]:  # at or past the last knot (and NaN, as numpy.interp's NaN)
        return p if p != p else _Y[-1]
    if p <= _X[0]:
        return _Y[0]
    j = bisect_right(_X, p) - 1
    if _X[j] == p:
        return _Y[j]
    slope = (_Y[j + 1] - _Y[j]) / (_X[j + 1] - _X[j])
    return slope * (p - _X[j]) + _Y[j]
