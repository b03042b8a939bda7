"""Scenario suites: many drawn scenarios (laas.sim.family), three methods, one report.

A suite is a list of (family, seeds) run at each of its sigma_pos values. Every job
(family, seed, sigma_pos) rebuilds its case from (family, seed) in its worker process
(nothing big is pickled), simulates it at that sigma_pos (seed = the scenario's seed;
the scenario's other error features as drawn) and answers every fix three ways:

  default   a fresh Engine in default mode
  paper     a fresh Engine in paper mode, at most PAPER_MAX_HYPOTHESES joint hypotheses
            per road element (users past it are placed alone, as the paper mode allows)
  oracle    the true common error subtracted from each fix, each user's own Kalman track
            (the engine's Track and configuration), placed on the nearest lane centre of
            the map (HdMap.locate, Segment.frame, lane_offsets): what knowing the common
            error alone is worth

The engine is configured as the live worker would be: EngineConfig(mode, sigma_pos,
sigma_vel) with sigma_vel = 0.25 m/s up to sigma_pos 1 m and 0.5 m/s above (the paper's
Table I pairs); it is told nothing else about the scenario. Scores are laas.evaluation.score's.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from laas.config import EngineConfig, Mode
from laas.engine.tracking import Fix, Track, TrackUpdate
from laas.errors import ConfigError
from laas.evaluation.integrity import Integrity, IntegrityTally, run_interval
from laas.evaluation.score import RunResult, answer_trace, score
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.progress import Progress
from laas.sim.family import FAMILIES, MAP_FAMILIES, FamilyCase, build_case
from laas.sim.foreign import FOREIGN_FAMILY, ForeignRoad, find_roads, load_road
from laas.sim.plan import Fixes
from laas.sim.scenario import Trace, simulate_with

__all__ = [
    "METHODS",
    "PAPER_MAX_HYPOTHESES",
    "SUITES",
    "MethodScore",
    "Suite",
    "SuiteRow",
    "Summary",
    "engine_config",
    "foreign_suite",
    "format_report",
    "get_suite",
    "oracle_answers",
    "run_case",
    "run_suite",
    "sigma_vel_for",
    "simulate_case",
    "suite_plots",
    "suite_report",
    "summarize",
    "worst_run",
]

Method = Literal["default", "paper", "oracle"]
METHODS: tuple[Method, ...] = ("default", "paper", "oracle")

PAPER_MAX_HYPOTHESES = 4096
"""Paper mode's cap on L^N in the suites (the engine's own default is 2^20)."""


class Suite(BaseModel):
    """A named list of (family, seeds), each run at every sigma_pos of `sigmas`."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    description: str
    cases: tuple[tuple[str, tuple[int, ...]], ...]
    sigmas: tuple[float, ...] = (1.0, 2.5)
    calibrated: bool = True  # default mode reports its lane probability calibrated
    # A recorded set (`laas.sim.foreign`): its folder, and its runs, each road recorded at
    # one sigma_pos.
    source: str | None = None
    runs: tuple[tuple[str, int, float], ...] | None = None

    def jobs(self) -> list[tuple[str, int, float]]:
        """(family, seed, sigma_pos) of every run, in report order."""
        if self.runs is not None:
            seeds = {f: set(s) for f, s in self.cases}
            return [
                (f, s, sp) for f, s, sp in self.runs if s in seeds.get(f, ()) and sp in self.sigmas
            ]
        return [(f, s, sp) for f, seeds in self.cases for s in seeds for sp in self.sigmas]

    def subset(
        self,
        *,
        families: Sequence[str] | None = None,
        seeds: int | None = None,
        sigmas: Sequence[float] | None = None,
        calibrated: bool | None = None,
    ) -> Suite:
        """The suite cut down for a quicker look: only `families`, the first `seeds`
        seeds of each, only `sigmas`; `calibrated=False` reports default mode's raw
        posterior. A name or a sigma_pos that the suite does not have is refused."""
        cases = self.cases
        if families is not None:
            known = [f for f, _ in cases]
            unknown = sorted(set(families) - set(known))
            if unknown:
                raise ConfigError(
                    f"suite {self.name!r} has no family {', '.join(unknown)}; "
                    f"choose from {', '.join(known)}"
                )
            cases = tuple((f, s) for f, s in cases if f in families)
        if seeds is not None:
            if seeds < 1:
                raise ConfigError(f"seeds must be 1 or more, not {seeds}")
            cases = tuple((f, s[:seeds]) for f, s in cases)
        picked = self.sigmas
        if sigmas is not None:
            unknown_s = sorted(set(sigmas) - set(self.sigmas))
            if unknown_s:
                raise ConfigError(
                    f"suite {self.name!r} runs sigma_pos {', '.join(f'{x:g}' for x in self.sigmas)}"
                    f", not {', '.join(f'{x:g}' for x in unknown_s)}"
                )
            picked = tuple(x for x in self.sigmas if x in sigmas)
        subset = cases != self.cases or picked != self.sigmas
        cal = self.calibrated if calibrated is None else calibrated
        what = []
        if subset:
            sig = ", ".join(f"{x:g}" for x in picked)
            what.append(f"{sum(len(s) for _, s in cases)} scenarios x sigma_pos {sig}")
        if not cal:
            what.append("default mode uncalibrated")
        description = self.description + (f" [subset: {'; '.join(what)}]" if what else "")
        return self.model_copy(
            update={
                "cases": cases,
                "sigmas": picked,
                "calibrated": cal,
                "description": description,
            }
        )


