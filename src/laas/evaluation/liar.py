"""A participant that lies: the suites' scenarios with one liar, scored against their twins.

Every run (family, seed, sigma_pos) of a suite is simulated twice with the same noise: as
drawn (the *honest twin*), and with one of its users lying (`draw_liar`; the lie draws
no random numbers, so every other fix is the same number for number). Both traces go to
a fresh `Engine` configured as the live worker would be (`laas.evaluation.suite.engine_config`),
once per engine variant (`VARIANTS`: `before`, the common error pooled from every user's
evidence in full, the default; `after`, the one-liar mixture with
K = `laas.config.LIAR_EVIDENCE_CAP`, see `laas.engine.common_error`). The liar's own
answers are not scored: what it is told does not matter. What is, over the fixes of the
other users (its *neighbours*) from the liar's first false fix on:

  common-error deviation   the common error the engine holds at the neighbour's place
                           with the liar against the same without it, across the road,
                           |n . (b_L - b_H)| (n the road's normal at the neighbour): per
                           run its median, 95th percentile and maximum, and the same in
                           standard deviations of the estimate without the liar (z)
  neighbours' lanes        their lane accuracy with and without the liar, and the drop

The liar (`draw_liar`), drawn from its own generator seeded by (crc32("liar"),
crc32(family), seed), so that the scenario's own draws are untouched:

  who      any user of the scenario, uniformly (a one-user scenario has no neighbours:
           it counts in the honest figures only)
  how      offset, drift or lane with p 1/3 each, from its first fix on:
             offset  a constant false offset: across the road +-U(1, 5) m (right or left
                     of its travel), along it +-U(0, 15) m
             drift   the same kind of offset, across +-U(2, 6) m and along +-U(0, 15) m,
                     growing linearly from nothing over U(20, 60) s
             lane    a neighbouring lane: its whole drive one lane to its right or left
                     (a side the road has at its first lane, else the other)
  every lie is a drive on or beside the road (the generated roads are 5-30 m wide), at
  the false path's own speed and heading, inside the area of the common error

`sweep` moves the liar across the road by fixed amounts instead (the influence curve).

    laas liar --suite dev --workers 2
    laas liar --suite heldout --workers 2
    laas liar --suite ci --sweep 0.5,1,1.5,2,3,4,6
"""

from __future__ import annotations

import math
import os
import time
import zlib
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field

import numpy as np

from laas.config import LIAR_EVIDENCE_CAP, EngineConfig
from laas.engine import Engine
from laas.errors import ConfigError
from laas.evaluation.suite import Suite, engine_config, sigma_vel_for
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.progress import Progress
from laas.sim.family import FamilyCase, build_case
from laas.sim.scenario import Lie, Scenario, Trace, simulate_with

__all__ = [
    "VARIANTS",
    "LiarRow",
    "LiarScore",
    "Tracked",
    "draw_liar",
    "format_liar_report",
    "liar_report",
    "liar_scenario",
    "run_liar_case",
    "run_liar_suite",
    "score_liar",
    "track_answers",
]

VARIANTS: dict[str, dict[str, object]] = {
    "before": {"max_user_evidence": None},
    "after": {"max_user_evidence": LIAR_EVIDENCE_CAP},
}
"""Engine variants: overrides of the suite's `engine_config("default", sigma_pos)`.
`before` is the estimator without the cap (the default), `after` the one-liar mixture."""


