"""Offline correction of a recorded trace with the same engine the worker runs."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Literal

from laas.config import EngineConfig
from laas.engine.engine import Engine
from laas.errors import TraceError
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.sim.batches import IDLE, Idle, in_batches
from laas.sim.trace import TraceLine

__all__ = ["ReplayResult", "replay"]


@dataclass(frozen=True, slots=True)
class ReplayResult:
    """The answer to one trace line."""

    line: int
    user: str
    answer: CorrectedPosition


def replay(
    hdmap: HdMap,
    lines: Iterable[TraceLine | TraceError | Literal[Idle.IDLE]],
    config: EngineConfig | None = None,
    on_error: Callable[[TraceError], None] | None = None,
) -> Iterator[ReplayResult]:
    """Feed the trace to one engine in file order, in batches as the live worker takes
    them (`laas.sim.batches`); bad lines go to `on_error`. `IDLE` among the lines (a
    live source with nothing more ready) answers the batch gathered so far.

    Lines the engine refuses (a duplicate or an older timestamp of the same user) are
    reported to `on_error` too, and produce no answer.
    """
    engine = Engine(hdmap, config)

    def good() -> Iterator[TraceLine | Literal[Idle.IDLE]]:
        for item in lines:
            if item is IDLE:
                yield item
            elif isinstance(item, TraceError):
                if on_error is not None:
                    on_error(item)
            else:
                yield item

    for batch in in_batches(good(), lambda item: item.measurement.timestamp):
        answers = engine.process_many([(item.user, item.measurement) for item in batch])
        for item, answer in zip(batch, answers, strict=True):
            if answer is not None:
                yield ReplayResult(item.line, item.user, answer)
            elif on_error is not None:
                on_error(
                    TraceError(
                        f"line {item.line}: user {item.user!r}: timestamp "
                        f"{item.measurement.timestamp} is not newer than the user's last fix; "
                        "skipped"
                    )
                )