_DEV_SEEDS = tuple(range(0, 40))
_HELDOUT_SEEDS = tuple(range(1000, 1040))

SUITES: dict[str, Suite] = {
    "dev": Suite(
        name="dev",
        description="development: seeds 0-39 of each family (tune on these)",
        cases=tuple((f, _DEV_SEEDS) for f in FAMILIES),
    ),
    "heldout": Suite(
        name="heldout",
        description="held out: seeds 1000-1039 of each family (report on these, never tune)",
        cases=tuple((f, _HELDOUT_SEEDS) for f in FAMILIES),
    ),
    "ci": Suite(
        name="ci",
        description="the test suite's guard: seeds 0-5 of each family (a dev subset)",
        cases=tuple((f, _DEV_SEEDS[:6]) for f in FAMILIES),
    ),
    "maps-dev": Suite(
        name="maps-dev",
        description="real imported maps: seeds 0-19 of each map family (tune on these)",
        cases=tuple((m, _DEV_SEEDS[:20]) for m in MAP_FAMILIES),
    ),
    "maps-heldout": Suite(
        name="maps-heldout",
        description="real imported maps, held out: seeds 1000-1019 of each (never tune)",
        cases=tuple((m, _HELDOUT_SEEDS[:20]) for m in MAP_FAMILIES),
    ),
    "smoke": Suite(
        name="smoke",
        description="a quick check: six small dev scenarios at sigma_pos 1.0",
        cases=(("urban", (1, 4)), ("arterial", (1, 2)), ("shared", (3, 8))),
        sigmas=(1.0,),
    ),
}
"""The suites by name."""


def foreign_suite(root: Path) -> Suite:
    """The roads of a foreign set (`laas.sim.foreign`) as a suite: one family, its roads
    as seeds, each at the sigma_pos it was recorded with."""
    roads = find_roads(root)
    return Suite(
        name="foreign",
        description=(f"roads from another generator ({root}; never tune on these)"),
        cases=((FOREIGN_FAMILY, tuple(r.road for r in roads)),),
        sigmas=tuple(sorted({r.sigma_pos for r in roads})),
        source=str(root),
        runs=tuple((FOREIGN_FAMILY, r.road, r.sigma_pos) for r in roads),
    )


def get_suite(name: str, foreign: Path | None = None) -> Suite:
    """A suite by name (`foreign`: the set in the folder `foreign`); the error lists the
    names there are."""
    if name == "foreign":
        if foreign is None:
            raise ConfigError(
                "suite 'foreign' needs the set's folder: give --foreign DIR "
                "(../shared/foreign-roads was not found)"
            )
        return foreign_suite(foreign)
    try:
        return SUITES[name]
    except KeyError:
        raise ConfigError(
            f"unknown suite {name!r}; choose one of {', '.join(sorted([*SUITES, 'foreign']))}"
        ) from None