def draw_liar(case: FamilyCase) -> tuple[str, Lie]:
    """The liar of a drawn case and its lie (see the module docstring)."""
    if case.road is None:
        raise ConfigError(
            f"{case.family}: a liar is drawn on the drawn families' roads only "
            "(a user roaming a real map drives a path, which cannot carry a lie yet)"
        )
    rng = np.random.default_rng([zlib.crc32(b"liar"), zlib.crc32(case.family.encode()), case.seed])
    users = case.scenario.users
    plan = users[int(rng.integers(0, len(users)))]
    kind = ("offset", "drift", "lane")[int(rng.integers(0, 3))]
    side = 1.0 if rng.random() < 0.5 else -1.0
    if kind == "offset":
        across = side * float(rng.uniform(1.0, 5.0))
        along = float(rng.uniform(-15.0, 15.0))
        return plan.user, Lie(across=across, along=along, start=plan.enter)
    if kind == "drift":
        across = side * float(rng.uniform(2.0, 6.0))
        along = float(rng.uniform(-15.0, 15.0))
        ramp = float(rng.uniform(20.0, 60.0))
        return plan.user, Lie(across=across, along=along, start=plan.enter, ramp=ramp)
    step = int(side)
    first = plan.lanes[0][1]
    right = step if not plan.reverse else -step  # in lane indices, left to right
    if not 0 <= first + right < len(case.road.lanes):
        step = -step
    return plan.user, Lie(lanes=step, start=plan.enter)


def liar_scenario(scenario: Scenario, user: str, lie: Lie) -> Scenario:
    """The scenario with `user` lying."""
    users = tuple(
        p.model_copy(update={"lie": lie}) if p.user == user else p for p in scenario.users
    )
    if users == scenario.users:
        raise ValueError(f"no user {user!r} in scenario {scenario.name}")
    return scenario.model_copy(update={"users": users})


@dataclass(frozen=True)
class Tracked:
    """A run's answers and, at each fix, the common error the engine held at its place."""

    answers: list[CorrectedPosition | None]
    common: np.ndarray  # (fixes, 2), nan where the engine held none
    cov: np.ndarray  # (fixes, 2, 2): its covariance


def track_answers(hdmap: HdMap, trace: Trace, config: EngineConfig) -> Tracked:
    """A fresh engine's answers to a trace and its common error (the area nearest the true
    position) after each fix."""
    engine = Engine(hdmap, config)
    answers: list[CorrectedPosition | None] = []
    common = np.full((len(trace.fixes), 2), np.nan)
    cov = np.full((len(trace.fixes), 2, 2), np.nan)
    for k, f in enumerate(trace.fixes):
        answers.append(engine.process(f.user, f.measurement))
        areas = engine.common_errors()
        if areas:
            here = np.array([f.true_e, f.true_n])
            area = min(areas, key=lambda a: float(np.hypot(*(a.centre - here))))
            common[k], cov[k] = area.b, area.P
    return Tracked(answers, common, cov)


@dataclass(frozen=True)
class LiarScore:
    """One engine variant on one run, with and without the liar."""

    honest_accuracy: float  # every user's lane accuracy, no liar (the suite's figure)
    honest_aed: float  # and their mean distance error, m (AED, the suite's figure)
    neighbours_honest: float  # the other users' lane accuracy without the liar
    neighbours_liar: float  # and with it
    deviation_p95: float  # 95th percentile over the neighbours' fixes of |b_L - b_H|, m
    deviation_max: float
    across_median: float  # median over the neighbours' fixes of |n . (b_L - b_H)|, m
    across_p95: float  # (n the road's normal at the neighbour) and its 95th percentile
    across_max: float
    z_p95: float  # 95th percentile of |n . (b_L - b_H)| / sqrt(n' P_H n): in the honest
    z_max: float  # estimate's own standard deviations across the road, and its maximum
    error_honest_p95: float  # 95th percentile of |n . (b_H - b_true)| across the road, m
    error_liar_p95: float  # and of |n . (b_L - b_true)|
    liar_accuracy: float  # the liar's own lane accuracy (by its true lane): not scored
    seconds: float

    @property
    def drop(self) -> float:
        """How much the liar lowers its neighbours' lane accuracy."""
        return self.neighbours_honest - self.neighbours_liar


def _accuracy(trace: Trace, answers: Sequence[CorrectedPosition | None], mask: np.ndarray) -> float:
    if not mask.any():
        return math.nan
    ok = [
        a is not None and a.segment == f.segment and a.lane == f.lane
        for f, a, m in zip(trace.fixes, answers, mask, strict=True)
        if m
    ]
    return float(np.mean(ok))


