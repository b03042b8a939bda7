"""The LDM wire formats: pydantic models, decoded once at the edge.

Meta messages (service lists, announcements, session notices) use readable field names;
the data envelope, sent at every hop for every input and reply, uses one-letter names.
All payloads are UTF-8 JSON; times are Unix seconds (float) taken by the sender.
"""

from __future__ import annotations

import json
from typing import Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ldm.wire.rotation import RotationPolicy
from ldm.wire.topics import NAME_PATTERN, TOKEN_PATTERN

__all__ = [
    "LIST_REFRESH",
    "Announcement",
    "CoreStatus",
    "Envelope",
    "Rejection",
    "ServiceDescription",
    "ServiceList",
    "ServiceSpec",
    "ServicesRequest",
    "SessionGrant",
    "SessionNotice",
    "SessionRequest",
    "Withdrawal",
    "canonical",
    "reply_bytes",
    "untagged",
]

_NAME = NAME_PATTERN.pattern
_TOKEN = TOKEN_PATTERN.pattern
_B64 = r"^[A-Za-z0-9+/=]*$"


def canonical(label: str, body: dict[str, Any]) -> bytes:
    """``label | JSON`` with sorted keys and no spaces: the same bytes on every side, the
    text a signature covers (`ldm.security.identity`).

    ``body`` is a message's ``model_dump(mode="json")``; JSON numbers round-trip
    exactly, so a receiver that decoded the message rebuilds the signer's bytes.
    """
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return f"{label}|{text}".encode()


class _Wire(BaseModel):
    """Immutable; unknown fields are dropped, so a core forwards only what it knows.

    NaN and infinities are refused: a time of NaN would pass every age check.
    """

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)


class ServiceSpec(_Wire):
    """What a provider offers: name, version, description and JSON schemas.

    Several providers may share one service among them by area: each is a service of
    its own name in the same ``family``, and announces its ``coverage``, a polygon of
    (longitude, latitude) vertices in degrees. A participant routes each input to the
    provider whose coverage holds its position (`ldm.client.routing.RoutedSession`).
    """

    name: str = Field(pattern=_NAME)
    version: str = "1"
    description: str = ""
    input_schema: dict[str, Any] = Field(default_factory=dict)
    output_schema: dict[str, Any] = Field(default_factory=dict)
    family: str | None = Field(default=None, pattern=_NAME)
    coverage: list[tuple[float, float]] | None = Field(default=None, min_length=3, max_length=4096)

    @field_validator("coverage")
    @classmethod
    def _lon_lat(cls, ring: list[tuple[float, float]] | None) -> list[tuple[float, float]] | None:
        if ring is not None:
            for lon, lat in ring:
                if not (-180.0 <= lon <= 180.0 and -90.0 <= lat <= 90.0):
                    raise ValueError(
                        f"coverage vertex ({lon}, {lat}) is not a (longitude, latitude) in degrees"
                    )
        return ring


class ServiceDescription(ServiceSpec):
    """A service spec plus the provider's X25519 public key (base64, 32 bytes raw).

    A provider with an identity signs it (`ldm.security.identity`): ``identity`` is its Ed25519
    public key, ``issued`` when this session key was made (a participant never goes
    back to an older one), ``signature`` covers every other field, and ``endorsement``
    is a trust anchor's signature of the identity for this service name, if it has one.
    """

    public_key: str = Field(pattern=_B64, min_length=44, max_length=44)
    identity: str | None = Field(default=None, pattern=_B64, min_length=44, max_length=44)
    issued: float = 0.0
    signature: str | None = Field(default=None, pattern=_B64, max_length=128)
    endorsement: str | None = Field(default=None, pattern=_B64, max_length=128)

    def signed_text(self) -> bytes:
        """What ``signature`` signs: every field but the signature and the endorsement."""
        body = self.model_dump(mode="json", exclude={"signature", "endorsement"})
        return canonical("ldm-service/1", body)


