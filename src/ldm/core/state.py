"""What a core holds: the services it knows, its participants' sessions and their
pseudonyms, and the routes of other clusters' pseudonyms (records the core's dispatch thread
thread owns; nothing else touches them)."""

from __future__ import annotations

import secrets
from dataclasses import dataclass, field

from ldm.wire.messages import ServiceDescription, SessionNotice

__all__ = [
    "Pseudonym",
    "Route",
    "ServiceEntry",
    "SessionSecret",
    "SessionState",
    "new_pseudonym",
]


def new_pseudonym() -> str:
    """A fresh random pseudonym (96 bits), unlinkable to anything else."""
    return secrets.token_urlsafe(12)


@dataclass(slots=True)
class ServiceEntry:
    description: ServiceDescription
    origin: str
    expires: float
    sig: str | None = None  # the announcement's signature, passed on to the backbone
    cluster: str | None = None  # the cluster the signature binds it to, passed on too


@dataclass(slots=True)
class Pseudonym:
    name: str
    key: str
    created: float
    service_key: str  # the service's public key when this pseudonym was made
    until: float = float("inf")  # end of grace once replaced


@dataclass(slots=True)
class SessionSecret:
    """A secret one grant shared: input tagged with it is the session's."""

    value: bytes
    used: float = 0.0  # when authentic input last came tagged with it (0: never)


@dataclass(slots=True)
class SessionState:
    client: str
    service: str
    last_seen: float
    current: Pseudonym | None = None
    old: list[Pseudonym] = field(default_factory=list)
    next_rotate: float = 0.0  # when to (re-)send the next ``rotate`` notice
    secrets: list[SessionSecret] = field(default_factory=list)
    """Shared with the participant by recent grants, newest last (`Sessions._keep_secret`)."""
    last_grant: SessionNotice | None = None  # sent again, unchanged, for a duplicate request
    granted: float = 0.0  # when the last grant that was no duplicate was made
    rekeys: float = 1.0
    """Key changes the session may still make early (`Sessions.pseudonym`), as of
    ``rekeys_at``: a bucket refilled at one per ``rekey_interval``, at most 2."""
    rekeys_at: float = 0.0


@dataclass(slots=True)
class Route:
    user_core: str
    last_seen: float
