"""The live map's feed: the worker's answered fixes as server-sent events, fanned out.

Threads, and what each may do:

- the provider's dispatch thread calls `Feed.observe` (it is `LaasService.observer`) once
  per batch of answered fixes. It only appends the batch, with the engine time it took
  and, at most every `areas_every` seconds, references to the common-error estimates
  (which the worker replaces whole, never changes in place), to a bounded inbox and,
  while a page is connected, wakes the feed's thread: no encoding, no lock held by
  anyone else, no socket. With no page the feed's thread takes the inbox at its stats
  tick.
- the feed's thread (``laas-dashboard-feed``) encodes each batch once as a ``batch``
  event, the areas as an ``areas`` event, and every `stats_every` seconds a ``stats``
  event (rates and engine times from `WorkerStats`), and puts each event into every
  client's queue. With no client connected it only keeps each pseudonym's last answered
  fix and the latest areas as they came, and makes the page's views of them when a
  client asks (`state`): no views and no encoding for nobody.
- each client (an HTTP handler thread) takes events from its own queue and writes them
  to its socket. The queue holds at most `queue` events; when it is full the oldest is
  dropped and counted, so a slow browser loses old positions and never slows the
  worker or the other clients.

What a client sees is what the worker knows: pseudonyms, fixes and answers; no
identity reaches the worker, so none can reach the page.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from typing import Any

from laas.errors import ConfigError
from laas.worker.dashboard.views import AreaSnapshot, area_views, observation_view
from laas.worker.service import LaasService, Observation
from ldm import Provider

__all__ = ["Client", "Feed", "sse"]

log = logging.getLogger(__name__)

_RATE_WINDOW = 5.0  # s of stats samples the rates are taken over
_INBOX = 4096  # batches waiting for the feed's thread; beyond, the oldest go

_Batch = tuple[float, Sequence[Observation], float, list[AreaSnapshot] | None]


def sse(event: str, data: Any) -> bytes:
    """One server-sent event: its name and its data as one line of JSON."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False)
    return f"event: {event}\ndata: {text}\n\n".encode()


class Client:
    """One connected page: a bounded queue of encoded events (oldest dropped first)."""

    def __init__(self, size: int) -> None:
        self._events: deque[bytes] = deque()
        self._size = size
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self.sent = 0
        self.dropped = 0
        """Events dropped because this client read too slowly."""

    def put(self, event: bytes) -> None:
        with self._lock:
            if len(self._events) >= self._size:
                self._events.popleft()
                self.dropped += 1
            self._events.append(event)
            self._ready.set()

    def next(self, timeout: float) -> bytes | None:
        """The oldest waiting event, or None after `timeout` seconds without one."""
        if not self._ready.wait(timeout):
            return None
        with self._lock:
            if not self._events:
                self._ready.clear()
                return None
            event = self._events.popleft()
            if not self._events:
                self._ready.clear()
            self.sent += 1
            return event

    def wake(self) -> None:
        self._ready.set()


