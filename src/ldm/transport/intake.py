"""Fair intake: one FIFO per sender, served round-robin, so a busy sender delays no one.

A `FairQueue` sits between the threads that receive messages (paho's) and the one
thread that handles them (an `ldm.transport.dispatch.Dispatcher`). Each item is queued under a key —
the LDM core uses the participant's client id — or in the urgent lane (key None).

Scheduling rule (what `FairQueue.get` returns next):

1. Urgent items first, in arrival order.
2. Otherwise the keys with waiting items form a ring, in the order in which each last
   became non-empty. ``get`` takes the oldest item of the key at the head of the ring
   and, if that key has more items, moves it to the tail.

So items of one key leave in the order they came; between two items of one key, every
other waiting key gets exactly one (a round); and an item that arrives for a key with
nothing waiting leaves after at most one item of each other waiting key (plus urgent
items), however many items any one key has queued. A flooding key costs every other
key at most one item per round, its own backlog waits behind itself.

``limit`` bounds the items waiting in all lanes together: `offer` refuses beyond it,
`put` (for the few items that must never be lost) does not. Memory is one deque per key
with items waiting; a key's deque is dropped when it runs empty.

Thread safety: every method may be called from any thread (one lock and a condition).
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from collections.abc import Hashable
from typing import Generic, TypeVar

__all__ = ["FairQueue"]

_T = TypeVar("_T")


class FairQueue(Generic[_T]):
    """Per-key FIFOs served round-robin, behind an urgent FIFO; see the module docstring.

    It has the part of `queue.SimpleQueue`'s interface a dispatcher needs: ``put``,
    ``get(timeout)`` (raises `queue.Empty`) and ``qsize``, plus ``offer`` with a key.
    """

    def __init__(self, limit: int | None = None) -> None:
        self._limit = limit
        self._lock = threading.Lock()
        self._ready = threading.Condition(self._lock)
        self._urgent: deque[_T] = deque()
        self._lanes: dict[Hashable, deque[_T]] = {}
        self._ring: deque[Hashable] = deque()
        """The keys with items waiting, head first; each key at most once."""
        self._size = 0

    def put(self, item: _T) -> None:
        """Queue an urgent item, even past ``limit``; never blocks."""
        with self._lock:
            self._urgent.append(item)
            self._size += 1
            self._ready.notify()

    def offer(self, item: _T, key: Hashable | None = None) -> bool:
        """Queue `item` under `key` (None: the urgent lane) unless ``limit`` items wait;
        False if it was not queued."""
        with self._lock:
            if self._limit is not None and self._size >= self._limit:
                return False
            if key is None:
                self._urgent.append(item)
            else:
                lane = self._lanes.get(key)
                if lane is None:
                    lane = self._lanes[key] = deque()
                    self._ring.append(key)
                lane.append(item)
            self._size += 1
            self._ready.notify()
            return True

    def get(self, timeout: float | None = None) -> _T:
        """The next item by the scheduling rule; waits up to `timeout` seconds (None:
        for ever) and raises `queue.Empty` if none came."""
        with self._lock:
            if not self._size and not self._ready.wait_for(lambda: self._size > 0, timeout):
                raise queue.Empty
            self._size -= 1
            if self._urgent:
                return self._urgent.popleft()
            key = self._ring.popleft()
            lane = self._lanes[key]
            item = lane.popleft()
            if lane:
                self._ring.append(key)
            else:
                del self._lanes[key]
            return item

    def take(self, limit: int) -> list[_T]:
        """Up to `limit` waiting items at once, in the order `get` would give them (one
        hand-off for everything that waited); empty if none wait. Never blocks."""
        items: list[_T] = []
        with self._lock:
            urgent, ring, lanes = self._urgent, self._ring, self._lanes
            while len(items) < limit and self._size:
                self._size -= 1
                if urgent:
                    items.append(urgent.popleft())
                    continue
                key = ring.popleft()
                lane = lanes[key]
                items.append(lane.popleft())
                if lane:
                    ring.append(key)
                else:
                    del lanes[key]
        return items

    def qsize(self) -> int:
        """Items waiting in all lanes."""
        return self._size

    def waiting(self, key: Hashable) -> int:
        """Items waiting under `key`."""
        with self._lock:
            lane = self._lanes.get(key)
            return 0 if lane is None else len(lane)

    def __len__(self) -> int:
        return self._size
