"""The LDM core: one per cluster, the same program in every cluster.

A core links its cluster broker (participants and providers connect there) to the
backbone broker (every core connects there). It

- learns local providers' announcements, forwards them to the backbone and learns
  every other core's; keeps the cluster's service list retained on ``ldm/services``;
  drops services on withdrawal, on their core's last will, or after ``service_ttl``;
  with ``service_keys``/``anchors`` it takes only announcements and withdrawals signed
  by a trusted identity; it signs its service list and puts it back if it is changed;
- grants participant sessions and gives each a random pseudonym, bound to the
  participant's current ephemeral key; a new key gets a new pseudonym (rotation),
  the old one is honoured for ``grace`` seconds; idle sessions are dropped;
- routes ciphertext: participant input leaves the user cluster under the pseudonym
  only; replies come back by pseudonym and are mapped to the participant here;
- signs every notice to a participant (its identity key), and shares a secret with
  each granted session, with which the participant tags its input: untagged input is
  dropped before it can change a session's key;
- guards the user cluster: a participant's messages are admitted on paho's thread
  against the client's budgets (``rate``, ``burst``: one for its sessions' tagged
  input, one for session requests, one for the rest), then wait in the client's own
  lane of a round-robin queue; payload size limit, clock-skew check, at most one new
  key per ``rekey_interval``; every refusal is counted and answered on its session
  topic (a ``rejected``, ``refused`` or ``nosession`` notice, within 10 notices per
  second and budget), and touches no other participant's state. Stale input is
  counted and dropped; retained participant messages are cleared.

Session state lives on the core's worker thread; what admission on paho's threads
shares with it (budgets, session keys, recent correlation ids) is under one lock.
"""

from __future__ import annotations

import hmac
import json
import logging
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import TypeAdapter, ValidationError

from ldm import topics
from ldm._worker import Worker
from ldm.config import BrokerSettings, CoreConfig, build
from ldm.crypto import KeyPair, input_tag
from ldm.hops import Hops
from ldm.identity import SigningKey, verify
from ldm.intake import FairQueue
from ldm.messages import (
    Announcement,
    CoreStatus,
    Envelope,
    Rejection,
    ServiceDescription,
    ServiceList,
    SessionGrant,
    SessionNotice,
    SessionRequest,
    Withdrawal,
)
from ldm.transport import Connected, Event, Message, Transport, Will
from ldm.trust import Trust

__all__ = ["Core", "CoreStats"]

log = logging.getLogger(__name__)

_CLUSTER = "cluster"
_BACKBONE = "backbone"
_MAX_OLD = 4  # pseudonyms kept in their grace per session; a key-churning client gets no more
_TOKEN = topics.TOKEN_PATTERN
_NOTICE_RATE = 10.0  # rejection notices per second and client, so refusing costs little
_ANNOUNCE_OR_WITHDRAW: TypeAdapter[Announcement | Withdrawal] = TypeAdapter(
    Announcement | Withdrawal
)
_REPAIR_RATE = 5.0  # service-list repairs per second: a second core on the broker cannot loop us


def new_pseudonym() -> str:
    """A fresh random pseudonym (96 bits), unlinkable to anything else."""
    return secrets.token_urlsafe(12)


@dataclass(slots=True)
class _Service:
    description: ServiceDescription
    origin: str
    expires: float
    sig: str | None = None  # the announcement's signature, passed on to the backbone


@dataclass(slots=True)
class _Pseudonym:
    name: str
    key: str
    created: float
    service_key: str  # the service's public key when this pseudonym was made
    until: float = float("inf")  # end of grace once replaced


@dataclass(slots=True)
class _Session:
    client: str
    service: str
    last_seen: float
    current: _Pseudonym | None = None
    old: list[_Pseudonym] = field(default_factory=list)
    next_rotate: float = 0.0  # when to (re-)send the next ``rotate`` notice
    secret: bytes | None = None  # shared with the participant by the latest grant
    last_grant: SessionNotice | None = None  # sent again, unchanged, for a duplicate request


@dataclass(slots=True)
class _Bucket:
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


_Charge = Literal["own", "other", "session"]
"""Which of a participant's budgets pays for one of its messages (`_Limits`)."""


@dataclass(slots=True)
class _Budget:
    """Input at ``rate``/``burst`` and the refusal notices that answer it at 10/s."""

    input: _Bucket
    notices: _Bucket

    @classmethod
    def new(cls, now: float, burst: float) -> _Budget:
        return cls(_Bucket(burst, now), _Bucket(_NOTICE_RATE, now))

    def full(self, now: float, rate: float, burst: float) -> bool:
        return self.input.full(now, rate, burst) and self.notices.full(
            now, _NOTICE_RATE, _NOTICE_RATE
        )


@dataclass(slots=True)
class _Limits:
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

    own: _Budget
    other: _Budget
    session: _Budget

    @classmethod
    def new(cls, now: float, burst: float) -> _Limits:
        return cls(_Budget.new(now, burst), _Budget.new(now, burst), _Budget.new(now, burst))

    def budget(self, charge: _Charge) -> _Budget:
        return self.own if charge == "own" else self.other if charge == "other" else self.session

    def full(self, now: float, rate: float, burst: float) -> bool:
        """Every bucket is full: the same as having none."""
        return all(b.full(now, rate, burst) for b in (self.own, self.other, self.session))


