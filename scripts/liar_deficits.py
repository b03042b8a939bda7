"""How far honest receivers' own evidence lies from the true common error: the scale for K.

    .venv/bin/python scripts/liar_deficits.py [--seeds 8] [--workers 2]

`EngineConfig.max_user_evidence` K is the deficit at which the robust common error
(`laas.engine.common_error`) takes a participant for more likely not honest than honest:
its evidence T_i, normalised to 0 at its own best, is more than K nats below it at the
others' estimate. This prints the deficit -T_i(b_true) of *honest* receivers at the true
common error, the largest over each receiver's time in the area, on the development
suite's first `--seeds` seeds of every family at both of its sigma_pos (the held-out suite
is never run here). T_i is each user's own record in a robust area with K so large that
nobody is ever forgiven (the pooled estimate).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from laas.engine import Engine
from laas.evaluation.suite import engine_config, get_suite, simulate_case


def _deficits(job: tuple[str, int, float]) -> list[float]:
    family, seed, sigma_pos = job
    case, trace = simulate_case(family, seed, sigma_pos)
    config = engine_config("default", sigma_pos).model_copy(update={"max_user_evidence": 1e6})
    engine = Engine(case.hdmap, config)
    worst: dict[str, float] = {}
    for f in trace.fixes:
        engine.process(f.user, f.measurement)
        for area in engine.common_errors():
            kept = area.user_evidence(f.user)
            if kept is None:
                continue
            frame, own = kept
            i, j = area.cell(np.array([f.common_e, f.common_n]))
            if frame[0] <= i < frame[1] and frame[2] <= j < frame[3]:
                d = -float(own[i - frame[0], j - frame[2]])
                worst[f.user] = max(worst.get(f.user, 0.0), d)
    return list(worst.values())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8, help="first seeds of each family")
    parser.add_argument("--workers", type=int, default=min(os.cpu_count() or 1, 2))
    a = parser.parse_args()
    dev = get_suite("dev")
    jobs = [(f, s, sp) for f, seeds in dev.cases for s in seeds[: a.seeds] for sp in dev.sigmas]
    with ProcessPoolExecutor(a.workers) as pool:
        values = np.array([d for run in pool.map(_deficits, jobs) for d in run])
    print(
        f"{values.size} honest receivers in {len(jobs)} dev runs: the largest deficit of "
        "each at the true common error, nats"
    )
    pct = (50, 75, 90, 95, 99)
    for p, v in zip(pct, np.percentile(values, pct), strict=True):
        print(f"  {p:>2}th percentile {v:6.2f}")
    print(f"  largest          {values.max():6.2f}")
    for k in (4.0, 6.0, 8.0, 12.0, 16.0):
        share = float(np.mean(values > k))
        print(f"  K = {k:>4g}: {share:6.1%} of them pass it once (bound {math.sqrt(2 * k):.1f} sd)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
