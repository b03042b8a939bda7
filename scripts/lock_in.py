"""The anatomy of one dev run's lock-in: what its first users' fixes say, and how each
`evidence_memory` answers it.

    .venv/bin/python scripts/lock_in.py [--family edge] [--seed 20] [--first 20]

Prints the road's lane widths, each user's receiver error across the road and the mean of
its fixes' offset from its true lane centre over the first `--first` seconds and after
(where the users agree on the true lanes and where one lane over), then default mode's answers,
uncalibrated, with evidence that never fades and with the 30 s memory: how many are
right (the answered lane holds the true position), how many said >= 0.9 and were
wrong, and the most a wrong answer said in the first seconds. docs/evaluation.md's
figures of dev `edge` seed 20 ("Tried on dev and left out", and "Roads nobody chose:
scenario families") come from it.
Development seeds only: it is a tool for model work, not a score.
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

from laas.engine import Engine
from laas.evaluation.integrity import lane_right
from laas.evaluation.suite import engine_config, simulate_case


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", default="edge")
    parser.add_argument("--seed", type=int, default=20)
    parser.add_argument("--first", type=float, default=20.0, help="seconds")
    a = parser.parse_args()
    case, trace = simulate_case(a.family, a.seed, 1.0)
    hdmap = case.hdmap
    first = trace.fixes[0].segment
    print(f"{a.family} seed {a.seed}: lanes of {first}:")
    for lane in hdmap.segments[first].lanes:
        print(f"  {lane.type:10s} {lane.width:.2f} m")
    t0 = trace.fixes[0].measurement.timestamp / 1000.0
    offsets: dict[tuple[bool, str], list[float]] = defaultdict(list)
    receiver: dict[str, float] = {}
    for fix in trace.fixes:
        m = fix.measurement
        segment = hdmap.segments[fix.segment]
        s, _ = segment.frame(fix.true_e, fix.true_n)
        e, n = hdmap.projection.to_utm(m.longitude, m.latitude)
        _, d = segment.frame(e, n)
        later = m.timestamp / 1000.0 - t0 > a.first
        offsets[later, fix.user].append(d - float(segment.lane_offsets(s)[fix.lane]))
        tangent = segment.tangent_many(np.array([s]))[0]
        receiver[fix.user] = float(tangent[1] * fix.receiver_e - tangent[0] * fix.receiver_n)
    print("fix less true lane centre, across the road (mean)")
    for (later, user), values in offsets.items():
        print(
            f"  {'after' if later else 'first'} {a.first:.0f} s  {user:12s}"
            f" {np.mean(values):6.2f} m over {len(values):3d} fixes"
            f" (its receiver: {receiver[user]:5.2f} m)"
        )
    for memory in (None, 30.0):
        update = {"calibrated": False, "evidence_memory": memory}
        engine = Engine(hdmap, engine_config("default", 1.0).model_copy(update=update))
        answered = right = wrong_90 = 0
        sure_early = 0.0  # the most any wrong answer of the first seconds said
        for fix in trace.fixes:
            answer = engine.process(fix.user, fix.measurement)
            if answer is None or answer.segment is None:
                continue
            ok = lane_right(
                hdmap,
                (answer.segment, answer.lane),
                (fix.segment, fix.lane),
                fix.true_e,
                fix.true_n,
            )
            answered += 1
            right += ok
            wrong_90 += (not ok) and answer.probability >= 0.9
            if not ok and fix.measurement.timestamp / 1000.0 - t0 <= a.first:
                sure_early = max(sure_early, answer.probability)
        print(
            f"evidence_memory {memory}: {right} of {answered} answers right, "
            f"{wrong_90} said >= 0.9 and wrong, a wrong lane said with up to {sure_early:.2f}"
            f" in the first {a.first:.0f} s (uncalibrated)"
        )


if __name__ == "__main__":
    main()