_UP = "ldm/p/"  # every participant topic the core subscribes to is ldm/p/{client}/up/...
_PSEUDONYM = "~"  # (_PSEUDONYM, pseudonym): a pseudonym's lane; a client's is its id


def pseudonym_of(topic: str) -> str | None:
    """The pseudonym of a data topic a core receives (``ldm/svc/S/out/P``,
    ``ldm/bb/in/C/S/U/P``, ``ldm/bb/out/C/S/P``), None for any other topic."""
    levels = topic.split("/")
    n = len(levels)
    if n == 5 and levels[1] == "svc" and levels[3] == "out":
        return levels[4]
    if levels[1:2] == ["bb"] and (
        (n == 7 and levels[2] == "in") or (n == 6 and levels[2] == "out")
    ):
        return levels[-1]
    return None


_K = b'"k":"'
_K_LEN = 44  # base64 of a 32-byte X25519 key
_TAG_CHECK_MAX = 4096  # bytes: larger input is not checked at intake (charged ``other``)


@dataclass(frozen=True, slots=True)
class _SessionKeys:
    """What intake knows of one session: its ephemeral keys with the end of their grace
    (inf: current), and the secret its input is tagged with (None: none yet)."""

    keys: tuple[tuple[bytes, float], ...]
    secret: bytes | None

    def claims(self, payload: bytes, now: float) -> bool:
        """Whether `payload` may be this session's input (cheap: a find or two): it has
        a tag (a session with a secret) or one of the session's keys (one without)."""
        if self.secret is not None:
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


def tagged(secret: bytes, payload: bytes) -> tuple[str, float] | None:
    """The correlation id and time of an input envelope of at most 4 KiB that carries a
    valid tag ``m`` of the session's secret (`ldm.crypto.input_tag`); None for
    anything else."""
    if len(payload) > _TAG_CHECK_MAX or b'"m"' not in payload:
        return None
    try:
        env = json.loads(payload)
    except (ValueError, RecursionError):
        return None
    if not isinstance(env, dict):
        return None
    c, t, k, d, m = (env.get(name) for name in ("c", "t", "k", "d", "m"))
    if not (isinstance(t, float) and all(isinstance(x, str) for x in (c, k, d, m))):
        return None
    if not hmac.compare_digest(str(m), input_tag(secret, str(c), t, str(k), str(d))):
        return None
    return str(c), t


@dataclass(frozen=True, slots=True)
class _Admitted(Message):
    """A participant message taken at intake (`Core.sink`), with what intake decided:
    ``charge``: the budget that paid for it; ``refused``: over the rate, only its
    ``rejected`` notice is left to send (the notice bucket already paid)."""

    charge: _Charge = "other"
    refused: bool = False


@dataclass(slots=True)
class _Route:
    user_core: str
    last_seen: float


@dataclass(slots=True)
class CoreStats:
    """Counters a test or an operator can read (``Core.stats``)."""

    forwarded_in: int = 0
    forwarded_out: int = 0
    dropped_stale: int = 0
    dropped_unroutable: int = 0
    dropped_invalid: int = 0
    dropped_overload: int = 0
    rejected_rate: int = 0
    rejected_size: int = 0
    rejected_clock: int = 0
    rejected_rekey: int = 0
    """Input under a new ephemeral key too soon after the last one (answered ``rate_limited``)."""
    granted: int = 0
    answered_nosession: int = 0
    """Input or requests for a session the core does not hold (answered ``nosession``)."""
    answered_refused: int = 0
    """Requests or input for a service the cluster does not offer (answered ``refused``)."""
    notices_suppressed: int = 0
    """Refusals not answered because the client's notice bucket was empty."""
    control: int = 0
    """Announcements, withdrawals and core statuses taken (valid, fresh), and this
    core's own service list seen back from the broker."""
    dropped_untrusted: int = 0
    """Announcements not signed by a pinned or endorsed identity (with trust set)."""
    repaired_list: int = 0
    """Service lists on the cluster that were not this core's own, replaced by it."""
    dropped_unauthentic: int = 0
    """Input without the tag of its session's secret: forged on the participant's topics
    (a broker without ACL). Not answered: an answer would spend the participant's
    notice budget; a participant whose secret a forged request replaced opens its
    session again when its request times out."""
    rotations: int = 0
    sessions_expired: int = 0
    dropped_retained: int = 0
    """Participant messages the broker delivered as retained (each cleared on the
    broker with an empty retained publish; old, so never taken as input), and empty
    ones (MQTT's deletion of a retained message, such as the echo of that clearing):
    dropped at intake, unanswered."""


