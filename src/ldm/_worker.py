"""The worker thread every LDM component runs its logic on.

paho's network thread only puts events on the worker's queue; the worker handles them
one at a time, so component state needs no locks, and runs ``tick`` between events.
``stop_worker`` ends the thread before the next item, however long the backlog.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Generic, TypeVar

from ldm.transport import Connected

__all__ = ["Worker"]

log = logging.getLogger(__name__)

_Item = TypeVar("_Item")
_STOP = object()


class Worker(Generic[_Item]):
    """A named thread that calls ``handle(item)`` per queued item and ``tick(now)``.

    With ``limit``, at most that many items wait: `offer` refuses what does not fit,
    while `put` always queues (for the few control events that must never be lost,
    such as a reconnect).
    """

    def __init__(self, name: str, interval: float, limit: int | None = None) -> None:
        self._queue: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._interval = interval
        self._limit = limit
        self._stopping = threading.Event()
        self._overflow_lock = threading.Lock()  # several paho threads may overflow at once
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def put(self, item: _Item) -> None:
        """Hand an item to the worker; safe from any thread, never blocks."""
        self._queue.put(item)

    def offer(self, item: _Item) -> bool:
        """Queue an item unless ``limit`` items already wait; False if it was dropped."""
        if self._limit is not None and self._queue.qsize() >= self._limit:
            return False
        self._queue.put(item)
        return True

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

    def start_worker(self) -> None:
        self._thread.start()

    def stop_worker(self, timeout: float = 5.0) -> None:
        """Stop before the next item (the backlog is dropped) and wait for the thread."""
        self._stopping.set()
        if self._thread.is_alive():
            self._queue.put(_STOP)  # wakes a worker waiting on an empty queue
            if threading.current_thread() is not self._thread:
                self._thread.join(timeout)

    def handle(self, item: _Item) -> None:
        raise NotImplementedError

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
                if item is not None:
                    self.handle(item)  # type: ignore[arg-type]
                now = time.time()
                if now >= next_tick:
                    next_tick = now + self._interval
                    self.tick(now)
            except Exception:
                log.exception("%s: error while handling an event", self._thread.name)
