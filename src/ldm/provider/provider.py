"""The provider library: offer a service on the LDM.

A provider connects to its cluster broker, announces its service (retained, with a last
will that withdraws it, re-announced every ``announce_interval``), takes the input of
all participants through one wildcard subscription and replies to pseudonyms. It never
learns who a participant is: only a pseudonym, which changes on rotation, and a fresh
ephemeral key with it.

The handler runs on the provider's dispatch thread, one request at a time; it returns the
reply payload (or None to reply later with `Provider.reply`). A batch handler instead
takes every input that waited together (up to ``max_batch``), decrypted, in order of
arrival, and returns one reply (or None) for each: a service whose work is cheaper per
item in bulk keeps up under load at no cost to a lone request.

Pay per batch: input arrives one envelope per message or many in one batch from the
core (`ldm.wire.batch`), cut apart on arrival into entries (`ldm.wire.batch.Entry`)
that carry the topic parsed there, once; the dispatch thread takes everything that
waited (up to ``max_batch``), and the replies to it leave together, one batch once the
thread has handled it all, or a single message when there is one.

Family notes: the providers of one family (regional workers, `ldm.client.routing`), which
serve under one identity, may pass each other what their neighbours need (a service's
own business: the LaaS workers share their common-error evidence). `Provider.note`
publishes on ``ldm/svc/{family}/note/{service}``, sealed with the region key
(`ldm.security.crypto.region_cipher`), which no core subscribes to and no broker can
read; each other provider of the family given ``on_note`` gets it on its dispatch thread,
as (sender, plaintext), once, in order: a note no newer than the sender's last, older
than ``max_age``, or that fails authentication is dropped and counted
(``ProviderStats.dropped_notes``).
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pydantic import ValidationError

from ldm.config import BrokerSettings, ProviderConfig, build
from ldm.errors import CryptoError, SessionError
from ldm.security.crypto import KeyPair, SessionCipher, aad, region_cipher
from ldm.security.identity import SigningKey, verify
from ldm.transport.dispatch import Dispatcher
from ldm.transport.hops import Hops
from ldm.transport.mqtt import Connected, Event, Message, Transport, Will
from ldm.wire import batch, topics
from ldm.wire.batch import Entry, Outbox
from ldm.wire.messages import (
    Announcement,
    Envelope,
    ServiceDescription,
    ServiceList,
    ServiceSpec,
    Withdrawal,
)

__all__ = ["BatchHandler", "Handler", "Provider", "ProviderStats", "Request"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Request:
    """One decrypted input: who (a pseudonym), which request (``correlation_id``), what."""

    pseudonym: str
    correlation_id: str
    payload: dict[str, Any]
    sent_at: float
    new_pseudonym: bool
    """True for the first input seen under this pseudonym (a new session or a rotation)."""


Item = Event | Entry
"""What a provider's dispatch thread takes: a reconnect, an input or a note with its
parsed topic (`Entry`), or a plain `Message` handed to `Provider.handle` (parsed there)."""

Handler = Callable[[Request], Mapping[str, Any] | None]
BatchHandler = Callable[[Sequence[Request]], Sequence[Mapping[str, Any] | None]]


@dataclass(slots=True)
class ProviderStats:
    """Counters (``Provider.stats``)."""

    requests: int = 0
    replies: int = 0
    dropped_stale: int = 0
    dropped_invalid: int = 0
    dropped_oversize: int = 0
    dropped_overload: int = 0
    """Input dropped on arrival because ``max_queue`` inputs were already waiting."""
    dropped_replay: int = 0
    """Input whose correlation id was already seen under its key within ``max_age``, and
    not answered yet (or no longer remembered)."""
    answered_again: int = 0
    """Input whose correlation id was already answered under its key within ``max_age``:
    a participant's retry (``ParticipantConfig.retry_after``), answered with the same
    reply again, the handler not called twice."""
    handler_errors: int = 0
    """The handler raised, or its reply could not be encoded or sent."""
    reply_batches: int = 0
    """Messages that carried more than one reply (the rest went one per message)."""
    notes_sent: int = 0
    notes_taken: int = 0
    dropped_notes: int = 0
    """Family notes dropped: malformed, failing authentication, stale or replayed."""


_REPLAY_IDS = 1024  # correlation ids remembered per participant key (within max_age)
_ANSWERS = 64  # replies remembered per participant key, for its retries (within max_age)


@dataclass(slots=True)
class _Peer:
    """One participant key: its derived cipher and the correlation ids it used lately."""

    cipher: SessionCipher
    seen: dict[str, float] = field(default_factory=dict)
    answers: OrderedDict[str, tuple[bytes, float]] = field(default_factory=OrderedDict)
    """Correlation id -> the sealed reply sent to it and when, newest last: a retry of
    the same input is answered with the same bytes (idempotent), not handled again."""

    def answered(self, c: str, sealed: bytes, now: float, oldest: float) -> None:
        """Remember the reply to `c` (at most ``_ANSWERS``, none older than `oldest`)."""
        answers = self.answers
        answers[c] = (sealed, now)
        while answers and (len(answers) > _ANSWERS or next(iter(answers.values()))[1] < oldest):
            answers.popitem(last=False)

    def replayed(self, c: str, t: float, oldest: float) -> bool:
        """True if ``c`` came before; else remember it (ids older than ``oldest`` go)."""
        if c in self.seen:
            return True
        if len(self.seen) >= _REPLAY_IDS:
            self.seen = {k: v for k, v in self.seen.items() if v >= oldest}
            while len(self.seen) >= _REPLAY_IDS:
                del self.seen[next(iter(self.seen))]
        self.seen[c] = t
        return False


@dataclass(slots=True)
class _Reply:
    """Where replies to one pseudonym go: its cipher and the QoS its input came with."""

    cipher: SessionCipher
    qos: int
    peer: _Peer | None = None
    """The participant key's record, which remembers the replies for retries."""


