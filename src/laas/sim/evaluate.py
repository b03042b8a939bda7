"""The paper's evaluation (section V, Table I), reproduced and extended.

Each configuration is run on `runs` seeds; every run simulates the scenario, feeds
its fixes to a fresh `Engine` one by one (exactly as `laas replay` and the worker do)
and scores the answers against the ground truth:

    RMSE_x = sqrt(mean (e_hat - e)^2),   RMSE_y = sqrt(mean (n_hat - n)^2),
    AED    = mean sqrt((e_hat - e)^2 + (n_hat - n)^2),
    Acc.   = share of fixes whose (segment, lane) is the true one.

The table shows the mean over runs. Errors are also split across and along the road
(the true direction of travel), and before and after the common error became
observable: the first time the orientations of the roads the users have driven so far
span more than `OBSERVABLE_SPAN` degrees (until then no lane constraint says anything
along the road).
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np

from laas.config import EngineConfig, Mode
from laas.engine.engine import Engine
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.sim.scenario import ErrorModel, Scenario, Trace, simulate

__all__ = [
    "PAPER_TABLE_I",
    "TABLE_I_CONFIGS",
    "Row",
    "RunResult",
    "answer_trace",
    "evaluate",
    "format_table",
    "print_progress",
    "run_trace",
    "score",
]

OBSERVABLE_SPAN = 20.0  # degrees

TABLE_I_CONFIGS: tuple[tuple[bool, float, float], ...] = tuple(
    (kf, sp, sv)
    for sp, sv in ((0.5, 0.25), (1.0, 0.25), (2.0, 0.5), (4.0, 0.5))
    for kf in (False, True)
)
"""(Kalman filter, sigma_pos, sigma_vel) of the eight rows of Table I."""

PAPER_TABLE_I: dict[tuple[bool, float], tuple[float, float, float, float]] = {
    (False, 0.5): (2.02, 2.76, 2.94, 0.91),
    (True, 0.5): (1.93, 2.58, 2.75, 0.91),
    (False, 1.0): (2.07, 2.90, 3.07, 0.87),
    (True, 1.0): (1.95, 2.70, 2.83, 0.88),
    (False, 2.0): (2.30, 3.30, 3.47, 0.79),
    (True, 2.0): (2.11, 2.95, 3.00, 0.80),
    (False, 4.0): (3.62, 4.42, 4.90, 0.68),
    (True, 4.0): (3.10, 3.70, 4.10, 0.66),
}
"""The paper's (RMSE_x, RMSE_y, AED, Acc.) per (Kalman filter, sigma_pos)."""


@dataclass(frozen=True)
class RunResult:
    """The scores of one run."""

    rmse_x: float
    rmse_y: float
    aed: float
    accuracy: float
    cross: float  # mean |error| across the road
    along: float  # mean |error| along the road
    aed_before: float  # AED before the common error was observable (nan if never)
    aed_after: float  # AED after (nan if it never became observable)
    raw_aed: float  # AED of the raw fixes
    answered: int


@dataclass(frozen=True)
class Row:
    """Mean scores of one configuration over its runs."""

    mode: Mode
    kalman: bool
    sigma_pos: float
    sigma_vel: float
    runs: int
    rmse_x: float
    rmse_y: float
    aed: float
    accuracy: float
    cross: float
    along: float
    aed_before: float
    aed_after: float
    raw_aed: float
    paper: tuple[float, float, float, float] | None

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def answer_trace(
    hdmap: HdMap, trace: Trace, config: EngineConfig | None = None
) -> list[CorrectedPosition | None]:
    """A fresh engine's answer to every fix of a simulated trace, in order."""
    engine = Engine(hdmap, config)
    return [engine.process(f.user, f.measurement) for f in trace.fixes]


def run_trace(hdmap: HdMap, trace: Trace, config: EngineConfig) -> RunResult:
    """Feed a simulated trace to a fresh engine and score its answers."""
    return score(hdmap, trace, answer_trace(hdmap, trace, config))


