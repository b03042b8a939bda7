"""An attacker's toolkit for the LDM, and the deployment it attacks (issue 11).

The deployment is real: three Mosquitto processes (user cluster, backbone, service
cluster), both cores, the echo provider, participants. It runs in one of two modes:

- ``"acl"``: every broker runs its shipped ACL (``deploy/security/acl-*``) with a
  password file, no anonymous clients and, on the user broker, ``use_username_as_clientid``,
  as docs/security.md deploys them. The attacker is a participant with its own account.
- ``"open"``: the same brokers with no ACL and anonymous access. The attacker can read
  and write every topic; only the cryptography (pinned service identities, a pinned
  core key) stands between it and the participants.

An attacker is an `ldm.transport.Transport` (the only module that imports paho) plus an
X25519 `KeyPair` it wants victims to encrypt to and an Ed25519 `SigningKey` it signs its
forgeries with: a forgery is well-formed and carries a valid signature, by the wrong key.
It listens on ``#`` (all it is allowed to read), keeps everything it publishes, and can
react to a message on paho's network thread, which is how it wins races against a core.
A `Recorder` with a read-only account (the *witness*) sees what the broker delivers, so a
test can tell whether the broker let a forgery through (`Attacker.reached`).

Each attack of the issue's table is one class or function here, usable on its own:

    with HostileDeployment("open") as d:
        alice = d.participant("alice")
        race = GrantRace(d.attacker, d.real("echo"), victims=["alice"]).start()
        load = Load(alice.open("echo"), "alice")
        window = drive([load], seconds=1.0)
        race.stop()
        load.settle()
        assert not d.attacker.decrypted and not load.forged()

`Load` sends requests at a steady pace and classifies every answer (genuine, forged,
failed, missing), and measures the longest stretch without an answer (a lock-out).
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import secrets
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Self, TypeVar

from ldm import Core, KeyPair, Participant, Provider, Session
from ldm.config import BrokerSettings, CoreConfig, ParticipantConfig, ProviderConfig, build
from ldm.errors import CryptoError
from ldm.local.brokers import MosquittoBroker, wait_for
from ldm.ops.passwd import random_password, set_passwords
from ldm.security.crypto import SessionCipher, aad
from ldm.security.identity import SigningKey
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire.messages import (
    Announcement,
    Envelope,
    ServiceDescription,
    ServiceList,
    ServicesRequest,
    SessionGrant,
    SessionNotice,
    SessionRequest,
)

from .deployment import ECHO, FAST, EchoService

__all__ = [
    "MODES",
    "Attacker",
    "FakeProvider",
    "GrantRace",
    "HostileDeployment",
    "InputFlood",
    "Load",
    "Mode",
    "NoticeStorm",
    "Recorder",
    "Repeater",
    "ReplyForger",
    "Shot",
    "Window",
    "drive",
    "falsify",
    "fix",
    "forged_description",
    "forged_list",
    "forged_notice",
    "future_announcement",
    "matches",
    "read_retained",
]

Mode = Literal["acl", "open"]
MODES: tuple[Mode, ...] = ("acl", "open")

SECURITY = Path(__file__).resolve().parents[2] / "deploy" / "security"

CORE_USER = "ldm-core-user"  # the user-cluster core's account (deploy/security/acl-user-cluster)
CORE_SERVICE = "ldm-core-service"  # the service-cluster core's (acl-service-cluster)
PROVIDER_USER = "svc-echo"  # the echo provider's, on the laas-worker lines' model
WITNESS = "hostile-witness"  # read-only observer on every broker (test-only account)
PROBE = "hostile-probe"  # a fresh subscriber that reads retained messages (test-only)
ATTACKER = "mallory"
PARTICIPANTS = ("alice", "bob", "carol", "dave")

_OBSERVERS = f"user {WITNESS}\ntopic read ldm/#\n\nuser {PROBE}\ntopic read ldm/#\n"
_ECHO_ACCOUNT = (
    f"user {PROVIDER_USER}\n"
    "topic readwrite ldm/svc/echo/announce\n"
    "topic read ldm/svc/echo/in/#\n"
    "topic read ldm/services\n"
    "topic write ldm/svc/echo/out/#\n"
)

Payload = dict[str, Any]
_R = TypeVar("_R", bound="Recorder")


def matches(topic_filter: str, topic: str) -> bool:
    """MQTT topic matching with ``+`` and ``#`` (paho is kept inside ldm.transport)."""
    flt, top = topic_filter.split("/"), topic.split("/")
    for i, level in enumerate(flt):
        if level == "#":
            return True
        if i >= len(top) or (level != "+" and level != top[i]):
            return False
    return len(flt) == len(top)


def _token() -> str:
    return secrets.token_urlsafe(9)


# --- payloads ------------------------------------------------------------------------