class Provider(Dispatcher[Item]):
    """A service provider. ``start()`` announces and serves; ``stop()`` withdraws."""

    def __init__(
        self,
        config: ProviderConfig,
        spec: ServiceSpec,
        handler: Handler,
        *,
        key: KeyPair | None = None,
        identity: SigningKey | None = None,
        batch_handler: BatchHandler | None = None,
        on_note: Callable[[str, bytes], None] | None = None,
    ) -> None:
        super().__init__(
            f"ldm-provider-{spec.name}",
            min(0.5, config.announce_interval / 4),
            limit=config.max_queue,
            batch=config.max_batch,
        )
        self._outbox = Outbox()
        """The dispatch thread's replies, sent once it handled what waited."""
        self.config = config
        self.key = key or KeyPair()
        if identity is None:
            path = config.identity_file
            identity = SigningKey.load_or_create(path) if path else SigningKey.generate()
        self.identity = identity
        """The service's Ed25519 identity: participants pin ``identity.public``."""
        unsigned = ServiceDescription(
            **spec.model_dump(),
            public_key=self.key.public,
            identity=identity.public,
            issued=time.time(),
            endorsement=config.endorsement,
        )
        self.description = unsigned.model_copy(
            update={"signature": identity.sign(unsigned.signed_text())}
        )
        self.name = spec.name
        goodbye = Withdrawal(withdrawn=spec.name, identity=identity.public, issued=unsigned.issued)
        goodbye = goodbye.model_copy(update={"sig": identity.sign(goodbye.signed_text())})
        self._goodbye = goodbye.model_dump_json().encode()
        """The signed withdrawal: the last will, and what `stop` publishes."""
        self.stats = ProviderStats()
        self.hops: Hops | None = None
        """Set to note when each input passes this provider (`ldm.transport.hops`; `laas bench`)."""
        self.timer: Callable[[str, float], None] | None = None
        """Told (stage, seconds) for each input opened (``open``), each reply sealed
        (``seal``) and each turn of the handler (``step``); None: not timed
        (`ldm.ops.metrics.Metrics.watch_provider` sets it)."""
        self._arrived: dict[int, float] = {}  # id(message) -> arrival, while hops are noted
        self._handler = handler
        self._batch_handler = batch_handler
        self._peers: OrderedDict[str, _Peer] = OrderedDict()
        self._by_pseudonym: OrderedDict[str, _Reply] = OrderedDict()
        self._count = threading.Lock()  # replies and their errors may come from any thread
        self._next_announce = 0.0
        client_id = config.client_id or f"ldm-svc-{spec.name}-{secrets.token_hex(3)}"
        self.transport = Transport(
            config.broker,
            client_id=client_id,
            sink=self.sink,
            name=f"provider-{spec.name}",
            will=Will(topics.announce(spec.name), self._goodbye, qos=1, retain=True),
        )
        # Subscribed at QoS 2 unless set, input arrives at the QoS the core sent it with.
        qos = 2 if config.data_qos is None else config.data_qos
        self.transport.subscribe(topics.provider_input_filter(spec.name), qos)
        self.transport.subscribe(topics.provider_input_batch(spec.name), qos)
        self._reply_topic = topics.provider_reply_batch(spec.name)
        self.cluster = config.cluster
        """The core's name every announcement is signed for (`Announcement.cluster`);
        None until the cluster's service list names it."""
        if self.cluster is None:
            self.transport.subscribe(topics.SERVICES, 1)
        self.family = spec.family
        self._region_key = None if spec.family is None else region_cipher(identity, spec.family)
        self._on_note = on_note
        self._note_times: dict[str, float] = {}  # sender -> its last note's time
        if spec.family is not None and on_note is not None:
            self.transport.subscribe(topics.family_note_filter(spec.family), 0)

    @classmethod
    def create(
        cls,
        broker: BrokerSettings | str,
        spec: ServiceSpec,
        handler: Handler,
        *,
        key: KeyPair | None = None,
        identity: SigningKey | None = None,
        batch_handler: BatchHandler | None = None,
        on_note: Callable[[str, bytes], None] | None = None,
        **settings: Any,
    ) -> Provider:
        """Build a provider from a URL or settings plus any ProviderConfig field."""
        config = build(ProviderConfig, broker=BrokerSettings.of(broker), **settings)
        return cls(
            config,
            spec,
            handler,
            key=key,
            identity=identity,
            batch_handler=batch_handler,
            on_note=on_note,
        )

    def start(self, timeout: float | None = 10.0) -> Provider:
        """Connect, announce and serve in background threads."""
        self.start_dispatch()
        self.transport.start(timeout)
        return self

    def stop(self) -> None:
        """Withdraw the announcement and disconnect."""
        self.stop_dispatch()
        self.transport.publish_and_wait(
            topics.announce(self.name), self._goodbye, qos=1, retain=True
        )
        self.transport.stop()

    def kill(self) -> None:
        """Vanish without a goodbye (for fault tests): the broker publishes the last will."""
        self.stop_dispatch()
        self.transport.kill()

    def __enter__(self) -> Provider:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    def reply(self, pseudonym: str, correlation_id: str, payload: Mapping[str, Any]) -> None:
        """Send a reply to a pseudonym seen recently (any thread)."""
        route = self._by_pseudonym.get(pseudonym)
        if route is None:
            raise SessionError(f"no recent input from pseudonym {pseudonym!r}; cannot reply")
        self._send(route, pseudonym, correlation_id, payload, now=True)

    def seal_shared(self, plaintext: bytes, context: str) -> str:
        """`plaintext` sealed for the family's providers alone (the region key, as a
        note), with `context` bound as associated data: what one passes another through
        someone it does not trust (a regional worker's hand-over, through the user)."""
        if self._region_key is None:
            raise SessionError(f"{self.name} is in no family: it holds no region key")
        return self._region_key.seal(plaintext, context)

    def open_shared(self, sealed: str, context: str) -> bytes:
        """What a provider of the family sealed with `seal_shared` under `context`;
        CryptoError if it was not, or was changed."""
        if self._region_key is None:
            raise SessionError(f"{self.name} is in no family: it holds no region key")
        return self._region_key.open(sealed, context)

    def note(self, payload: bytes) -> None:
        """Send `payload` to the family's other providers (the module docstring)."""
        if self.family is None or self._region_key is None:
            raise SessionError(f"{self.name} is in no family: it has nobody to send notes to")
        t = time.time()
        sealed = self._region_key.seal(payload, _note_aad(self.name, t))
        body = json.dumps({"t": t, "d": sealed}, separators=(",", ":")).encode()
        self.transport.publish(topics.family_note(self.family, self.name), body, 0)
        with self._count:
            self.stats.notes_sent += 1

    def _note(self, msg: Entry) -> None:
        """A family note (dispatch thread): opened, checked, given to ``on_note``."""
        sender = msg.topic.service
        if sender == self.name or self._on_note is None or self._region_key is None:
            return
        try:
            body = json.loads(msg.payload)
            t = float(body["t"])
            if not time.time() - t <= self.config.max_age or t <= self._note_times.get(
                sender, -1.0
            ):
                raise CryptoError("a stale or replayed note")
            plaintext = self._region_key.open(str(body["d"]), _note_aad(sender, t))
        except (CryptoError, ValueError, KeyError, TypeError, RecursionError):
            self.stats.dropped_notes += 1
            return
        self._note_times[sender] = t
        self.stats.notes_taken += 1
        try:
            self._on_note(sender, plaintext)
        except Exception:
            log.error("%s: a note from %s was not taken", self.name, sender, exc_info=True)

    @property
    def cached_ciphers(self) -> int:
        """Derived session ciphers held now (at most ``cipher_cache``)."""
        return len(self._peers)

    def overflowed(self) -> None:
        self.stats.dropped_overload += 1

    def sink(self, item: Item) -> None:
        """The transport's sink (paho's thread), where each message's topic is parsed,
        once: a message is queued as an `Entry`, and a batch is cut into its envelopes,
        each an `Entry` with the batch's topic; a malformed line is counted."""
        if isinstance(item, Message):
            if item.topic == topics.SERVICES:
                self._service_list(item.payload)
                return
            topic = topics.parse(item.topic)
            if topic.kind == "provider_input_batch" and topic.service == self.name:
                entries, bad = batch.cut(item.payload, topic, item.qos, item.source)
                if bad:
                    with self._count:
                        self.stats.dropped_invalid += bad
                for entry in entries:
                    self._take(entry)
                return
            item = Entry(topic, topic.pseudonym, item.payload, item.qos, item.source)
        self._take(item)

    def _service_list(self, payload: bytes) -> None:
        """Learn the cluster's name from its core's list (paho's thread): signed by the
        pinned ``core_key`` if set, else the latest list that names one. A new name is
        announced at the next tick."""
        if not payload or len(payload) > self.config.max_payload * 16:
            return
        try:
            listing = ServiceList.model_validate_json(payload)
        except ValidationError:
            return
        key = self.config.core_key
        if listing.cluster is None or (
            key is not None and not verify(key, listing.signed_text(), listing.sig)
        ):
            return
        if listing.cluster != self.cluster:
            self.cluster = listing.cluster
            self._next_announce = 0.0

    def _take(self, item: Item) -> None:
        if self.hops is not None and isinstance(item, Entry):
            self._arrived[id(item)] = time.time()  # paho's thread; `open` takes it
        super().sink(item)

    # --- dispatch thread ----------------------------------------------------------------

    def handle(self, item: Item) -> None:
        self.handle_many([item])

    def handle_many(self, items: list[Item]) -> None:
        """Inputs that waited together go to the batch handler as one batch (a reconnect
        among them is handled in its place), or one by one to the handler; then their
        replies leave."""
        try:
            if self._batch_handler is None:
                for item in items:
                    if isinstance(item, Connected):
                        self._connected(time.time())
                        continue
                    entry = _entry(item)
                    if self._is_note(entry):
                        self._note(entry)
                    else:
                        self._input(entry)
                return
            run: list[Entry] = []
            for item in items:
                if isinstance(item, Connected):
                    self._inputs(run)
                    run = []
                    self._connected(time.time())
                    continue
                entry = _entry(item)
                if self._is_note(entry):
                    self._note(entry)
                else:
                    run.append(entry)
            self._inputs(run)
        finally:
            self._outbox.flush()
            self.stats.reply_batches = self._outbox.batches

    def _is_note(self, entry: Entry) -> bool:
        return self._on_note is not None and entry.topic.kind == "family_note"

    def tick(self, now: float) -> None:
        if now >= self._next_announce and self.transport.connected:
            self._announce(now)

    def _connected(self, now: float) -> None:
        """Announce on (re)connecting; not knowing the cluster yet, wait up to a second
        for its retained list first (it names the cluster: `_service_list`)."""
        if self.cluster is None:
            self._next_announce = now + min(1.0, self.config.announce_interval)
        else:
            self._announce(now)

    def _announce(self, now: float) -> None:
        self._next_announce = now + self.config.announce_interval
        ann = Announcement(service=self.description, t=now, cluster=self.cluster)
        ann = ann.model_copy(update={"sig": self.identity.sign(ann.signed_text())})
        self.transport.publish(
            topics.announce(self.name), ann.model_dump_json().encode(), qos=1, retain=True
        )

    def _peer(self, key: str) -> _Peer:
        peer = self._peers.get(key)
        if peer is None:
            peer = _Peer(self.key.cipher(key, initiator=False))
            self._peers[key] = peer
            if len(self._peers) > self.config.cipher_cache:
                self._peers.popitem(last=False)
        else:
            self._peers.move_to_end(key)
        return peer

    def _timed(self, stage: str, started: float) -> None:
        timer = self.timer
        if timer is not None:
            timer(stage, time.perf_counter() - started)

    def _input(self, msg: Entry) -> None:
        started = time.perf_counter()
        opened = self.open(msg)
        self._timed("open", started)
        if opened is None:
            return
        request, route = opened
        try:
            started = time.perf_counter()
            answer = self._handler(request)
            self._timed("step", started)
            if self.hops is not None:
                self.hops.mark("answered", request.correlation_id)
            if answer is not None:
                self._send(route, request.pseudonym, request.correlation_id, answer)
        except Exception:
            with self._count:
                self.stats.handler_errors += 1
            log.error("%s: no reply to a request", self.name, exc_info=True)

    def _inputs(self, messages: list[Entry]) -> None:
        """A batch of input: opened one by one, answered by the batch handler at once."""
        assert self._batch_handler is not None
        opened = []
        for msg in messages:
            started = time.perf_counter()
            one = self.open(msg)
            self._timed("open", started)
            if one is not None:
                opened.append(one)
        if not opened:
            return
        try:
            started = time.perf_counter()
            answers = self._batch_handler([request for request, _ in opened])
            self._timed("step", started)
            if self.hops is not None:
                for request, _ in opened:
                    self.hops.mark("answered", request.correlation_id)
            if len(answers) != len(opened):
                raise ValueError(f"{len(answers)} replies to a batch of {len(opened)}")
        except Exception:
            with self._count:
                self.stats.handler_errors += len(opened)
            log.error("%s: no reply to a batch of %d", self.name, len(opened), exc_info=True)
            return
        for (request, route), answer in zip(opened, answers, strict=True):
            if answer is not None:
                self._send(route, request.pseudonym, request.correlation_id, answer)

    def open(self, msg: Entry | Message) -> tuple[Request, _Reply] | None:
        """One input (an `Entry`, or a message, whose topic is then parsed here) -> the
        decrypted request and the route of its reply; None (and counted) if it is
        oversize, invalid, stale or a replay. The dispatch thread's first step, apart so
        `laas bench --worker-only` can time it."""
        pseudonym = msg.pseudonym if isinstance(msg, Entry) else topics.parse(msg.topic).pseudonym
        arrived = self._arrived.pop(id(msg), None) if self.hops is not None else None
        if len(msg.payload) > self.config.max_payload:
            self.stats.dropped_oversize += 1
            return None
        try:
            env = Envelope.model_validate_json(msg.payload)
            if env.k is None:
                raise CryptoError("input without a key")
            now = time.time()
            if now - env.t > self.config.max_age:
                self.stats.dropped_stale += 1
                return None
            peer = self._peer(env.k)
            payload = json.loads(peer.cipher.open(env.d, aad(env.c, env.t)))
            if not isinstance(payload, dict):
                raise CryptoError("payload is not a JSON object")
        except (ValidationError, CryptoError, ValueError, RecursionError):
            self.stats.dropped_invalid += 1
            return None
        qos = msg.qos if self.config.data_qos is None else self.config.data_qos
        if peer.replayed(env.c, env.t, now - self.config.max_age):
            with self._count:
                again = peer.answers.get(env.c)
            if again is None or now - again[1] > self.config.max_age:
                self.stats.dropped_replay += 1
                return None
            # A retry (or a broker's duplicate) of an input answered lately: the same
            # reply again, so a reply lost on the way costs the participant one retry.
            self._outbox.add(self.transport, self._reply_topic, pseudonym, again[0], qos)
            self.stats.answered_again += 1
            return None
        new = pseudonym not in self._by_pseudonym
        route = self._by_pseudonym[pseudonym] = _Reply(peer.cipher, qos, peer)
        self._by_pseudonym.move_to_end(pseudonym)
        if len(self._by_pseudonym) > self.config.cipher_cache:
            self._by_pseudonym.popitem(last=False)
        self.stats.requests += 1
        if self.hops is not None and arrived is not None:
            self.hops.mark("arrived", env.c, arrived)
            self.hops.mark("taken", env.c, now)
        return Request(pseudonym, env.c, payload, env.t, new), route

    @staticmethod
    def seal(route: _Reply, correlation_id: str, payload: Mapping[str, Any]) -> bytes:
        """A reply's wire bytes: the payload as JSON, encrypted for its session."""
        plaintext = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
        t = time.time()
        env = Envelope(
            c=correlation_id, t=t, d=route.cipher.seal(plaintext, aad(correlation_id, t))
        )
        return env.encode()

    def _send(
        self,
        route: _Reply,
        pseudonym: str,
        correlation_id: str,
        payload: Mapping[str, Any],
        now: bool = False,
    ) -> None:
        """Seal a reply and send it: into the dispatch thread's outbox, or at once (`now`: from
        another thread, `reply`)."""
        started = time.perf_counter()
        sealed = self.seal(route, correlation_id, payload)
        self._timed("seal", started)
        if now:
            self.transport.publish(topics.provider_reply(self.name, pseudonym), sealed, route.qos)
        else:
            self._outbox.add(self.transport, self._reply_topic, pseudonym, sealed, route.qos)
        with self._count:
            self.stats.replies += 1
            if route.peer is not None:
                sent = time.time()
                route.peer.answered(correlation_id, sealed, sent, sent - self.config.max_age)


def _entry(item: Entry | Message) -> Entry:
    """`item` as an entry: a plain message handed to `Provider.handle` is parsed here."""
    if isinstance(item, Entry):
        return item
    topic = topics.parse(item.topic)
    return Entry(topic, topic.pseudonym, item.payload, item.qos, item.source)


def _note_aad(sender: str, t: float) -> str:
    """A note's associated data: its sender and time, so neither can be changed."""
    return f"note|{sender}|{t!r}"