def _aed(hdmap: HdMap, trace: Trace, answers: Sequence[CorrectedPosition | None]) -> float:
    """Mean distance of the answers from the truth (AED), m, as `laas.evaluation.score` has it."""
    dist = []
    for f, a in zip(trace.fixes, answers, strict=True):
        if a is not None:
            e, n = hdmap.projection.to_utm(a.longitude, a.latitude)
            dist.append(math.hypot(e - f.true_e, n - f.true_n))
    return float(np.mean(dist)) if dist else math.nan


def _pct(values: np.ndarray, q: float) -> float:
    v = values[~np.isnan(values)]
    return float(np.percentile(v, q)) if v.size else math.nan


def score_liar(
    hdmap: HdMap,
    honest: Trace,
    lying: Trace,
    liar: str,
    a: Tracked,
    b: Tracked,
    seconds: float = 0.0,
) -> LiarScore:
    """Score a variant's answers to the honest twin (`a`) and the liar's trace (`b`)."""
    users = np.array([f.user for f in honest.fixes])
    others = users != liar
    started = next((k for k, f in enumerate(lying.fixes) if f.lie), len(lying.fixes))
    after = others & (np.arange(len(users)) >= started)
    heading = np.radians([f.true_heading for f in honest.fixes])
    normal = np.stack([np.cos(heading), -np.sin(heading)], axis=1)  # right of travel
    diff = b.common - a.common
    dev = np.hypot(diff[:, 0], diff[:, 1])[after]
    across = np.abs((diff * normal).sum(axis=1))[after]
    var = np.einsum("ki,kij,kj->k", normal, a.cov, normal)
    z = across / np.sqrt(np.maximum(var[after], 1e-12))
    truth = np.array([(f.common_e, f.common_n) for f in honest.fixes])
    err_h = np.abs(((a.common - truth) * normal).sum(axis=1))[after]
    err_l = np.abs(((b.common - truth) * normal).sum(axis=1))[after]
    return LiarScore(
        honest_accuracy=_accuracy(honest, a.answers, np.ones(len(users), dtype=bool)),
        honest_aed=_aed(hdmap, honest, a.answers),
        neighbours_honest=_accuracy(honest, a.answers, others),
        neighbours_liar=_accuracy(lying, b.answers, others),
        deviation_p95=_pct(dev, 95),
        deviation_max=float(np.nanmax(dev)) if np.isfinite(dev).any() else math.nan,
        across_median=_pct(across, 50),
        across_p95=_pct(across, 95),
        across_max=float(np.nanmax(across)) if np.isfinite(across).any() else math.nan,
        z_p95=_pct(z, 95),
        z_max=float(np.nanmax(z)) if np.isfinite(z).any() else math.nan,
        error_honest_p95=_pct(err_h, 95),
        error_liar_p95=_pct(err_l, 95),
        liar_accuracy=_accuracy(lying, b.answers, ~others),
        seconds=seconds,
    )


@dataclass(frozen=True)
class LiarRow:
    """One (family, seed, sigma_pos) run with its liar: the lie and each variant's scores."""

    family: str
    seed: int
    sigma_pos: float
    users: int
    liar: str
    lie: dict[str, float]
    variants: dict[str, LiarScore] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        out = asdict(self)
        for name, sc in self.variants.items():
            out["variants"][name]["drop"] = sc.drop
        return out