def fix(who: str, i: int) -> Payload:
    """A position fix as a participant would send it (what an attacker wants to read)."""
    return {"who": who, "i": i, "lat": 53.55 + i * 1e-5, "lon": 9.99, "secret": f"fix-{who}-{i}"}


def falsify(payload: Payload) -> Payload:
    """The attacker's answer to a fix: the echo reply, placed 111 m north, marked."""
    lat = payload.get("lat")
    moved = {**payload, "lat": lat + 0.001 if isinstance(lat, float) else 0.0, "forged": True}
    return {"echo": moved}


# --- observers -----------------------------------------------------------------------


class Recorder:
    """An MQTT client that keeps every message it receives on its filters.

    ``on(filter, reaction)`` runs ``reaction(message)`` on paho's network thread as the
    message arrives: it must not block (publishing is fine). A witness is a Recorder
    with a read-only account on ``ldm/#``.
    """

    def __init__(
        self,
        settings: BrokerSettings,
        client_id: str,
        filters: Iterable[str] = ("ldm/#",),
    ) -> None:
        self._lock = threading.Lock()
        self._messages: list[Message] = []
        self._seen: dict[tuple[str, bytes], list[float]] = {}
        self._reactions: list[tuple[str, Callable[[Message], None]]] = []
        self.reaction_errors: list[BaseException] = []
        self.transport = Transport(settings, client_id=client_id, sink=self._sink, name=client_id)
        for flt in filters:
            self.transport.subscribe(flt, 1)

    def start(self, timeout: float = 5.0) -> Self:
        self.transport.start(timeout)
        return self

    def stop(self) -> None:
        self.transport.stop()

    def on(self, topic_filter: str, reaction: Callable[[Message], None]) -> None:
        """React to every message matching ``topic_filter`` (also subscribes to it)."""
        with self._lock:
            self._reactions.append((topic_filter, reaction))
        self.transport.subscribe(topic_filter, 1)

    def _sink(self, event: Event) -> None:
        if not isinstance(event, Message):
            return
        with self._lock:
            self._messages.append(event)
            self._seen.setdefault((event.topic, event.payload), []).append(time.time())
            reactions = [r for f, r in self._reactions if matches(f, event.topic)]
        for react in reactions:
            try:
                react(event)
            except Exception as exc:  # a reaction's bug must show, not kill paho's thread
                self.reaction_errors.append(exc)

    def messages(self, topic_filter: str = "#") -> list[Message]:
        """What arrived so far on topics matching ``topic_filter``."""
        with self._lock:
            return [m for m in self._messages if matches(topic_filter, m.topic)]

    def saw(self, topic: str, payload: bytes, since: float = 0.0) -> bool:
        """Whether this exact message arrived (at or after ``since``, wall clock)."""
        with self._lock:
            return any(t >= since for t in self._seen.get((topic, payload), ()))


def read_retained(settings: BrokerSettings, topic: str, timeout: float = 1.0) -> bytes | None:
    """What a brand-new subscriber gets on ``topic``: the retained payload, or None.

    Connects a fresh client, subscribes and waits up to ``timeout`` for the first
    message (a retained one arrives right after the subscription).
    """
    got: list[bytes] = []
    arrived = threading.Event()

    def sink(event: Event) -> None:
        if isinstance(event, Message) and event.topic == topic:
            got.append(event.payload)
            arrived.set()

    transport = Transport(settings, client_id=f"{PROBE}-{_token()}", sink=sink, name="probe")
    transport.subscribe(topic, 1)
    transport.start(5.0)
    try:
        arrived.wait(timeout)
    finally:
        transport.stop()
    return got[0] if got else None


# --- the attacker --------------------------------------------------------------------


