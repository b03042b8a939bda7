"""Fixes in batches, offline as the live worker takes them.

The live worker hands the engine what waited in its queue together, at most
`ProviderConfig.max_batch` (64) inputs (`Engine.process_many`). GNSS receivers emit on
the whole second, so under a crowd a batch holds fixes of one epoch, which reach the
worker within tens of milliseconds of each other. `laas replay` and `laas evaluate`
cut a trace the same way, so that an offline figure is a live one: consecutive fixes,
in order, while each lies within `WINDOW_MS` of the batch's first and the batch holds
fewer than `MAX_BATCH`.

    WINDOW_MS = 100: one epoch's fixes arrive within this (the cores' flush and the
    brokers' hops are milliseconds), and the next epoch is 1 s later at 1 Hz, so a
    window never joins two epochs of one receiver and no answer waits for a fix that
    would not have arrived with it live.

A live source (`laas replay -` on a pipe) puts `IDLE` among its items whenever it has
no further item ready: the batch gathered so far is answered then, as the live worker
answers what waited in its queue, instead of waiting for the next item to close it. A
file has none, so its batches are those above.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from enum import Enum
from typing import Final, Literal, TypeVar

__all__ = ["IDLE", "MAX_BATCH", "WINDOW_MS", "Idle", "in_batches"]

WINDOW_MS = 100
MAX_BATCH = 64  # the live worker's ProviderConfig.max_batch default

T = TypeVar("T")


class Idle(Enum):
    """The type of `IDLE`."""

    IDLE = "idle"


IDLE: Final = Idle.IDLE
"""Among a source's items: nothing more is ready now; the batch so far is complete."""


def in_batches(
    items: Iterable[T | Literal[Idle.IDLE]],
    timestamp: Callable[[T], int],
    window_ms: int = WINDOW_MS,
    max_batch: int = MAX_BATCH,
) -> Iterator[list[T]]:
    """Consecutive items, in order, in batches of at most `max_batch` whose timestamps
    (ms) lie within `window_ms` of their batch's first; `max_batch` 1 gives the items
    one at a time. `IDLE` among the items ends the batch gathered so far."""
    if max_batch < 1 or window_ms < 0:
        raise ValueError(
            f"batches need max_batch >= 1 and window_ms >= 0, not {max_batch} and {window_ms}"
        )
    batch: list[T] = []
    first = 0
    for item in items:
        if item is IDLE:
            if batch:
                yield batch
                batch = []
            continue
        t = timestamp(item)
        if batch and (len(batch) >= max_batch or abs(t - first) > window_ms):
            yield batch
            batch = []
        if not batch:
            first = t
        batch.append(item)
    if batch:
        yield batch
