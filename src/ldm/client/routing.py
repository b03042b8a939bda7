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

Hand-over: a provider may put an opaque string ``handover`` in its replies (a regional
LaaS worker does, near its border: the user's state, sealed with the region key for
the family's other providers, `ldm.security.crypto.region_cipher`). The session keeps
the latest one from its current provider and adds it, as the input's ``handover``
field, to the first input it sends to the next provider, which so goes on where the
last one stopped. The participant cannot read it; the cores see it only inside the
sealed envelopes.

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

__all__ = ["HANDOVER", "RoutedSession", "covers", "depth"]

Payload = dict[str, Any]

HANDOVER = "handover"
"""The reply field a provider hands over in, and the input field the next one gets it in."""


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
        self._token: tuple[str, str] | None = None  # (provider, its latest hand-over)
        self._carry: str | None = None  # the token for the first input to a new provider
        # guards the two above; never held while waiting, since replies are kept on the
        # participant's network thread (a future's callback), which must not wait for
        # `_lock`: that is held while a new session waits for its grant on that thread
        self._token_lock = threading.Lock()

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
        session, payload = self._routed(payload, where)
        future = session.submit(payload)
        name = session.service.name
        future.add_done_callback(lambda f: self._keep(name, f))
        return future

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
        session, payload = self._routed(payload, where)
        reply = session.request(payload, timeout)
        self._took(session.service.name, reply)
        return reply

    def _routed(
        self, payload: Mapping[str, Any], where: tuple[float, float]
    ) -> tuple[Session, Mapping[str, Any]]:
        """The session for `where`, and the payload with the hand-over it carries (the
        first input to a new provider)."""
        session = self._session(where)
        with self._token_lock:
            carry, self._carry = self._carry, None
        if carry is not None:
            payload = {**payload, HANDOVER: carry}
        return session, payload

    def _keep(self, provider: str, future: Future[Payload]) -> None:
        if not future.cancelled() and future.exception() is None:
            self._took(provider, future.result())

    def _took(self, provider: str, reply: Payload) -> None:
        """Keep a reply's hand-over, if it is from the current provider (any thread)."""
        token = reply.get(HANDOVER) if isinstance(reply, dict) else None
        if isinstance(token, str):
            current = self._current
            with self._token_lock:
                if current is not None and current.name == provider:
                    self._token = (provider, token)

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
                with self._token_lock:
                    token, self._token = self._token, None
                    if token is not None and token[0] == current.name:
                        self._carry = token[1]
            return self._open(best)

    def _open(self, desc: ServiceDescription) -> Session:
        """The session with this provider, opened on first use (the lock is held)."""
        self._current = desc
        session = self._sessions.get(desc.name)
        if session is None:
            session = self._sessions[desc.name] = self._participant.open(desc.name, self._timeout)
        return session