class Attacker(Recorder):
    """A hostile MQTT client: listens to all it may, forges, decrypts what it can.

    ``keys`` is the X25519 key it hands out as a service's key; ``identity`` the
    Ed25519 key it signs forgeries with. Every publication is kept (`published`), so a
    witness can tell which ones the broker delivered (`reached`). `act_as_service`
    makes it decrypt any input sealed for ``keys`` (kept in `decrypted`) and answer it
    with `falsify` on the right reply topic (counted in `forged_answers`).
    """

    def __init__(self, settings: BrokerSettings, client_id: str = ATTACKER) -> None:
        super().__init__(settings, client_id, filters=("#",))
        self.client_id = client_id
        self.keys = KeyPair()
        self.identity = SigningKey.generate()
        self.decrypted: list[Payload] = []
        self.forged_answers = 0
        self._published: list[tuple[str, bytes, float]] = []
        self._canaries: set[bytes] = set()
        self._serving = False

    # -- publishing

    def publish(self, topic: str, payload: bytes, *, retain: bool = False, qos: int = 1) -> None:
        with self._lock:
            self._published.append((topic, payload, time.time()))
        self.transport.publish(topic, payload, qos=qos, retain=retain)

    def publish_and_wait(self, topic: str, payload: bytes, *, retain: bool = False) -> None:
        """Publish at QoS 1 and wait for the broker's acknowledgement."""
        with self._lock:
            self._published.append((topic, payload, time.time()))
        self.transport.publish_and_wait(topic, payload, qos=1, retain=retain)

    @property
    def published(self) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(t, p) for t, p, _ in self._published]

    def fence(self, witness: Recorder, timeout: float = 5.0) -> None:
        """Publish on the attacker's own topic (allowed by every ACL) and wait until the
        witness has it: MQTT keeps one client's messages in order, so every forgery
        published before has had its turn at the broker by then."""
        own = f"ldm/p/{self.client_id}/up/session"
        payload = SessionRequest(c=_token(), service="fence", t=time.time()).model_dump_json()
        raw = payload.encode()
        with self._lock:
            self._canaries.add(raw)
        self.transport.publish(own, raw, qos=1)
        assert wait_for(lambda: witness.saw(own, raw), timeout), "the witness saw no fence"

    def reached(self, witness: Recorder) -> list[tuple[str, bytes]]:
        """The attacker's publications (other than fences) that the witness received
        after they were published (a replayed message counts only if it arrived again)."""
        with self._lock:
            forged = [(t, p, s) for t, p, s in self._published if p not in self._canaries]
        return [(t, p) for t, p, sent in forged if witness.saw(t, p, since=sent)]

    def heard_topics(self) -> set[str]:
        """Every topic the broker delivered to the attacker."""
        return {m.topic for m in self.messages()}

    # -- what it learns

    def ask_for_list(self) -> None:
        """Ask the core for the service list on its own topics, as a participant does
        (where the ACL lets it read no other, that is how the list comes)."""
        asked = ServicesRequest(t=time.time()).model_dump_json().encode()
        self.transport.publish(f"ldm/p/{self.client_id}/up/services", asked, qos=1)

    def genuine_list_payloads(self) -> list[bytes]:
        """Every non-empty service list it received that it did not forge, in order
        (on ``ldm/services`` or its own list topic)."""
        mine = {p for t, p in self.published if t == "ldm/services"}
        return [
            m.payload
            for m in self.messages()
            if m.topic in ("ldm/services", f"ldm/p/{self.client_id}/down/services")
            and m.payload
            and m.payload not in mine
        ]

    def genuine_lists(self) -> list[ServiceList]:
        """Every decodable service list it received (not its own forgeries)."""
        out = []
        for payload in self.genuine_list_payloads():
            with contextlib.suppress(ValueError):
                out.append(ServiceList.model_validate_json(payload))
        return out

    def real(self, service: str) -> ServiceDescription:
        """The latest description of ``service`` it read in a genuine service list."""
        for listing in reversed(self.genuine_lists()):
            for desc in listing.services:
                if desc.name == service:
                    return desc
        raise LookupError(f"the attacker never saw {service!r} listed")

    # -- acting as the service

    def act_as_service(self) -> None:
        """Decrypt every input sealed for ``keys`` and answer it with a forged reply:
        participant input (``ldm/p/+/up/data/+``) on the participant's reply topic,
        routed input (``ldm/svc/+/in/+``) as a provider would."""
        if self._serving:
            return
        self._serving = True
        self.on("ldm/p/+/up/data/+", self._serve)
        self.on("ldm/svc/+/in/+", self._serve)

    def open_input(self, payload: bytes) -> tuple[Envelope, SessionCipher, Payload] | None:
        """Decrypt an input envelope sealed for the attacker's key; None if it cannot."""
        try:
            env = Envelope.model_validate_json(payload)
            if env.k is None:
                return None
            cipher = self.keys.cipher(env.k, initiator=False)
            plain = json.loads(cipher.open(env.d, aad(env.c, env.t)))
        except (ValueError, CryptoError):
            return None
        return (env, cipher, plain) if isinstance(plain, dict) else None

    def could_decrypt(self, witness: Recorder) -> list[Payload]:
        """Every input the witness saw (participant input and routed input) that the
        attacker's key opens: what it would have read had the broker shown it all."""
        inputs = witness.messages("ldm/p/+/up/data/+") + witness.messages("ldm/svc/+/in/+")
        return [opened[2] for m in inputs if (opened := self.open_input(m.payload)) is not None]

    def _serve(self, msg: Message) -> None:
        opened = self.open_input(msg.payload)
        if opened is None:
            return
        env, cipher, plain = opened
        with self._lock:
            self.decrypted.append(plain)
        levels = msg.topic.split("/")
        if levels[1] == "p":  # ldm/p/{client}/up/data/{service}
            topic = f"ldm/p/{levels[2]}/down/data/{levels[5]}"
        else:  # ldm/svc/{service}/in/{pseudonym}
            topic = f"ldm/svc/{levels[2]}/out/{levels[4]}"
        t = time.time()
        answer = json.dumps(falsify(plain)).encode()
        reply = Envelope(c=env.c, t=t, d=cipher.seal(answer, aad(env.c, t)))
        self.publish(topic, reply.encode(), qos=0)
        self.forged_answers += 1