class Core(Worker[Event]):
    """An LDM core. ``start()`` connects and runs it in background threads; ``stop()`` ends it."""

    def __init__(self, config: CoreConfig) -> None:
        self._intake: FairQueue[object] = FairQueue(config.max_queue)
        """Participant messages wait per client id, data per pseudonym, served
        round-robin; control first (`sink`)."""
        super().__init__(f"ldm-core-{config.name}", config.tick, inbox=self._intake)
        self._guard = threading.Lock()
        """What paho's threads share with the worker: ``_limits``, ``_keys``, and the
        counters admission writes (rejected_rate, notices_suppressed, dropped_overload,
        dropped_retained)."""
        self._keys: dict[tuple[str, str], _SessionKeys] = {}
        """(client, service) -> what intake needs to know of the session, to charge its
        input to the right bucket; the worker writes it."""
        self._charge: _Charge = "other"  # worker: the budget that paid for this message
        self._recent: OrderedDict[tuple[str, str, str], float] = OrderedDict()
        """(client, service, c) of input charged to its session in the last ``max_age``,
        oldest first: a replay of one is not the session's (intake, under ``_guard``)."""
        self._next_sweep = time.time() + config.retain_sweep
        self.config = config
        self.name = config.name
        self.stats = CoreStats()
        self.hops: Hops | None = None
        """Set to note when each input passes this core (`ldm.hops`; `laas bench`)."""
        self._services: dict[str, _Service] = {}
        self._sessions: dict[tuple[str, str], _Session] = {}
        self._pseudonyms: dict[str, _Session] = {}
        self._routes: dict[str, _Route] = {}
        self._limits: dict[str, _Limits] = {}
        self._published_list: list[ServiceDescription] | None = None
        self._list_payload = b""  # the retained list as this core last published it
        self._repairs = _Bucket(_REPAIR_RATE, 0.0)
        path = config.identity_file
        self.identity = SigningKey.load_or_create(path) if path else SigningKey.generate()
        self.trust = Trust(config.service_keys, config.anchors)
        self.timer: Callable[[str, float], None] | None = None
        """Told (stage, seconds) for each participant message admitted on paho's threads
        (``admit``) and each event handled on the worker thread (``route``); None: not
        timed (`ldm.metrics.Metrics.watch_core` sets it)."""
        self.cluster = Transport(
            config.cluster, client_id=f"ldm-core-{self.name}", sink=self.sink, name=_CLUSTER
        )
        for flt in (topics.PARTICIPANT_UP_FILTER, topics.ANNOUNCE_FILTER, topics.SERVICES):
            self.cluster.subscribe(flt, 1)
        self.cluster.subscribe(topics.PROVIDER_REPLY_FILTER, config.data_qos)
        self.backbone: Transport | None = None
        if config.backbone is not None:
            offline = CoreStatus(name=self.name, online=False).model_dump_json().encode()
            self.backbone = Transport(
                config.backbone,
                client_id=f"ldm-core-{self.name}-bb",
                sink=self.sink,
                name=_BACKBONE,
                will=Will(topics.bb_core(self.name), offline, qos=1, retain=True),
            )
            for flt in (topics.BB_ANNOUNCE_FILTER, topics.BB_CORE_FILTER):
                self.backbone.subscribe(flt, 1)
            self.backbone.subscribe(topics.bb_input_filter(self.name), config.data_qos)
            self.backbone.subscribe(topics.bb_reply_filter(self.name), config.data_qos)

    @classmethod
    def create(
        cls,
        name: str,
        cluster: BrokerSettings | str,
        backbone: BrokerSettings | str | None = None,
        **settings: Any,
    ) -> Core:
        """Build a core from URLs or settings plus any CoreConfig field."""
        return cls(
            build(
                CoreConfig,
                name=name,
                cluster=BrokerSettings.of(cluster),
                backbone=None if backbone is None else BrokerSettings.of(backbone),
                **settings,
            )
        )

    # --- lifecycle (caller's thread) --------------------------------------------------

    def start(self, timeout: float | None = 10.0) -> Core:
        """Start the worker and connect; with a timeout, wait for both brokers."""
        self.start_worker()
        self.cluster.start(timeout)
        if self.backbone is not None:
            self.backbone.start(timeout)
        return self

    def stop(self) -> None:
        """Withdraw this core's services from the backbone, clear the list, disconnect."""
        self.stop_worker()  # state is not touched by the worker after this
        if self.backbone is not None:
            for name, svc in list(self._services.items()):
                if svc.origin == self.name:
                    self.backbone.publish_and_wait(topics.bb_announce(name), b"", retain=True)
            status = CoreStatus(name=self.name, online=False).model_dump_json().encode()
            self.backbone.publish_and_wait(topics.bb_core(self.name), status, retain=True)
            self.backbone.stop()
        self.cluster.publish_and_wait(topics.SERVICES, b"", retain=True)
        self.cluster.stop()

    def __enter__(self) -> Core:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    @property
    def services(self) -> list[ServiceDescription]:
        """A snapshot of the services this core knows (read from any thread)."""
        return [s.description for s in list(self._services.values())]

    @property
    def public_key(self) -> str:
        """The core's Ed25519 public key: participants pin it (``core_key``)."""
        return self.identity.public

    @property
    def session_count(self) -> int:
        return len(self._sessions)

    @property
    def pseudonym_count(self) -> int:
        """Live pseudonyms of this cluster's participants (current and in their grace)."""
        return len(self._pseudonyms)

    @property
    def route_count(self) -> int:
        """Pseudonyms of other clusters' participants whose replies this core routes."""
        return len(self._routes)

    # --- intake (paho's threads) ---------------------------------------------------------

    def sink(self, item: Event) -> None:
        """Both transports' sink (paho's threads). A participant's message is admitted
        here (`_admit`), before it shares a queue with anyone, and waits in its client's
        lane of the fair queue; data under a pseudonym (a provider's reply, input and
        replies over the backbone) waits in that pseudonym's lane; control (service
        announcements and lists, core statuses, reconnects) is handled first."""
        if not isinstance(item, Message):
            super().sink(item)
        elif item.source == _CLUSTER and item.topic.startswith(_UP):
            timer = self.timer
            if timer is None:
                self._admit(item)
            else:
                started = time.perf_counter()
                self._admit(item)
                timer("admit", time.perf_counter() - started)
        else:
            pseudonym = pseudonym_of(item.topic)
            if pseudonym is None:
                super().sink(item)
            elif not self._intake.offer(item, (_PSEUDONYM, pseudonym)):
                self.overflowed()

    def overflowed(self) -> None:
        with self._guard:
            self.stats.dropped_overload += 1

    def _admit(self, msg: Message) -> None:
        """Intake of ``ldm/p/{client}/up/...`` on paho's thread, before any queue.

        Retained (old: cleared on the broker) and empty messages are dropped. The rest
        is charged to one of the client's budgets (`_Limits`): what looks like a session
        request to ``session``, its session's input (`_owned`) to ``own``,
        anything else to ``other``. Over the rate it is refused here (its ``rejected``
        notice, if the notice bucket pays, is queued in the client's lane), else queued
        in the client's lane of the fair queue. Costs a few finds per message, and a
        JSON parse and an HMAC only for input that claims to be its session's while the
        session's budget can still pay for it.
        """
        if msg.retain or not msg.payload:
            if msg.payload:  # an empty retained publish deletes it on the broker
                self.cluster.publish(msg.topic, b"", qos=1, retain=True)
            with self._guard:
                self.stats.dropped_retained += 1
            return
        levels = msg.topic.split("/", 6)  # ldm, p, client, up, kind, service, (more)
        client = levels[2]
        kind = levels[4] if len(levels) > 4 else ""
        service = levels[5] if len(levels) == 6 and kind == "data" else ""
        cfg = self.config
        now = time.time()
        charge: _Charge = "other"
        verified = True  # whether `charge` is known to be right
        if kind == "session" and len(levels) == 5 and request_like(msg.payload):
            charge = "session"
        elif service:
            with self._guard:
                known = self._keys.get((client, service))
            if known is not None and known.claims(msg.payload, now):
                # The tag is checked (outside the lock) only while the session's budget
                # could pay: a participant over its rate costs no parsing. Unchecked,
                # it is refused, and the refusal is answered from ``other``.
                with self._guard:
                    verified = self._limits_of(client, now).own.input.ready(
                        now, cfg.rate, cfg.burst
                    )
                own = not verified or self._owned(known, client, service, msg.payload, now)
                charge = "own" if own else "other"
        notice = False
        with self._guard:
            limits = self._limits_of(client, now)
            budget = limits.budget(charge)
            admitted = verified and budget.input.take(now, cfg.rate, cfg.burst)
            if not admitted:
                self.stats.rejected_rate += 1
                payer = budget if verified else limits.other
                notice = len(levels) >= 5 and self._take_notice(payer, now)
        if admitted or notice:
            item = _Admitted(
                msg.topic, msg.payload, msg.qos, False, msg.source, charge, not admitted
            )
            if not self._intake.offer(item, client) and admitted:
                self.overflowed()

    def _owned(
        self, known: _SessionKeys, client: str, service: str, payload: bytes, now: float
    ) -> bool:
        """Whether `payload` is its session's input, and new: tagged with the session's
        secret (under any key: a new key after a rotation is the session's too), fresh
        (``max_age``), and not a copy of one taken in the last ``max_age`` (an
        eavesdropper's replay on a broker without ACL). A session without a secret has
        nothing to check beyond its key (`_SessionKeys.claims`)."""
        if known.secret is None:
            return True
        tag = tagged(known.secret, payload)
        if tag is None:
            return False
        c, t = tag
        cfg = self.config
        if not now - cfg.max_age <= t <= now + cfg.max_clock_skew:
            return False
        with self._guard:
            recent = self._recent
            while recent and next(iter(recent.values())) < now - cfg.max_age:
                recent.popitem(last=False)
            if (client, service, c) in recent:
                return False
            recent[(client, service, c)] = now
        return True

    def _limits_of(self, client: str, now: float) -> _Limits:
        """The client's budgets, new (full) if it has none (hold ``_guard``)."""
        limits = self._limits.get(client)
        if limits is None:
            limits = self._limits[client] = _Limits.new(now, self.config.burst)
        return limits

    def _take_notice(self, budget: _Budget, now: float) -> bool:
        """A token from the budget's notice bucket (hold ``_guard``)."""
        if budget.notices.take(now, _NOTICE_RATE, _NOTICE_RATE):
            return True
        self.stats.notices_suppressed += 1
        return False

    # --- worker thread ----------------------------------------------------------------

    def handle(self, item: Event) -> None:
        timer = self.timer
        if timer is None:
            self._handle(item)
            return
        started = time.perf_counter()
        try:
            self._handle(item)
        finally:
            timer("route", time.perf_counter() - started)

    def _handle(self, item: Event) -> None:
        if isinstance(item, Connected):
            self._on_connected(item.source)
            return
        levels = item.topic.split("/")
        try:
            if item.source == _CLUSTER:
                self._from_cluster(item, levels)
            else:
                self._from_backbone(item, levels)
        except ValidationError:
            self.stats.dropped_invalid += 1
            log.debug(
                "%s: dropped a malformed message on %s",
                self.name,
                item.topic,
                extra={"event": "malformed_message"},
            )

    def tick(self, now: float) -> None:
        self._expire_services(now)
        self._expire_sessions(now)
        for pseudonym, route in list(self._routes.items()):
            if now - route.last_seen > self.config.idle_timeout + self.config.grace:
                del self._routes[pseudonym]
        cfg = self.config
        with self._guard:
            for client, limits in list(self._limits.items()):
                if limits.full(now, cfg.rate, cfg.burst):
                    del self._limits[client]  # full buckets are the same as none
            for gone in [key for key in self._keys if key not in self._sessions]:
                del self._keys[gone]
        if now >= self._next_sweep:
            # The broker sends what is retained under the filter again, flagged retained:
            # `_admit` clears each. (A live message never shows the flag in MQTT 3.1.1.)
            self._next_sweep = now + cfg.retain_sweep
            self.cluster.subscribe(topics.PARTICIPANT_UP_FILTER, 1)

    def _on_connected(self, source: str) -> None:
        if source == _CLUSTER:
            self._published_list = None
            self._publish_list()
        elif self.backbone is not None:
            status = CoreStatus(name=self.name, online=True).model_dump_json().encode()
            self.backbone.publish(topics.bb_core(self.name), status, qos=1, retain=True)
            for name, svc in self._services.items():
                if svc.origin == self.name:
                    self._announce_backbone(name, svc)

    # Every message ends in exactly one counter: forwarded_*, dropped_*, rejected_*,
    # answered_*, granted, or control (an announcement, withdrawal or core status taken).

    def _from_cluster(self, msg: Message, levels: list[str]) -> None:
        if levels[1] == "p" and len(levels) >= 5:
            self._from_participant(msg, levels)
        elif levels[1] == "svc" and len(levels) == 4 and levels[3] == "announce":
            self._local_announcement(levels[2], msg.payload)
        elif levels[1] == "svc" and len(levels) == 5 and levels[3] == "out":
            self._reply(levels[2], levels[4], Envelope.model_validate_json(msg.payload))
        elif msg.topic == topics.SERVICES:
            self._check_list(msg.payload)
        else:
            self.stats.dropped_invalid += 1

    def _from_backbone(self, msg: Message, levels: list[str]) -> None:
        kind = levels[2] if len(levels) > 2 else ""
        if kind == "announce" and len(levels) == 4:
            self._remote_announcement(levels[3], msg.payload)
        elif kind == "core" and len(levels) == 4:
            if msg.payload:
                status = CoreStatus.model_validate_json(msg.payload)
                if not status.online and status.name != self.name:
                    self._drop_origin(status.name)
            self.stats.control += 1
        elif kind == "in" and len(levels) == 7:
            # ldm/bb/in/{me}/{service}/{user_core}/{pseudonym}
            service, user_core, pseudonym = levels[4], levels[5], levels[6]
            env = Envelope.model_validate_json(msg.payload)
            if self._stale(env):
                return
            if self.hops is not None:
                self.hops.mark("service_core", env.c)
            svc = self._services.get(service)
            if svc is None or svc.origin != self.name:
                self.stats.dropped_unroutable += 1
                return
            self._routes[pseudonym] = _Route(user_core, time.time())
            self.cluster.publish(
                topics.provider_input(service, pseudonym), env.encode(), self.config.data_qos
            )
            self.stats.forwarded_in += 1
        elif kind == "out" and len(levels) == 6:
            # ldm/bb/out/{me}/{service}/{pseudonym}
            env = Envelope.model_validate_json(msg.payload)
            if not self._stale(env):
                self._deliver(levels[4], levels[5], env)
        else:
            self.stats.dropped_invalid += 1

    # --- participant input: the user cluster's boundary ---------------------------------

    def _from_participant(self, msg: Message, levels: list[str]) -> None:
        """``ldm/p/{client}/up/session`` or ``ldm/p/{client}/up/data/{service}``.

        The client's token bucket was applied at intake (`_admit`, paho's thread; a
        message refused there arrives only to have its notice sent). Here, in order,
        each cheaper than the next: the size limit, the topic, then decoding. Every
        refusal is counted and answered to this client only, from the notice bucket
        that intake charged the message to.
        """
        client = levels[2]
        is_session = levels[4] == "session" and len(levels) == 5
        is_data = levels[4] == "data" and len(levels) == 6
        service = levels[5] if is_data else ""
        admitted = msg if isinstance(msg, _Admitted) else None
        self._charge = (
            admitted.charge if admitted is not None else "session" if is_session else "other"
        )
        try:
            if admitted is not None and admitted.refused:
                cfg = self.config
                error = (
                    f"more than {cfg.rate:g} messages per second (burst {cfg.burst:g}); slow down"
                )
                self._reject(client, service, "rate_limited", error, payload=msg.payload, paid=True)
            else:
                self._participant_message(msg, client, service, is_session, is_data)
        finally:
            self._charge = "other"

    def _participant_message(
        self, msg: Message, client: str, service: str, is_session: bool, is_data: bool
    ) -> None:
        cfg = self.config
        now = time.time()
        if len(msg.payload) > cfg.max_payload:
            self.stats.rejected_size += 1
            self._reject(
                client,
                service,
                "too_large",
                f"payload: {len(msg.payload)} bytes is over the limit of {cfg.max_payload}",
            )
            return
        if not (is_session or is_data):
            self.stats.dropped_invalid += 1
            self._reject(
                client,
                service,
                "invalid",
                f"topic: {msg.topic!r} is neither .../up/session nor .../up/data/SERVICE",
            )
            return
        try:
            if is_session:
                request = SessionRequest.model_validate_json(msg.payload)
                self._session_request(client, request)
                self._share_keys(client, request.service)  # a grant may bring a new secret
            else:
                self._participant_input(
                    client, service, Envelope.model_validate_json(msg.payload), now
                )
                self._share_keys(client, service)
        except ValidationError as exc:
            self.stats.dropped_invalid += 1
            what = "session request" if is_session else "input envelope"
            error = f"{what}: {describe(exc)}"
            self._reject(client, service, "invalid", error, payload=msg.payload)

    def _share_keys(self, client: str, service: str) -> None:
        """Tell intake the session's keys (current, and old ones until their grace ends)
        and its secret, after each message that may have changed them."""
        session = self._sessions.get((client, service))
        known: _SessionKeys | None = None
        if session is not None and (session.current is not None or session.secret is not None):
            current = [] if session.current is None else [session.current]
            keys = tuple((p.key.encode(), p.until) for p in (*current, *session.old))
            known = _SessionKeys(keys, session.secret)
        if self._keys.get((client, service)) != known:  # only the worker writes it
            with self._guard:
                if known is not None:
                    self._keys[(client, service)] = known
                else:
                    self._keys.pop((client, service), None)

    def _reject(
        self,
        client: str,
        service: str,
        reason: Rejection,
        error: str,
        *,
        c: str | None = None,
        payload: bytes = b"",
        paid: bool = False,
    ) -> None:
        """Answer a refused message on the client's session topic, within its notice bucket
        (``paid``: intake took the token already).

        The correlation id is ``c``, or read from ``payload`` only once the notice is
        admitted and only if the payload is within ``max_payload``, so a flood costs no
        parsing.
        """
        if not paid and not self._admit_notice(client):
            return
        if c is None and len(payload) <= self.config.max_payload:
            c = correlation(payload)
        notice = SessionNotice(kind="rejected", service=service, c=c, reason=reason, error=error)
        self._notify(client, notice)

    def _answer(self, client: str, notice: SessionNotice) -> None:
        """Send a ``refused`` or ``nosession`` notice within the client's notice bucket."""
        if self._admit_notice(client):
            self._notify(client, notice)

    def _admit_notice(self, client: str) -> bool:
        """Take a token from the notice bucket (10/s) of the budget that paid for the
        message being handled (`_Limits`): False when it is empty. A client intake never
        saw (no buckets) is answered."""
        with self._guard:
            limits = self._limits.get(client)
            if limits is None:
                return True
            return self._take_notice(limits.budget(self._charge), time.time())

    # --- services ---------------------------------------------------------------------

    def _local_announcement(self, service: str, payload: bytes) -> None:
        ann = _ANNOUNCE_OR_WITHDRAW.validate_json(payload) if payload else None
        if not isinstance(ann, Announcement):
            svc = self._services.get(service)
            if svc is not None and svc.origin == self.name and self._withdrawn(svc, ann):
                self._remove_service(service)
            self.stats.control += 1
            return
        if ann.service.name != service:
            self.stats.dropped_invalid += 1
            return
        if not self._acceptable(ann):
            return
        self.stats.control += 1
        svc = _Service(ann.service, self.name, ann.t + self.config.service_ttl, ann.sig)
        self._services[service] = svc
        self._announce_backbone(service, svc)
        self._publish_list()

    def _withdrawn(self, svc: _Service, goodbye: Withdrawal | None) -> bool:
        """Whether a withdrawal (None: an empty payload) ends ``svc``.

        With trust set, only the service's own signed withdrawal of its current key
        does: anyone could clear a retained topic on a broker without ACL.
        """
        if self.trust.open:
            return True
        desc = svc.description
        return (
            goodbye is not None
            and goodbye.identity is not None
            and goodbye.identity == desc.identity
            and goodbye.issued == desc.issued
            and verify(goodbye.identity, goodbye.signed_text(), goodbye.sig)
        )

    def _acceptable(self, ann: Announcement) -> bool:
        """Fresh, not from the future, and signed by a trusted identity (else counted).

        A time ahead of the clock would make a retained announcement outlive its
        provider; ``max_clock_skew`` is the same limit participants' input has.
        """
        now = time.time()
        if ann.t > now + self.config.max_clock_skew:
            self.stats.dropped_invalid += 1
            log.warning(
                "%s: announcement of %s from the future dropped",
                self.name,
                ann.service.name,
                extra={"event": "announcement_from_future"},
            )
            return False
        if ann.t + self.config.service_ttl <= now:
            self.stats.dropped_stale += 1  # a retained announcement of a provider that is gone
            return False
        if not self.trust.announcement(ann):
            self.stats.dropped_untrusted += 1
            log.warning(
                "%s: announcement of %s dropped: %s",
                self.name,
                ann.service.name,
                self.trust.problem(ann.service) or "its time is not signed by its identity",
                extra={"event": "announcement_untrusted"},
            )
            return False
        return True

    def _announce_backbone(self, service: str, svc: _Service) -> None:
        if self.backbone is None:
            return
        stamp = svc.expires - self.config.service_ttl
        ann = Announcement(service=svc.description, t=stamp, origin=self.name, sig=svc.sig)
        self.backbone.publish(
            topics.bb_announce(service), ann.model_dump_json().encode(), qos=1, retain=True
        )

    def _remote_announcement(self, service: str, payload: bytes) -> None:
        if not payload:
            svc = self._services.get(service)
            if svc is not None and svc.origin != self.name:
                self._remove_service(service)
            self.stats.control += 1
            return
        ann = Announcement.model_validate_json(payload)
        if ann.origin is None or ann.service.name != service:
            self.stats.dropped_invalid += 1
            return
        if not self._acceptable(ann):
            return
        self.stats.control += 1
        current = self._services.get(service)
        if ann.origin == self.name or (current is not None and current.origin == self.name):
            return  # our own, back from the backbone; or a local provider wins over a remote one
        expires = ann.t + self.config.service_ttl
        self._services[service] = _Service(ann.service, ann.origin, expires, ann.sig)
        self._publish_list()

    def _remove_service(self, service: str) -> None:
        svc = self._services.pop(service, None)
        if svc is None:
            return
        log.info("%s: service %s is gone", self.name, service, extra={"event": "service_gone"})
        if svc.origin == self.name and self.backbone is not None:
            self.backbone.publish(topics.bb_announce(service), b"", qos=1, retain=True)
        self._publish_list()

    def _drop_origin(self, origin: str) -> None:
        for name in [n for n, s in self._services.items() if s.origin == origin]:
            self._remove_service(name)

    def _expire_services(self, now: float) -> None:
        for name in [n for n, s in self._services.items() if s.expires <= now]:
            self._remove_service(name)

    def _publish_list(self) -> None:
        services = sorted((s.description for s in self._services.values()), key=lambda d: d.name)
        if services == self._published_list:
            return
        self._published_list = services
        listing = ServiceList(t=time.time(), services=services, core=self.identity.public)
        listing = listing.model_copy(update={"sig": self.identity.sign(listing.signed_text())})
        self._list_payload = listing.model_dump_json().encode()
        self.cluster.publish(topics.SERVICES, self._list_payload, qos=1, retain=True)

    def _check_list(self, payload: bytes) -> None:
        """The retained list on the cluster must be this core's: if not, publish it again.

        Anyone who can write ``ldm/services`` (a broker without ACL) could replace it;
        the core sees the change one broker round trip later and puts its own back, so
        a tampered list stands for milliseconds, not until the next change.
        """
        if payload == self._list_payload or self._published_list is None:
            self.stats.control += 1  # our own, or before we published (it follows)
            return
        self.stats.repaired_list += 1
        if self._repairs.take(time.time(), _REPAIR_RATE, _REPAIR_RATE):
            log.warning(
                "%s: the service list on the cluster was not ours; repaired",
                self.name,
                extra={"event": "service_list_repaired"},
            )
            self.cluster.publish(topics.SERVICES, self._list_payload, qos=1, retain=True)

    # --- participant sessions ---------------------------------------------------------

    def _notify(self, client: str, notice: SessionNotice) -> None:
        """Send a notice to one participant, addressed, timed and signed by this core."""
        notice = notice.model_copy(update={"to": client, "t": time.time()})
        notice = notice.model_copy(update={"sig": self.identity.sign(notice.signed_text())})
        payload = notice.model_dump_json(exclude_none=True).encode()
        self.cluster.publish(topics.session_notice(client), payload, qos=1)

    def _session_request(self, client: str, req: SessionRequest) -> None:
        svc = self._services.get(req.service)
        if svc is None:
            self.stats.answered_refused += 1
            error = f"no service {req.service!r} in this cluster; list the services first"
            self._answer(
                client, SessionNotice(kind="refused", service=req.service, c=req.c, error=error)
            )
            return
        now = time.time()
        session = self._sessions.get((client, req.service))
        if session is None:
            session = _Session(client, req.service, now)
            self._sessions[(client, req.service)] = session
        session.last_seen = now
        last = session.last_grant
        if last is not None and last.c == req.c:  # a duplicate (QoS 1): the same answer
            self.stats.granted += 1
            self._notify(client, last)
            return
        cfg = self.config
        auth_key = None
        if req.k is not None:  # the latest grant's secret is the session's
            ours = KeyPair()
            session.secret = ours.session_secret(req.k)
            auth_key = ours.public
        grant = SessionGrant(
            service=svc.description,
            session=secrets.token_urlsafe(9),
            input_topic=topics.participant_input(client, req.service),
            reply_topic=topics.participant_reply(client, req.service),
            rotation_period=cfg.rotation_period,
            grace=cfg.grace,
            idle_timeout=cfg.idle_timeout,
            max_age=cfg.max_age,
            data_qos=cfg.data_qos,
            rekey_interval=cfg.rekey_interval,
            auth_key=auth_key,
        )
        self.stats.granted += 1
        session.last_grant = SessionNotice(kind="grant", service=req.service, c=req.c, grant=grant)
        self._notify(client, session.last_grant)

    def _stale(self, env: Envelope) -> bool:
        if time.time() - env.t > self.config.max_age:
            self.stats.dropped_stale += 1
            return True
        return False

    def _participant_input(self, client: str, service: str, env: Envelope, now: float) -> None:
        if env.t > now + self.config.max_clock_skew:
            self.stats.rejected_clock += 1
            error = (
                f"t: {env.t - now:.0f} s ahead of the core's clock (limit "
                f"{self.config.max_clock_skew:g} s); synchronise the clock"
            )
            self._reject(client, service, "clock", error, c=env.c)
            return
        if self._stale(env):
            return
        session = self._sessions.get((client, service))
        if session is None or env.k is None:
            self.stats.answered_nosession += 1
            self._answer(client, SessionNotice(kind="nosession", service=service, c=env.c))
            return
        if session.secret is not None and (
            env.m is None
            or not hmac.compare_digest(env.m, input_tag(session.secret, env.c, env.t, env.k, env.d))
        ):
            self.stats.dropped_unauthentic += 1
            return
        svc = self._services.get(service)
        if svc is None:
            self.stats.answered_refused += 1
            error = f"service {service!r} is gone"
            self._answer(
                client, SessionNotice(kind="refused", service=service, c=env.c, error=error)
            )
            return
        now = time.time()
        session.last_seen = now
        pseudonym = self._pseudonym_for(session, env.k, svc.description.public_key, now)
        if pseudonym is None:
            self.stats.rejected_rekey += 1
            error = (
                f"k: a new ephemeral key at most every {self.config.rekey_interval:g} s "
                "per session; keep the current key until the core asks to rotate"
            )
            self._reject(client, service, "rate_limited", error, c=env.c)
            return
        payload = Envelope(c=env.c, t=env.t, k=env.k, d=env.d).encode()  # without the tag
        if self.hops is not None:
            self.hops.mark("sent", env.c, env.t)
            self.hops.mark("user_core", env.c, now)
        if svc.origin == self.name:
            self.cluster.publish(
                topics.provider_input(service, pseudonym), payload, self.config.data_qos
            )
        elif self.backbone is not None:
            topic = topics.bb_input(svc.origin, service, self.name, pseudonym)
            self.backbone.publish(topic, payload, self.config.data_qos)
        else:
            self.stats.dropped_unroutable += 1
            return
        self.stats.forwarded_in += 1

    def _pseudonym_for(
        self, session: _Session, key: str, service_key: str, now: float
    ) -> str | None:
        """The pseudonym bound to this ephemeral key; a new key means a new pseudonym.

        Every pseudonym is new state here, at the service core, the provider and the
        service, so a session may change keys at most every ``rekey_interval`` seconds
        (None: refused), except when the service's own key changed (a restarted service).
        """
        current = session.current
        if current is not None and current.key == key:
            return current.name
        for old in session.old:
            if old.key == key and old.until > now:
                return old.name  # input sent before the rotation, still in its grace
        if (
            current is not None
            and current.service_key == service_key
            and now - current.created < self.config.rekey_interval
        ):
            return None
        fresh = _Pseudonym(new_pseudonym(), key, now, service_key)
        if current is not None:
            current.until = now + self.config.grace
            session.old.append(current)
            if len(session.old) > _MAX_OLD:  # a client that churns keys keeps only a few
                self._pseudonyms.pop(session.old.pop(0).name, None)
            self.stats.rotations += 1
        session.current = fresh
        session.next_rotate = now + self.config.rotation_period
        self._pseudonyms[fresh.name] = session
        return fresh.name

    def _reply(self, service: str, pseudonym: str, env: Envelope) -> None:
        """A local provider replied: to a local participant, or back over the backbone."""
        if self._stale(env):
            return
        if pseudonym in self._pseudonyms:
            self._deliver(service, pseudonym, env)
            return
        route = self._routes.get(pseudonym)
        if route is None or self.backbone is None:
            self.stats.dropped_unroutable += 1
            return
        self.backbone.publish(
            topics.bb_reply(route.user_core, service, pseudonym), env.encode(), self.config.data_qos
        )
        self.stats.forwarded_out += 1

    def _deliver(self, service: str, pseudonym: str, env: Envelope) -> None:
        """A fresh reply (the caller checked its age) to the participant of a pseudonym."""
        session = self._pseudonyms.get(pseudonym)
        if session is None or session.service != service:
            self.stats.dropped_unroutable += 1
            return
        reply = Envelope(c=env.c, t=env.t, d=env.d).encode()
        self.cluster.publish(
            topics.participant_reply(session.client, service), reply, self.config.data_qos
        )
        if self.hops is not None:
            self.hops.mark("delivered", env.c)
        self.stats.forwarded_out += 1

    def _expire_sessions(self, now: float) -> None:
        cfg = self.config
        for key, session in list(self._sessions.items()):
            if now - session.last_seen > cfg.idle_timeout:
                del self._sessions[key]
                for p in [session.current, *session.old]:
                    if p is not None:
                        self._pseudonyms.pop(p.name, None)
                self.stats.sessions_expired += 1
                continue
            for old in [p for p in session.old if p.until <= now]:
                session.old.remove(old)
                self._pseudonyms.pop(old.name, None)
            if session.current is not None and now >= session.next_rotate:
                # Again every period until a new key arrives: a lost notice (or a
                # participant that reconnected with a clean session) only delays rotation.
                session.next_rotate = now + cfg.rotation_period
                self._notify(session.client, SessionNotice(kind="rotate", service=session.service))


def describe(error: ValidationError) -> str:
    """pydantic's errors as ``field: problem; ...`` (the field dotted, or ``payload``)."""
    return "; ".join(
        f"{'.'.join(str(x) for x in e['loc']) or 'payload'}: {e['msg']}" for e in error.errors()
    )


def correlation(payload: bytes) -> str | None:
    """The correlation id ``c`` of a JSON object payload, if it has a well-formed one."""
    try:
        value = json.loads(payload).get("c")
    except (ValueError, AttributeError, RecursionError):
        return None
    return value if isinstance(value, str) and _TOKEN.fullmatch(value) else None