class Announcement(_Wire):
    """Provider -> core (``origin`` unset) and core -> cores (``origin`` = service core).

    ``cluster`` is the name of the core of the cluster the provider announced in, and
    signed: a genuine announcement replayed on another cluster's broker is not that
    cluster's service, and a backbone copy must come from that core (``origin``).
    """

    service: ServiceDescription
    t: float
    origin: str | None = Field(default=None, pattern=_NAME)
    sig: str | None = Field(default=None, pattern=_B64, max_length=128)
    """The service identity's signature of the description's signature, ``t`` and
    ``cluster``."""
    cluster: str | None = Field(default=None, pattern=_NAME)

    def signed_text(self) -> bytes:
        if self.cluster is None:  # a provider that does not know its cluster (yet)
            return f"ldm-announce/1|{self.service.signature}|{self.t!r}".encode()
        return f"ldm-announce/2|{self.service.signature}|{self.t!r}|{self.cluster}".encode()


class Withdrawal(_Wire):
    """Provider -> core, on the announce topic: the service with this key is gone.

    A provider's last will and its goodbye. Signed by the service's identity for the
    session key it withdraws (``issued``), so a replay cannot withdraw a later key.
    """

    withdrawn: str = Field(pattern=_NAME)
    identity: str | None = Field(default=None, pattern=_B64, min_length=44, max_length=44)
    issued: float = 0.0
    sig: str | None = Field(default=None, pattern=_B64, max_length=128)

    def signed_text(self) -> bytes:
        return canonical("ldm-withdraw/1", self.model_dump(mode="json", exclude={"sig"}))


class ServiceList(_Wire):
    """The retained list of services a cluster's participants can use."""

    t: float
    services: list[ServiceDescription]
    core: str | None = Field(default=None, pattern=_B64, min_length=44, max_length=44)
    """The publishing core's Ed25519 public key; ``sig`` is its signature."""
    sig: str | None = Field(default=None, pattern=_B64, max_length=128)
    cluster: str | None = Field(default=None, pattern=_NAME)
    """The publishing core's name: a provider binds its announcements to it."""

    def signed_text(self) -> bytes:
        return canonical("ldm-list/1", self.model_dump(mode="json", exclude={"sig"}))


LIST_REFRESH = 600.0
"""s: a participant asks its core for the service list at least this often (and at each
connect); the core sends changes of the list to each client that asked within three
times this (`ServicesRequest`)."""


class ServicesRequest(_Wire):
    """Participant -> user core: send me the cluster's service list, now and when it
    changes (on ``ldm/p/{client}/down/services``). Needed where the broker's ACL lets a
    participant read only its own topics; the retained ``ldm/services`` holds the same."""

    t: float


class CoreStatus(_Wire):
    """Retained liveness of a core on the backbone; its last will says offline."""

    name: str = Field(pattern=_NAME)
    online: bool


class SessionRequest(_Wire):
    """Participant -> user core: open (or re-open) a session with a service."""

    c: str = Field(pattern=_TOKEN)
    service: str = Field(pattern=_NAME)
    t: float
    k: str | None = Field(default=None, pattern=_B64, min_length=44, max_length=44)
    """A fresh X25519 public key: the core derives the session's secret with it."""


class SessionGrant(_Wire):
    """Everything a participant needs to talk to a service."""

    service: ServiceDescription
    session: str
    input_topic: str
    reply_topic: str
    rotation_period: float
    grace: float
    idle_timeout: float
    max_age: float
    data_qos: int
    rekey_interval: float = 1.0
    """The shortest time between two ephemeral keys the core accepts for a session."""
    rotation: RotationPolicy | None = None
    """The core's rotation strategy and silence (`ldm.wire.rotation`); None (an older core):
    ``periodic``, without silence."""
    auth_key: str | None = Field(default=None, pattern=_B64, min_length=44, max_length=44)
    """The core's X25519 key for this grant, answering the request's ``k``: from the
    two the participant derives the secret with which it tags its input (``m``)."""


Rejection = Literal["invalid", "too_large", "rate_limited", "clock", "unavailable"]


