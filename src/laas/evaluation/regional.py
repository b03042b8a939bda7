"""Regional workers offline: a trace answered by one worker and by N regional ones.

Each fix goes to the worker of its region as a participant routes it live
(`ldm.client.routing.RoutedSession`): it stays with its worker while the fix lies in that
worker's coverage (`laas.worker.regions`, the strip grown by the overlap) and else goes
to the worker whose coverage holds it deepest. Every worker is an `Engine` fed in the
batches the live worker takes (`laas.sim.batches`). With ``handover`` on, a user's
state moves with it (`Engine.export_user` -> `Engine.import_user`, what the live workers
seal and pass through the participant: `laas.worker.service`), and every
``share_every`` seconds of the trace each worker gives its neighbours its own estimate of
the areas they may use (`Engine.export_areas` -> `Engine.import_areas`); off, each worker
starts every user afresh and estimates its areas alone.

`compare_regions` scores both runs against the truth: lane accuracy, mean position
error (AED), and lane accuracy in the ``after`` fixes that follow each hand-over.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from laas.config import EngineConfig
from laas.engine import Engine
from laas.evaluation.score import RunResult, answer_trace, judge, score
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.sim.batches import in_batches
from laas.sim.scenario import Trace
from laas.worker.regions import Region, split

__all__ = [
    "RegionalComparison",
    "compare_answers",
    "compare_regions",
    "regional_answers",
    "route_fixes",
]


@dataclass(frozen=True)
class RegionalComparison:
    """One worker against `workers` regional ones on the same trace."""

    workers: int
    handover: bool
    one: RunResult
    many: RunResult
    handovers: int  # fixes that went to another worker than the user's one before
    after: int  # fixes counted after each hand-over
    after_one: float  # lane accuracy in those fixes, one worker
    after_many: float  # and regional workers

    def format(self) -> str:
        """The comparison as a few lines."""
        ratio = self.many.aed / self.one.aed if self.one.aed else float("nan")
        way = "with hand-over" if self.handover else "without hand-over (each worker alone)"
        return "\n".join(
            [
                f"{self.workers} regional workers {way}, against one worker:",
                f"  lane accuracy      {self.one.accuracy:.3f} -> {self.many.accuracy:.3f} "
                f"(difference {self.many.accuracy - self.one.accuracy:+.3f})",
                f"  mean error (AED)   {self.one.aed:.2f} -> {self.many.aed:.2f} m "
                f"(ratio {ratio:.3f})",
                f"  lane accuracy in the {self.after} fixes after each of {self.handovers} "
                f"hand-overs  {self.after_one:.3f} -> {self.after_many:.3f}",
            ]
        )


def route_fixes(hdmap: HdMap, trace: Trace, regions: Sequence[Region]) -> list[int]:
    """The region (its index) each fix of `trace` goes to: RoutedSession's rule, in the
    map's frame."""
    xy = hdmap.projection.to_utm_array(
        [f.measurement.longitude for f in trace.fixes],
        [f.measurement.latitude for f in trace.fixes],
    )
    current: dict[str, int] = {}
    out = []
    for fix, (x, y) in zip(trace.fixes, xy, strict=True):

        def depth(r: Region, x: float = float(x), y: float = float(y)) -> float:
            x0, y0, x1, y1 = r.box
            return min(x - x0, x1 - x, y - y0, y1 - y)

        k = current.get(fix.user)
        if k is None or depth(regions[k]) < 0:
            k = max(range(len(regions)), key=lambda i: (depth(regions[i]), regions[i].name))
        current[fix.user] = k
        out.append(k)
    return out


