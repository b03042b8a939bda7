"""Scores of a run: the engine's answers against the ground truth of a simulated trace.

    RMSE_x = sqrt(mean (e_hat - e)^2),   RMSE_y = sqrt(mean (n_hat - n)^2),
    AED    = mean sqrt((e_hat - e)^2 + (n_hat - n)^2),
    Acc.   = share of fixes whose answered lane is the true one by geometry: it holds
             the true position, or it is the truth's lane continued across element seams
             (`laas.evaluation.integrity`; the same physical lane wherever a map cuts its road
             into elements); Acc. by id, beside it for one release, the share
             whose (segment, lane) is the true one.

Each answer's stated confidence is scored too (`laas.evaluation.integrity`): its probability
against whether its (segment, lane) was the true one (the probability is that of the road
element and the lane it names: near a seam, within the error along the road, the
neighbouring element's lane is a wrong answer), its accuracies across and along the road
against its errors there.

Errors are also split across and along the road (the true direction of travel), and
before and after the common error became observable: the first time the orientations of
the roads the users have driven so far span more than `OBSERVABLE_SPAN` degrees (until
then no lane constraint says anything along the road).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from laas.config import EngineConfig
from laas.engine import Engine
from laas.evaluation.integrity import IntegrityTally, lane_right
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.sim.batches import MAX_BATCH, in_batches
from laas.sim.plan import Fixes
from laas.sim.scenario import SimulatedFix

__all__ = ["OBSERVABLE_SPAN", "RunResult", "answer_trace", "judge", "run_trace", "score"]

OBSERVABLE_SPAN = 20.0  # degrees


@dataclass(frozen=True)
class RunResult:
    """The scores of one run."""

    rmse_x: float
    rmse_y: float
    aed: float
    accuracy: float  # the answered lane holds the true position (geometry)
    cross: float  # mean |error| across the road
    along: float  # mean |error| along the road
    aed_before: float  # AED before the common error was observable (nan if never)
    aed_after: float  # AED after (nan if it never became observable)
    raw_aed: float  # AED of the raw fixes
    answered: int
    accuracy_id: float  # the answered (segment, lane) is the true one
    integrity: IntegrityTally  # stated confidence against the truth

    @property
    def worse_than_raw(self) -> bool:
        """The corrected positions are, on average, further from the truth than the fixes."""
        return self.aed > self.raw_aed


def answer_trace(
    hdmap: HdMap, trace: Fixes, config: EngineConfig | None = None, max_batch: int = MAX_BATCH
) -> list[CorrectedPosition | None]:
    """A fresh engine's answer to every fix of a simulated trace, in order, given to it
    in batches as the live worker takes them (`laas.sim.batches`; `max_batch` 1: one
    at a time)."""
    engine = Engine(hdmap, config)
    fixes = [(f.user, f.measurement) for f in trace.fixes]
    out: list[CorrectedPosition | None] = []
    for batch in in_batches(fixes, lambda f: f[1].timestamp, max_batch=max_batch):
        out.extend(engine.process_many(batch))
    return out


def run_trace(hdmap: HdMap, trace: Fixes, config: EngineConfig) -> RunResult:
    """Feed a simulated trace to a fresh engine and score its answers."""
    return score(hdmap, trace, answer_trace(hdmap, trace, config))


def judge(
    hdmap: HdMap, fix: SimulatedFix, answer: CorrectedPosition
) -> tuple[float, float, bool, bool]:
    """One answer against its fix's truth: (east, north error in m, its (segment, lane) is
    the true one, its lane is right by geometry (`lane_right`))."""
    e, n = hdmap.projection.to_utm(answer.longitude, answer.latitude)
    by_id = answer.segment == fix.segment and answer.lane == fix.lane
    right = by_id or lane_right(
        hdmap, (answer.segment, answer.lane), (fix.segment, fix.lane), fix.true_e, fix.true_n
    )
    return e - fix.true_e, n - fix.true_n, by_id, right


def score(hdmap: HdMap, trace: Fixes, answers: Sequence[CorrectedPosition | None]) -> RunResult:
    """Score answers (one per fix of the trace, None where none came) against the truth."""
    proj = hdmap.projection
    n = len(trace.fixes)
    if len(answers) != n:
        raise ValueError(f"{len(answers)} answers for {n} fixes; give one (or None) per fix")
    err = np.full((n, 2), np.nan)
    raw = np.zeros(n)
    ok = np.zeros(n, dtype=bool)
    ok_id = np.zeros(n, dtype=bool)
    prob = np.zeros(n)
    sigma = np.full((n, 2), np.nan)  # reported 1-sigma across, along
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
        err[i, 0], err[i, 1], ok_id[i], ok[i] = judge(hdmap, fix, answer)
        prob[i] = answer.probability
        sigma[i] = (answer.accuracy_cross, answer.accuracy_along)
    answered = ~np.isnan(err[:, 0])
    if not answered.any():
        raise ValueError("no fix of the trace was answered; nothing to score")
    e_ok = err[answered]
    dist = np.hypot(e_ok[:, 0], e_ok[:, 1])
    t_ok = tangent[answered]
    along = np.abs((e_ok * t_ok).sum(axis=1))
    cross = np.abs(e_ok[:, 0] * t_ok[:, 1] - e_ok[:, 1] * t_ok[:, 0])
    obs = observable[answered]
    tally = IntegrityTally()
    for p, right in zip(prob[answered], ok_id[answered], strict=True):
        tally.add_answer(float(p), bool(right))
    rated = ~np.isnan(sigma[answered, 0])
    tally.add_errors(
        cross[rated], along[rated], sigma[answered][rated, 0], sigma[answered][rated, 1]
    )
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
        accuracy_id=float(ok_id.mean()),
        integrity=tally,
    )
