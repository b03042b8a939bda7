"""Routing by area: one service shared among providers, each for its own region.

A service family (``ServiceSpec.family``) is offered by several providers, each a
service of its own name that announces its ``coverage``: a polygon of (longitude,
latitude) vertices. Neighbouring coverages overlap along their borders. A
`RoutedSession` sends each input of a participant to the provider whose coverage holds
the participant's position, which only the participant knows:

- it stays with its current provider while the position is inside that coverage, so a
  participant in the overlap does not flap between two providers;
- leaving it, it hands over to the provider whose coverage holds the position deepest
  (farthest from its edge), opening a session with it on first use. The next input goes
  there: a hand-over costs no input, only the new session's round trip.

A plain service of the family's own name with no coverage covers everywhere, so a
participant written for regions works unchanged with one provider.

What the cores learn: which provider a pseudonym sends to, so a region, never a
position (docs/security.md).
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Mapping
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

import shapely

from ldm.errors import ServiceNotFound
from ldm.wire.messages import ServiceDescription

if TYPE_CHECKING:
    from ldm.client.participant import Participant, Session

__all__ = ["RoutedSession", "covers", "depth"]

Payload = dict[str, Any]


def _polygon(desc: ServiceDescription) -> Any:
    assert desc.coverage is not None
    return _prepared(tuple(desc.coverage))


@functools.lru_cache(maxsize=256)
def _prepared(ring: tuple[tuple[float, float], ...]) -> Any:
    """A coverage as a prepared shapely polygon, built once (every input asks)."""
    polygon = shapely.Polygon(ring)
    shapely.prepare(polygon)
    return polygon


def covers(desc: ServiceDescription, where: tuple[float, float]) -> bool:
    """Whether the provider's coverage holds (longitude, latitude) `where` (no
    coverage: everywhere)."""
    if desc.coverage is None:
        return True
    return bool(shapely.covers(_polygon(desc), shapely.Point(where)))


def depth(desc: ServiceDescription, where: tuple[float, float]) -> float:
    """How far inside the coverage `where` lies, in degrees (infinite without one)."""
    if desc.coverage is None:
        return float("inf")
    polygon = _polygon(desc)
    return float(shapely.distance(polygon.exterior, shapely.Point(where)))


class RoutedSession:
    """Sessions with the providers of one family; each input goes to the provider whose
    coverage holds the participant's position (the module docstring). Thread-safe."""

    def __init__(self, participant: Participant, family: str, timeout: float = 5.0) -> None:
        self._participant = participant
        self.family = family
        self._timeout = timeout
        self._sessions: dict[str, Session] = {}
        self._current: ServiceDescription | None = None
        self._lock = threading.Lock()
        self.handovers = 0
        """How many times an input went to another provider than the one before it."""

    @property
    def current(self) -> str | None:
        """The name of the provider the last input went to."""
        return None if self._current is None else self._current.name

    def prepare(self, where: tuple[float, float]) -> str:
        """Open the session for (longitude, latitude) `where` now, before the first
        input; the name of the provider chosen."""
        self._session(where)
        assert self._current is not None
        return self._current.name

    def submit(self, payload: Mapping[str, Any], where: tuple[float, float]) -> Future[Payload]:
        """Send one input to the provider for (longitude, latitude) `where`."""
        return self._session(where).submit(payload)

    def moved(self, metres: float, speed: float) -> bool:
        """Report motion to the current provider's session (`ldm.Session.moved`)."""
        with self._lock:
            current = self._current
            session = None if current is None else self._sessions.get(current.name)
        return session is not None and session.moved(metres, speed)

    def request(
        self, payload: Mapping[str, Any], where: tuple[float, float], timeout: float = 2.0
    ) -> Payload:
        """Send one input and wait for the reply (`ldm.Session.request`)."""
        return self._session(where).request(payload, timeout)

    def _session(self, where: tuple[float, float]) -> Session:
        with self._lock:
            listed = {s.name: s for s in self._participant.services(timeout=self._timeout)}
            current = self._current
            if current is not None:
                fresh = listed.get(current.name)
                if fresh is not None and covers(fresh, where):
                    return self._open(fresh)
            candidates = [
                s
                for s in listed.values()
                if (s.name == self.family or s.family == self.family) and covers(s, where)
            ]
            if not candidates:
                raise ServiceNotFound(
                    f"no provider of {self.family!r} covers ({where[0]:.5f}, {where[1]:.5f}); "
                    "is the position inside the service's area?"
                )
            best = max(candidates, key=lambda s: (depth(s, where), s.name))
            if current is not None and best.name != current.name:
                self.handovers += 1
            return self._open(best)

    def _open(self, desc: ServiceDescription) -> Session:
        """The session with this provider, opened on first use (the lock is held)."""
        self._current = desc
        session = self._sessions.get(desc.name)
        if session is None:
            session = self._sessions[desc.name] = self._participant.open(desc.name, self._timeout)
        return session