# --- forgeries -----------------------------------------------------------------------


def forged_description(
    real: ServiceDescription, attacker: Attacker, *, keep_identity: bool = False
) -> ServiceDescription:
    """``real`` with the attacker's X25519 key and a fresh ``issued``.

    By default it is re-signed by the attacker's own identity (a consistent, validly
    signed description of an identity nobody pinned). With ``keep_identity`` it keeps
    the real identity and signature, which then no longer match the contents.
    """
    desc = real.model_copy(update={"public_key": attacker.keys.public, "issued": time.time()})
    if keep_identity:
        return desc
    desc = desc.model_copy(
        update={"identity": attacker.identity.public, "signature": None, "endorsement": None}
    )
    return desc.model_copy(update={"signature": attacker.identity.sign(desc.signed_text())})


def forged_notice(
    attacker: Attacker,
    kind: Literal["grant", "refused", "rotate", "nosession", "rejected"],
    service: str,
    to: str,
    *,
    c: str | None = None,
    grant: SessionGrant | None = None,
) -> bytes:
    """A session notice addressed to ``to`` and signed by the attacker's identity."""
    notice = SessionNotice(kind=kind, service=service, c=c, grant=grant, to=to, t=time.time())
    notice = notice.model_copy(update={"sig": attacker.identity.sign(notice.signed_text())})
    return notice.model_dump_json(exclude_none=True).encode()


def forged_grant(attacker: Attacker, client: str, desc: ServiceDescription, c: str | None) -> bytes:
    """A grant for ``client`` whose service description is ``desc`` (the attacker's key)."""
    grant = SessionGrant(
        service=desc,
        session=_token(),
        input_topic=f"ldm/p/{client}/up/data/{desc.name}",
        reply_topic=f"ldm/p/{client}/down/data/{desc.name}",
        rotation_period=600.0,
        grace=5.0,
        idle_timeout=600.0,
        max_age=FAST["max_age"],
        data_qos=0,
    )
    return forged_notice(attacker, "grant", desc.name, client, c=c, grant=grant)


def forged_list(attacker: Attacker, services: Sequence[ServiceDescription]) -> bytes:
    """A service list that names the attacker as its core and is signed by it."""
    listing = ServiceList(t=time.time(), services=list(services), core=attacker.identity.public)
    listing = listing.model_copy(update={"sig": attacker.identity.sign(listing.signed_text())})
    return listing.model_dump_json().encode()


def future_announcement(
    identity: SigningKey, real: ServiceDescription, key: str, ahead: float
) -> bytes:
    """An announcement validly signed by the service's *own* identity, with the session key
    ``key`` and a time ``ahead`` seconds in the future.

    Only the time is wrong, so a core that takes it checks signatures but not clocks:
    what a provider with a broken clock, or a thief of its identity key who wants an
    announcement that never expires, would send.
    """
    desc = real.model_copy(update={"public_key": key, "issued": time.time(), "signature": None})
    desc = desc.model_copy(update={"signature": identity.sign(desc.signed_text())})
    ann = Announcement(service=desc, t=time.time() + ahead)
    ann = ann.model_copy(update={"sig": identity.sign(ann.signed_text())})
    return ann.model_dump_json().encode()


# --- attacks -------------------------------------------------------------------------


class Repeater:
    """Calls ``action()`` every ``interval`` seconds on its own thread until `stop`."""

    def __init__(self, interval: float, action: Callable[[], None]) -> None:
        self._interval = interval
        self._action = action
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hostile-repeater", daemon=True)
        self.runs = 0

    def start(self) -> Self:
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            self._action()
            self.runs += 1
            self._stop.wait(self._interval)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)


class GrantRace:
    """Forged ``nosession`` notices plus raced forged grants (the issue's third row).

    Every ``interval`` it tells each victim its session is gone (a ``nosession`` signed
    by the attacker), so the victim asks for its session again. Every session request it
    can read (only on an open broker) it answers at once, from paho's thread, ahead of
    the core, with two forged grants carrying the attacker's X25519 key: one signed by
    the attacker as the service's identity, one keeping the real identity and signature.
    It also acts as the service (`Attacker.act_as_service`): whatever a victim then
    seals for the attacker's key is decrypted and answered with a false position.
    """

    def __init__(
        self,
        attacker: Attacker,
        real: ServiceDescription,
        victims: Sequence[str],
        interval: float = 0.1,
    ) -> None:
        self.attacker = attacker
        self.real = real
        self.victims = list(victims)
        self.raced = 0
        """Session requests answered with forged grants."""
        self._repeater = Repeater(interval, self._nosession)

    def start(self) -> Self:
        self.attacker.act_as_service()
        self.attacker.on("ldm/p/+/up/session", self._race)
        self._repeater.start()
        return self

    def stop(self) -> None:
        self._repeater.stop()

    def _nosession(self) -> None:
        for victim in self.victims:
            payload = forged_notice(self.attacker, "nosession", self.real.name, victim)
            self.attacker.publish(f"ldm/p/{victim}/down/session", payload, qos=0)

    def _race(self, msg: Message) -> None:
        client = msg.topic.split("/")[2]
        if client not in self.victims:
            return
        try:
            req = SessionRequest.model_validate_json(msg.payload)
        except ValueError:
            return
        if req.service != self.real.name:
            return
        for keep in (False, True):
            desc = forged_description(self.real, self.attacker, keep_identity=keep)
            grant = forged_grant(self.attacker, client, desc, req.c)
            self.attacker.publish(f"ldm/p/{client}/down/session", grant, qos=0)
        self.raced += 1


