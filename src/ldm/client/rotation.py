"""The participant's side of rotation (`ldm.wire.rotation`): whether it may, or wants
to, change its key now, and whether it keeps quiet after a change."""

from __future__ import annotations

import math
import random

from ldm.wire.rotation import RotationPolicy

__all__ = [
    "CITS_FIRST",
    "CITS_GAP",
    "CITS_MIN_DISTANCE",
    "REKEY_MARGIN",
    "STOP_SPEED",
    "STOP_TIME",
    "Rotator",
]

CITS_FIRST = (800.0, 1500.0)  # m: the first change after a random distance (ETSI TR 103 415)
CITS_MIN_DISTANCE = 800.0  # m: later changes at least this far apart (ETSI TR 103 415)
CITS_GAP = (120.0, 360.0)  # s: and a random 2-6 min after the last (ETSI TR 103 415)
STOP_SPEED = 0.5  # m/s: below this a user stands (GNSS speed noise of a parked receiver)
STOP_TIME = 2.0  # s: standing this long is a stop, not a slow corner (two 1 Hz fixes)
REKEY_MARGIN = 1.0  # s: a change the participant decides waits this much longer than the
#                     core's rule, for the network delay between its clock and the core's


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
        self.silent_until = now + self._silence() if quiet else -math.inf
        self._travelled = 0.0
        self._need = CITS_MIN_DISTANCE
        self._wait = self._rng.uniform(*CITS_GAP)
        self._still_since = None

    def _silence(self) -> float:
        """This change's silence: the policy's, or drawn from its range."""
        lo, hi = self.policy.silence, self.policy.silence_max
        return lo if hi is None or hi <= lo else self._rng.uniform(lo, hi)

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
