"""The engine's answers recorded, to test that speed work changes none.

Speed work must keep every answer: the same lane, and the position, both accuracies
(`accuracy_cross`, `accuracy_along`) and the lane's probability within 1e-6 (m, or of
probability). This module names the
recorded cases, answers them with the engine as it is now, one fix at a time
(`Engine.process`) and in batches as the live worker takes them (`laas.sim.batches`,
`Engine.process_many`), and writes or compares the record in
`tests/data/reference-answers.npz`:

    .venv/bin/python -m tests.reference_answers --record   # after a deliberate change
    .venv/bin/python -m tests.reference_answers            # compare, print the worst

(`--workers N` answers the cases on N processes; about 2 minutes on two.) Cases: both
bundled scenarios in both modes, the first `FAMILY_SEEDS` of the `ci` suite's dev seeds
of each random-road family at sigma_pos 1 (default mode), and two dev seeds of each
real-map family. Recording again is a decision that the answers *should* change (a
model change), never a way to make a speed change pass: say so in the commit.
"""

from __future__ import annotations

import argparse
import functools
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from laas.config import EngineConfig, Mode
from laas.evaluation.score import answer_trace
from laas.evaluation.suite import engine_config, get_suite, sigma_vel_for
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.sim.batches import MAX_BATCH
from laas.sim.family import MAP_FAMILIES, build_case
from laas.sim.scenario import SCENARIOS, Trace, simulate_with

RECORD = Path(__file__).parent / "data" / "reference-answers.npz"
TOLERANCE_M = 1e-6
# Dev seeds per random-road family (16 cases of four families): a change of the engine's
# answers shows in most cases, and `tests/test_same_answers.py` answers each case one at
# a time (their batched answers come from the ci suite that `tests/test_accuracy.py`
# scores: `tests/ci_suite.py`), so more would cost the test command time.
FAMILY_SEEDS = 4


@dataclass(frozen=True)
class Case:
    name: str
    hdmap: HdMap
    trace: Trace
    config: EngineConfig


def _makers() -> dict[str, Callable[[], Case]]:
    """Each recorded case's name and how to build it (seeded: the same trace every time)."""

    def scenario_case(name: str, mode: Mode) -> Case:
        scenario = SCENARIOS[name]()
        hdmap = read_geojson_file(Path(__file__).parents[1] / "maps" / f"{name}.geojson")
        trace = simulate_with(hdmap, scenario, 0, sigma_pos=1.0, sigma_vel=0.25)
        return Case(f"{name}/{mode}", hdmap, trace, EngineConfig(mode=mode))

    def family_case(family: str, seed: int) -> Case:
        case = build_case(family, seed)
        trace = simulate_with(case.hdmap, case.scenario, seed, sigma_pos=1.0, sigma_vel=0.25)
        config = engine_config("default", 1.0)
        assert config.sigma_vel == sigma_vel_for(1.0)
        return Case(f"{family}/{seed}", case.hdmap, trace, config)

    out: dict[str, Callable[[], Case]] = {}
    for name in SCENARIOS:
        modes: tuple[Mode, ...] = ("default", "paper")
        for mode in modes:
            out[f"{name}/{mode}"] = functools.partial(scenario_case, name, mode)
    runs = [(f, s) for f, seeds in get_suite("ci").cases for s in seeds[:FAMILY_SEEDS]]
    runs += [(m, s) for m in MAP_FAMILIES for s in (0, 1)]
    for family, seed in runs:
        out[f"{family}/{seed}"] = functools.partial(family_case, family, seed)
    return out


def case_names() -> list[str]:
    """The names of the recorded cases, in recording order (nothing is built)."""
    return list(_makers())


def build(name: str) -> Case:
    """One recorded case, built afresh."""
    return _makers()[name]()


def cases() -> list[Case]:
    """Every recorded case, built afresh (seeded, so the same traces every time)."""
    return [make() for make in _makers().values()]