def score(hdmap: HdMap, trace: Trace, answers: Sequence[CorrectedPosition | None]) -> RunResult:
    """Score answers (one per fix of the trace, None where none came) against the truth."""
    proj = hdmap.projection
    n = len(trace.fixes)
    if len(answers) != n:
        raise ValueError(f"{len(answers)} answers for {n} fixes; give one (or None) per fix")
    err = np.full((n, 2), np.nan)
    raw = np.zeros(n)
    ok = np.zeros(n, dtype=bool)
    tangent = np.zeros((n, 2))
    observable = np.zeros(n, dtype=bool)
    lo = hi = None
    for i, (fix, answer) in enumerate(zip(trace.fixes, answers, strict=True)):
        h = math.radians(fix.true_heading)
        tangent[i] = (math.sin(h), math.cos(h))
        heading = fix.true_heading
        if lo is None or hi is None:
            lo = hi = heading
        else:  # the span of road orientations seen so far (mod 180: both ways are one road)
            rel = (heading - lo + 90.0) % 180.0 - 90.0
            lo, hi = (lo + min(rel, 0.0)) % 180.0, max(hi, lo + max(rel, 0.0))
        observable[i] = (hi - lo) > OBSERVABLE_SPAN
        m = fix.measurement
        me, mn = proj.to_utm(m.longitude, m.latitude)
        raw[i] = math.hypot(me - fix.true_e, mn - fix.true_n)
        if answer is None:
            continue
        e, nn = proj.to_utm(answer.longitude, answer.latitude)
        err[i] = (e - fix.true_e, nn - fix.true_n)
        ok[i] = answer.segment == fix.segment and answer.lane == fix.lane
    answered = ~np.isnan(err[:, 0])
    if not answered.any():
        raise ValueError("no fix of the trace was answered; nothing to score")
    e_ok = err[answered]
    dist = np.hypot(e_ok[:, 0], e_ok[:, 1])
    t_ok = tangent[answered]
    along = np.abs((e_ok * t_ok).sum(axis=1))
    cross = np.abs(e_ok[:, 0] * t_ok[:, 1] - e_ok[:, 1] * t_ok[:, 0])
    obs = observable[answered]
    return RunResult(
        rmse_x=float(np.sqrt(np.mean(e_ok[:, 0] ** 2))),
        rmse_y=float(np.sqrt(np.mean(e_ok[:, 1] ** 2))),
        aed=float(dist.mean()),
        accuracy=float(ok.mean()),
        cross=float(cross.mean()),
        along=float(along.mean()),
        aed_before=float(dist[~obs].mean()) if (~obs).any() else math.nan,
        aed_after=float(dist[obs].mean()) if obs.any() else math.nan,
        raw_aed=float(raw.mean()),
        answered=int(answered.sum()),
    )


@lru_cache(maxsize=4)
def _load(path: str) -> HdMap:
    return HdMap.load(path)


def _job(args: tuple[Scenario, ErrorModel, EngineConfig, int]) -> RunResult:
    scenario, errors, config, seed = args
    hdmap = _load(scenario.map)
    return run_trace(hdmap, simulate(hdmap, scenario, errors, seed), config)


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan


def evaluate(
    scenario: Scenario,
    *,
    modes: Sequence[Mode] = ("paper", "default"),
    runs: int = 20,
    configs: Sequence[tuple[bool, float, float]] = TABLE_I_CONFIGS,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[Row]:
    """Run every (mode, configuration) on seeds 0..runs-1; the same seeds for every mode.

    The engine is told the sensor sigmas of each configuration, as the paper tunes its
    Kalman filter "by approximating the sensor accuracy".
    """
    base = scenario.errors
    jobs: list[tuple[Scenario, ErrorModel, EngineConfig, int]] = []
    keys: list[tuple[Mode, bool, float, float]] = []
    for mode in modes:
        for kalman, sp, sv in configs:
            errors = base.model_copy(update={"sigma_pos": sp, "sigma_vel": sv})
            config = EngineConfig(
                mode=mode,
                kalman=kalman,
                sigma_pos=sp,
                sigma_vel=sv,
                sigma_heading=max(errors.sigma_heading, 0.01),
            )
            for seed in range(runs):
                jobs.append((scenario, errors, config, seed))
                keys.append((mode, kalman, sp, sv))
    workers = workers or min(os.cpu_count() or 1, 4)
    results: list[RunResult] = []

    def _iter() -> Iterator[RunResult]:
        if workers <= 1:
            yield from map(_job, jobs)
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                yield from pool.map(_job, jobs, chunksize=max(1, runs // 4))

    for k, result in enumerate(_iter(), start=1):
        results.append(result)
        if progress is not None:
            progress(k, len(jobs))
    rows: list[Row] = []
    for key in dict.fromkeys(keys):
        mine = [r for r, kk in zip(results, keys, strict=True) if kk == key]
        mode, kalman, sp, sv = key
        rows.append(
            Row(
                mode=mode,
                kalman=kalman,
                sigma_pos=sp,
                sigma_vel=sv,
                runs=len(mine),
                rmse_x=_mean([r.rmse_x for r in mine]),
                rmse_y=_mean([r.rmse_y for r in mine]),
                aed=_mean([r.aed for r in mine]),
                accuracy=_mean([r.accuracy for r in mine]),
                cross=_mean([r.cross for r in mine]),
                along=_mean([r.along for r in mine]),
                aed_before=_mean([r.aed_before for r in mine]),
                aed_after=_mean([r.aed_after for r in mine]),
                raw_aed=_mean([r.raw_aed for r in mine]),
                paper=PAPER_TABLE_I.get((kalman, sp)) if scenario.name == "messe-hamburg" else None,
            )
        )
    return rows


def format_table(rows: Sequence[Row]) -> str:
    """Table I with our figures beside the paper's (in brackets) and the extra columns."""
    head = (
        f"{'mode':<8}{'KF':<4}{'s_pos':>6}{'s_vel':>6}  {'RMSE_x':>13}{'RMSE_y':>13}"
        f"{'AED':>13}{'Acc.':>13}   {'cross':>6}{'along':>6}{'AED<obs':>8}{'AED>obs':>8}"
        f"{'raw AED':>8}{'AED cut':>8}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        p = r.paper

        def cell(v: float, i: int, p: tuple[float, ...] | None = p) -> str:
            return f"{v:.2f} ({p[i]:.2f})" if p is not None else f"{v:.2f}"

        cut = 1.0 - r.aed / r.raw_aed if r.raw_aed > 0 else math.nan
        lines.append(
            f"{r.mode:<8}{'yes' if r.kalman else 'no':<4}{r.sigma_pos:>6.1f}{r.sigma_vel:>6.2f}  "
            f"{cell(r.rmse_x, 0):>13}{cell(r.rmse_y, 1):>13}{cell(r.aed, 2):>13}"
            f"{cell(r.accuracy, 3):>13}   {r.cross:>6.2f}{r.along:>6.2f}"
            f"{r.aed_before:>8.2f}{r.aed_after:>8.2f}{r.raw_aed:>8.2f}{cut:>8.0%}"
        )
    lines.append(
        "(paper's Table I in brackets; cross/along: mean |error| across/along the road; "
        "AED<obs / AED>obs: before/after the common error became observable; "
        "AED cut: 1 - AED / raw AED)"
    )
    return "\n".join(lines)


def print_progress(done: int, total: int) -> None:
    """A progress line on stderr, rewritten in place on a terminal."""
    end = "\n" if done == total or not sys.stderr.isatty() else "\r"
    if done == total or sys.stderr.isatty() or done % max(1, total // 10) == 0:
        print(f"evaluate: {done}/{total} runs", end=end, file=sys.stderr, flush=True)