def sigma_vel_for(sigma_pos: float) -> float:
    """The receiver speed sigma paired with a position sigma (the paper's Table I pairs)."""
    return 0.25 if sigma_pos <= 1.0 else 0.5


def engine_config(mode: Mode, sigma_pos: float) -> EngineConfig:
    """The engine as the live worker would run it, told only the sensor sigmas."""
    extra = {"max_hypotheses": PAPER_MAX_HYPOTHESES} if mode == "paper" else {}
    return EngineConfig(mode=mode, sigma_pos=sigma_pos, sigma_vel=sigma_vel_for(sigma_pos), **extra)


def oracle_answers(
    hdmap: HdMap, trace: Fixes, config: EngineConfig
) -> list[CorrectedPosition | None]:
    """Each fix less the true common error, Kalman-filtered per user, on the nearest lane."""
    proj = hdmap.projection
    x0, y0, x1, y1 = hdmap.bounds
    convergence = math.radians(proj.convergence(*proj.to_wgs84((x0 + x1) / 2, (y0 + y1) / 2)))
    tracks: dict[str, Track] = {}
    out: list[CorrectedPosition | None] = []
    for sim in trace.fixes:
        m = sim.measurement
        e, n = proj.to_utm(m.longitude, m.latitude)
        fix = Fix(
            t=m.timestamp / 1000.0,
            e=e - sim.common_e,
            n=n - sim.common_n,
            speed=m.speed,
            heading=math.radians(m.heading) - convergence,
            # as the engine reads a fix: the receiver's radius is sqrt(2) sigma per axis
            accuracy=None if m.accuracy is None else m.accuracy / math.sqrt(2.0),
        )
        track = tracks.get(sim.user)
        if track is None:
            track = tracks[sim.user] = Track(config, fix)
        elif track.update(fix) in (TrackUpdate.DUPLICATE, TrackUpdate.OUT_OF_ORDER):
            out.append(None)
            continue
        px, py = (float(v) for v in track.position)
        cov = track.position_cov
        spread = math.sqrt(max(float(np.trace(cov)), 0.0))
        segment = hdmap.locate(px, py, config.max_map_distance)
        lane = None
        if segment is not None:
            s, d = segment.frame(px, py)
            offsets = segment.lane_offsets(s)
            lane = int(np.argmin(np.abs(offsets - d)))
            px, py = segment.point(s, float(offsets[lane]))
        lon, lat = proj.to_wgs84(px, py)
        out.append(
            CorrectedPosition(
                timestamp=m.timestamp,
                latitude=lat,
                longitude=lon,
                segment=None if segment is None else segment.id,
                lane=lane,
                lane_type=None if segment is None or lane is None else segment.lanes[lane].type,
                probability=1.0,
                accuracy=spread,
                accuracy_cross=spread,
                accuracy_along=spread,
            )
        )
    return out


@dataclass(frozen=True)
class MethodScore:
    """One method's scores on one run (nan where it failed; `error` says why)."""

    accuracy: float
    aed: float
    cross: float
    along: float
    aed_before: float
    aed_after: float
    answered: int
    seconds: float
    accuracy_id: float = math.nan  # by (segment, lane) id, beside the geometric score
    raw_aed: float = math.nan
    integrity: IntegrityTally = field(default_factory=IntegrityTally)
    error: str | None = None

    @property
    def worse_than_raw(self) -> bool:
        """The corrected positions were further from the truth than the raw fixes."""
        return self.aed > self.raw_aed

    @classmethod
    def of(cls, result: RunResult, seconds: float) -> MethodScore:
        return cls(
            result.accuracy,
            result.aed,
            result.cross,
            result.along,
            result.aed_before,
            result.aed_after,
            result.answered,
            seconds,
            result.accuracy_id,
            result.raw_aed,
            result.integrity,
        )

    @classmethod
    def failed(cls, error: str, seconds: float) -> MethodScore:
        nan = math.nan
        return cls(nan, nan, nan, nan, nan, nan, 0, seconds, error=error)