def answer_arrays(case: Case, max_batch: int = 1) -> dict[str, np.ndarray]:
    """The case's answers as arrays: UTM position, lane key, accuracy (the fixes given
    to the engine one at a time, or in batches of up to `max_batch` as the live worker
    takes them)."""
    return arrays(case.hdmap, answer_trace(case.hdmap, case.trace, case.config, max_batch))


def arrays(hdmap: HdMap, answers: list[CorrectedPosition | None]) -> dict[str, np.ndarray]:
    n = len(answers)
    xy = np.full((n, 2), np.nan)
    acc = np.full((n, 2), np.nan)
    prob = np.full(n, np.nan)
    lane = np.full(n, "", dtype=object)
    for i, a in enumerate(answers):
        if a is None:
            lane[i] = "none"
            continue
        xy[i] = hdmap.projection.to_utm(a.longitude, a.latitude)
        acc[i] = (a.accuracy_cross, a.accuracy_along)
        prob[i] = a.probability
        lane[i] = f"{a.segment}:{a.lane}"
    return {"xy": xy, "acc": acc, "prob": prob, "lane": lane.astype(str)}


PATHS = ("one", "batched")
"""How a record's answers were given to the engine: one fix at a time, or in batches
as the live worker takes them (`answer_trace`'s default `max_batch`)."""
_FIELDS = ("xy", "acc", "prob", "lane")


def answer_both(case: Case) -> dict[str, dict[str, np.ndarray]]:
    """The case's answers one at a time and in batches (`PATHS`)."""
    return {"one": answer_arrays(case, 1), "batched": answer_arrays(case, MAX_BATCH)}


def differences(now: dict[str, np.ndarray], record: dict[str, np.ndarray]) -> tuple[int, float]:
    """(answers on another lane, largest difference of a position or an accuracy in m,
    or of a probability) of `now` against `record`; inf when they are not answers to the
    same fixes."""
    if now["lane"].shape != record["lane"].shape:  # another trace: the case itself changed
        return len(now["lane"]), float("inf")
    other = int(np.sum(now["lane"] != record["lane"]))
    worst = 0.0
    for field in ("xy", "acc", "prob"):
        if not np.array_equal(np.isnan(now[field]), np.isnan(record[field])):
            return other, float("inf")
        diff = np.abs(now[field] - record[field])
        worst = max(worst, float(np.nanmax(diff, initial=0.0)))
    return other, worst


def load_record() -> dict[str, dict[str, dict[str, np.ndarray]]]:
    """Case name -> path ("one", "batched") -> field (`_FIELDS`) -> array."""
    with np.load(RECORD) as data:
        names = sorted({k.split("|", 1)[0] for k in data.files})
        return {n: {p: {f: data[f"{n}|{p}|{f}"] for f in _FIELDS} for p in PATHS} for n in names}


def _answer(name: str) -> tuple[str, dict[str, dict[str, np.ndarray]]]:
    return name, answer_both(build(name))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--record", action="store_true", help="write the record anew")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    a = parser.parse_args()
    names = case_names()
    with ProcessPoolExecutor(max_workers=max(1, a.workers)) as pool:
        answered = dict(pool.map(_answer, names))
    if a.record:
        flat = {}
        for name in names:
            for path, fields in answered[name].items():
                for field, values in fields.items():
                    flat[f"{name}|{path}|{field}"] = values
            print(f"recorded {name}: {len(answered[name]['one']['lane'])} answers x 2")
        RECORD.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(RECORD, **flat)  # type: ignore[arg-type]
        return 0
    record = load_record()
    bad = 0
    for name in names:
        for path in PATHS:
            other, worst = differences(answered[name][path], record[name][path])
            ok = other == 0 and worst <= TOLERANCE_M
            bad += not ok
            verdict = "ok" if ok else "DIFF"
            print(f"{name:28s} {path:8s} other lanes {other:4d}  worst {worst:.2e} m  {verdict}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
