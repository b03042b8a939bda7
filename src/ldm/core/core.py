"""The LDM core: one per cluster, the same program in every cluster.

A core links its cluster broker (participants and providers connect there) to the
backbone broker (every core connects there). It owns four objects, one per idea:

- `ldm.core.admission.Admission`: a participant's message is charged to one of its
  client's budgets on paho's thread, before it shares a queue with anyone, and waits
  in the client's own lane of a round-robin queue (`ldm.transport.intake.FairQueue`);
- `ldm.core.services.Catalog`: the services of every cluster, and the signed service
  list kept retained on ``ldm/services``;
- `ldm.core.sessions.Sessions`: participant sessions, each with a random pseudonym
  bound to its current ephemeral key (a new key, a new pseudonym: rotation);
- `ldm.core.notices.Notices`: signed notices to participants, refusals within the
  client's notice budget;
- `ldm.core.routing.Router`: ciphertext between clusters and back, under pseudonyms.

The core itself (this module) runs them: its lifecycle, which object each message
goes to, and the user cluster's boundary, where it checks a participant's message in
order, each check cheaper than the next: the size limit, the topic, the clock skew, the
session, the input's tag (a secret shared at the grant: untagged input never changes a
session's key), the service, the key. Every refusal is counted and answered on the
session topic; stale input is dropped.

Threads: paho's threads run `Core.sink` (admission, and cutting batches apart); the
core's dispatch thread runs everything else, on what waited, in the fair queue's order.
The only state both touch is the admission's, behind its own lock.

Pay per batch: every message's topic is parsed once, in `Core.sink`, and travels with
it: a participant's message as an `Admitted`, any other as `ldm.wire.batch.Entry` (a
batch's envelopes each as one, with the batch's parsed topic and its pseudonym). A
participant's input is decoded and its tag checked once, at admission, and the decoded
envelope travels with it to the dispatch thread, which takes everything that waited (up
to ``max_batch``) at once, and the envelopes it forwards to one destination (a
provider, another core) leave as one batch (`ldm.wire.batch`) once it has handled them
all; a lone envelope leaves at once. A core forwards the envelope bytes it received
(the user core cuts the tag off them, and delivers a reply as it came).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from pydantic import ValidationError

from ldm.config import BrokerSettings, CoreConfig, build
from ldm.core.admission import Admission, Admitted
from ldm.core.budgets import Charge
from ldm.core.notices import Notices, describe
from ldm.core.routing import Router
from ldm.core.services import Catalog
from ldm.core.sessions import Sessions
from ldm.core.stats import CoreStats
from ldm.security.identity import SigningKey
from ldm.security.trust import Trust
from ldm.transport.dispatch import Dispatcher
from ldm.transport.hops import Hops
from ldm.transport.intake import FairQueue
from ldm.transport.mqtt import Connected, Event, Message, Transport, Will
from ldm.wire import batch, topics
from ldm.wire.batch import Entry
from ldm.wire.messages import (
    CoreStatus,
    Envelope,
    ServiceDescription,
    ServicesRequest,
    SessionNotice,
    SessionRequest,
)

__all__ = ["Core", "CoreStats"]

log = logging.getLogger(__name__)

_CLUSTER = "cluster"
_BACKBONE = "backbone"
_PSEUDONYM = "~"  # (_PSEUDONYM, pseudonym): a pseudonym's lane; a client's is its id
_DATA = frozenset({"provider_reply", "bb_input", "bb_reply"})
"""Single data messages a core receives: each waits in its pseudonym's lane."""
_BATCH = frozenset({"provider_reply_batch", "bb_input_batch", "bb_reply_batch"})
"""Batches a core receives: each envelope in them waits in its pseudonym's lane."""

Item = Event | Entry
"""What a core's dispatch thread takes: a reconnect, a participant's message (an
`Admitted`; a plain `Message` handed to `Core.handle` is parsed there), or an entry:
an envelope under a pseudonym, or a control message, with its parsed topic."""


