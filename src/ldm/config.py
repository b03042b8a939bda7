"""Validated settings for broker connections, cores, providers and participants.

Build them once at start; a bad value raises ConfigError naming the setting.
Durations are seconds.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Self, TypeVar
from urllib.parse import urlsplit

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)

from ldm.errors import ConfigError
from ldm.wire.rotation import RotationPolicy
from ldm.wire.topics import NAME_PATTERN

__all__ = [
    "BrokerSettings",
    "CoreConfig",
    "ParticipantConfig",
    "ProviderConfig",
    "build",
]

_Model = TypeVar("_Model", bound=BaseModel)


def build(model: type[_Model], /, **values: Any) -> _Model:
    """Validate `values` into `model`, turning pydantic's error into a ConfigError."""
    try:
        return model(**values)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or model.__name__}: {err['msg']}"
            for err in exc.errors()
        )
        raise ConfigError(f"invalid {model.__name__}: {problems}") from None


class _Settings(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class BrokerSettings(_Settings):
    """How to reach one MQTT broker, ``mqtt://host:port`` or ``mqtts://host:port`` (TLS),
    or one clustered broker through any of its nodes, ``mqtt://h1:p1,h2:p2,h3:p3``.

    With several nodes the client tries them in the order given and moves to the next
    one on every failed or lost connection (`ldm.transport`). Its MQTT session is then
    persistent unless ``persistent_session`` says otherwise: the cluster keeps the
    client's subscriptions and undelivered QoS 1/2 messages while it moves to another
    node, and a clean `stop` discards the session.

    The password is a SecretStr (never printed); ``password_env`` names an environment
    variable to read it from instead.
    """

    url: str
    username: str | None = None
    password: SecretStr | None = None
    password_env: str | None = None
    ca_file: Path | None = None
    keepalive: int = Field(default=30, ge=5, le=3600)
    reconnect_min: float = Field(default=0.1, gt=0, le=60)
    reconnect_max: float = Field(default=5.0, gt=0, le=600)
    persistent_session: bool | None = None
    """MQTT clean session off (True) or on (False); None: persistent exactly when the
    URL names several nodes."""

    @classmethod
    def of(cls, value: BrokerSettings | str) -> BrokerSettings:
        """Accept a settings object or a bare URL."""
        return value if isinstance(value, BrokerSettings) else build(cls, url=value)

    @field_validator("url")
    @classmethod
    def _url(cls, url: str) -> str:
        _parse_url(url)
        return url

    @model_validator(mode="after")
    def _password(self) -> Self:
        if self.password_env and self.password is None:
            secret = os.environ.get(self.password_env)
            if secret is None:
                raise ValueError(f"environment variable {self.password_env} is not set")
            object.__setattr__(self, "password", SecretStr(secret))
        if self.ca_file is not None and not self.ca_file.is_file():
            raise ValueError(f"ca_file {self.ca_file} does not exist")
        return self

    @property
    def tls(self) -> bool:
        return _split_url(self.url)[0] == "mqtts"

    @property
    def addresses(self) -> tuple[tuple[str, int], ...]:
        """Every (host, port) the URL names, in order; one for a single broker."""
        return _parse_url(self.url)

    @property
    def host(self) -> str:
        """The first node's host."""
        return self.addresses[0][0]

    @property
    def port(self) -> int:
        """The first node's port."""
        return self.addresses[0][1]

    @property
    def clean_session(self) -> bool:
        """Whether the MQTT session starts clean (see ``persistent_session``)."""
        if self.persistent_session is None:
            return len(self.addresses) == 1
        return not self.persistent_session


_URL_FORMS = (
    "use mqtt://HOST:PORT or mqtts://HOST:PORT, or for a cluster mqtt://HOST:PORT,HOST:PORT"
)


def _split_url(url: str) -> tuple[str, str]:
    """(scheme, the comma-separated nodes) of a broker URL. Not `urlsplit` on the whole:
    a cluster's netloc with an IPv6 node among others is no valid single netloc, and
    Python releases with the bracketed-host check refuse it."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        return "", ""
    for end in "/?#":
        rest = rest.partition(end)[0]
    return scheme.lower(), rest


def _parse_url(url: str) -> tuple[tuple[str, int], ...]:
    """The (host, port) pairs of a broker URL; ValueError says what is wrong."""
    scheme, netloc = _split_url(url)
    if scheme not in ("mqtt", "mqtts") or not netloc:
        raise ValueError(_URL_FORMS)
    if "@" in netloc:
        raise ValueError("put credentials in username/password_env, not in the URL")
    default = 8883 if scheme == "mqtts" else 1883
    addresses: list[tuple[str, int]] = []
    for node in netloc.split(","):
        try:
            one = urlsplit(f"//{node.strip()}")
            port = one.port or default
        except ValueError:
            raise ValueError(f"{node!r} has no valid port; {_URL_FORMS}") from None
        if not one.hostname:
            raise ValueError(f"{node!r} names no host; {_URL_FORMS}")
        if (one.hostname, port) in addresses:
            raise ValueError(f"{node!r} is listed twice")
        addresses.append((one.hostname, port))
    return tuple(addresses)


def _url_as_broker(value: object) -> object:
    """A bare URL where broker settings are expected means {"url": URL}."""
    return {"url": value} if isinstance(value, str) else value


_B64_KEY = r"^[A-Za-z0-9+/]{43}=$"


def _keys(value: dict[str, str]) -> dict[str, str]:
    for service, key in value.items():
        _name(service)
        if not re.fullmatch(_B64_KEY, key):
            raise ValueError(
                f"{service}: {key!r} is not an Ed25519 public key (base64 of 32 bytes, "
                "as `ldm keys show FILE` prints it)"
            )
    return value


def _anchors(value: list[str]) -> list[str]:
    for key in value:
        if not re.fullmatch(_B64_KEY, key):
            raise ValueError(f"{key!r} is not an Ed25519 public key (base64 of 32 bytes)")
    return value


def _name(value: str) -> str:
    if not NAME_PATTERN.match(value):
        raise ValueError("use 1-128 characters from letters, digits and . _ : -")
    return value


class CoreConfig(_Settings):
    """One LDM core: its cluster broker, the backbone broker and the session policy.

    Pseudonyms: a participant session's pseudonym lives ``rotation_period`` seconds
    (default 120 s); then the core tells the participant to make a new ephemeral key,
    and the first input under the new key gets a fresh random pseudonym. The old one
    stays valid for ``grace`` seconds so replies in flight still reach the participant.
    A session with no input for ``idle_timeout`` seconds is dropped. Services that are
    not re-announced within ``service_ttl`` seconds disappear from every list. Data
    older than ``max_age`` seconds (by its send timestamp) is dropped, never delivered late.

    Protection against misbehaving participants (each refusal is answered with a
    ``rejected`` notice on the participant's session topic, at most 10 notices per
    second and bucket, and counted in `CoreStats`): a token bucket per participant
    client id admits ``rate`` messages per second on average and ``burst`` at once. It
    is applied as messages arrive, on the network thread, before they share a queue
    with anyone; what it admits waits in the client's own queue, and the queues are
    served round-robin (`ldm.transport.intake`), so a flooding client delays each other client
    by at most one message per round. A client has three such buckets: for its
    sessions' input (tagged with the session's secret), for well-formed session
    requests, and for everything else, each with its own 10 notices per second; so on
    a broker without ACLs, input forged on a client's topics uses up neither its
    sessions' budget nor its session requests' (forged well-formed session requests do
    use up the latter). Payloads over ``max_payload`` bytes are refused before
    they are parsed; input stamped more than ``max_clock_skew`` seconds in the future
    is refused (it would escape the ``max_age`` check); a session's new ephemeral key
    sooner than ``rekey_interval`` after the last is refused. Stale input is dropped and
    counted (``dropped_stale``), not answered.

    Nothing a participant publishes stays retained on the cluster broker: the core
    clears each retained message it is sent under ``ldm/p/+/up/#`` (an empty retained
    publish) and never takes one as input; as MQTT 3.1.1 brokers hide the flag on live
    delivery, it subscribes again every ``retain_sweep`` seconds, so the broker re-sends
    what is retained there, flagged. A retained participant message is gone within
    ``retain_sweep`` plus one ``tick`` and a round trip.
    """

    name: str
    cluster: BrokerSettings
    backbone: BrokerSettings | None = None
    rotation_period: float = Field(default=120.0, gt=0)
    rotation: RotationPolicy = Field(default_factory=RotationPolicy)
    """Who decides when a session's pseudonym changes, and the silence after a change
    (`ldm.wire.rotation`); sent to participants in each grant. ``rotation_period`` is the
    period (``periodic``, ``epoch``) or the longest a pseudonym lives (``distance``,
    ``stop``)."""
    grace: float = Field(default=5.0, ge=0)
    idle_timeout: float = Field(default=30.0, gt=0)
    service_ttl: float = Field(default=30.0, gt=0)
    max_age: float = Field(default=2.0, gt=0)
    data_qos: int = Field(default=0, ge=0, le=2)
    rate: float = Field(default=100.0, gt=0)
    """Messages per second per participant, on average. Every message admitted may
    reach the service, so this is also the most work one client can give a service.
    The default, 100, is ten times the fastest positioning receiver (10 Hz), so that
    simulated participants replayed up to 100x real time still fit (the Hamburg
    users, at 1 Hz: ``laas demo`` at 10x, the privacy runs of ``laas bench`` at 20x and
    in the tests at 50x); a deployment of real devices can set 20. Raise it for a
    chattier service."""
    burst: float = Field(default=20.0, ge=1)
    """Messages a participant may send at once. What a client sends in a burst reaches
    the service at once and, in the queues after the user core (the service core's,
    the provider's), waits ahead of everyone else's input: each message of a burst
    adds about half a millisecond there, so a large burst spoils other users' p99
    under a flood. The default, 20, is ``max_age`` (2 s) of a 10 Hz receiver, what
    it may send at once after a reconnect: anything older is stale anyway."""
    max_payload: int = Field(default=64 * 1024, ge=256)
    max_clock_skew: float = Field(default=30.0, gt=0)
    max_queue: int = Field(default=100_000, ge=1)
    """Messages waiting for the core's dispatch thread; more are dropped (``dropped_overload``)."""
    max_batch: int = Field(default=512, ge=1)
    """Messages the core's dispatch thread takes at once from what waited; the envelopes among
    them bound for one provider or core leave as one batch (`ldm.wire.batch`)."""
    retain_sweep: float = Field(default=5.0, gt=0)
    """Seconds between re-subscriptions of the participant filter, after which the core
    clears what participants left retained (see above)."""
    identity_file: Path | None = None
    """The core's Ed25519 key (PEM; made there if missing), with which it signs its
    notices and service lists; None: a new key each start (participants cannot pin it)."""
    service_keys: dict[str, str] = Field(default_factory=dict)
    """Service name -> pinned identity key: only announcements signed by it are taken."""
    anchors: list[str] = Field(default_factory=list)
    """Trust anchors whose endorsement makes a service identity trusted. With neither
    pins nor anchors, any announcement on the cluster's announce topics is taken."""

    _check_name = field_validator("name")(_name)
    _check_keys = field_validator("service_keys")(_keys)
    _check_anchors = field_validator("anchors")(_anchors)

    _check_brokers = field_validator("cluster", "backbone", mode="before")(_url_as_broker)

    @model_validator(mode="after")
    def _check_silence(self) -> Self:
        # Each pseudonym is used for at least rekey_interval of its period (else, under
        # ``epoch``, it would be too young to change at the next multiple and skip it).
        silence = self.rotation.longest_silence
        longest = self.rotation_period - self.rekey_interval
        if silence > longest or silence >= self.idle_timeout:
            raise ValueError(
                f"rotation.silence {silence:g} s (the longest) must be at most the "
                f"rotation_period less rekey_interval ({longest:g} s) and below idle_timeout "
                f"({self.idle_timeout:g} s): a participant silent longer would rarely send, "
                "or lose its session"
            )
        return self

    @property
    def rekey_interval(self) -> float:
        """Shortest time between two ephemeral keys of one session: a quarter of the
        rotation period, at least 1 s, but never longer than the period itself."""
        return min(self.rotation_period, max(1.0, self.rotation_period / 4))

    @property
    def tick(self) -> float:
        """Housekeeping interval: a fraction of the shortest period, 20 ms to 0.5 s."""
        shortest = min(self.grace or 2.0, self.idle_timeout, self.service_ttl, self.rotation_period)
        return max(0.02, min(0.5, shortest / 5))


class ProviderConfig(_Settings):
    """A service provider: its cluster broker and how often it re-announces.

    Load shedding: at most ``max_queue`` inputs wait for the handler; more are dropped
    on arrival (``ProviderStats.dropped_overload``), and input older than ``max_age``
    when its turn comes is dropped (``dropped_stale``), so a slow handler never works
    through a backlog nobody waits for. Payloads over ``max_payload`` bytes are dropped
    unread; at most ``cipher_cache`` derived session ciphers are kept (least recently
    used go first).
    """

    broker: BrokerSettings
    announce_interval: float = Field(default=10.0, gt=0)
    max_age: float = Field(default=2.0, gt=0)
    data_qos: int | None = Field(default=None, ge=0, le=2)
    """None (default): follow the core — input arrives at the QoS the core sends it with
    (the subscription is QoS 2) and each reply goes back at its input's QoS, so
    ``CoreConfig.data_qos`` holds on every hop. A number fixes both instead."""
    client_id: str | None = None
    max_queue: int = Field(default=10_000, ge=1)
    max_batch: int = Field(default=64, ge=1)
    """At most this many waiting inputs are taken at once: a batch handler gets them in
    one call; the replies to them leave together (`ldm.wire.batch`)."""
    max_payload: int = Field(default=64 * 1024, ge=256)
    cipher_cache: int = Field(default=50_000, ge=1)
    identity_file: Path | None = None
    """The service's Ed25519 identity key (PEM; made there if missing), which signs its
    description and announcements; None: a new identity each start."""
    endorsement: str | None = Field(default=None, pattern=r"^[A-Za-z0-9+/=]{88}$")
    """A trust anchor's endorsement of the identity (`ldm keys endorse`)."""
    cluster: str | None = None
    """The name of the core of the provider's cluster, which every announcement is
    signed for (a copy replayed on another cluster is refused there). None: taken from
    the cluster's retained service list (signed by ``core_key``, when that is set)."""
    core_key: str | None = Field(default=None, pattern=_B64_KEY)
    """The cluster core's Ed25519 public key: only its list names the cluster."""

    _check_name = field_validator("client_id")(lambda v: None if v is None else _name(v))
    _check_cluster = field_validator("cluster")(lambda v: None if v is None else _name(v))

    _check_broker = field_validator("broker", mode="before")(_url_as_broker)


class ParticipantConfig(_Settings):
    """A participant: its user-cluster broker and MQTT client id (the core's only handle)."""

    broker: BrokerSettings
    client_id: str | None = None
    max_age: float = Field(default=2.0, gt=0)
    """A reply older than this (s, by its send time) is dropped as stale. A request not
    answered 2 x max_age + 1 s after it was submitted fails with `RequestTimeout`,
    re-sends included."""
    data_qos: int | None = Field(default=None, ge=0, le=2)
    """QoS of input messages; None takes the core's value from the session grant."""
    service_keys: dict[str, str] = Field(default_factory=dict)
    """Service name -> the service's pinned identity key (`ldm keys show FILE`)."""
    anchors: list[str] = Field(default_factory=list)
    """Trust anchors: a service whose identity one of them endorsed is trusted.
    With neither pins nor anchors the participant trusts whatever key its core hands
    it, and so trusts the core and the brokers with what it sends (docs/security.md)."""
    core_key: str | None = Field(default=None, pattern=_B64_KEY)
    """The user core's pinned Ed25519 key: then only notices and service lists it
    signed act; unsigned or forged ones change nothing."""
    notice_window: float = Field(default=30.0, gt=0)
    """A signed notice older (or further ahead) than this is ignored as a replay."""
    retry_after: float | None = Field(default=None, gt=0)
    """Send an input again, unchanged, when no reply came this many seconds after it was
    last sent, while it is younger than ``max_age`` (checked every 0.25 s); the provider
    answers a retry with the reply it made (idempotent). None (default): no retries.
    With data at QoS 0 on a broker cluster, 0.5 makes a lost input or reply cost one
    retry instead of the request (docs/brokers.md)."""
    unreachable_after: float = Field(default=1.5, gt=0)
    """With no broker node connected for this long, every request waiting, and each new
    one, fails at once with `ConnectError` saying so (a cluster that lost its quorum
    refuses every connection), instead of timing out after 2 x max_age + 1 s. 1.5 s
    and a tick (0.25 s): the error comes within 2 s of the loss."""
    max_list: int = Field(default=512 * 1024, ge=1024)
    """A service list longer than this (bytes) is ignored unread: a forged list must
    not cost a participant more than reading this much."""

    _check_name = field_validator("client_id")(lambda v: None if v is None else _name(v))
    _check_keys = field_validator("service_keys")(_keys)
    _check_anchors = field_validator("anchors")(_anchors)

    _check_broker = field_validator("broker", mode="before")(_url_as_broker)
