"""When a participant's pseudonym changes: the rotation strategies every LDM service shares.

A pseudonym is bound to the participant's ephemeral key, so a new key is a new pseudonym
(`ldm.core.core`). Which side decides when depends on what it knows: the user core knows
the time and never a position; the participant knows its own motion, as far as its
application tells the library (`Session.moved`). The core's policy, `RotationPolicy`,
travels in every grant, so all participants of a cluster follow the same one.

    strategy   who     when the key changes
    periodic   core    ``period`` s after the pseudonym's first input (the core's
                       ``rotate`` notice; the library's behaviour before issue 27)
    epoch      core    at every multiple of ``period`` on the shared Unix clock: every
                       session of the cluster (and of every cluster with synchronised
                       clocks) is told at the same moment, so everyone changes together
    distance   client  the C-ITS profile (ETSI TR 103 415): a session starts with a fresh
                       pseudonym; the next after U(800, 1500) m travelled, then each once
                       >= 800 m and U(120, 360) s have passed
    stop       client  where users meet: once the participant has stood still for
                       ``STOP_TIME`` s (a light, a junction, a queue), and at least
                       ``rekey_interval`` after its last change

With ``distance`` and ``stop`` the core's ``rotate`` notice after ``period`` remains, a
backstop for a participant whose application reports no motion. ``silence`` (s) goes with
any strategy: after each change the participant sends nothing for that long, and its
application answers itself meanwhile (a positioning client dead-reckons from its last
answer). The service learns no more under any of them than under ``periodic``: it sees
fewer inputs (silence), or changes at times it could already see.

Every change still obeys the core's rule that a session gets a new key at most once per
``rekey_interval``: `Rotator.may_change` checks it on the participant's side, so a
participant never asks for a change the core would refuse.
"""

from __future__ import annotations

import math
import random
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "CITS_FIRST",
    "CITS_GAP",
    "CITS_MIN_DISTANCE",
    "MAX_SILENCE",
    "REKEY_MARGIN",
    "STOP_SPEED",
    "STOP_TIME",
    "RotationPolicy",
    "Rotator",
    "Strategy",
    "next_rotation",
]

Strategy = Literal["periodic", "epoch", "distance", "stop"]

CITS_FIRST = (800.0, 1500.0)  # m: the first change after a random distance (ETSI TR 103 415)
CITS_MIN_DISTANCE = 800.0  # m: later changes at least this far apart (ETSI TR 103 415)
CITS_GAP = (120.0, 360.0)  # s: and a random 2-6 min after the last (ETSI TR 103 415)
STOP_SPEED = 0.5  # m/s: below this a user stands (GNSS speed noise of a parked receiver)
STOP_TIME = 2.0  # s: standing this long is a stop, not a slow corner (two 1 Hz fixes)
MAX_SILENCE = 20.0  # s: below the core's idle_timeout (30 s), which would drop a quiet session
REKEY_MARGIN = 1.0  # s: a change the participant decides waits this much longer than the
#                     core's rule, for the network delay between its clock and the core's


class RotationPolicy(BaseModel):
    """How the pseudonyms of a cluster's sessions change (module docstring); travels in
    the grant, so the participant follows its core's policy."""

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)

    strategy: Strategy = "periodic"
    silence: float = Field(default=0.0, ge=0.0, le=MAX_SILENCE)
    """Seconds the participant sends nothing after each change of key."""


def next_rotation(strategy: Strategy, period: float, now: float) -> float:
    """When the core next tells a session to change key, after a change (or a notice)
    at `now`: ``period`` later, or with ``epoch`` the next multiple of ``period`` on
    the Unix clock (strictly after `now`)."""
    if strategy == "epoch":
        return (math.floor(now / period) + 1.0) * period
    return now + period


class Rotator:
    """A participant session's side of rotation: whether it may, or wants to, change its
    key now, and whether it is keeping quiet after a change. Pure: times are inputs,
    and random draws come from `rng` (`random.SystemRandom` in the library)."""

    def __init__(
        self,
        policy: RotationPolicy,
        rekey_interval: float,
        now: float,
        rng: random.Random | None = None,
    ) -> None:
        self.policy = policy
        self.rekey_interval = rekey_interval
        self._rng = rng if rng is not None else random.SystemRandom()
        self.changed_at = now
        self.first_use: float | None = None  # the current key's first input (the core's clock)
        self.silent_until = -math.inf  # a session's first pseudonym is new: no silence
        self._travelled = 0.0
        self._need = self._rng.uniform(*CITS_FIRST)  # m before the next change
        self._wait = 0.0  # s after the last change before the next (the first: none)
        self._still_since: float | None = None

    def may_change(self, now: float, margin: float = 0.0) -> bool:
        """The core would take a new key now: it takes one per ``rekey_interval``,
        counted from the current key's first input (or, if it sent none yet, from when it
        was made: the core still holds the older key, made before)."""
        since = self.first_use if self.first_use is not None else self.changed_at
        return now - since >= self.rekey_interval + margin

    def used(self, now: float) -> None:
        """An input left under the current key at `now`."""
        if self.first_use is None:
            self.first_use = now

    def silent(self, now: float) -> bool:
        """Inside the silent period after a change: send nothing."""
        return now < self.silent_until

    def changed(self, now: float, quiet: bool = True) -> None:
        """The session made a new key at `now`: start counting again, and keep quiet for
        the policy's silence (unless not `quiet`: a session granted anew, say)."""
        self.changed_at = now
        self.first_use = None
        self.silent_until = now + self.policy.silence if quiet else -math.inf
        self._travelled = 0.0
        self._need = CITS_MIN_DISTANCE
        self._wait = self._rng.uniform(*CITS_GAP)
        self._still_since = None

    def moved(self, metres: float, speed: float, now: float) -> bool:
        """The application's report: `metres` travelled since its last report, at
        `speed` m/s now. True when the participant's own strategy changes the key now."""
        self._travelled += max(0.0, metres)
        if speed < STOP_SPEED:
            if self._still_since is None:
                self._still_since = now
        else:
            self._still_since = None
        if not self.may_change(now, REKEY_MARGIN):
            return False
        if self.policy.strategy == "distance":
            return self._travelled >= self._need and now - self.changed_at >= self._wait
        if self.policy.strategy == "stop":
            return self._still_since is not None and now - self._still_since >= STOP_TIME
        return False