def regional_answers(
    hdmap: HdMap,
    trace: Trace,
    config: EngineConfig | None,
    regions: Sequence[Region],
    *,
    handover: bool = True,
    share_every: float = 1.0,
) -> tuple[list[CorrectedPosition | None], list[int]]:
    """Every fix answered by the worker of its region (module docstring): the answers,
    in order, and the indices of the fixes that came to a worker by a hand-over."""
    route = route_fixes(hdmap, trace, regions)
    engines = [Engine(hdmap, config) for _ in regions]
    if handover:
        for engine in engines:
            engine.record_areas()
    margin = engines[0].config.bias_area / 2.0
    owner: dict[str, int] = {}
    answers: list[CorrectedPosition | None] = [None] * len(trace.fixes)
    handed: list[int] = []
    next_share = None
    order = range(len(trace.fixes))
    for batch in in_batches(order, lambda i: trace.fixes[i].measurement.timestamp):
        t = trace.fixes[batch[0]].measurement.timestamp / 1000.0
        if handover and len(regions) > 1 and (next_share is None or t >= next_share):
            next_share = t + share_every
            _share(engines, regions, margin)
        by_region: dict[int, list[int]] = {}
        for i in batch:
            user, k = trace.fixes[i].user, route[i]
            was = owner.get(user)
            if was is not None and was != k:
                handed.append(i)
                state = engines[was].export_user(user)
                engines[was].forget(user)
                if handover and state is not None:
                    engines[k].import_user(user, state)
            owner[user] = k
            by_region.setdefault(k, []).append(i)
        for k, idx in by_region.items():
            got = engines[k].process_many(
                [(trace.fixes[i].user, trace.fixes[i].measurement) for i in idx]
            )
            for i, answer in zip(idx, got, strict=True):
                answers[i] = answer
    return answers, handed


def _share(engines: Sequence[Engine], regions: Sequence[Region], margin: float) -> None:
    """Each worker's own area evidence to the others, as a family note goes to every
    sibling (`laas.worker.service`): each exports the areas of its coverage once, and
    each other takes those within its own (both grown by half an area)."""
    boxes = [_grown(r.box, margin) for r in regions]
    notes = [(r.name, engines[k].export_areas(boxes[k])) for k, r in enumerate(regions)]
    for k, engine in enumerate(engines):
        for j, (source, states) in enumerate(notes):
            if j != k and states:
                engine.import_areas(source, states, boxes[k])


def _grown(box: tuple[float, float, float, float], by: float) -> tuple[float, float, float, float]:
    return (box[0] - by, box[1] - by, box[2] + by, box[3] + by)


def compare_regions(
    hdmap: HdMap,
    trace: Trace,
    config: EngineConfig | None = None,
    workers: int = 2,
    *,
    handover: bool = True,
    overlap: float = 150.0,
    after: int = 10,
) -> RegionalComparison:
    """One worker against `workers` regional ones on `trace` (module docstring)."""
    regions = split(hdmap, workers, overlap)
    one = answer_trace(hdmap, trace, config)
    many, _ = regional_answers(hdmap, trace, config, regions, handover=handover)
    return compare_answers(hdmap, trace, regions, one, many, handover=handover, after=after)


def compare_answers(
    hdmap: HdMap,
    trace: Trace,
    regions: Sequence[Region],
    one: Sequence[CorrectedPosition | None],
    many: Sequence[CorrectedPosition | None],
    *,
    handover: bool,
    after: int = 10,
) -> RegionalComparison:
    """Score one worker's answers `one` against the regional workers' `many` (offline
    or live, `laas.run.regional`); the hand-overs are where a participant routing the
    fixes changes workers (`RoutedSession`'s rule)."""
    route = route_fixes(hdmap, trace, regions)
    by_user: dict[str, list[int]] = {}
    for i, fix in enumerate(trace.fixes):
        by_user.setdefault(fix.user, []).append(i)
    handed = 0
    following: list[int] = []
    for mine in by_user.values():
        for k in range(1, len(mine)):
            if route[mine[k]] != route[mine[k - 1]]:
                handed += 1
                following += mine[k : k + after]

    def accuracy(answers: Sequence[CorrectedPosition | None]) -> float:
        right = [
            judge(hdmap, trace.fixes[i], a)[3]
            for i in following
            if (a := answers[i]) is not None and a.segment is not None
        ]
        return sum(right) / len(right) if right else float("nan")

    return RegionalComparison(
        len(regions),
        handover,
        score(hdmap, trace, one),
        score(hdmap, trace, many),
        handed,
        after,
        accuracy(one),
        accuracy(many),
    )