@dataclass(frozen=True)
class SuiteRow:
    """One (family, seed, sigma_pos) run: the scenario's size and each method's scores."""

    family: str
    seed: int
    sigma_pos: float
    sigma_vel: float
    users: int
    fixes: int
    lanes: int
    duration: float
    raw_aed: float
    methods: dict[str, MethodScore] = field(default_factory=dict)

    @property
    def failed(self) -> bool:
        """True when a method raised on this run (its score says what, in ``error``)."""
        return any(m.error is not None for m in self.methods.values())

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


Answerer = Callable[[HdMap, Fixes, EngineConfig], list[CorrectedPosition | None]]


def _answerers(
    sigma_pos: float, calibrated: bool = True
) -> dict[Method, tuple[Answerer, EngineConfig]]:
    default = engine_config("default", sigma_pos)
    if not calibrated:
        default = default.model_copy(update={"calibrated": False})
    return {
        "default": (answer_trace, default),
        "paper": (answer_trace, engine_config("paper", sigma_pos)),
        "oracle": (oracle_answers, engine_config("default", sigma_pos)),
    }


def simulate_case(family: str, seed: int, sigma_pos: float) -> tuple[FamilyCase, Trace]:
    """The case of (family, seed) and its trace at sigma_pos (the suite's sigma_vel)."""
    case = build_case(family, seed)
    sigma_vel = sigma_vel_for(sigma_pos)
    trace = simulate_with(case.hdmap, case.scenario, seed, sigma_pos=sigma_pos, sigma_vel=sigma_vel)
    return case, trace


def run_case(
    family: str, seed: int, sigma_pos: float, calibrated: bool = True, source: str | None = None
) -> SuiteRow:
    """Build, simulate and answer one run three ways (see the module docstring); with
    `source`, read road `seed` of that foreign set instead."""
    hdmap: HdMap
    fixes: Fixes
    if source is not None:
        hdmap, foreign = load_road(ForeignRoad(seed, sigma_pos, _road_folder(source, seed)))
        fixes = foreign
        users = len({f.user for f in foreign.fixes})
        lanes = len(foreign.meta.get("lanes", ()))  # type: ignore[arg-type]
        t = [f.measurement.timestamp for f in foreign.fixes]
        duration = (max(t) - min(t)) / 1000.0
    else:
        case, trace = simulate_case(family, seed, sigma_pos)
        hdmap, fixes = case.hdmap, trace
        users, lanes, duration = len(case.scenario.users), case.lanes, case.scenario.duration
    methods: dict[str, MethodScore] = {}
    raw = math.nan
    for method, (answer, config) in _answerers(sigma_pos, calibrated).items():
        t0 = time.perf_counter()
        try:
            result = score(hdmap, fixes, answer(hdmap, fixes, config))
        except Exception as exc:  # a failure is a finding: report it, run the rest
            methods[method] = MethodScore.failed(
                f"{type(exc).__name__}: {exc}", time.perf_counter() - t0
            )
            continue
        methods[method] = MethodScore.of(result, time.perf_counter() - t0)
        raw = result.raw_aed
    return SuiteRow(
        family=family,
        seed=seed,
        sigma_pos=sigma_pos,
        sigma_vel=sigma_vel_for(sigma_pos),
        users=users,
        fixes=len(fixes.fixes),
        lanes=lanes,
        duration=duration,
        raw_aed=raw,
        methods=methods,
    )


def _road_folder(source: str, road: int) -> Path:
    for found in find_roads(Path(source)):
        if found.road == road:
            return found.path
    raise ConfigError(f"{source}: no road {road}")


def _run(job: tuple[str, int, float, bool, str | None]) -> SuiteRow:
    return run_case(*job)


