"""The `ci` suite, answered once per test session and shared.

`tests/test_accuracy.py` scores every run of it; `tests/test_same_answers.py` needs
default mode's batched answers of its first `FAMILY_SEEDS` dev seeds of each random-road
family at sigma_pos 1, which are recorded cases (`tests/reference_answers`): the same
case, trace and engine configuration, so they are taken from here instead of answered
again. Each run is answered as `laas.evaluation.suite.run_case` answers it (the same
answerers, in the same order), keeping those answers as arrays.

The test command runs the test files on two processes (pytest-xdist, `--dist loadfile`),
so the two files may be in different ones: the first to ask answers the suite under a
file lock and leaves it in the run's temporary directory, and the other loads it.
"""

from __future__ import annotations

import fcntl
import functools
import os
import pickle
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from laas.evaluation.score import score
from laas.evaluation.suite import (
    MethodScore,
    SuiteRow,
    _answerers,
    get_suite,
    sigma_vel_for,
    simulate_case,
)
from tests.reference_answers import arrays, case_names


@dataclass(frozen=True)
class CiSuite:
    rows: list[SuiteRow]
    batched: dict[str, dict[str, np.ndarray]]
    """Recorded case name -> default mode's batched answers (`arrays`)."""


def _job(job: tuple[str, int, float, bool]) -> tuple[SuiteRow, dict[str, np.ndarray] | None]:
    family, seed, sigma_pos, keep = job
    case, trace = simulate_case(family, seed, sigma_pos)
    methods: dict[str, MethodScore] = {}
    kept = None
    raw = float("nan")
    for method, (answer, config) in _answerers(sigma_pos).items():
        t0 = time.perf_counter()
        answers = answer(case.hdmap, trace, config)
        result = score(case.hdmap, trace, answers)
        methods[method] = MethodScore.of(result, time.perf_counter() - t0)
        raw = result.raw_aed
        if method == "default" and keep:
            kept = arrays(case.hdmap, answers)
    row = SuiteRow(
        family=family,
        seed=seed,
        sigma_pos=sigma_pos,
        sigma_vel=sigma_vel_for(sigma_pos),
        users=len(case.scenario.users),
        fixes=len(trace.fixes),
        lanes=case.lanes,
        duration=case.scenario.duration,
        raw_aed=raw,
        methods=methods,
    )
    return row, kept


def recorded_runs() -> set[str]:
    """The recorded cases that are runs of the suite (their batched answers are kept)."""
    recorded = set(case_names())
    return {f"{f}/{s}" for f, s, sp in get_suite("ci").jobs() if sp == 1.0} & recorded


def ci_suite(cache: Path | None = None, workers: int = 2) -> CiSuite:
    """Every run of the `ci` suite, answered once per process, and once per test run
    when `cache` (a file in a directory the run's processes share) is given."""
    if cache is None:
        return _answered(workers)
    with open(cache.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # the other process waits here, then loads
        if cache.exists():
            loaded: CiSuite = pickle.loads(cache.read_bytes())
            return loaded
        suite = _answered(workers)
        cache.write_bytes(pickle.dumps(suite))
        return suite


@functools.cache
def _answered(workers: int) -> CiSuite:
    recorded = set(case_names())
    jobs = [(f, s, sp, sp == 1.0 and f"{f}/{s}" in recorded) for f, s, sp in get_suite("ci").jobs()]
    with ProcessPoolExecutor(max_workers=min(workers, os.cpu_count() or 1)) as pool:
        done = list(pool.map(_job, jobs))
    batched = {f"{row.family}/{row.seed}": kept for row, kept in done if kept is not None}
    return CiSuite([row for row, _ in done], batched)