def run_liar_case(
    family: str,
    seed: int,
    sigma_pos: float,
    *,
    lie: Lie | None = None,
    variants: dict[str, dict[str, object]] | None = None,
) -> LiarRow:
    """Simulate a run with and without its liar and score every engine variant on both.
    `lie` replaces the drawn lie (the drawn liar keeps lying, in this way)."""
    case = build_case(family, seed)
    liar, drawn = draw_liar(case)
    lie = drawn if lie is None else lie.model_copy(update={"start": drawn.start})
    sigma_vel = sigma_vel_for(sigma_pos)
    honest = simulate_with(
        case.hdmap, case.scenario, seed, sigma_pos=sigma_pos, sigma_vel=sigma_vel
    )
    lying = simulate_with(
        case.hdmap,
        liar_scenario(case.scenario, liar, lie),
        seed,
        sigma_pos=sigma_pos,
        sigma_vel=sigma_vel,
    )
    scores: dict[str, LiarScore] = {}
    for name, overrides in (variants or VARIANTS).items():
        config = engine_config("default", sigma_pos).model_copy(update=overrides)
        t0 = time.perf_counter()
        a = track_answers(case.hdmap, honest, config)
        b = track_answers(case.hdmap, lying, config)
        scores[name] = score_liar(case.hdmap, honest, lying, liar, a, b, time.perf_counter() - t0)
    return LiarRow(
        family=family,
        seed=seed,
        sigma_pos=sigma_pos,
        users=len(case.scenario.users),
        liar=liar,
        lie={k: float(v) for k, v in lie.model_dump().items()},
        variants=scores,
    )


_Job = tuple[str, int, float, Lie | None, dict[str, dict[str, object]] | None]


def _run(job: _Job) -> LiarRow:
    family, seed, sigma_pos, lie, variants = job
    return run_liar_case(family, seed, sigma_pos, lie=lie, variants=variants)


def run_liar_suite(
    suite: Suite,
    *,
    lies: Sequence[Lie | None] = (None,),
    variants: dict[str, dict[str, object]] | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
) -> list[LiarRow]:
    """Every run of the suite with its liar (each of `lies`; None: the drawn lie), scored
    for each engine variant (default `VARIANTS`)."""
    jobs: list[_Job] = [(f, s, sp, lie, variants) for lie in lies for f, s, sp in suite.jobs()]
    workers = workers or min(os.cpu_count() or 1, 4)

    def _iter() -> Iterator[tuple[int, LiarRow]]:
        if workers <= 1:
            yield from enumerate(map(_run, jobs))
            return
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = {pool.submit(_run, job): k for k, job in enumerate(jobs)}
            for future in as_completed(futures):
                yield futures[future], future.result()

    rows: dict[int, LiarRow] = {}
    for done, (k, row) in enumerate(_iter(), start=1):
        rows[k] = row
        if progress is not None:
            progress(done, len(jobs))
    return [rows[k] for k in range(len(jobs))]


# --- the report -------------------------------------------------------------------------


def _describe(lie: dict[str, float]) -> str:
    if lie.get("lanes"):
        return "lane"
    return "drift" if lie.get("ramp") else "offset"


BOUND = math.sqrt(2.0 * LIAR_EVIDENCE_CAP)
"""The stated bound: sqrt(2 K) standard deviations of the others' estimate (5.7 at K = 16)."""


def _line(label: str, rows: Sequence[LiarRow], variant: str) -> str:
    sc = [r.variants[variant] for r in rows]
    nb = [s for s, r in zip(sc, rows, strict=True) if r.users > 1]  # runs with neighbours

    def col(name: str, where: Sequence[LiarScore]) -> np.ndarray:
        return np.array([getattr(s, name) for s in where], dtype=float)

    def q(v: np.ndarray, p: float) -> float:
        return _pct(v, p) if v.size else math.nan

    drop = np.array([s.drop for s in nb])
    z95 = col("z_p95", sc)
    over = int(np.sum(z95 > BOUND))
    mean_drop = float(np.nanmean(drop)) if drop.size else math.nan
    max_drop = float(np.nanmax(drop)) if drop.size else math.nan
    x50, x95 = col("across_median", sc), col("across_p95", sc)
    return (
        f"{label:<20}{variant:<7}{len(rows):>5}{q(col('honest_accuracy', sc), 50):>7.3f}"
        f"{q(col('honest_aed', sc), 50):>6.2f}{q(col('neighbours_honest', nb), 50):>7.3f}"
        f"{q(col('neighbours_liar', nb), 50):>7.3f}{mean_drop:>7.3f}{q(drop, 90):>6.3f}"
        f"{max_drop:>6.3f}{q(x50, 50):>6.2f}{q(x50, 90):>6.2f}{q(x95, 50):>6.2f}"
        f"{q(x95, 90):>6.2f}{q(z95, 50):>6.1f}{q(z95, 90):>6.1f}{over:>5}"
    )