class SessionNotice(_Wire):
    """User core -> participant, on ``ldm/p/{client}/down/session``.

    ``grant``: the session is open (``grant`` set). ``refused``: no such service
    (``error`` says why). ``rotate``: start a new ephemeral key now; the core gives
    it a new pseudonym. ``nosession``: the core does not know this session (idle,
    or the core restarted); request it again. ``rejected``: the core refused one
    message of the participant (``reason``; ``error`` names the field and the
    problem; ``c`` is the message's correlation id when it could be read).
    """

    kind: Literal["grant", "refused", "rotate", "nosession", "rejected"]
    service: str
    c: str | None = None
    grant: SessionGrant | None = None
    error: str | None = None
    reason: Rejection | None = None
    to: str | None = None
    """The client id it is meant for, and ``t`` when it was sent: both signed, so a
    signed notice cannot be replayed to another participant or much later."""
    t: float | None = None
    sig: str | None = Field(default=None, pattern=_B64, max_length=128)
    """The core's Ed25519 signature of every other field."""

    def signed_text(self) -> bytes:
        body = self.model_dump(mode="json", exclude={"sig"}, exclude_none=True)
        return canonical("ldm-notice/1", body)


class Envelope(_Wire):
    """One data message: correlation id, send time, sender's ephemeral key, ciphertext.

    ``k`` (base64 X25519 public key of the participant's current ephemeral key) is set
    on input and absent on replies; ``d`` is base64(nonce || ChaCha20-Poly1305 output).
    """

    c: str = Field(pattern=_TOKEN)
    t: float
    k: str | None = Field(default=None, pattern=_B64, min_length=44, max_length=44)
    d: str = Field(pattern=_B64)
    m: str | None = Field(default=None, pattern=_B64, min_length=24, max_length=24)
    """The participant's tag (`ldm.security.crypto.input_tag`), checked and removed by its core."""

    def encode(self) -> bytes:
        """Compact JSON, without unset optional fields."""
        return self.model_dump_json(exclude_none=True).encode()


_TAG_TAIL: Final = b',"m":"'
_TAG_TAIL_LEN: Final = len(_TAG_TAIL) + 24 + len(b'"}')  # the tag's base64 is 24 characters


def untagged(env: Envelope, payload: bytes) -> bytes:
    """The bytes of input envelope `env`, decoded from `payload`, without its tag ``m``
    (what a user core forwards), cut from `payload` where it holds the five fields alone
    as `Envelope.encode` writes them (18 quotes, no escapes, ``m`` last), else encoded
    again: either way the same envelope without ``m``.

    >>> env = Envelope(c="c1", t=1.5, k="A" * 44, d="QUJD", m="B" * 24)
    >>> untagged(env, env.encode()) == Envelope(c="c1", t=1.5, k="A" * 44, d="QUJD").encode()
    True
    """
    if (
        env.m is not None
        and env.k is not None
        and payload.endswith(b'"}')
        and payload[-_TAG_TAIL_LEN : -_TAG_TAIL_LEN + len(_TAG_TAIL)] == _TAG_TAIL
        and payload.count(b'"') == 18
        and b"\\" not in payload
    ):
        return payload[:-_TAG_TAIL_LEN] + b"}"
    return Envelope(c=env.c, t=env.t, k=env.k, d=env.d).encode()


def reply_bytes(env: Envelope, payload: bytes) -> bytes:
    """The bytes of reply envelope `env`, decoded from `payload`, as a user core
    delivers them (``c``, ``t`` and ``d``, nothing else): `payload` itself when it holds
    those three fields alone (10 quotes, no escapes, no ``k`` or ``m``), else encoded.

    >>> env = Envelope(c="c1", t=1.5, d="QUJD")
    >>> payload = env.encode()
    >>> reply_bytes(env, payload) is payload
    True
    >>> reply_bytes(env, b'{"c":"c1","t":1.5,"d":"QUJD","x":1}') == payload
    True
    """
    if env.k is None and env.m is None and payload.count(b'"') == 10 and b"\\" not in payload:
        return payload
    return Envelope(c=env.c, t=env.t, d=env.d).encode()
