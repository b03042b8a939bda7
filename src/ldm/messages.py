"""The LDM wire formats: pydantic models, decoded once at the edge.

Meta messages (service lists, announcements, session notices) use readable field names;
the data envelope, sent at every hop for every input and reply, uses one-letter names.
All payloads are UTF-8 JSON; times are Unix seconds (float) taken by the sender.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ldm.topics import NAME_PATTERN, TOKEN_PATTERN

__all__ = [
    "Announcement",
    "CoreStatus",
    "Envelope",
    "Rejection",
    "ServiceDescription",
    "ServiceList",
    "ServiceSpec",
    "SessionGrant",
    "SessionNotice",
    "SessionRequest",
]

_NAME = NAME_PATTERN.pattern
_TOKEN = TOKEN_PATTERN.pattern
_B64 = r"^[A-Za-z0-9+/=]*$"


class _Wire(BaseModel):
    """Immutable; unknown fields are dropped, so a core forwards only what it knows.

    NaN and infinities are refused: a time of NaN would pass every age check.
    """

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)


class ServiceSpec(_Wire):
    """What a provider offers: name, version, description and JSON schemas."""

    name: str = Field(pattern=_NAME)
    version: str = "1"
    description: str = ""
    input_schema: dict[str, Any] = Field(default_factory=dict)
    output_schema: dict[str, Any] = Field(default_factory=dict)


class ServiceDescription(ServiceSpec):
    """A service spec plus the provider's X25519 public key (base64, 32 bytes raw)."""

    public_key: str = Field(pattern=_B64, min_length=44, max_length=44)


class Announcement(_Wire):
    """Provider -> core (``origin`` unset) and core -> cores (``origin`` = service core)."""

    service: ServiceDescription
    t: float
    origin: str | None = Field(default=None, pattern=_NAME)


class ServiceList(_Wire):
    """The retained list of services a cluster's participants can use."""

    t: float
    services: list[ServiceDescription]


class CoreStatus(_Wire):
    """Retained liveness of a core on the backbone; its last will says offline."""

    name: str = Field(pattern=_NAME)
    online: bool


class SessionRequest(_Wire):
    """Participant -> user core: open (or re-open) a session with a service."""

    c: str = Field(pattern=_TOKEN)
    service: str = Field(pattern=_NAME)
    t: float


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


Rejection = Literal["invalid", "too_large", "rate_limited", "clock"]


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


class Envelope(_Wire):
    """One data message: correlation id, send time, sender's ephemeral key, ciphertext.

    ``k`` (base64 X25519 public key of the participant's current ephemeral key) is set
    on input and absent on replies; ``d`` is base64(nonce || ChaCha20-Poly1305 output).
    """

    c: str = Field(pattern=_TOKEN)
    t: float
    k: str | None = Field(default=None, pattern=_B64, min_length=44, max_length=44)
    d: str = Field(pattern=_B64)

    def encode(self) -> bytes:
        """Compact JSON, without unset optional fields."""
        return self.model_dump_json(exclude_none=True).encode()