def run_suite(
    suite: Suite, *, workers: int | None = None, progress: Progress | None = None
) -> list[SuiteRow]:
    """Every run of the suite on a pool of `workers` processes; rows in `suite.jobs()` order."""
    jobs = [(f, s, sp, suite.calibrated, suite.source) for f, s, sp in suite.jobs()]
    workers = workers or min(os.cpu_count() or 1, 4)
    rows: dict[tuple[str, int, float], SuiteRow] = {}

    def _iter() -> Iterator[SuiteRow]:
        if workers <= 1:
            yield from map(_run, jobs)
            return
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(_run, job) for job in jobs]
            for future in as_completed(futures):
                yield future.result()

    for k, row in enumerate(_iter(), start=1):
        rows[(row.family, row.seed, row.sigma_pos)] = row
        if progress is not None:
            progress(k, len(jobs))
    return [rows[job] for job in suite.jobs()]


def suite_plots(row: SuiteRow, out: Path) -> list[Path]:
    """The pictures of one run: the traces on the lanes, and each method's lanes over time."""
    from laas.evaluation.plots import plot_lanes_over_time, plot_traces

    case, trace = simulate_case(row.family, row.seed, row.sigma_pos)
    out.mkdir(parents=True, exist_ok=True)
    name = f"{row.family}-{row.seed}-s{row.sigma_pos:g}"
    paths = [plot_traces(case.hdmap, trace, out / f"{name}-traces.png")]
    for method, (answer, config) in _answerers(row.sigma_pos).items():
        answers = answer(case.hdmap, trace, config)
        paths.append(plot_lanes_over_time(trace, answers, out / f"{name}-lanes-{method}.png"))
    return paths


# --- the report -------------------------------------------------------------------------


@dataclass(frozen=True)
class Summary:
    """The distribution over one group of runs (a family at one sigma_pos, or all of them)."""

    family: str  # or "all"
    sigma_pos: float
    runs: int
    accuracy_median: dict[str, float]
    accuracy_p10: dict[str, float]
    accuracy_worst: dict[str, float]
    aed_median: dict[str, float]
    aed_after_median: dict[str, float]
    ratio_default_oracle: float  # median over runs of AED>obs default / oracle
    ratio_runs: int  # runs where both were observable
    default_below_paper: int  # runs where default's accuracy < paper's - 0.05
    failures: int  # method runs that raised
    accuracy_id_median: dict[str, float]  # lane accuracy by id, beside the geometric one
    integrity: dict[str, Integrity]  # every answer of the group's runs, pooled
    wrong_90_interval: dict[str, tuple[float, float]]  # 90 % of integrity.wrong_90, by runs
    worse_than_raw: dict[str, int]  # runs whose AED is above the raw fixes'

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def _stat(values: Sequence[float], how: Callable[[np.ndarray], float]) -> float:
    v = np.asarray([x for x in values if not math.isnan(x)], dtype=float)
    return float(how(v)) if v.size else math.nan


def _summary(family: str, sigma_pos: float, rows: Sequence[SuiteRow]) -> Summary:
    def col(method: str, name: str) -> list[float]:
        return [float(getattr(r.methods[method], name)) for r in rows]

    ratios = [
        r.methods["default"].aed_after / r.methods["oracle"].aed_after
        for r in rows
        if r.methods["oracle"].aed_after > 0.0 and not math.isnan(r.methods["default"].aed_after)
    ]
    below = sum(
        1 for r in rows if r.methods["default"].accuracy < r.methods["paper"].accuracy - 0.05
    )
    return Summary(
        family=family,
        sigma_pos=sigma_pos,
        runs=len(rows),
        accuracy_median={m: _stat(col(m, "accuracy"), np.median) for m in METHODS},
        accuracy_p10={
            m: _stat(col(m, "accuracy"), lambda v: np.percentile(v, 10)) for m in METHODS
        },
        accuracy_worst={m: _stat(col(m, "accuracy"), np.min) for m in METHODS},
        aed_median={m: _stat(col(m, "aed"), np.median) for m in METHODS},
        aed_after_median={m: _stat(col(m, "aed_after"), np.median) for m in METHODS},
        ratio_default_oracle=_stat(ratios, np.median),
        ratio_runs=len(ratios),
        default_below_paper=below,
        failures=sum(1 for r in rows for s in r.methods.values() if s.error is not None),
        accuracy_id_median={m: _stat(col(m, "accuracy_id"), np.median) for m in METHODS},
        integrity={
            m: IntegrityTally.total(r.methods[m].integrity for r in rows).summary() for m in METHODS
        },
        wrong_90_interval={
            m: run_interval([r.methods[m].integrity for r in rows]) for m in METHODS
        },
        worse_than_raw={
            m: sum(1 for r in rows if r.methods[m].error is None and r.methods[m].worse_than_raw)
            for m in METHODS
        },
    )


