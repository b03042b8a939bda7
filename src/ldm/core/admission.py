"""Admission: what a core decides about a participant's message on paho's thread,
before the message shares a queue with anyone (`ldm.core.core.Core.sink`).

Each participant client id has three budgets (`Limits`), token buckets for its input
and for the refusal notices that answer it. Intake charges each message to one of
them (`Charge`), as far as it can tell cheaply: what looks like a session request
(`request_like`), its session's input (`SessionKeys`, `tagged`: decoded once and its
tag checked, here), and everything else. The message then travels to the core's
worker as an `Admitted`, with what intake decided and the envelope it decoded.
"""

from __future__ import annotations

import hmac
from dataclasses import dataclass
from typing import Literal

from pydantic import ValidationError

from ldm.security.crypto import input_tag
from ldm.transport.mqtt import Message
from ldm.wire.messages import Envelope

__all__ = [
    "NOTICE_RATE",
    "Admitted",
    "Bucket",
    "Budget",
    "Charge",
    "Limits",
    "SessionKeys",
    "envelope_key",
    "request_like",
    "tag_secret",
    "tagged",
]

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

    - ``own``: its sessions' input, as far as intake can tell (`Core._owned`: fresh
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


_K = b'"k":"'
_K_LEN = 44  # base64 of a 32-byte X25519 key
_TAG_CHECK_MAX = 4096  # bytes: larger input is not checked at intake (charged ``other``)


@dataclass(frozen=True, slots=True)
class SessionKeys:
    """What intake knows of one session: its ephemeral keys with the end of their grace
    (inf: current), and the secrets its input may be tagged with (none yet: empty)."""

    keys: tuple[tuple[bytes, float], ...]
    secrets: tuple[bytes, ...]

    def claims(self, payload: bytes, now: float) -> bool:
        """Whether `payload` may be this session's input (cheap: a find or two): it has
        a tag (a session with a secret) or one of the session's keys (one without)."""
        if self.secrets:
            return b'"m"' in payload
        k = envelope_key(payload)
        return k is not None and any(key == k and until > now for key, until in self.keys)


def envelope_key(payload: bytes) -> bytes | None:
    """The ``k`` of an input envelope as `Envelope.encode` writes it, found without
    parsing (``"k":"`` within the first 256 bytes, then 44 characters and ``"``).

    Only to choose the budget that pays for a message of a session without a secret
    (the message is parsed properly later); anyone who copies the key gets the same.
    """
    at = payload.find(_K, 0, 256)
    if at < 0:
        return None
    start = at + len(_K)
    end = start + _K_LEN
    return payload[start:end] if payload[end : end + 1] == b'"' else None


def request_like(payload: bytes) -> bool:
    """Whether a payload may be a session request (at most 1 KiB, naming a
    ``"service"``), to charge it to the client's ``session`` budget; cheap, and
    validated properly later."""
    return len(payload) <= 1024 and b'"service"' in payload


def tagged(secrets: tuple[bytes, ...], payload: bytes) -> tuple[Envelope, bytes] | None:
    """An input envelope of at most 4 KiB, decoded, that carries a valid tag ``m`` of
    one of the session's secrets (`ldm.crypto.input_tag`), with that secret; None for
    anything else. The core decodes and checks it here, once: the worker takes it as it
    is."""
    if len(payload) > _TAG_CHECK_MAX or b'"m"' not in payload:
        return None
    try:
        env = Envelope.model_validate_json(payload)
    except ValidationError:
        return None
    secret = tag_secret(env, secrets)
    return None if secret is None else (env, secret)


def tag_secret(env: Envelope, secrets: tuple[bytes, ...] | list[bytes]) -> bytes | None:
    """The secret among `secrets` whose tag `env` carries (None: none of them)."""
    if env.k is None or env.m is None:
        return None
    for secret in reversed(secrets):  # the newest first: the participant's usual case
        if hmac.compare_digest(env.m, input_tag(secret, env.c, env.t, env.k, env.d)):
            return secret
    return None


@dataclass(frozen=True, slots=True)
class Admitted(Message):
    """A participant message taken at intake (`Core.sink`), with what intake decided:
    ``charge``: the budget that paid for it; ``refused``: over the rate, only its
    ``rejected`` notice is left to send (the notice bucket already paid);
    ``envelope``: the input decoded, its tag checked with ``secret`` (the session's
    secret when intake took it), so the worker neither decodes nor checks it again."""

    charge: Charge = "other"
    refused: bool = False
    envelope: Envelope | None = None
    secret: bytes | None = None