class FakeProvider:
    """A retained forged announcement of a service on the user broker (fourth row).

    The announcement carries the attacker's X25519 key in a description signed by the
    attacker's identity, and a time ``ahead`` seconds in the future so that it would
    never expire. The attacker acts as the service behind it (`Attacker.act_as_service`).
    `withdraw` clears it, as the issue's attacker did (the core then cleared the real
    service's backbone announcement too).
    """

    def __init__(self, attacker: Attacker, real: ServiceDescription, ahead: float = 1e6) -> None:
        self.attacker = attacker
        self.real = real
        self.ahead = ahead
        self.topic = f"ldm/svc/{real.name}/announce"

    def announce(self, *, keep_identity: bool = False, ahead: float | None = None) -> None:
        """Publish (retained) and wait for the broker; ``ahead`` overrides the time offset."""
        desc = forged_description(self.real, self.attacker, keep_identity=keep_identity)
        ann = Announcement(service=desc, t=time.time() + (self.ahead if ahead is None else ahead))
        ann = ann.model_copy(update={"sig": self.attacker.identity.sign(ann.signed_text())})
        self.attacker.act_as_service()
        self.attacker.publish_and_wait(self.topic, ann.model_dump_json().encode(), retain=True)

    def withdraw(self) -> None:
        self.attacker.publish_and_wait(self.topic, b"", retain=True)


class NoticeStorm:
    """Forged ``rotate`` notices and forged service lists with another key (sixth row).

    Every ``interval``: a ``rotate`` to each victim, signed by the attacker; a replay of
    every genuine (core-signed) notice the attacker overheard on a victim's session
    topic (only on an open broker; they carry a valid signature and the right ``to``);
    and a retained service list that gives ``real`` the attacker's key and is signed by
    the attacker as the core, which reaches every participant of the cluster.
    """

    def __init__(
        self,
        attacker: Attacker,
        real: ServiceDescription,
        victims: Sequence[str],
        interval: float = 0.05,
        *,
        lists: bool = True,
        replay: bool = True,
    ) -> None:
        self.attacker = attacker
        self.real = real
        self.victims = list(victims)
        self.lists = lists
        self.replay = replay
        self._repeater = Repeater(interval, self._storm)
        self._forged: set[bytes] = set()
        self.replayed = 0
        """Genuine notices sent again (each one every ``interval``)."""

    def start(self) -> Self:
        self._repeater.start()
        return self

    def stop(self) -> None:
        self._repeater.stop()

    def _storm(self) -> None:
        a = self.attacker
        for victim in self.victims:
            topic = f"ldm/p/{victim}/down/session"
            forged = forged_notice(a, "rotate", self.real.name, victim)
            self._forged.add(forged)
            a.publish(topic, forged, qos=0)
            if self.replay:
                heard = {m.payload for m in a.messages(topic)}
                for payload in heard - self._forged:
                    if b'"rotate"' in payload:
                        a.publish(topic, payload, qos=0)
                        self.replayed += 1
        if self.lists:
            desc = forged_description(self.real, a)
            a.publish("ldm/services", forged_list(a, [desc]), retain=True, qos=0)