def summarize(rows: Sequence[SuiteRow]) -> list[Summary]:
    """Per (family, sigma_pos), then per sigma_pos over all families."""
    out: list[Summary] = []
    sigmas = sorted({r.sigma_pos for r in rows})
    families = list(dict.fromkeys(r.family for r in rows))
    for sp in sigmas:
        for f in families:
            mine = [r for r in rows if r.family == f and r.sigma_pos == sp]
            if mine:
                out.append(_summary(f, sp, mine))
        out.append(_summary("all", sp, [r for r in rows if r.sigma_pos == sp]))
    return out


def worst_run(rows: Sequence[SuiteRow]) -> SuiteRow:
    """The run with default mode's lowest lane accuracy (then its largest AED)."""
    return min(
        rows,
        key=lambda r: (
            np.nan_to_num(r.methods["default"].accuracy, nan=-1.0),
            -np.nan_to_num(r.methods["default"].aed, nan=math.inf),
        ),
    )


USER_BANDS = ((1, 2), (3, 4), (5, 9), (10, 1_000))
"""Bands of users per scenario: how much the group can tell about the common error."""


def _by_users(rows: Sequence[SuiteRow]) -> list[str]:
    """Lane accuracy by the number of users in the scenario, over all families."""
    lines = ["by users per scenario (all families): lane accuracy median / p10 / worst"]
    for sp in sorted({r.sigma_pos for r in rows}):
        for lo, hi in USER_BANDS:
            mine = [r for r in rows if r.sigma_pos == sp and lo <= r.users <= hi]
            if not mine:
                continue
            acc = np.array([r.methods["default"].accuracy for r in mine])
            oracle = np.nanmedian([r.methods["oracle"].accuracy for r in mine])
            below = sum(
                r.methods["default"].accuracy < r.methods["paper"].accuracy - 0.05 for r in mine
            )
            band = f"{lo}-{hi}" if hi < 1_000 else f"{lo}+"
            lines.append(
                f"  s_pos {sp:g} users {band:<5} runs {len(mine):>3}: default "
                f"{np.nanmedian(acc):.3f} / {np.nanpercentile(acc, 10):.2f} / "
                f"{np.nanmin(acc):.2f}; oracle median {oracle:.3f}; default below paper "
                f"by > 0.05: {below}"
            )
        mine = [r for r in rows if r.sigma_pos == sp and r.users >= 3]
        if mine:
            acc = np.array([r.methods["default"].accuracy for r in mine])
            lines.append(
                f"  s_pos {sp:g} users 3+    runs {len(mine):>3}: default "
                f"{np.nanmedian(acc):.3f} / {np.nanpercentile(acc, 10):.2f} / {np.nanmin(acc):.2f}"
            )
    lines.append("")
    return lines


def _integrity(summaries: Sequence[Summary]) -> list[str]:
    """Whether the stated confidence holds: per family and sigma_pos, pooled over runs."""
    lines = [
        "integrity (every answer pooled): ECE; share of all answers that said p >= 0.9 and "
        "were wrong, [its 90 % interval over resampled runs] (>= 0.99); share that said "
        ">= 0.9; errors within 1 / 2 sigma across and "
        "along (honest: 0.68 / 0.95); runs with AED above the raw fixes'",
    ]
    for s in summaries:
        for m in ("default", "oracle") if s.family == "all" else ("default",):
            g = s.integrity[m]
            lo, hi = s.wrong_90_interval[m]
            lines.append(
                f"  {s.family:<9}{s.sigma_pos:>4.1f} {m:<8} ECE {g.ece:.3f}  wrong>=.9 "
                f"{g.wrong_90:6.2%} [{lo:.2%}, {hi:.2%}] (>=.99 {g.wrong_99:6.2%})  "
                f"said>=.9 {g.said_90:4.0%}  "
                f"cross {g.cross_1:.2f}/{g.cross_2:.2f}  along {g.along_1:.2f}/{g.along_2:.2f}  "
                f"worse than raw {s.worse_than_raw[m]}/{s.runs}"
            )
        if s.family == "all":
            lines.append(
                f"  reliability of default mode's lane probability, s_pos {s.sigma_pos:g}:"
            )
            lines.extend("    " + line for line in s.integrity["default"].reliability().split("\n"))
    lines.append("")
    return lines


