"""The dispatch thread every LDM component runs its logic on.

paho's network thread only puts events on the dispatcher's inbox; its thread handles
them one at a time, so component state needs no locks, and runs ``tick`` between events.
``stop_dispatch`` ends the thread before the next item, however long the backlog.
With ``batch`` above one, the thread takes what is waiting, up to ``batch`` items, and
hands them to ``handle_many`` at once (a provider's batch handler, a core's outbox):
the inbox gives them in one hand-off (`Inbox.take`), not one at a time.

The inbox is a plain FIFO unless the component brings its own `Inbox`: the core uses an
`ldm.transport.intake.FairQueue`, which serves its participants round-robin.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Generic, Protocol, TypeVar

from ldm.transport.mqtt import Connected

__all__ = ["Dispatcher", "Inbox"]

log = logging.getLogger(__name__)

_Item = TypeVar("_Item")
_STOP = object()


class Inbox(Protocol):
    """Where a dispatcher's items wait; every method is safe from any thread."""

    def put(self, item: object) -> None:
        """Queue an item, even past any limit (control events, the stop sentinel)."""

    def offer(self, item: object) -> bool:
        """Queue an item within the inbox's limit; False if it was not queued."""
        ...

    def get(self, timeout: float | None = None) -> object:
        """The next item, waiting up to `timeout` s; `queue.Empty` if none came."""
        ...

    def qsize(self) -> int:
        """Items waiting."""
        ...

    def take(self, limit: int) -> list[object]:
        """Up to `limit` waiting items at once (none: empty); never blocks."""
        ...


class _Fifo:
    """The default inbox: one FIFO, at most ``limit`` items offered."""

    def __init__(self, limit: int | None) -> None:
        self._queue: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._limit = limit

    def put(self, item: object) -> None:
        self._queue.put(item)

    def offer(self, item: object) -> bool:
        if self._limit is not None and self._queue.qsize() >= self._limit:
            return False
        self._queue.put(item)
        return True

    def get(self, timeout: float | None = None) -> object:
        return self._queue.get(timeout=timeout)

    def qsize(self) -> int:
        return self._queue.qsize()

    def take(self, limit: int) -> list[object]:
        items: list[object] = []
        get = self._queue.get_nowait
        while len(items) < limit:
            try:
                items.append(get())
            except queue.Empty:
                break
        return items


class Dispatcher(Generic[_Item]):
    """A named thread that calls ``handle(item)`` per queued item and ``tick(now)``.

    With ``limit``, at most that many items wait: `offer` refuses what does not fit,
    while `put` always queues (for the few control events that must never be lost,
    such as a reconnect). ``inbox`` replaces the default FIFO (``limit`` is then the
    inbox's business).
    """

    def __init__(
        self,
        name: str,
        interval: float,
        limit: int | None = None,
        inbox: Inbox | None = None,
        batch: int = 1,
    ) -> None:
        self._queue: Inbox = _Fifo(limit) if inbox is None else inbox
        self._interval = interval
        self._batch = batch
        self._stopping = threading.Event()
        self._overflow_lock = threading.Lock()  # several paho threads may overflow at once
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def put(self, item: _Item) -> None:
        """Hand an item to the dispatch thread; safe from any thread, never blocks."""
        self._queue.put(item)

    def offer(self, item: _Item) -> bool:
        """Queue an item unless the inbox is full; False if it was dropped."""
        return self._queue.offer(item)

    def sink(self, item: _Item) -> None:
        """A transport's sink (paho's thread): a reconnect is always queued; other items
        past ``limit`` are dropped and reported to `overflowed`, one call at a time."""
        if isinstance(item, Connected):
            self.put(item)
        elif not self.offer(item):
            with self._overflow_lock:
                self.overflowed()

    def overflowed(self) -> None:
        """One item was dropped by `sink` (count it); the default does nothing."""

    @property
    def queued(self) -> int:
        """Items waiting in the inbox now (read from any thread, e.g. by metrics)."""
        return self._queue.qsize()

    @property
    def alive(self) -> bool:
        """Whether the dispatch thread is running (started and not stopped)."""
        return self._thread.is_alive()

    def start_dispatch(self) -> None:
        self._thread.start()

    def stop_dispatch(self, timeout: float = 5.0) -> None:
        """Stop before the next item (the backlog is dropped) and wait for the thread."""
        self._stopping.set()
        if self._thread.is_alive():
            self._queue.put(_STOP)  # wakes a thread waiting on an empty queue
            if threading.current_thread() is not self._thread:
                self._thread.join(timeout)

    def handle(self, item: _Item) -> None:
        raise NotImplementedError

    def handle_many(self, items: list[_Item]) -> None:
        """Items that were waiting together, in order; the default handles each."""
        for item in items:
            self.handle(item)

    def tick(self, now: float) -> None:
        """Periodic housekeeping; the default does nothing."""

    def _run(self) -> None:
        next_tick = time.time() + self._interval
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, next_tick - time.time()))
            except queue.Empty:
                item = None
            if item is _STOP or self._stopping.is_set():
                return
            try:
                if item is not None and self._batch > 1:
                    items = self._waiting(item)
                    if self._stopping.is_set():
                        return
                    self.handle_many(items)  # type: ignore[arg-type]
                elif item is not None:
                    self.handle(item)  # type: ignore[arg-type]
                now = time.time()
                if now >= next_tick:
                    next_tick = now + self._interval
                    self.tick(now)
            except Exception:
                log.exception("%s: error while handling an event", self._thread.name)

    def _waiting(self, first: object) -> list[object]:
        """`first` and what waits behind it, up to ``batch`` items, taken from the inbox
        in one hand-off (never the stop: what follows it is dropped)."""
        items = [first, *self._queue.take(self._batch - 1)]
        for i, item in enumerate(items):
            if item is _STOP:
                return items[:i]
        return items