class ReplyForger:
    """One forged reply per request (seventh row).

    Reads each input's correlation id on ``ldm/p/+/up/data/+`` (only on an open broker)
    and answers it at once, ahead of the real reply, on the victim's reply topic: a
    fresh envelope whose ciphertext is sealed with the attacker's key for the victim's
    ephemeral key, so it cannot authenticate. Blind forgeries with random ids are sent
    to ``victims`` too (`blind`), for the broker that hides the ids.
    """

    def __init__(self, attacker: Attacker, victims: Sequence[str] = ()) -> None:
        self.attacker = attacker
        self.victims = list(victims)
        self.forged = 0

    def start(self) -> Self:
        self.attacker.on("ldm/p/+/up/data/+", self._reply)
        return self

    def _reply(self, msg: Message) -> None:
        levels = msg.topic.split("/")
        if levels[2] == self.attacker.client_id:
            return
        try:
            env = Envelope.model_validate_json(msg.payload)
        except ValueError:
            return
        if env.k is None:
            return
        t = time.time()
        cipher = self.attacker.keys.cipher(env.k, initiator=False)
        sealed = cipher.seal(json.dumps({"echo": {"forged": True}}).encode(), aad(env.c, t))
        forged = Envelope(c=env.c, t=t, d=sealed).encode()
        self.attacker.publish(f"ldm/p/{levels[2]}/down/data/{levels[5]}", forged, qos=0)
        self.forged += 1

    def blind(self, service: str, count: int = 10) -> None:
        """Forged replies with guessed correlation ids to each victim."""
        for victim in self.victims:
            for _ in range(count):
                t = time.time()
                d = base64.b64encode(os.urandom(48)).decode()
                env = Envelope(c=_token(), t=t, d=d).encode()
                self.attacker.publish(f"ldm/p/{victim}/down/data/{service}", env, qos=0)


class InputFlood:
    """Forged input on a victim's own topics (eighth row).

    Publishes, at about ``rate`` messages per second, a mix of what an attacker can
    forge without the victim's keys: input envelopes under keys of its own (the core
    sees a new ephemeral key too soon, or a session it does not hold), undecodable
    JSON on the data topic and malformed session requests. ``keys=False`` leaves out
    the envelopes (garbage only). With ``mimic``, it also repeats the victim's latest
    real envelope it overheard (same ``k``, ``c``, ``d``): a core that cannot decrypt
    cannot tell those from the victim's own.
    """

    def __init__(
        self,
        attacker: Attacker,
        victim: str,
        service: str,
        real_key: str,
        rate: float = 2000.0,
        *,
        keys: bool = True,
        mimic: bool = False,
    ) -> None:
        self.attacker = attacker
        self.victim = victim
        self.service = service
        self.rate = rate
        self.mimic = mimic
        self.sent = 0
        self._data = f"ldm/p/{victim}/up/data/{service}"
        session = f"ldm/p/{victim}/up/session"
        self._envelopes: list[Envelope] = []
        for _ in range(16 if keys else 0):
            k = KeyPair()
            c, t = _token(), time.time()
            sealed = k.cipher(real_key, initiator=True).seal(b"{}", aad(c, t))
            self._envelopes.append(Envelope(c=c, t=t, k=k.public, d=sealed))
        self._garbage = [
            (self._data, b"{"),
            (self._data, b'{"c":"x"}'),
            (session, b"[]"),
            (session, b'{"c":1}'),
        ]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hostile-flood", daemon=True)

    def start(self) -> Self:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def batch(self) -> list[tuple[str, bytes]]:
        """One round of forgeries: every envelope stamped now (never stale), the garbage,
        and with ``mimic`` the victim's latest real envelope."""
        now = time.time()
        out = [(self._data, e.model_copy(update={"t": now}).encode()) for e in self._envelopes]
        out += self._garbage
        if self.mimic:
            mine = {p for t, p in self.attacker.published if t == self._data}
            real = [m for m in self.attacker.messages(self._data) if m.payload not in mine]
            if real:
                out.append((self._data, real[-1].payload))
        return out

    def _run(self) -> None:
        started = time.monotonic()
        while not self._stop.is_set():
            for topic, payload in self.batch():
                self.attacker.publish(topic, payload, qos=0)
                self.sent += 1
            ahead = self.sent / self.rate - (time.monotonic() - started)
            if ahead > 0:
                self._stop.wait(ahead)


# --- measuring the victims -----------------------------------------------------------


@dataclass
class Shot:
    """One request: when it was sent, what, its future, and when that completed."""

    sent: float
    payload: Payload
    future: Future[Payload]
    done: float | None = None

    def result(self) -> Payload | BaseException | None:
        """The reply, the error, or None while it is pending."""
        if not self.future.done():
            return None
        error = self.future.exception()
        return error if error is not None else self.future.result()

    def genuine(self, deadline: float = float("inf")) -> bool:
        """Answered with the true echo, within ``deadline`` seconds of sending."""
        answer = self.result()
        return (
            answer == {"echo": self.payload}
            and self.done is not None
            and self.done - self.sent <= deadline
        )

    def forged(self) -> bool:
        """Answered, but not with the true echo: a forged answer was accepted."""
        answer = self.result()
        return isinstance(answer, dict) and answer != {"echo": self.payload}


@dataclass(frozen=True)
class Window:
    """A span of wall-clock time (``time.time()``)."""

    start: float
    end: float