def suite_report(suite: Suite, rows: Sequence[SuiteRow], seconds: float) -> dict[str, object]:
    """What `laas evaluate --suite --json` prints: the suite, its time, the summaries and
    every run."""
    return {
        "suite": suite.name,
        "seconds": seconds,
        "summaries": [s.as_dict() for s in summarize(rows)],
        "runs": [r.as_dict() for r in rows],
    }


def format_report(suite: Suite, rows: Sequence[SuiteRow], seconds: float | None = None) -> str:
    """The suite's distributions per family and sigma_pos, one line per method."""
    fixes = sum(r.fixes for r in rows)
    head = (
        f"suite {suite.name}: {suite.description}; {len(rows)} runs "
        f"({len({(r.family, r.seed) for r in rows})} scenarios x sigma_pos "
        f"{', '.join(f'{s:g}' for s in suite.sigmas)}), {fixes} fixes"
    )
    if seconds is not None:
        head += f", {seconds:.0f} s"
    cols = (
        f"{'family':<9}{'s_pos':>5}{'runs':>5}  {'method':<8}{'acc med':>8}{'p10':>6}"
        f"{'worst':>6}{'id med':>7}{'AED med':>8}{'AED>obs':>8}{'s/run':>7}"
    )
    lines = [head, "", cols, "-" * len(cols)]
    summaries = summarize(rows)
    for s in summaries:
        mine = [r for r in rows if r.sigma_pos == s.sigma_pos and s.family in ("all", r.family)]
        for k, m in enumerate(METHODS):
            secs = float(np.mean([r.methods[m].seconds for r in mine]))
            lead = f"{s.family:<9}{s.sigma_pos:>5.1f}{s.runs:>5}" if k == 0 else " " * 19
            lines.append(
                f"{lead}  {m:<8}{s.accuracy_median[m]:>8.3f}{s.accuracy_p10[m]:>6.2f}"
                f"{s.accuracy_worst[m]:>6.2f}{s.accuracy_id_median[m]:>7.3f}{s.aed_median[m]:>8.2f}"
                f"{s.aed_after_median[m]:>8.2f}{secs:>7.1f}"
            )
        lines.append(
            f"{'':19}  AED>obs default/oracle (median of {s.ratio_runs}): "
            f"{s.ratio_default_oracle:.2f}; default below paper by > 0.05: "
            f"{s.default_below_paper}/{s.runs}"
            + (f"; FAILED method runs: {s.failures}" if s.failures else "")
        )
        if s.family == "all":
            lines.append("")
    lines.extend(_by_users(rows))
    lines.extend(_integrity(summaries))
    worst = worst_run(rows)
    lines.append(
        f"worst run (default mode): {worst.family} seed {worst.seed} at sigma_pos "
        f"{worst.sigma_pos:g}: lane accuracy {worst.methods['default'].accuracy:.3f} "
        f"(paper {worst.methods['paper'].accuracy:.3f}, oracle "
        f"{worst.methods['oracle'].accuracy:.3f}), {worst.users} user"
        f"{'' if worst.users == 1 else 's'}, {worst.lanes} lanes"
    )
    for r in rows:
        for name, sc in r.methods.items():
            if sc.error is not None:
                lines.append(
                    f"FAILED: {r.family} seed {r.seed} sigma_pos {r.sigma_pos:g} {name}: {sc.error}"
                )
    lines.append(
        "(acc: lane accuracy by geometry (the answered lane holds the true position), p10 its "
        "10th percentile; id med: the median by (segment, lane) id; AED>obs: AED once the "
        "common error is observable; s/run: mean seconds per run of the method, one core)"
    )
    return "\n".join(lines)
