"""Where default mode's confident-and-wrong answers come from, on dev runs.

    .venv/bin/python scripts/confident_wrong.py [--families urban,arterial,shared,edge]
        [--seeds 0-20] [--sigma-pos 1] [--workers 2]
    .venv/bin/python scripts/confident_wrong.py --timeline urban 5 car-3 84 97

The first form answers each run as `laas evaluate --suite dev` does (`answer_trace`,
calibrated) and counts the answers that said p >= 0.9 and were wrong (`judge`): per
family, the runs that hold most of them, and by the time since the user's last true lane
change. The second prints one user's answers between two times (s from the run's first
fix): true and answered lane, the probability, and the receiver's own error across the
road (the fix less the true common error and the true position). The figures
docs/evaluation.md gives of them come from it. Development seeds only: it is a tool for
model work, not a score.
"""

from __future__ import annotations

import argparse
from collections import Counter
from concurrent.futures import ProcessPoolExecutor

from laas.evaluation.integrity import same_lane
from laas.evaluation.score import answer_trace, judge
from laas.evaluation.suite import engine_config, simulate_case

_Answer = tuple[str, int, str, float, bool, float]  # family, seed, user, since change, right, p


def _run(job: tuple[str, int, float]) -> list[_Answer]:
    family, seed, sigma_pos = job
    case, trace = simulate_case(family, seed, sigma_pos)
    answers = answer_trace(case.hdmap, trace, engine_config("default", sigma_pos))
    t0 = trace.fixes[0].measurement.timestamp / 1000.0
    last: dict[str, tuple[str, int]] = {}
    changed: dict[str, float] = {}
    out: list[_Answer] = []
    for fix, answer in zip(trace.fixes, answers, strict=True):
        t = fix.measurement.timestamp / 1000.0 - t0
        was, now = last.get(fix.user), (fix.segment, fix.lane)
        # a lane change: another lane of the same element (a seam is not a change)
        if was is not None and was[0] == fix.segment and not same_lane(case.hdmap, was, now):
            changed[fix.user] = t
        last[fix.user] = now
        if answer is None or answer.segment is None:
            continue
        right = judge(case.hdmap, fix, answer)[3]
        since = t - changed.get(fix.user, -1e9)
        out.append((family, seed, fix.user, since, right, answer.probability))
    return out


def anatomy(families: list[str], seeds: range, sigma_pos: float, workers: int) -> None:
    jobs = [(f, s, sigma_pos) for f in families for s in seeds]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        answers = [a for run in pool.map(_run, jobs) for a in run]
    wrong = [a for a in answers if not a[4] and a[5] >= 0.9]
    print(
        f"dev seeds {seeds.start}-{seeds.stop - 1}, sigma_pos {sigma_pos:g}, calibrated: "
        f"{len(wrong)} of {len(answers)} answers said >= 0.9 and were wrong"
    )
    for family in families:
        mine = [a for a in wrong if a[0] == family]
        runs = Counter(a[1] for a in mine).most_common(3)
        users = Counter(a[2] for a in mine if runs and a[1] == runs[0][0]).most_common(4)
        print(
            f"  {family:9s} {len(mine):4d}; most in seeds {runs}; in seed "
            f"{runs[0][0] if runs else '-'}, users {users}"
        )
    for lo, hi in ((0, 5), (5, 15), (15, 30), (30, float("inf"))):
        inside = [a for a in answers if lo <= a[3] < hi]
        bad = sum(1 for a in inside if not a[4] and a[5] >= 0.9)
        print(
            f"  {lo:>2}-{hi:<4} s after the user's last true lane change: {bad:4d} of "
            f"{len(inside):6d} ({bad / max(1, len(inside)):.2%})"
        )


def timeline(family: str, seed: int, user: str, start: float, end: float) -> None:
    case, trace = simulate_case(family, seed, 1.0)
    answers = answer_trace(case.hdmap, trace, engine_config("default", 1.0))
    proj = case.hdmap.projection
    t0 = trace.fixes[0].measurement.timestamp / 1000.0
    for fix, answer in zip(trace.fixes, answers, strict=True):
        t = fix.measurement.timestamp / 1000.0 - t0
        if fix.user != user or not start <= t <= end or answer is None:
            continue
        segment = case.hdmap.segments[fix.segment]
        _, d_true = segment.frame(fix.true_e, fix.true_n)
        e, n = proj.to_utm(fix.measurement.longitude, fix.measurement.latitude)
        _, d_fix = segment.frame(e - fix.common_e, n - fix.common_n)
        right = judge(case.hdmap, fix, answer)[3]
        print(
            f"{t:6.1f} s  true lane {fix.lane}  answered {answer.lane}  p {answer.probability:.2f}"
            f"  receiver across {d_fix - d_true:+5.2f} m  {'' if right else 'WRONG'}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", default="urban,arterial,shared,edge")
    parser.add_argument("--seeds", default="0-20", help="first-last+1, dev seeds")
    parser.add_argument("--sigma-pos", type=float, default=1.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timeline", nargs=5, metavar=("FAMILY", "SEED", "USER", "T0", "T1"))
    a = parser.parse_args()
    if a.timeline:
        family, seed, user, start, end = a.timeline
        timeline(family, int(seed), user, float(start), float(end))
        return
    first, stop = (int(x) for x in a.seeds.split("-"))
    anatomy(a.families.split(","), range(first, stop), a.sigma_pos, a.workers)


if __name__ == "__main__":
    main()