def format_liar_report(
    suite: Suite, rows: Sequence[LiarRow], seconds: float | None = None, title: str = ""
) -> str:
    """Per sigma_pos, lie kind and group size, per variant: what the liar does."""
    variants = list(rows[0].variants) if rows else []
    head = f"suite {suite.name} with a liar{title}: {len(rows)} runs"
    if seconds is not None:
        head += f", {seconds:.0f} s"
    cols = (
        f"{'group':<20}{'engine':<7}{'runs':>5}{'honest':>7}{'AED':>6}{'nb w/o':>7}"
        f"{'nb w/':>7}{'drop':>7}{'p90':>6}{'max':>6}{'x50':>6}{'p90':>6}{'x95':>6}"
        f"{'p90':>6}{'z95':>6}{'p90':>6}{'> bd':>5}"
    )
    lines = [head, "", cols, "-" * len(cols)]
    groups: list[tuple[str, list[LiarRow]]] = []
    for sp in sorted({r.sigma_pos for r in rows}):
        mine = [r for r in rows if r.sigma_pos == sp]
        groups.append((f"s_pos {sp:g} all", mine))
        for kind in ("offset", "drift", "lane"):
            groups.append((f"s_pos {sp:g} {kind}", [r for r in mine if _describe(r.lie) == kind]))
        for lo, hi in ((1, 1), (2, 4), (5, 9), (10, 1000)):
            band = f"{lo}-{hi}" if hi < 1000 else f"{lo}+"
            groups.append((f"s_pos {sp:g} users {band}", [r for r in mine if lo <= r.users <= hi]))
    for label, mine in groups:
        if not mine:
            continue
        for v in variants:
            lines.append(_line(label, mine, v))
    lines.append(
        "(honest, AED: every user's lane accuracy and AED (m) without the liar, median over "
        "runs; nb w/o, nb w/: the neighbours' (every user but the liar) lane accuracy "
        "without and with it, median over runs with neighbours; drop: the first minus the "
        "second, mean, 90th percentile and max over those runs; x50, x95: per run the "
        "median and 95th percentile over the neighbours' fixes (from the first false one) "
        "of the common error's deviation across the road |n.(b_L - b_H)|, m, each as median "
        "and 90th percentile over runs; z95: per run the 95th percentile of that deviation "
        "in standard deviations of the estimate without the liar, median and p90 over runs; "
        f"> bd: runs whose z95 passes the stated bound sqrt(2 K) = {BOUND:.1f})"
    )
    return "\n".join(lines)


def liar_report(
    suite: Suite,
    *,
    sweep: Sequence[float] = (),
    caps: Sequence[float] = (),
    workers: int | None = None,
    progress: Progress | None = None,
) -> tuple[list[LiarRow], str]:
    """`laas liar`: every run of the suite with its liar, scored for each engine variant
    (`VARIANTS`, and beside them K = each of `caps`), and the report. With `sweep`, the
    drawn liar lies across the road by each of its offsets (m) instead, one report each."""
    variants: dict[str, dict[str, object]] = dict(VARIANTS)
    for k in caps:
        variants[f"K={float(k):g}"] = {"max_user_evidence": float(k)}
    lies_across = [Lie(across=float(x)) for x in sweep]
    lies: list[Lie | None] = [*lies_across] if lies_across else [None]
    t0 = time.perf_counter()
    rows = run_liar_suite(suite, lies=lies, variants=variants, workers=workers, progress=progress)
    seconds = time.perf_counter() - t0
    if not lies_across:
        return rows, format_liar_report(suite, rows, seconds)
    per = len(rows) // len(lies_across)
    parts = [
        format_liar_report(suite, rows[k * per : (k + 1) * per], None, f", across {lie.across:g} m")
        + "\n"
        for k, lie in enumerate(lies_across)
    ]
    return rows, "\n".join([*parts, f"{seconds:.0f} s"])
