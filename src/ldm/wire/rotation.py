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
application answers itself meanwhile (a positioning client dead-reckons from its last
answer). The service learns no more under any of them than under ``periodic``: it sees
fewer inputs (silence), or changes at times it could already see.

Every change still obeys the core's rule that a session gets a new key at most once per
``rekey_interval``: `ldm.client.rotation.Rotator.may_change` checks it on the
participant's side, so a participant never asks for a change the core would refuse. The
core's side is `ldm.core.rotation`, the participant's `ldm.client.rotation`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["MAX_SILENCE", "RotationPolicy", "Strategy"]

Strategy = Literal["periodic", "epoch", "distance", "stop"]

MAX_SILENCE = 20.0  # s: below the core's idle_timeout (30 s), which would drop a quiet session


class RotationPolicy(BaseModel):
    """How the pseudonyms of a cluster's sessions change (module docstring); travels in
    the grant, so the participant follows its core's policy."""

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)

    strategy: Strategy = "periodic"
    silence: float = Field(default=0.0, ge=0.0, le=MAX_SILENCE)
    """Seconds the participant sends nothing after each change of key."""
