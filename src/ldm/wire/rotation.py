"""When a participant's pseudonym changes: the rotation policy every LDM service shares.

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
application answers itself meanwhile (a positioning client applies its last answer's
correction to its own fixes). With ``silence_max`` each silence is drawn anew, uniformly
between ``silence`` and ``silence_max``, by the participant (from `random.SystemRandom`):
a new pseudonym's first input then says nothing of which old one went quiet when, even
where everyone changes at the same moment (``epoch``). The service learns no more under
any of them than under ``periodic``: it sees fewer inputs (silence), or changes at times
it could already see.

Every change still obeys the core's rule that a session gets a new key at most once per
``rekey_interval``: `ldm.client.rotation.Rotator.may_change` checks it on the
participant's side, so a participant never asks for a change the core would refuse. The
core's side is `ldm.core.rotation`, the participant's `ldm.client.rotation`.
"""

from __future__ import annotations

from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["MAX_SILENCE", "RotationPolicy", "Strategy"]

Strategy = Literal["periodic", "epoch", "distance", "stop"]

MAX_SILENCE = 120.0  # s: the longest silence a policy may ask for (the core also keeps it
#                      at most its rotation period less rekey_interval (3/4 of it) and
#                      below its idle_timeout, which would drop a quiet session:
#                      `ldm.config.CoreConfig`)


class RotationPolicy(BaseModel):
    """How the pseudonyms of a cluster's sessions change (module docstring); travels in
    the grant, so the participant follows its core's policy."""

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)

    strategy: Strategy = "periodic"
    silence: float = Field(default=0.0, ge=0.0, le=MAX_SILENCE)
    """Seconds the participant sends nothing after each change of key (the shortest, with
    ``silence_max``)."""
    silence_max: float | None = Field(default=None, ge=0.0, le=MAX_SILENCE)
    """The longest silence: each is drawn uniformly from [silence, silence_max]; None: always
    ``silence``."""

    @model_validator(mode="after")
    def _check_range(self) -> Self:
        if self.silence_max is not None and self.silence_max < self.silence:
            raise ValueError(
                f"silence_max {self.silence_max:g} s is below silence {self.silence:g} s: "
                "give the shortest silence as silence and the longest as silence_max"
            )
        return self

    @property
    def longest_silence(self) -> float:
        """The longest silence a participant may keep after a change (s)."""
        return self.silence if self.silence_max is None else self.silence_max