class Feed:
    """Watches a `LaasService` (and its `Provider`, for the queue depth) for the page.

    `start` takes the service's observer hook (an observer already there is still
    called after this one); `stop` gives it back.
    """

    def __init__(
        self,
        service: LaasService,
        provider: Provider | None = None,
        *,
        queue: int = 256,
        stats_every: float = 1.0,
        areas_every: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if queue < 1:
            raise ConfigError(f"a client's event queue must hold at least 1 event, not {queue}")
        self.service = service
        self.provider = provider
        self.queue = queue
        self.stats_every = stats_every
        self.areas_every = areas_every
        self._clock = clock
        self._inbox: deque[_Batch] = deque(maxlen=_INBOX)
        self._wake = threading.Event()
        self._closed = threading.Event()
        self._clients: list[Client] = []
        self._lock = threading.Lock()  # clients, and the state a new client is sent
        # each pseudonym's last answered fix, and the areas, as they came (views made
        # when a client needs them)
        self._latest: OrderedDict[str, tuple[float, Observation]] = OrderedDict()
        self._areas: list[AreaSnapshot] = []
        self._stats: dict[str, Any] = {}
        self._samples: deque[tuple[float, int, float, int]] = deque()
        self._batches = 0
        self._batch_ms: list[float] = []
        self._engine_seen = service.stats.engine_seconds
        self._next_areas = 0.0
        self._previous: Callable[[Sequence[Observation]], None] | None = None
        self._thread = threading.Thread(target=self._run, name="laas-dashboard-feed", daemon=True)

    @property
    def forget_after(self) -> float:
        """Seconds after which the worker forgets a silent pseudonym (the page greys it)."""
        return float(self.service.engine.config.track_timeout)

    def start(self) -> Feed:
        self._previous = self.service.observer
        self.service.observer = self.observe
        self._thread.start()
        return self

    def stop(self) -> None:
        if self.service.observer == self.observe:
            self.service.observer = self._previous
        self._closed.set()
        self._wake.set()
        with self._lock:
            for client in self._clients:
                client.wake()
        if self._thread.is_alive():
            self._thread.join(5.0)

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    # -- the dispatch thread -----------------------------------------------------------------

    def observe(self, batch: Sequence[Observation]) -> None:
        """`LaasService.observer`: hand the batch to the feed's thread (dispatch thread)."""
        spent = self.service.stats.engine_seconds - self._engine_seen
        self._engine_seen += spent
        areas = None
        now = self._clock()
        if now >= self._next_areas:
            self._next_areas = now + self.areas_every
            areas = [AreaSnapshot(a.centre, a.b, a.P) for a in self.service.engine.common_errors()]
        self._inbox.append((time.time(), batch, spent, areas))
        # With no page connected nothing is sent, so the feed's thread is not woken for
        # each batch: it takes what waited at its next stats tick (or once the inbox is
        # half full), a thread switch per batch saved.
        if self._clients or len(self._inbox) >= _INBOX // 2:
            self._wake.set()
        if self._previous is not None:
            self._previous(batch)

    # -- clients (HTTP handler threads) ----------------------------------------------------

    def subscribe(self) -> Client:
        """A new client, whose queue starts with a ``hello`` event: the live pseudonyms'
        last answers, the areas and the latest stats."""
        client = Client(self.queue)
        with self._lock:
            client.put(sse("hello", self._state()))
            self._clients.append(client)
        return client

    def unsubscribe(self, client: Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)

    def clients(self) -> list[Client]:
        """The clients connected now."""
        with self._lock:
            return list(self._clients)

    def state(self) -> dict[str, Any]:
        """What a new page is shown first (the ``hello`` event; ``/api/state``)."""
        with self._lock:
            return self._state()

    def _state(self) -> dict[str, Any]:
        return {
            "forget_after": self.forget_after,
            "users": [observation_view(seen) for _, seen in self._latest.values()],
            "areas": area_views(self.service.engine.map, self._areas),
            "stats": self._stats,
        }

    # -- the feed's thread -----------------------------------------------------------------

    def _run(self) -> None:
        next_stats = self._clock()
        while not self._closed.is_set():
            self._wake.wait(max(0.0, next_stats - self._clock()))
            self._wake.clear()
            try:
                while self._inbox:
                    self._batch(*self._inbox.popleft())
                now = self._clock()
                if now >= next_stats:
                    next_stats = now + self.stats_every
                    self._tick(now)
            except Exception:  # a bug: the page misses an event, the feed goes on
                log.exception("the live map could not show a batch or the stats")

    def _batch(
        self,
        wall: float,
        batch: Sequence[Observation],
        spent: float,
        areas: list[AreaSnapshot] | None,
    ) -> None:
        now = self._clock()
        self._batches += 1
        self._batch_ms.append(1000.0 * spent)
        with self._lock:
            for seen in batch:
                self._latest[seen.pseudonym] = (now, seen)
                self._latest.move_to_end(seen.pseudonym)
            if areas is not None:
                self._areas = areas
            watched = bool(self._clients)
        if not watched:
            return
        if batch:  # none: every fix of the batch was stale
            views = [observation_view(seen) for seen in batch]
            wall_ms, engine_ms = round(wall * 1000), round(1000.0 * spent, 3)
            event = {"time": wall_ms, "engine_ms": engine_ms, "fixes": views}
            self._publish(sse("batch", event))
        if areas is not None:
            shown = area_views(self.service.engine.map, areas)
            self._publish(sse("areas", {"areas": shown}))

    def _tick(self, now: float) -> None:
        """The ``stats`` event; pseudonyms silent for `forget_after` leave the state."""
        stats = self.service.stats
        self._samples.append((now, stats.answered, stats.engine_seconds, self._batches))
        while len(self._samples) > 2 and now - self._samples[0][0] > _RATE_WINDOW:
            self._samples.popleft()
        t0, answered0, engine0, batches0 = self._samples[0]
        span = now - t0
        answers = stats.answered - answered0
        batch_ms, self._batch_ms = self._batch_ms, []
        view = {
            "answered": stats.answered,
            "answers_per_s": round(answers / span, 2) if span > 0 else 0.0,
            "batches_per_s": round((self._batches - batches0) / span, 2) if span > 0 else 0.0,
            "engine_ms_per_fix": (
                round(1000.0 * (stats.engine_seconds - engine0) / answers, 3) if answers else None
            ),
            "engine_ms_per_batch": round(sum(batch_ms) / len(batch_ms), 3) if batch_ms else None,
            "engine_ms_per_batch_max": round(max(batch_ms), 3) if batch_ms else None,
            "refused": {
                "invalid": stats.invalid,
                "clock": stats.clock,
                "outside": stats.outside,
                "stale": stats.refused,
                "internal": stats.failed,
            },
            "pseudonyms": self.service.sessions,
            "tracks": self.service.engine.users,
            "areas": len(self._areas),
            "queue": None if self.provider is None else self.provider.queued,
        }
        with self._lock:
            self._stats = view
            view["clients"] = len(self._clients)
            while self._latest:
                heard, _ = next(iter(self._latest.values()))
                if now - heard <= self.forget_after:
                    break
                self._latest.popitem(last=False)
        self._publish(sse("stats", view))

    def _publish(self, event: bytes) -> None:
        with self._lock:
            for client in self._clients:
                client.put(event)