@dataclass
class Load:
    """A participant session's requests at a steady pace, and what became of each."""

    session: Session
    who: str
    shots: list[Shot] = field(default_factory=list)

    def fire(self) -> Shot:
        payload = fix(self.who, len(self.shots))
        sent = time.time()
        shot = Shot(sent, payload, self.session.submit(payload))

        def finished(_f: Future[Payload]) -> None:
            shot.done = time.time()

        shot.future.add_done_callback(finished)
        self.shots.append(shot)
        return shot

    def settle(self, timeout: float = 15.0) -> None:
        """Wait until every request is answered or failed, at most ``timeout`` seconds
        (longer than a request's own timeout under FAST, 2 x max_age + 1 s)."""
        wait_futures([s.future for s in self.shots], timeout)

    def within(self, window: Window | None = None) -> list[Shot]:
        if window is None:
            return list(self.shots)
        return [s for s in self.shots if window.start <= s.sent < window.end]

    def answered_fraction(self, window: Window | None = None, deadline: float = 1.0) -> float:
        shots = self.within(window)
        return sum(s.genuine(deadline) for s in shots) / len(shots) if shots else 1.0

    def forged(self) -> list[Shot]:
        return [s for s in self.shots if s.forged()]

    def failures(self) -> list[BaseException]:
        return [r for s in self.shots if isinstance(r := s.result(), BaseException)]

    def missing(self, deadline: float = float("inf")) -> list[Shot]:
        """Requests not answered genuinely (within ``deadline``): failed, forged, pending."""
        return [s for s in self.shots if not s.genuine(deadline)]

    def longest_outage(self, window: Window, deadline: float = 1.0) -> float:
        """The longest stretch in ``window`` during which no request was answered in time:
        from the first unanswered request of a run to the next request that was answered
        (or the window's end)."""
        longest, run = 0.0, None
        for shot in self.within(window):
            if shot.genuine(deadline):
                if run is not None:
                    longest = max(longest, shot.sent - run)
                run = None
            elif run is None:
                run = shot.sent
        if run is not None:
            longest = max(longest, window.end - run)
        return longest

    def summary(self, window: Window | None = None, deadline: float = 1.0) -> str:
        shots = self.within(window)
        kinds: dict[str, int] = {}
        for s in shots:
            r = s.result()
            kind = (
                "answered"
                if s.genuine(deadline)
                else "late"
                if s.genuine()
                else "forged"
                if s.forged()
                else type(r).__name__
                if isinstance(r, BaseException)
                else "pending"
            )
            kinds[kind] = kinds.get(kind, 0) + 1
        return f"{self.who}: {len(shots)} requests {kinds}"


def drive(loads: Sequence[Load], seconds: float, interval: float = 0.05) -> Window:
    """Fire each load every ``interval`` seconds for ``seconds``; the window it took."""
    start = time.time()
    next_at = time.monotonic()
    end_at = next_at + seconds
    while time.monotonic() < end_at:
        for load in loads:
            load.fire()
        next_at += interval
        time.sleep(max(0.0, next_at - time.monotonic()))
    return Window(start, time.time())


# --- the deployment ------------------------------------------------------------------


