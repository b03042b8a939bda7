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

Pay per batch: a participant's input is decoded and its tag checked once, at intake,
and the decoded envelope travels with it to the worker. The worker takes everything
that waited (up to ``max_batch``) at once, and the envelopes it forwards to one
destination (a provider, another core) leave as one batch (`ldm.wire.batch`) once it
has handled them all; a lone envelope leaves at once, as a single message. A core
forwards the envelope bytes it received (the user core drops the tag first).
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pydantic import TypeAdapter, ValidationError

from ldm.config import BrokerSettings, CoreConfig, build
from ldm.core.admission import (
    NOTICE_RATE,
    Admitted,
    Bucket,
    Budget,
    Charge,
    Limits,
    SessionKeys,
    request_like,
    tag_secret,
    tagged,
)
from ldm.core.rotation import next_rotation
from ldm.core.state import (
    Pseudonym,
    Route,
    ServiceEntry,
    SessionSecret,
    SessionState,
    new_pseudonym,
)
from ldm.ops.hops import Hops
from ldm.security.crypto import KeyPair
from ldm.security.identity import SigningKey, verify
from ldm.security.trust import Trust
from ldm.transport.intake import FairQueue
from ldm.transport.mqtt import Connected, Event, Message, Transport, Will
from ldm.transport.worker import Worker
from ldm.wire import batch, topics
from ldm.wire.batch import Outbox
from ldm.wire.messages import (
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

__all__ = ["Core", "CoreStats"]

log = logging.getLogger(__name__)

_CLUSTER = "cluster"
_BACKBONE = "backbone"
_MAX_OLD = 4  # pseudonyms kept in their grace per session; a key-churning client gets no more
_MAX_SECRETS = 4  # grant secrets kept per session (`Core._grant_secret`)
_UNREACHABLE = 1.0
"""s: a backbone broker unreachable this long fails QoS 1/2 input for other clusters'
services at once (``unavailable``), rather than after its timeout."""
_CLEAR_RATE = 1000.0  # clearings a second of participant topics that are no session's
_REKEY_SLACK = 0.1
"""A new key is taken 10 % before ``rekey_interval`` is over: the participant counts
from sending its first input under the current key, the core from its arrival, and
the two trips may differ (`Session.rotate`)."""
_TOKEN = topics.TOKEN_PATTERN
_ANNOUNCE_OR_WITHDRAW: TypeAdapter[Announcement | Withdrawal] = TypeAdapter(
    Announcement | Withdrawal
)
_REPAIR_RATE = 5.0  # service-list repairs per second: a second core on the broker cannot loop us


_PSEUDONYM = "~"  # (_PSEUDONYM, pseudonym): a pseudonym's lane; a client's is its id


_DATA = frozenset({"provider_reply", "bb_input", "bb_reply"})
"""Single data messages a core receives: each waits in its pseudonym's lane."""
_BATCH = frozenset({"provider_reply_batch", "bb_input_batch", "bb_reply_batch"})
"""Batches a core receives: each envelope in them waits in its pseudonym's lane."""


def single_topic(topic: topics.Topic, pseudonym: str) -> str:
    """The single message's topic of `pseudonym`'s envelope in a batch on `topic`."""
    if topic.kind == "bb_input_batch":
        return topics.bb_input(topic.core, topic.service, topic.user_core, pseudonym)
    if topic.kind == "bb_reply_batch":
        return topics.bb_reply(topic.core, topic.service, pseudonym)
    return topics.provider_reply(topic.service, pseudonym)


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
    rejected_unavailable: int = 0
    """Input for another cluster's service while the backbone broker is unreachable
    (`Core._backbone_problem`; answered ``unavailable``)."""
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
    """Announcements not signed by a pinned or endorsed identity, or bound to no
    cluster (with trust set)."""
    dropped_elsewhere: int = 0
    """Announcements signed for another cluster than the one they came from (replays)."""
    repaired_list: int = 0
    """Service lists on the cluster that were not this core's own, replaced by it."""
    dropped_unauthentic: int = 0
    """Input without the tag of its session's secret: forged on the participant's topics
    (a broker without ACL). Not answered: an answer would spend the participant's
    notice budget; a participant whose secret a forged request replaced opens its
    session again when its request times out."""
    rotations: int = 0
    sessions_expired: int = 0
    batches_sent: int = 0
    """Messages that carried more than one envelope to a provider or another core."""
    batched: int = 0
    """Envelopes forwarded in those batches (the rest went one per message)."""
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
        super().__init__(
            f"ldm-core-{config.name}", config.tick, inbox=self._intake, batch=config.max_batch
        )
        self._outbox = Outbox()
        """The worker's: envelopes to forward, sent once it handled what waited."""
        self._guard = threading.Lock()
        """What paho's threads share with the worker: ``_limits``, ``_keys``, and the
        counters admission writes (rejected_rate, notices_suppressed, dropped_overload,
        dropped_retained)."""
        self._keys: dict[tuple[str, str], SessionKeys] = {}
        """(client, service) -> what intake needs to know of the session, to charge its
        input to the right bucket; the worker writes it."""
        self._recent: OrderedDict[tuple[str, str, str], float] = OrderedDict()
        """(client, service, c) of input charged to its session in the last ``max_age``,
        oldest first: a replay of one is not the session's (intake, under ``_guard``)."""
        self._next_sweep = time.time() + config.retain_sweep
        self._clears = Bucket(_CLEAR_RATE, time.time())  # `_clear`, under ``_guard``
        self.config = config
        self.name = config.name
        self.stats = CoreStats()
        self.hops: Hops | None = None
        """Set to note when each input passes this core (`ldm.hops`; `laas bench`)."""
        self._services: dict[str, ServiceEntry] = {}
        self._latest: dict[str, tuple[str | None, float, float]] = {}
        """Service -> (identity, issued, t) of the last announcement taken, also for a
        while after it is gone: an older one is refused (`_forward_only`)."""
        self._sessions: dict[tuple[str, str], SessionState] = {}
        self._pseudonyms: dict[str, SessionState] = {}
        self._routes: dict[str, Route] = {}
        self._limits: dict[str, Limits] = {}
        self._published_list: list[ServiceDescription] | None = None
        self._list_payload = b""  # the retained list as this core last published it
        self._repairs = Bucket(_REPAIR_RATE, 0.0)
        self._repair_owed = False  # a foreign list was seen and not yet replaced (`_repair`)
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
        self.cluster.subscribe(topics.PROVIDER_REPLY_BATCH_FILTER, config.data_qos)
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
            self.backbone.subscribe(topics.bb_input_batch_filter(self.name), config.data_qos)
            self.backbone.subscribe(topics.bb_reply_batch_filter(self.name), config.data_qos)

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
        announcements and lists, core statuses, reconnects) is handled first. A batch
        is cut into its envelopes here (without decoding them), each in its lane."""
        if not isinstance(item, Message):
            super().sink(item)
            return
        topic = topics.parse(item.topic)
        if item.source == _CLUSTER and topic.client:
            timer = self.timer
            if timer is None:
                self._admit(item, topic)
            else:
                started = time.perf_counter()
                self._admit(item, topic)
                timer("admit", time.perf_counter() - started)
        elif topic.kind in _DATA:
            if not self._intake.offer(item, (_PSEUDONYM, topic.pseudonym)):
                self.overflowed()
        elif topic.kind in _BATCH:
            self._unbatch(item, topic)
        else:
            super().sink(item)

    def _unbatch(self, msg: Message, topic: topics.Topic) -> None:
        """A batch (paho's thread): each envelope waits in its pseudonym's lane as the
        single message it stands for; a malformed line is counted and skipped."""
        entries, bad = batch.decode(msg.payload)
        dropped = 0
        for pseudonym, envelope in entries:
            single = Message(single_topic(topic, pseudonym), envelope, msg.qos, False, msg.source)
            if not self._intake.offer(single, (_PSEUDONYM, pseudonym)):
                dropped += 1
        if bad or dropped:
            with self._guard:
                self.stats.dropped_invalid += bad
                self.stats.dropped_overload += dropped

    def overflowed(self) -> None:
        with self._guard:
            self.stats.dropped_overload += 1

    def _admit(self, msg: Message, topic: topics.Topic) -> None:
        """Intake of ``ldm/p/{client}/up/...`` on paho's thread, before any queue.

        Retained (old: cleared on the broker) and empty messages are dropped. The rest
        is charged to one of the client's budgets (`Limits`): what looks like a session
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
        client = topic.client
        service = topic.service if topic.kind == "participant_input" else ""
        cfg = self.config
        now = time.time()
        if topic.kind == "participant_up" or (service and service not in self._services):
            self._clear(msg.topic, now)
        charge: Charge = "other"
        verified = True  # whether `charge` is known to be right
        envelope: Envelope | None = None  # decoded and its tag checked with `secret`
        secret: bytes | None = None
        if topic.kind == "session_request" and request_like(msg.payload):
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
                if verified:
                    own, envelope, secret = self._owned(known, client, service, msg.payload, now)
                else:
                    own = True
                charge = "own" if own else "other"
        notice = False
        with self._guard:
            limits = self._limits_of(client, now)
            budget = limits.budget(charge)
            admitted = verified and budget.input.take(now, cfg.rate, cfg.burst)
            if not admitted:
                self.stats.rejected_rate += 1
                payer = budget if verified else limits.other
                deep = msg.topic.count("/") >= 4  # ldm/p/{client}/up/...: its notice topic
                notice = deep and self._take_notice(payer, now)
        if admitted or notice:
            item = Admitted(
                msg.topic,
                msg.payload,
                msg.qos,
                False,
                msg.source,
                charge,
                not admitted,
                envelope if admitted else None,
                secret,
            )
            if not self._intake.offer(item, client) and admitted:
                self.overflowed()

    def _clear(self, topic: str, now: float) -> None:
        """Clear what may be retained on `topic`, a participant's topic that is no
        session's (paho's thread), at once.

        A live message does not show the retain flag, so retained junk on topics of a
        participant's own (one participant made the broker hold 120 MB, which Mosquitto
        never gives back: issue 25) would wait for the next sweep (``retain_sweep``).
        The session topics are few per participant and swept; any other topic is
        cleared as its message arrives, within ``_CLEAR_RATE`` a second, beyond which
        the next sweep comes within a second.
        """
        with self._guard:
            cleared = self._clears.take(now, _CLEAR_RATE, _CLEAR_RATE)
            if not cleared:
                self._next_sweep = min(self._next_sweep, now + 1.0)
        if cleared:
            self.cluster.publish(topic, b"", qos=0, retain=True)

    def _owned(
        self, known: SessionKeys, client: str, service: str, payload: bytes, now: float
    ) -> tuple[bool, Envelope | None, bytes | None]:
        """Whether `payload` is its session's input, and new: tagged with the session's
        secret (under any key: a new key after a rotation is the session's too), fresh
        (``max_age``), and not a copy of one taken in the last ``max_age`` (an
        eavesdropper's replay on a broker without ACL). A session without a secret has
        nothing to check beyond its key (`SessionKeys.claims`). With it, the envelope
        decoded and the secret its tag was checked with (None when there is no secret
        or it is not its own)."""
        if not known.secrets:
            return True, None, None
        found = tagged(known.secrets, payload)
        if found is None:
            return False, None, None
        env, secret = found
        c, t = env.c, env.t
        cfg = self.config
        if not now - cfg.max_age <= t <= now + cfg.max_clock_skew:
            return False, None, None
        with self._guard:
            recent = self._recent
            while recent and next(iter(recent.values())) < now - cfg.max_age:
                recent.popitem(last=False)
            if (client, service, c) in recent:
                return False, None, None
            recent[(client, service, c)] = now
        return True, env, secret

    def _limits_of(self, client: str, now: float) -> Limits:
        """The client's budgets, new (full) if it has none (hold ``_guard``)."""
        limits = self._limits.get(client)
        if limits is None:
            limits = self._limits[client] = Limits.new(now, self.config.burst)
        return limits

    def _take_notice(self, budget: Budget, now: float) -> bool:
        """A token from the budget's notice bucket (hold ``_guard``)."""
        if budget.notices.take(now, NOTICE_RATE, NOTICE_RATE):
            return True
        self.stats.notices_suppressed += 1
        return False

    # --- worker thread ----------------------------------------------------------------

    def handle(self, item: Event) -> None:
        self.handle_many([item])

    def handle_many(self, items: list[Event]) -> None:
        """Everything that waited, in the order the fair queue gave it; then the
        envelopes to forward leave, one message per destination (`Outbox`)."""
        timer = self.timer
        try:
            for item in items:
                if timer is None:
                    self._handle(item)
                    continue
                started = time.perf_counter()
                try:
                    self._handle(item)
                finally:
                    timer("route", time.perf_counter() - started)
        finally:
            self._outbox.flush()
            self.stats.batches_sent = self._outbox.batches
            self.stats.batched = self._outbox.batched

    def _handle(self, item: Event) -> None:
        if isinstance(item, Connected):
            self._on_connected(item.source)
            return
        topic = topics.parse(item.topic)
        try:
            if item.source == _CLUSTER:
                self._from_cluster(item, topic)
            else:
                self._from_backbone(item, topic)
        except ValidationError:
            self.stats.dropped_invalid += 1
            log.debug(
                "%s: dropped a malformed message on %s",
                self.name,
                item.topic,
                extra={"event": "malformed_message"},
            )

    def tick(self, now: float) -> None:
        self._repair(now)
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

    def _from_cluster(self, msg: Message, topic: topics.Topic) -> None:
        kind = topic.kind
        if topic.client and msg.topic.count("/") >= 4:  # ldm/p/{client}/up/...
            self._from_participant(msg, topic)
        elif kind == "announce":
            self._local_announcement(topic.service, msg.payload)
        elif kind == "provider_reply":
            env = Envelope.model_validate_json(msg.payload)
            self._reply(topic.service, topic.pseudonym, env, msg.payload)
        elif kind == "services":
            self._check_list(msg.payload)
        else:
            self.stats.dropped_invalid += 1

    def _from_backbone(self, msg: Message, topic: topics.Topic) -> None:
        kind = topic.kind
        if kind == "bb_announce":
            self._remote_announcement(topic.service, msg.payload)
        elif kind == "bb_core":
            if msg.payload:
                status = CoreStatus.model_validate_json(msg.payload)
                if not status.online and status.name != self.name:
                    self._drop_origin(status.name)
            self.stats.control += 1
        elif kind == "bb_input":
            service, user_core, pseudonym = topic.service, topic.user_core, topic.pseudonym
            env = Envelope.model_validate_json(msg.payload)
            if self._stale(env):
                return
            if self.hops is not None:
                self.hops.mark("service_core", env.c)
            svc = self._services.get(service)
            if svc is None or svc.origin != self.name:
                self.stats.dropped_unroutable += 1
                return
            self._routes[pseudonym] = Route(user_core, time.time())
            self._forward(
                self.cluster, topics.provider_input_batch(service), pseudonym, env, msg.payload
            )
            self.stats.forwarded_in += 1
        elif kind == "bb_reply":
            env = Envelope.model_validate_json(msg.payload)
            if not self._stale(env):
                self._deliver(topic.service, topic.pseudonym, env)
        else:
            self.stats.dropped_invalid += 1

    # --- participant input: the user cluster's boundary ---------------------------------

    def _from_participant(self, msg: Message, topic: topics.Topic) -> None:
        """``ldm/p/{client}/up/session`` or ``ldm/p/{client}/up/data/{service}``.

        The client's token bucket was applied at intake (`_admit`, paho's thread; a
        message refused there arrives only to have its notice sent). Here, in order,
        each cheaper than the next: the size limit, the topic, then decoding. Every
        refusal is counted and answered to this client only, from the notice bucket
        that intake charged the message to.
        """
        client = topic.client
        is_session = topic.kind == "session_request"
        is_data = topic.kind == "participant_input"
        service = topic.service
        admitted = msg if isinstance(msg, Admitted) else None
        charge: Charge = (
            admitted.charge if admitted is not None else "session" if is_session else "other"
        )
        if admitted is not None and admitted.refused:
            cfg = self.config
            error = f"more than {cfg.rate:g} messages per second (burst {cfg.burst:g}); slow down"
            self._reject(
                charge, client, service, "rate_limited", error, payload=msg.payload, paid=True
            )
        else:
            self._participant_message(msg, charge, client, service, is_session, is_data)

    def _participant_message(
        self,
        msg: Message,
        charge: Charge,
        client: str,
        service: str,
        is_session: bool,
        is_data: bool,
    ) -> None:
        """A participant's message that intake admitted; `charge`: the budget that paid
        for it, whose notice bucket pays for any refusal."""
        cfg = self.config
        now = time.time()
        if len(msg.payload) > cfg.max_payload:
            self.stats.rejected_size += 1
            self._reject(
                charge,
                client,
                service,
                "too_large",
                f"payload: {len(msg.payload)} bytes is over the limit of {cfg.max_payload}",
            )
            return
        if not (is_session or is_data):
            self.stats.dropped_invalid += 1
            self._reject(
                charge,
                client,
                service,
                "invalid",
                f"topic: {msg.topic!r} is neither .../up/session nor .../up/data/SERVICE",
            )
            return
        try:
            if is_session:
                request = SessionRequest.model_validate_json(msg.payload)
                self._session_request(charge, client, request)
                self._share_keys(client, request.service)  # a grant may bring a new secret
            else:
                known = msg.envelope if isinstance(msg, Admitted) else None
                env = Envelope.model_validate_json(msg.payload) if known is None else known
                secret = msg.secret if known is not None and isinstance(msg, Admitted) else None
                if self._participant_input(charge, client, service, env, now, secret):
                    self._share_keys(client, service)
        except ValidationError as exc:
            self.stats.dropped_invalid += 1
            what = "session request" if is_session else "input envelope"
            error = f"{what}: {describe(exc)}"
            self._reject(charge, client, service, "invalid", error, payload=msg.payload)

    def _share_keys(self, client: str, service: str) -> None:
        """Tell intake the session's keys (current, and old ones until their grace ends)
        and its secret, after each message that may have changed them."""
        session = self._sessions.get((client, service))
        known: SessionKeys | None = None
        if session is not None and (session.current is not None or session.secrets):
            current = [] if session.current is None else [session.current]
            keys = tuple((p.key.encode(), p.until) for p in (*current, *session.old))
            known = SessionKeys(keys, tuple(s.value for s in session.secrets))
        if self._keys.get((client, service)) != known:  # only the worker writes it
            with self._guard:
                if known is not None:
                    self._keys[(client, service)] = known
                else:
                    self._keys.pop((client, service), None)

    def _reject(
        self,
        charge: Charge,
        client: str,
        service: str,
        reason: Rejection,
        error: str,
        *,
        c: str | None = None,
        payload: bytes = b"",
        paid: bool = False,
    ) -> None:
        """Answer a refused message on the client's session topic, within the notice
        bucket of the budget that paid for it (`charge`; ``paid``: intake took the token
        already).

        The correlation id is ``c``, or read from ``payload`` only once the notice is
        admitted and only if the payload is within ``max_payload``, so a flood costs no
        parsing.
        """
        if not paid and not self._admit_notice(charge, client):
            return
        if c is None and len(payload) <= self.config.max_payload:
            c = correlation(payload)
        notice = SessionNotice(kind="rejected", service=service, c=c, reason=reason, error=error)
        self._notify(client, notice)

    def _answer(self, charge: Charge, client: str, notice: SessionNotice) -> None:
        """Send a ``refused`` or ``nosession`` notice within the notice bucket of the
        budget that paid for the message it answers (`charge`)."""
        if self._admit_notice(charge, client):
            self._notify(client, notice)

    def _admit_notice(self, charge: Charge, client: str) -> bool:
        """Take a token from the notice bucket (10/s) of the client's budget `charge`
        (`Limits`): False when it is empty. A client intake never saw (no buckets) is
        answered."""
        with self._guard:
            limits = self._limits.get(client)
            if limits is None:
                return True
            return self._take_notice(limits.budget(charge), time.time())

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
        if not self._bound(ann, self.name) or not self._acceptable(ann):
            return
        if not self._forward_only(ann):
            return
        self.stats.control += 1
        expires = ann.t + self.config.service_ttl
        svc = ServiceEntry(ann.service, self.name, expires, ann.sig, ann.cluster)
        self._services[service] = svc
        self._announce_backbone(service, svc)
        self._publish_list()

    def _withdrawn(self, svc: ServiceEntry, goodbye: Withdrawal | None) -> bool:
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

    def _bound(self, ann: Announcement, cluster: str) -> bool:
        """Whether `ann` was announced in `cluster` (this core's name for a local
        announcement, its ``origin`` for a backbone copy), as its signed ``cluster``
        says (else counted). An announcement signed for another cluster is a replay:
        taken here, the service would look local and every input would go to a topic
        no one serves. With trust set, an unbound announcement is refused as well."""
        if ann.cluster == cluster:
            return True
        if ann.cluster is not None:
            self.stats.dropped_elsewhere += 1
            log.warning(
                "%s: announcement of %s made for cluster %s, not %s, dropped (a replay)",
                self.name,
                ann.service.name,
                ann.cluster,
                cluster,
                extra={"event": "announcement_elsewhere"},
            )
            return False
        if self.trust.open:
            return True
        self.stats.dropped_untrusted += 1
        log.warning(
            "%s: announcement of %s names no cluster, dropped: the provider has not read "
            "this cluster's service list (let it read ldm/services, or set "
            "ProviderConfig.cluster to %r)",
            self.name,
            ann.service.name,
            cluster,
            extra={"event": "announcement_unbound"},
        )
        return False

    def _forward_only(self, ann: Announcement) -> bool:
        """Whether `ann` is not older than the last announcement taken for its service
        under the same identity (else counted as stale).

        Order: (``issued``, ``t``). A replayed announcement of a withdrawn or replaced
        key is genuine and fresh (within ``service_ttl``), so only its order gives it
        away: taken, it put a dead provider's key back in the list (issue 25). The same
        announcement again is taken while its service is listed (a redelivery), never
        once it is gone. What was last taken is kept ``service_ttl`` after it was made,
        after which a replay of it is stale anyway (`_expire_services`).
        """
        desc = ann.service
        last = self._latest.get(desc.name)
        if last is not None and last[0] == desc.identity:
            new, old = (desc.issued, ann.t), (last[1], last[2])
            if new < old or (new == old and desc.name not in self._services):
                self.stats.dropped_stale += 1
                log.info(
                    "%s: an older announcement of %s dropped (a replay)",
                    self.name,
                    desc.name,
                    extra={"event": "announcement_older"},
                )
                return False
        self._latest[desc.name] = (desc.identity, desc.issued, ann.t)
        return True

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

    def _announce_backbone(self, service: str, svc: ServiceEntry) -> None:
        if self.backbone is None:
            return
        stamp = svc.expires - self.config.service_ttl
        ann = Announcement(
            service=svc.description, t=stamp, origin=self.name, sig=svc.sig, cluster=svc.cluster
        )
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
        if not self._bound(ann, ann.origin) or not self._acceptable(ann):
            return
        if not self._forward_only(ann):
            return
        self.stats.control += 1
        current = self._services.get(service)
        if ann.origin == self.name or (current is not None and current.origin == self.name):
            return  # our own, back from the backbone; or a local provider wins over a remote one
        expires = ann.t + self.config.service_ttl
        entry = ServiceEntry(ann.service, ann.origin, expires, ann.sig, ann.cluster)
        self._services[service] = entry
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
        ttl = self.config.service_ttl
        for name in [n for n, last in self._latest.items() if last[2] + ttl <= now]:
            if name not in self._services:
                del self._latest[name]

    def _publish_list(self) -> None:
        services = sorted((s.description for s in self._services.values()), key=lambda d: d.name)
        if services == self._published_list:
            return
        self._published_list = services
        listing = ServiceList(
            t=time.time(), services=services, core=self.identity.public, cluster=self.name
        )
        listing = listing.model_copy(update={"sig": self.identity.sign(listing.signed_text())})
        self._list_payload = listing.model_dump_json().encode()
        self.cluster.publish(topics.SERVICES, self._list_payload, qos=1, retain=True)

    def _check_list(self, payload: bytes) -> None:
        """The retained list on the cluster must be this core's: if not, publish it again.

        Anyone who can write ``ldm/services`` (a broker without ACL) could replace it;
        the core sees the change one broker round trip later and puts its own back.
        Repairs are bounded (``_REPAIR_RATE`` a second, so two cores on one broker
        cannot loop fast), and one the bucket cannot pay for now is owed, not skipped:
        `_repair` pays it from ``tick`` as soon as the bucket allows, so the last list
        of any burst is repaired within 1 / ``_REPAIR_RATE`` s plus a tick.
        """
        if payload == self._list_payload or self._published_list is None:
            if payload == self._list_payload:
                self._repair_owed = False  # ours is back: nothing after it is owed
            self.stats.control += 1  # our own, or before we published (it follows)
            return
        self.stats.repaired_list += 1
        self._repair_owed = True
        self._repair(time.time())

    def _repair(self, now: float) -> None:
        """Publish this core's list again if a repair is owed and the bucket pays."""
        if self._repair_owed and self._repairs.take(now, _REPAIR_RATE, _REPAIR_RATE):
            self._repair_owed = False
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

    def _session_request(self, charge: Charge, client: str, req: SessionRequest) -> None:
        svc = self._services.get(req.service)
        if svc is None:
            self.stats.answered_refused += 1
            error = f"no service {req.service!r} in this cluster; list the services first"
            self._answer(
                charge,
                client,
                SessionNotice(kind="refused", service=req.service, c=req.c, error=error),
            )
            return
        now = time.time()
        session = self._sessions.get((client, req.service))
        if session is None:
            session = SessionState(client, req.service, now)
            self._sessions[(client, req.service)] = session
        session.last_seen = now
        last = session.last_grant
        if last is not None and last.c == req.c:  # a duplicate (QoS 1): the same answer
            self.stats.granted += 1
            self._notify(client, last)
            return
        cfg = self.config
        auth_key = None
        if req.k is not None:
            ours = KeyPair()
            self._grant_secret(session, ours.session_secret(req.k))
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
            rotation=cfg.rotation,
        )
        self.stats.granted += 1
        session.last_grant = SessionNotice(kind="grant", service=req.service, c=req.c, grant=grant)
        self._notify(client, session.last_grant)

    @staticmethod
    def _grant_secret(session: SessionState, secret: bytes) -> None:
        """Add a grant's secret to the session's, keeping those before it.

        On a broker without ACL anyone can send a well-formed request on a participant's
        topic; had its secret replaced the session's, the participant's correctly tagged
        input would be dropped until its request timed out (issue 25: one forged request
        every 2 s left 22-26 % answered). So the secrets in use stay: at most
        ``_MAX_SECRETS`` are kept, and the one dropped to make room is the oldest never
        used by tagged input, else the least recently used. A forged request's secret is
        used only by its forger's tagged input: see docs/security.md for what remains.
        """
        held = session.secrets
        held.append(SessionSecret(secret))
        if len(held) > _MAX_SECRETS:
            unused = [s for s in held[:-1] if s.used == 0.0]
            victim = unused[0] if unused else min(held[:-1], key=lambda s: s.used)
            held.remove(victim)

    def _stale(self, env: Envelope) -> bool:
        if time.time() - env.t > self.config.max_age:
            self.stats.dropped_stale += 1
            return True
        return False

    def _participant_input(
        self,
        charge: Charge,
        client: str,
        service: str,
        env: Envelope,
        now: float,
        checked: bytes | None = None,
    ) -> bool:
        """Input of a participant's session, forwarded under its pseudonym. `checked`:
        the secret intake checked the tag with (it is not checked again while the
        session still has it). True if what intake knows of the session may have
        changed (a new session, key or pseudonym)."""
        if env.t > now + self.config.max_clock_skew:
            self.stats.rejected_clock += 1
            error = (
                f"t: {env.t - now:.0f} s ahead of the core's clock (limit "
                f"{self.config.max_clock_skew:g} s); synchronise the clock"
            )
            self._reject(charge, client, service, "clock", error, c=env.c)
            return False
        if self._stale(env):
            return False
        session = self._sessions.get((client, service))
        if session is None or env.k is None:
            self.stats.answered_nosession += 1
            self._answer(charge, client, SessionNotice(kind="nosession", service=service, c=env.c))
            return True
        if session.secrets and not self._authentic(session, env, checked):
            self.stats.dropped_unauthentic += 1
            return False
        svc = self._services.get(service)
        if svc is None:
            self.stats.answered_refused += 1
            error = f"service {service!r} is gone"
            self._answer(
                charge, client, SessionNotice(kind="refused", service=service, c=env.c, error=error)
            )
            return False
        now = time.time()
        session.last_seen = now
        before = session.current
        pseudonym = self._pseudonym_for(session, env.k, svc.description.public_key, now)
        if pseudonym is None:
            self.stats.rejected_rekey += 1
            error = (
                f"k: a new ephemeral key at most every {self.config.rekey_interval:g} s "
                "per session; keep the current key until the core asks to rotate"
            )
            self._reject(charge, client, service, "rate_limited", error, c=env.c)
            return False
        payload = Envelope(c=env.c, t=env.t, k=env.k, d=env.d).encode()  # without the tag
        if self.hops is not None:
            self.hops.mark("sent", env.c, env.t)
            self.hops.mark("user_core", env.c, now)
        qos = self.config.data_qos
        if svc.origin == self.name:
            self._outbox.add(
                self.cluster, topics.provider_input_batch(service), pseudonym, payload, qos
            )
        elif self.backbone is not None:
            problem = self._backbone_problem(now, service)
            if problem is not None:
                self.stats.rejected_unavailable += 1
                # Answered whatever the notice bucket holds: the input is authentic (its
                # tag was checked) and paid for, and an unanswered one would be lost
                # silently until it times out.
                self._reject(charge, client, service, "unavailable", problem, c=env.c, paid=True)
                return session.current is not before
            self._outbox.add(
                self.backbone,
                topics.bb_input_batch(svc.origin, service, self.name),
                pseudonym,
                payload,
                qos,
            )
        else:
            self.stats.dropped_unroutable += 1
            return False
        self.stats.forwarded_in += 1
        return session.current is not before

    @staticmethod
    def _authentic(session: SessionState, env: Envelope, checked: bytes | None) -> bool:
        """Whether `env` is tagged with one of the session's secrets (`checked`: the one
        intake checked it with, taken as it is while the session still holds it); the
        secret is then marked used, which keeps it when a new grant comes."""
        held = [s.value for s in session.secrets]
        secret = checked if checked is not None and checked in held else tag_secret(env, held)
        if secret is None:
            return False
        for s in session.secrets:
            if s.value == secret:
                s.used = time.time()
        return True

    def _backbone_problem(self, now: float, service: str) -> str | None:
        """Why input for `service`, on another cluster, cannot leave now: the backbone
        broker is unreachable (at QoS 0, which the transport does not hold, at once; at
        QoS 1/2, which it holds for the reconnect, after ``_UNREACHABLE`` s). None when
        it can. (A broker that is connected but slow to acknowledge, as NATS while it
        elects leaders, still gets QoS 1/2 input: it is stored and delivered late.)"""
        backbone = self.backbone
        if backbone is None:
            return None
        down = backbone.down_since
        if down is None or (self.config.data_qos > 0 and now - down < _UNREACHABLE):
            return None
        return (
            f"service {service!r} is in another cluster and this core's backbone broker "
            f"has been unreachable for {now - down:.1f} s ({backbone.problem}): nothing "
            "reaches it now; send again later"
        )

    def _pseudonym_for(
        self, session: SessionState, key: str, service_key: str, now: float
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
            and now - current.created < self.config.rekey_interval * (1.0 - _REKEY_SLACK)
        ):
            return None
        fresh = Pseudonym(new_pseudonym(), key, now, service_key)
        if current is not None:
            current.until = now + self.config.grace
            session.old.append(current)
            if len(session.old) > _MAX_OLD:  # a client that churns keys keeps only a few
                self._pseudonyms.pop(session.old.pop(0).name, None)
            self.stats.rotations += 1
        session.current = fresh
        session.next_rotate = next_rotation(
            self.config.rotation.strategy, self.config.rotation_period, now
        )
        self._pseudonyms[fresh.name] = session
        return fresh.name

    def _reply(self, service: str, pseudonym: str, env: Envelope, payload: bytes) -> None:
        """A local provider replied: to a local participant, or back over the backbone
        (`payload`, the envelope's bytes as the provider sent them)."""
        if self._stale(env):
            return
        if pseudonym in self._pseudonyms:
            self._deliver(service, pseudonym, env)
            return
        route = self._routes.get(pseudonym)
        if route is None or self.backbone is None:
            self.stats.dropped_unroutable += 1
            return
        self._forward(
            self.backbone, topics.bb_reply_batch(route.user_core, service), pseudonym, env, payload
        )
        self.stats.forwarded_out += 1

    def _forward(
        self,
        to: Transport,
        batch_topic: str,
        pseudonym: str,
        env: Envelope,
        payload: bytes,
    ) -> None:
        """Forward an envelope as the bytes it came in (decoded, checked, not encoded
        again), unless they hold a newline, which a batch line cannot: then as encoded."""
        if b"\n" in payload:
            payload = env.encode()
        self._outbox.add(to, batch_topic, pseudonym, payload, self.config.data_qos)

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
                session.next_rotate = next_rotation(cfg.rotation.strategy, cfg.rotation_period, now)
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
