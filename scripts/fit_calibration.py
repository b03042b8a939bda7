"""Fit the lane probability's calibration map on the development suite.

    .venv/bin/python scripts/fit_calibration.py [--seeds 12] [--workers 2]

Runs default mode, uncalibrated (`EngineConfig(calibrated=False)`), on the dev suite's
first `--seeds` seeds of every family at both of its sigma_pos (the held-out suite is never
run here), pairs every answer's P(l*) with whether its lane holds the true position
(`laas.sim.integrity.lane_right`), fits the isotonic regression of the one on the other
(`scipy.optimize.isotonic_regression`, pool adjacent violators) and prints the knots for
`laas.engine.calibration.KNOTS`, with the reliability before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from scipy.optimize import isotonic_regression

from laas.engine import Engine
from laas.sim.integrity import IntegrityTally, lane_right
from laas.sim.suite import engine_config, get_suite, simulate_case

_STEP = 0.005  # a knot is kept where g has moved this much since the last one


def _pairs(job: tuple[str, int, float]) -> list[tuple[float, bool]]:
    """(P(l*), right) of every answer of one dev run, the engine uncalibrated."""
    family, seed, sigma_pos = job
    case, trace = simulate_case(family, seed, sigma_pos)
    config = engine_config("default", sigma_pos).model_copy(update={"calibrated": False})
    engine = Engine(case.hdmap, config)
    out: list[tuple[float, bool]] = []
    for fix in trace.fixes:
        answer = engine.process(fix.user, fix.measurement)
        if answer is None:
            continue
        right = lane_right(
            case.hdmap,
            (answer.segment, answer.lane),
            (fix.segment, fix.lane),
            fix.true_e,
            fix.true_n,
        )
        out.append((answer.probability, right))
    return out


def _knots(x: np.ndarray, y: np.ndarray) -> list[tuple[float, float]]:
    """Thin the isotonic fit (x sorted, y non-decreasing) to knots of g."""
    knots = [(0.0, float(y[0]))]
    for xi, yi in zip(x, y, strict=True):
        if yi - knots[-1][1] >= _STEP:
            knots.append((float(xi), float(yi)))
    knots.append((1.0, float(y[-1])))
    return knots


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=12)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    a = parser.parse_args()
    suite = get_suite("dev")
    jobs = [(f, s, sp) for f, seeds in suite.cases for s in seeds[: a.seeds] for sp in suite.sigmas]
    pairs: list[tuple[float, bool]] = []
    with ProcessPoolExecutor(a.workers) as pool:
        for k, found in enumerate(pool.map(_pairs, jobs), start=1):
            pairs.extend(found)
            print(f"fit: {k}/{len(jobs)} runs", file=sys.stderr, flush=True)
    p = np.array([q for q, _ in pairs])
    right = np.array([r for _, r in pairs], dtype=float)
    order = np.argsort(p, kind="stable")
    fitted = isotonic_regression(right[order]).x
    knots = _knots(p[order], fitted)
    g = np.interp(p, [k[0] for k in knots], [k[1] for k in knots])
    for name, probs in (("model", p), ("calibrated", g)):
        tally = IntegrityTally()
        for q, r in zip(probs, right, strict=True):
            tally.add_answer(float(q), bool(r))
        s = tally.summary()
        print(f"{name}: ECE {s.ece:.4f}, said >= 0.9 and wrong {s.wrong_90:.2%}")
        print(s.reliability())
    print(f"{len(pairs)} answers of {len(jobs)} dev runs; KNOTS = (")
    for x, y in knots:
        print(f"    ({x:.4f}, {y:.4f}),")
    print(")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
