"""Budgets: what each participant client id may send to a core, as token buckets.

A client has three budgets (`Limits`), each an input bucket at the core's ``rate`` and
``burst`` and a bucket of refusal notices at `NOTICE_RATE`. Admission (`ldm.core.admission`)
charges each of its messages to one of them (`Charge`), so input forged in its name on a
broker without ACL uses up neither its sessions' budget nor its requests'.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["NOTICE_RATE", "Bucket", "Budget", "Charge", "Limits"]

NOTICE_RATE = 10.0  # rejection notices per second and client, so refusing costs little


@dataclass(slots=True)
class Bucket:
    """A token bucket: ``rate`` tokens per second, at most ``burst`` saved up."""

    tokens: float
    stamp: float

    def take(self, now: float, rate: float, burst: float) -> bool:
        self.tokens = min(burst, self.tokens + (now - self.stamp) * rate)
        self.stamp = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    def full(self, now: float, rate: float, burst: float) -> bool:
        return self.tokens + (now - self.stamp) * rate >= burst

    def ready(self, now: float, rate: float, burst: float) -> bool:
        """Whether `take` would succeed now; takes nothing."""
        return min(burst, self.tokens + (now - self.stamp) * rate) >= 1.0


Charge = Literal["own", "other", "session"]
"""Which of a participant's budgets pays for one of its messages (`Limits`)."""


@dataclass(slots=True)
class Budget:
    """Input at ``rate``/``burst`` and the refusal notices that answer it at 10/s."""

    input: Bucket
    notices: Bucket

    @classmethod
    def new(cls, now: float, burst: float) -> Budget:
        return cls(Bucket(burst, now), Bucket(NOTICE_RATE, now))

    def full(self, now: float, rate: float, burst: float) -> bool:
        return self.input.full(now, rate, burst) and self.notices.full(
            now, NOTICE_RATE, NOTICE_RATE
        )


@dataclass(slots=True)
class Limits:
    """One participant client id's budgets, each paying for one kind of its messages:

    - ``own``: its sessions' input, as far as intake can tell (`Admission.owned`: fresh
      and tagged with the session's secret, not a replay; for a session without a
      secret, under a current or in-grace key of it);
    - ``session``: its session requests, as far as intake can tell (`request_like`);
    - ``other``: everything else (input under new or unknown keys, untagged or
      unreadable input, malformed session requests, other topics).

    On a broker without ACL, input forged on the client's topics is ``other`` (it lacks
    the session's tag, or is not a well-formed session request), so it uses up neither
    the sessions' budget nor the one for session requests. Well-formed session requests
    forged in its name use up ``session``: nothing tells them from its own.
    """

    own: Budget
    other: Budget
    session: Budget

    @classmethod
    def new(cls, now: float, burst: float) -> Limits:
        return cls(Budget.new(now, burst), Budget.new(now, burst), Budget.new(now, burst))

    def budget(self, charge: Charge) -> Budget:
        return self.own if charge == "own" else self.other if charge == "other" else self.session

    def full(self, now: float, rate: float, burst: float) -> bool:
        """Every bucket is full: the same as having none."""
        return all(b.full(now, rate, burst) for b in (self.own, self.other, self.session))
