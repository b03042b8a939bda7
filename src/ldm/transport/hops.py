"""Where each message was when: the time an input passed each point of the LDM.

A `Hops` given to a core or a provider notes, per correlation id, the wall-clock time
at which the message passed each of its points. Joined by correlation id they give each
stage's own duration for every message, which `laas bench` reports. Components hold
``None`` by default, and then note nothing (one attribute test per message).

The points, in the order an input and its reply pass them:

- ``sent``: the participant sealed the input (the envelope's own ``t``, noted by the
  user core);
- ``user_core``: the user core's dispatch thread took the input;
- ``service_core``: the service core's dispatch thread took it from the backbone;
- ``arrived``: it reached the provider (its MQTT client's thread);
- ``taken``: the provider's dispatch thread took it off its queue;
- ``answered``: the handler's reply was ready;
- ``delivered``: the user core passed the reply on to the participant.

Only correlation ids and times are kept: nothing of who sent what. The clocks are one
machine's wall clock (every process of a local deployment shares it).
"""

from __future__ import annotations

import time

__all__ = ["POINTS", "Hops"]

POINTS = ("sent", "user_core", "service_core", "arrived", "taken", "answered", "delivered")


class Hops:
    """Times by point and correlation id; at most `limit` messages per point."""

    def __init__(self, limit: int = 2_000_000) -> None:
        self.limit = limit
        self.marks: dict[str, dict[str, float]] = {p: {} for p in POINTS}

    def mark(self, point: str, c: str, t: float | None = None) -> None:
        """Message `c` passed `point` at `t` (now if None). Safe from any thread."""
        at = self.marks[point]
        if len(at) < self.limit:
            at[c] = time.time() if t is None else t

    def merge(self, marks: dict[str, dict[str, float]]) -> None:
        """Add the marks of another process's `Hops` (for example a LaaS worker's)."""
        for point, times in marks.items():
            self.marks[point].update(times)

    def stage(self, start: str, end: str) -> list[float]:
        """Seconds from `start` to `end` for every message that passed both."""
        a, b = self.marks[start], self.marks[end]
        return [b[c] - t for c, t in a.items() if c in b]