class Core(Dispatcher[Item]):
    """An LDM core. ``start()`` connects and runs it in background threads; ``stop()`` ends it."""

    def __init__(self, config: CoreConfig) -> None:
        self._intake: FairQueue[object] = FairQueue(config.max_queue)
        """Participant messages wait per client id, data per pseudonym, served
        round-robin; control first (`sink`)."""
        super().__init__(
            f"ldm-core-{config.name}", config.tick, inbox=self._intake, batch=config.max_batch
        )
        self.config = config
        self.name = config.name
        self.stats = CoreStats()
        self.timer: Callable[[str, float], None] | None = None
        """Told (stage, seconds) for each participant message admitted on paho's threads
        (``admit``) and each event handled on the dispatch thread (``route``); None: not
        timed (`ldm.ops.metrics.Metrics.watch_core` sets it)."""
        path = config.identity_file
        self.identity = SigningKey.load_or_create(path) if path else SigningKey.generate()
        self.trust = Trust(config.service_keys, config.anchors)
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
            for flt in (
                topics.bb_input_filter(self.name),
                topics.bb_reply_filter(self.name),
                topics.bb_input_batch_filter(self.name),
                topics.bb_reply_batch_filter(self.name),
            ):
                self.backbone.subscribe(flt, config.data_qos)
        self.catalog = Catalog(
            config, self.stats, self.identity, self.trust, self.cluster, self.backbone
        )
        self.sessions = Sessions(config, self.stats)
        self.admission = Admission(config, self.stats, self._clear, self.catalog.__contains__)
        self.notices = Notices(config, self.identity, self.cluster, self.admission)
        self.router = Router(config, self.stats, self.sessions, self.cluster, self.backbone)

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
        """Start the dispatch thread and connect; with a timeout, wait for both brokers."""
        self.start_dispatch()
        self.cluster.start(timeout)
        if self.backbone is not None:
            self.backbone.start(timeout)
        return self

    def stop(self) -> None:
        """Withdraw this core's services from the backbone, clear the list, disconnect."""
        self.stop_dispatch()  # state is not touched by the dispatch thread after this
        if self.backbone is not None:
            for name in self.catalog.own():
                self.backbone.publish_and_wait(topics.bb_announce(name), b"", retain=True)
            status = CoreStatus(name=self.name, online=False).model_dump_json().encode()
            self.backbone.publish_and_wait(topics.bb_core(self.name), status, retain=True)
            self.backbone.stop()
        self.catalog.clear_askers()
        self.cluster.publish_and_wait(topics.SERVICES, b"", retain=True)
        self.cluster.stop()

    def __enter__(self) -> Core:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    @property
    def services(self) -> list[ServiceDescription]:
        """A snapshot of the services this core knows (read from any thread)."""
        return self.catalog.descriptions()

    @property
    def public_key(self) -> str:
        """The core's Ed25519 public key: participants pin it (``core_key``)."""
        return self.identity.public

    @property
    def session_count(self) -> int:
        return len(self.sessions)

    @property
    def pseudonym_count(self) -> int:
        """Live pseudonyms of this cluster's participants (current and in their grace)."""
        return self.sessions.pseudonym_count

    @property
    def route_count(self) -> int:
        """Pseudonyms of other clusters' participants whose replies this core routes."""
        return self.router.route_count

    @property
    def hops(self) -> Hops | None:
        """Set to note when each input passes this core (`ldm.transport.hops`; `laas bench`)."""
        return self.router.hops

    @hops.setter
    def hops(self, hops: Hops | None) -> None:
        self.router.hops = hops

    # --- intake (paho's threads) ------------------------------------------------------

    def sink(self, item: Item) -> None:
        """Both transports' sink (paho's threads), where each message's topic is parsed,
        once. A participant's message is admitted here (`Admission.admit`), before it
        shares a queue with anyone, and waits in its client's lane of the fair queue;
        data under a pseudonym (a provider's reply, input and replies over the backbone)
        waits in that pseudonym's lane as an `Entry`; control (service announcements and
        lists, core statuses, reconnects) is handled first. A batch is cut into its
        envelopes here (without decoding them), each an `Entry` in its lane."""
        if isinstance(item, Entry):
            self._offer(item)
            return
        if not isinstance(item, Message):
            super().sink(item)
            return
        topic = topics.parse(item.topic)
        if item.source == _CLUSTER and topic.client:
            timer = self.timer
            started = time.perf_counter()
            admitted = self.admission.admit(item, topic)
            queued = admitted is not None and self._intake.offer(admitted, topic.client)
            if admitted is not None and not queued and not admitted.refused:
                self.admission.overflowed()
            if timer is not None:
                timer("admit", time.perf_counter() - started)
        elif topic.kind in _BATCH:
            self._unbatch(item, topic)
        else:
            self._offer(Entry(topic, topic.pseudonym, item.payload, item.qos, item.source))

    def _offer(self, entry: Entry) -> None:
        """Queue an entry: data in its pseudonym's lane, control first."""
        if entry.topic.kind in _DATA or entry.topic.kind in _BATCH:
            queued = self._intake.offer(entry, (_PSEUDONYM, entry.pseudonym))
        else:
            queued = self._intake.offer(entry)
        if not queued:
            self.admission.overflowed()

    def _unbatch(self, msg: Message, topic: topics.Topic) -> None:
        """A batch (paho's thread): each envelope waits in its pseudonym's lane as an
        `Entry` that carries the batch's parsed topic; a malformed line is counted and
        skipped."""
        entries, bad = batch.cut(msg.payload, topic, msg.qos, msg.source)
        dropped = 0
        offer = self._intake.offer
        for entry in entries:
            if not offer(entry, (_PSEUDONYM, entry.pseudonym)):
                dropped += 1
        if bad:
            self.admission.malformed(bad)
        if dropped:
            self.admission.overflowed(dropped)

    def overflowed(self) -> None:
        self.admission.overflowed()

    def _clear(self, topic: str, qos: int) -> None:
        """Delete what the cluster broker retains on a participant's topic."""
        self.cluster.publish(topic, b"", qos=qos, retain=True)

    # --- dispatch thread ----------------------------------------------------------------

    def handle(self, item: Item) -> None:
        self.handle_many([item])

    def handle_many(self, items: list[Item]) -> None:
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
            self.router.flush()

    def _handle(self, item: Item) -> None:
        if isinstance(item, Connected):
            self._on_connected(item.source)
            return
        try:
            if isinstance(item, Entry):
                self._entry(item)
            elif isinstance(item, Admitted):
                self._from_participant_topic(item, item.parsed)
            else:
                self._plain(item)
        except ValidationError:
            self.stats.dropped_invalid += 1
            log.debug(
                "%s: dropped a malformed message on %s",
                self.name,
                item.topic.kind if isinstance(item, Entry) else item.topic,
                extra={"event": "malformed_message"},
            )

    def _plain(self, msg: Message) -> None:
        """A message handed to `handle` itself, not taken through `sink`: its topic is
        parsed here, once."""
        topic = topics.parse(msg.topic)
        if msg.source == _CLUSTER and topic.client:
            self._from_participant_topic(msg, topic)
        elif topic.kind in _BATCH:
            entries, bad = batch.cut(msg.payload, topic, msg.qos, msg.source)
            self.stats.dropped_invalid += bad
            for entry in entries:
                self._handle(entry)
        else:
            self._entry(Entry(topic, topic.pseudonym, msg.payload, msg.qos, msg.source))

    def tick(self, now: float) -> None:
        self.catalog.repair(now)
        self.catalog.expire(now)
        for session in self.sessions.expire(now):
            self.notices.send(session.client, SessionNotice(kind="rotate", service=session.service))
        self.router.expire(now)
        self.admission.forget(now, self.sessions)
        if self.admission.sweep_due(now):
            # The broker sends what is retained under the filter again, flagged retained:
            # admission clears each. (A live message never shows the flag in MQTT 3.1.1.)
            self.cluster.subscribe(topics.PARTICIPANT_UP_FILTER, 1)

    def _on_connected(self, source: str) -> None:
        if source == _CLUSTER:
            self.catalog.connected()
        elif self.backbone is not None:
            status = CoreStatus(name=self.name, online=True).model_dump_json().encode()
            self.backbone.publish(topics.bb_core(self.name), status, qos=1, retain=True)
            self.catalog.announce_own()

    # Every message ends in exactly one counter: forwarded_*, dropped_*, rejected_*,
    # answered_*, granted, or control (an announcement, withdrawal or core status taken).

    def _from_participant_topic(self, msg: Message, topic: topics.Topic) -> None:
        if topic.client and msg.topic.count("/") >= 4:  # ldm/p/{client}/up/...
            self._from_participant(msg, topic)
        else:
            self.stats.dropped_invalid += 1

    def _entry(self, entry: Entry) -> None:
        """An envelope under a pseudonym, or a control message (`Entry`)."""
        topic, payload = entry.topic, entry.payload
        kind = topic.kind
        if entry.source == _CLUSTER:
            if kind == "announce":
                self.catalog.local(topic.service, payload)
            elif kind == "provider_reply" or kind == "provider_reply_batch":
                env = Envelope.model_validate_json(payload)
                self.router.reply(topic.service, entry.pseudonym, env, payload)
            elif kind == "services":
                self.catalog.check_list(payload)
            else:
                self.stats.dropped_invalid += 1
        elif kind == "bb_announce":
            self.catalog.remote(topic.service, payload)
        elif kind == "bb_core":
            self.catalog.core_status(payload)
        elif kind == "bb_input" or kind == "bb_input_batch":
            env = Envelope.model_validate_json(payload)
            local = self.catalog.served_here(topic.service, time.time())
            self.router.remote_input(topic, entry.pseudonym, env, payload, local)
        elif kind == "bb_reply" or kind == "bb_reply_batch":
            env = Envelope.model_validate_json(payload)
            if not self.router.stale(env):
                self.router.deliver(topic.service, entry.pseudonym, env, payload)
        else:
            self.stats.dropped_invalid += 1

    # --- participant input: the user cluster's boundary -------------------------------

    def _from_participant(self, msg: Message, topic: topics.Topic) -> None:
        """``ldm/p/{client}/up/session`` or ``ldm/p/{client}/up/data/{service}``.

        The client's budget was charged at admission (a message refused there arrives
        only to have its notice sent). Here, in order, each cheaper than the next: the
        size limit, the topic, then decoding. Every refusal is counted and answered to
        this client only, from the notice bucket of the budget that paid for it.
        """
        client, service = topic.client, topic.service
        is_session = topic.kind == "session_request"
        is_list = topic.kind == "services_request"
        admitted = msg if isinstance(msg, Admitted) else None
        charge: Charge = (
            admitted.charge
            if admitted is not None
            else "session"
            if is_session or is_list
            else "other"
        )
        cfg = self.config
        if admitted is not None and admitted.refused:
            error = f"more than {cfg.rate:g} messages per second (burst {cfg.burst:g}); slow down"
            self.notices.reject(
                charge, client, service, "rate_limited", error, payload=msg.payload, paid=True
            )
            return
        if len(msg.payload) > cfg.max_payload:
            self.stats.rejected_size += 1
            error = f"payload: {len(msg.payload)} bytes is over the limit of {cfg.max_payload}"
            self.notices.reject(charge, client, service, "too_large", error)
            return
        if not (is_session or is_list or topic.kind == "participant_input"):
            self.stats.dropped_invalid += 1
            error = (
                f"topic: {msg.topic!r} is none of .../up/session, .../up/services "
                "and .../up/data/SERVICE"
            )
            self.notices.reject(charge, client, service, "invalid", error)
            return
        try:
            if is_list:
                ServicesRequest.model_validate_json(msg.payload)
                self.catalog.send_to(client, time.time())
                return
            if is_session:
                request = SessionRequest.model_validate_json(msg.payload)
                self._session_request(charge, client, request)
                service = request.service
            else:
                known = admitted.envelope if admitted is not None else None
                env = Envelope.model_validate_json(msg.payload) if known is None else known
                secret = admitted.secret if admitted is not None and known is not None else None
                if not self._participant_input(charge, client, service, env, msg.payload, secret):
                    return
        except ValidationError as exc:
            self.stats.dropped_invalid += 1
            what = (
                "list request" if is_list else "session request" if is_session else "input envelope"
            )
            error = f"{what}: {describe(exc)}"
            self.notices.reject(charge, client, service, "invalid", error, payload=msg.payload)
            return
        # What admission knows of the session may have changed (a grant's secret, a new
        # session, key or pseudonym): tell it.
        self.admission.know(client, service, self.sessions.keys(client, service))

    def _session_request(self, charge: Charge, client: str, req: SessionRequest) -> None:
        svc = self.catalog.get(req.service)
        if svc is None:
            self.stats.answered_refused += 1
            error = f"no service {req.service!r} in this cluster; list the services first"
            notice = SessionNotice(kind="refused", service=req.service, c=req.c, error=error)
            self.notices.answer(charge, client, notice)
            return
        self.notices.send(client, self.sessions.grant(client, req, svc.description, time.time()))

    def _participant_input(
        self,
        charge: Charge,
        client: str,
        service: str,
        env: Envelope,
        received: bytes,
        checked: bytes | None,
    ) -> bool:
        """Input of a participant's session (`env`, decoded from `received`), forwarded
        under its pseudonym. `checked`: the secret admission checked the tag with (not
        checked again while the session still has it). True if what admission knows of
        the session may have changed (a new session, key or pseudonym)."""
        cfg = self.config
        now = time.time()
        if env.t > now + cfg.max_clock_skew:
            self.stats.rejected_clock += 1
            error = (
                f"t: {env.t - now:.0f} s ahead of the core's clock (limit "
                f"{cfg.max_clock_skew:g} s); synchronise the clock"
            )
            self.notices.reject(charge, client, service, "clock", error, c=env.c)
            return False
        if self.router.stale(env):
            return False
        session = self.sessions.get(client, service)
        if session is None or env.k is None:
            self.stats.answered_nosession += 1
            notice = SessionNotice(kind="nosession", service=service, c=env.c)
            self.notices.answer(charge, client, notice)
            return True
        if session.secrets and not self.sessions.authentic(session, env, checked, now):
            self.stats.dropped_unauthentic += 1
            return False
        svc = self.catalog.get(service)
        if svc is None:
            self.stats.answered_refused += 1
            error = f"service {service!r} is gone"
            notice = SessionNotice(kind="refused", service=service, c=env.c, error=error)
            self.notices.answer(charge, client, notice)
            return False
        before = session.current
        pseudonym = self.sessions.pseudonym(session, env.k, svc.description.public_key, now)
        if pseudonym is None:
            self.stats.rejected_rekey += 1
            error = (
                f"k: a new ephemeral key at most every {cfg.rekey_interval:g} s "
                "per session; keep the current key until the core asks to rotate"
            )
            self.notices.reject(charge, client, service, "rate_limited", error, c=env.c)
            return False
        problem = self.router.forward_input(svc.origin, service, pseudonym, env, received, now)
        if problem is not None:
            self.stats.rejected_unavailable += 1
            # Answered whatever the notice bucket holds: the input is authentic (its tag
            # was checked) and paid for, and an unanswered one would be lost silently
            # until it times out.
            self.notices.reject(charge, client, service, "unavailable", problem, c=env.c, paid=True)
        return session.current is not before