class HostileDeployment:
    """Three Mosquitto brokers, both cores, the echo provider, a witness and an attacker.

    ``trust`` (default): the cores pin the echo service's identity (``service_keys``)
    and participants pin it and the user core's key (``core_key``). The attacker and
    the witnesses start before the cores, so they hear everything they are allowed to,
    from the first retained list on. ``core`` overrides the cores' FAST timings.
    """

    def __init__(
        self, mode: Mode, *, trust: bool = True, core: Mapping[str, float] | None = None
    ) -> None:
        self.mode = mode
        self.trust = trust
        self.timing: dict[str, float] = {**FAST, **(core or {})}
        self.identity = SigningKey.generate()
        """The echo service's identity (what participants and cores pin)."""
        users = (CORE_USER, CORE_SERVICE, PROVIDER_USER, WITNESS, PROBE, ATTACKER, *PARTICIPANTS)
        self.passwords = {u: random_password() for u in users}
        self._stack = contextlib.ExitStack()
        self.participants: list[Participant] = []
        try:
            self._start()
        except BaseException:
            self._stack.close()
            raise

    def _broker(self, acl_file: str, extra_acl: str, *, user_cluster: bool) -> MosquittoBroker:
        if self.mode == "open":
            broker = MosquittoBroker()
        else:
            acl = (SECURITY / acl_file).read_text() + "\n" + extra_acl
            broker = MosquittoBroker(allow_anonymous=False, acl=acl)
            passwd = broker.directory / "passwd"
            set_passwords(passwd, self.passwords, mode=0o644)
            config = broker.config_file.read_text() + f"password_file {passwd}\n"
            if user_cluster:
                config += "use_username_as_clientid true\n"
            broker.config_file.write_text(config)
        self._stack.enter_context(broker)
        return broker

    def account(self, broker: MosquittoBroker, user: str) -> BrokerSettings:
        """How ``user`` connects to ``broker`` (anonymous on an open broker)."""
        if self.mode == "open":
            return BrokerSettings(url=broker.url)
        return build(BrokerSettings, url=broker.url, username=user, password=self.passwords[user])

    def _start(self) -> None:
        self.user = self._broker("acl-user-cluster", _OBSERVERS, user_cluster=True)
        self.backbone = self._broker("acl-backbone", _OBSERVERS, user_cluster=False)
        self.service = self._broker(
            "acl-service-cluster", _ECHO_ACCOUNT + "\n" + _OBSERVERS, user_cluster=False
        )
        self.witness = self._recorder(Recorder(self.account(self.user, WITNESS), WITNESS))
        self.backbone_witness = self._recorder(
            Recorder(self.account(self.backbone, WITNESS), f"{WITNESS}-bb")
        )
        self.attacker: Attacker = self._recorder(Attacker(self.account(self.user, ATTACKER)))
        pins = {ECHO.name: self.identity.public} if self.trust else {}
        self.user_core = self._core("user-edge", self.user, CORE_USER, pins)
        self.attacker.ask_for_list()  # once the core listens, as a participant does
        self.service_core = self._core("svc-cluster", self.service, CORE_SERVICE, pins)
        self.echo = EchoService()
        config = build(
            ProviderConfig,
            broker=self.account(self.service, PROVIDER_USER),
            announce_interval=0.3,
            max_age=self.timing["max_age"],
        )
        self._provider_config = config
        self.provider = Provider(config, ECHO, self.echo, identity=self.identity).start(timeout=5)
        self._stack.callback(lambda: self.provider.stop())
        assert wait_for(lambda: self._listed(self.witness), 5), "echo never listed"
        assert wait_for(lambda: self._listed(self.attacker), 5), "the attacker saw no list"

    def restart_provider(self) -> Provider:
        """A new echo provider, same identity, new session key (after a kill or stop)."""
        self.provider = Provider(self._provider_config, ECHO, self.echo, identity=self.identity)
        return self.provider.start(timeout=5)

    def _recorder(self, recorder: _R) -> _R:
        recorder.start()
        self._stack.callback(recorder.stop)
        return recorder

    def _core(self, name: str, cluster: MosquittoBroker, user: str, pins: dict[str, str]) -> Core:
        config = build(
            CoreConfig,
            name=name,
            cluster=self.account(cluster, user),
            backbone=self.account(self.backbone, user),
            service_keys=pins,
            **self.timing,
        )
        core = Core(config).start(timeout=5)
        self._stack.callback(core.stop)
        return core

    def _listed(self, recorder: Recorder) -> bool:
        lists = recorder.messages("ldm/services") + recorder.messages("ldm/p/+/down/services")
        for m in lists:
            with contextlib.suppress(ValueError):
                if any(
                    s.name == ECHO.name for s in ServiceList.model_validate_json(m.payload).services
                ):
                    return True
        return False

    def real(self, service: str = ECHO.name) -> ServiceDescription:
        """The genuine description of the service, as the provider announces it."""
        assert service == ECHO.name
        return self.provider.description

    def participant(self, name: str, *, trusted: bool | None = None) -> Participant:
        """A started participant with its own account (``name`` in PARTICIPANTS).

        ``trusted`` (default: the deployment's ``trust``) pins the echo identity and
        the user core's key.
        """
        trusted = self.trust if trusted is None else trusted
        pins: dict[str, Any] = (
            {
                "service_keys": {ECHO.name: self.identity.public},
                "core_key": self.user_core.public_key,
            }
            if trusted
            else {}
        )
        config = build(
            ParticipantConfig,
            broker=self.account(self.user, name),
            client_id=name,
            max_age=self.timing["max_age"],
            **pins,
        )
        p = Participant(config).start(timeout=5)
        self.participants.append(p)
        self._stack.callback(p.stop)
        return p

    def listed(self, participant: Participant) -> bool:
        """The participant lists echo with its genuine key."""
        key = self.provider.description.public_key
        return any(
            s.name == ECHO.name and s.public_key == key for s in participant.services(timeout=0.05)
        )

    def wait_listed(self, participant: Participant, timeout: float = 5.0) -> None:
        assert wait_for(lambda: self.listed(participant), timeout), "echo never listed"

    def retained_list(self) -> ServiceList | None:
        """The service list a brand-new subscriber of the user broker gets."""
        payload = read_retained(self.account(self.user, PROBE), "ldm/services", 0.5)
        if not payload:
            return None
        try:
            return ServiceList.model_validate_json(payload)
        except ValueError:
            return None

    def list_is_genuine(self) -> bool:
        """A fresh subscriber gets the user core's own list, with echo's genuine key."""
        listing = self.retained_list()
        return (
            listing is not None
            and listing.core == self.user_core.public_key
            and any(
                s.name == ECHO.name and s.public_key == self.provider.description.public_key
                for s in listing.services
            )
        )

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
