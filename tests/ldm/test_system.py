"""The whole LDM over real brokers: discovery, sessions, encryption, rotation, privacy.

Every test runs on the embedded amqtt broker and on Mosquitto (``broker_kind``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from concurrent.futures import Future
from typing import Any

import pytest

from ldm import Core, Participant, Provider, Request, ServiceNotFound
from ldm.config import BrokerSettings
from ldm.local.brokers import wait_for
from ldm.transport.mqtt import Connected, Message, Transport
from ldm.wire import batch, topics
from ldm.wire.messages import Envelope, ServiceList

from .deployment import (
    ECHO,
    FAST,
    Deployment,
    EchoService,
    Sniffer,
    deploy,
    echo_provider,
    has_service,
    lacks_service,
)

PLAINTEXT = "PLAINTEXT-MARKER-4711"
CLIENTS = [("alice-car-7Q", "alice-user"), ("bob-truck-3Z", "bob-user"), ("carol-bike-9K", None)]


@pytest.fixture
def deployment(broker_factory):
    d = deploy(broker_factory)
    yield d
    d.close()


def stream(
    session, tag: str, count: int, interval: float
) -> list[tuple[dict[str, Any], Future[dict[str, Any]]]]:
    """Pipeline ``count`` requests, one every ``interval`` s, without waiting for replies."""
    sent = []
    for i in range(count):
        payload = {"secret": PLAINTEXT, "who": tag, "i": i}
        sent.append((payload, session.submit(payload)))
        time.sleep(interval)
    return sent


def test_full_exchange_across_three_brokers(deployment: Deployment) -> None:
    d = deployment
    participants = [d.participant(cid, user) for cid, user in CLIENTS]

    # Discovery: the retained list reaches each participant at once, with the schemas.
    for p in participants:
        d.wait_listed(p)
    echo = next(s for s in participants[0].services() if s.name == "echo")
    assert echo.version == "1.0" and echo.output_schema["type"] == "object"
    assert len(echo.public_key) == 44

    # Sessions, then encrypted request-response while pseudonyms rotate (period 0.5 s).
    sessions = [p.open("echo") for p in participants]
    assert sessions[0].grant.rotation_period == FAST["rotation_period"]
    assert sessions[0].grant.input_topic.startswith(f"ldm/p/{CLIENTS[0][0]}/")
    streams = [stream(s, cid, 12, 0.0) for s, (cid, _) in zip(sessions, CLIENTS, strict=True)]
    for sent in streams:
        for payload, future in sent:
            assert future.result(5) == {"echo": payload}
    # 3 participants, a request each every 20 ms, until the service has seen every one
    # of them under three pseudonyms (two rotations); the deadline only bounds a wait
    # for a rotation that never comes.
    sent_all: list[tuple[dict[str, Any], Future[dict[str, Any]]]] = []
    deadline = time.monotonic() + 30.0
    while min(len(d.echo.pseudonyms_of(cid)) for cid, _ in CLIENTS) < 3:
        assert time.monotonic() < deadline, "pseudonyms should rotate every 0.5 s"
        for s, (cid, _) in zip(sessions, CLIENTS, strict=True):
            sent_all.extend(stream(s, cid, 1, 0.0))
        time.sleep(0.02)
    assert d.user_core.session_count == 3
    for payload, future in sent_all:
        assert future.result(5) == {"echo": payload}, "a reply was lost or altered"
    for s in sessions:
        assert s.rotations >= 2, "pseudonyms should rotate every 0.5 s"
    assert d.user_core.stats.rotations >= 6
    # Each rotation shows up at the service as a brand-new pseudonym, never a client id.
    seen = d.echo.pseudonyms()
    assert len(seen) >= 3 * 3
    assert not seen & {cid for cid, _ in CLIENTS}

    # Idle participants are dropped by the core, with no log-off message.
    assert wait_for(lambda: d.user_core.session_count == 0, FAST["idle_timeout"] + 3)
    assert d.user_core.stats.sessions_expired >= 3
    # ... and a participant that comes back gets its session again transparently.
    assert sessions[0].request({"back": True}, timeout=5) == {"echo": {"back": True}}

    # A provider that leaves disappears from every list.
    d.provider.stop()
    assert wait_for(lambda: not d.user_core.services and not d.service_core.services, 5)
    for p in participants:
        assert wait_for(lacks_service(p, "echo"), 5)
    with pytest.raises(ServiceNotFound):
        participants[0].open("echo", timeout=3)

    check_privacy(d, participants)


def envelopes(messages: Sequence[Message]) -> list[tuple[str, str, bytes]]:
    """Every envelope between cores and providers in `messages`, single or in a batch:
    (kind of its single topic, pseudonym, envelope)."""
    found: list[tuple[str, str, bytes]] = []
    for m in messages:
        topic = topics.parse(m.topic)
        if topic.pseudonym:
            found.append((topic.kind, topic.pseudonym, m.payload))
        elif topic.kind.endswith("_batch"):
            entries, bad = batch.decode(m.payload)
            assert bad == 0, f"a malformed batch on {m.topic}"
            found += [(topic.kind.removesuffix("_batch"), p, e) for p, e in entries]
    return found


def check_privacy(d: Deployment, participants: list[Participant]) -> None:
    """Nothing on the backbone or service-cluster broker names or reveals a participant."""
    forbidden = [cid for cid, _ in CLIENTS] + [u for _, u in CLIENTS if u] + [PLAINTEXT]
    for sniffer in d.sniffers:
        messages = sniffer.snapshot()
        data = envelopes(messages)
        assert len(data) > 50, f"{sniffer.transport.name}: sniffer saw too little to judge"
        for m in messages:
            blob = m.topic.encode() + b" " + m.payload
            for word in forbidden:
                assert word.encode() not in blob, f"{word!r} leaked on {m.topic}"
        # Unlinkable rotation: one key per pseudonym and one pseudonym per key.
        inputs = [(kind, p, e) for kind, p, e in data if kind == "provider_input"]
        pairs = {(p, Envelope.model_validate_json(e).k) for _, p, e in inputs}
        if inputs:
            assert len({p for p, _ in pairs}) == len(pairs) == len({k for _, k in pairs})
    assert {p.client_id for p in participants} == {cid for cid, _ in CLIENTS}


def test_service_list_is_retained_qos1(deployment: Deployment, broker_kind) -> None:
    got: list[Message | Connected] = []
    p = deployment.participant("late-joiner")
    deployment.wait_listed(p)
    watcher = Transport(
        BrokerSettings(url=deployment.user.url), client_id="watcher", sink=got.append
    )
    watcher.subscribe("ldm/services", 1)
    watcher.start(timeout=5)
    try:
        assert wait_for(lambda: any(isinstance(m, Message) for m in got), 5)
        msg = next(m for m in got if isinstance(m, Message))
        assert msg.retain
        # amqtt 0.12 re-delivers retained messages at QoS 0 whatever they were sent with.
        assert msg.qos == (1 if broker_kind == "mosquitto" else 0)
        assert [s.name for s in ServiceList.model_validate_json(msg.payload).services] == ["echo"]
    finally:
        watcher.stop()


def test_provider_that_vanishes_is_dropped_by_will_and_by_ttl(deployment: Deployment) -> None:
    d = deployment
    p = d.participant("dana-car-1")
    d.wait_listed(p)
    d.provider.kill()  # no goodbye: the broker publishes the provider's last will
    assert wait_for(lacks_service(p, "echo"), 5)

    # A provider that stays connected but stops re-announcing expires after the TTL.
    silent = echo_provider(d.service.url, EchoService())
    assert wait_for(has_service(p, "echo"), 5)
    silent.stop_dispatch()  # no more announcements, connection kept
    start = time.monotonic()
    assert wait_for(lacks_service(p, "echo"), FAST["service_ttl"] + 3)
    assert time.monotonic() - start >= FAST["service_ttl"] - 0.6
    silent.transport.stop()


def test_stale_input_is_dropped_not_delivered(deployment: Deployment) -> None:
    d = deployment
    p = d.participant("eve-car-2")
    d.wait_listed(p)
    session = p.open("echo")
    assert session.request({"fresh": 1}) == {"echo": {"fresh": 1}}
    # Forge an envelope that is older than max_age: the user core must drop it.
    keys = session._keys
    old = time.time() - FAST["max_age"] - 1
    env = Envelope(c="stale1", t=old, k=keys.pair.public, d=keys.cipher.seal(b"{}", "stale1"))
    before = d.user_core.stats.dropped_stale
    p.transport.publish(session.grant.input_topic, env.encode(), qos=1)
    assert wait_for(lambda: d.user_core.stats.dropped_stale == before + 1, 3)
    assert d.echo.requests[-1].payload == {"fresh": 1}


def test_unknown_service_and_timeout_errors(deployment: Deployment) -> None:
    p = deployment.participant("frank-car-3")
    deployment.wait_listed(p)
    with pytest.raises(ServiceNotFound, match="no service 'nope'"):
        p.open("nope", timeout=3)
    session = p.open("echo")
    deployment.provider.kill()
    assert wait_for(lacks_service(p, "echo"), 5)
    with pytest.raises(ServiceNotFound, match=r"'echo' is gone|no service 'echo'"):
        session.request({"x": 1}, timeout=3)
    # Once the core has forgotten the idle session, re-opening it is refused as well.
    assert wait_for(lambda: deployment.user_core.session_count == 0, 5)
    with pytest.raises(ServiceNotFound, match="no service 'echo'"):
        session.request({"x": 1}, timeout=3)


def test_edge_deployment_two_brokers(broker_factory) -> None:
    """A user-cluster broker bridged straight to the service-cluster broker (no third one)."""
    d = deploy(broker_factory, backbone_is_service_broker=True)
    try:
        p = d.participant("gina-car-4", "gina-user")
        d.wait_listed(p)
        session = p.open("echo")
        sent = stream(session, "gina", 60, 0.01)
        for payload, future in sent:
            assert future.result(5) == {"echo": payload}
        assert session.rotations >= 1
        blob = b"".join(m.topic.encode() + m.payload for m in d.sniffers[0].snapshot())
        assert b"ldm/svc/echo/in" in blob  # the service's input, batched
        for word in ("gina-car-4", "gina-user", PLAINTEXT):
            assert word.encode() not in blob
    finally:
        d.close()


def test_payload_on_the_wire_is_ciphertext(deployment: Deployment) -> None:
    d = deployment
    spy = Sniffer(d.user.url, "user")
    try:
        p = d.participant("hal-car-5")
        d.wait_listed(p)
        session = p.open("echo")
        assert session.request({"secret": PLAINTEXT}) == {"echo": {"secret": PLAINTEXT}}

        def data() -> list[Message]:
            return [
                m
                for m in spy.snapshot()
                if m.topic.startswith("ldm/p/hal-car-5/") and "/data/" in m.topic
            ]

        # One input, one reply: the core sees who, not what.
        assert wait_for(lambda: len(data()) == 2, 3)
        for m in data():
            assert PLAINTEXT.encode() not in m.payload
            assert set(json.loads(m.payload)) <= {"c", "t", "k", "d", "m"}  # m: the tag
    finally:
        spy.stop()


def test_cores_and_providers_survive_garbage(deployment: Deployment) -> None:
    d = deployment
    p = d.participant("kim-car-9")
    d.wait_listed(p)
    session = p.open("echo")
    vandal = Transport(BrokerSettings(url=d.user.url), client_id="vandal", sink=lambda e: None)
    inside = Transport(BrokerSettings(url=d.service.url), client_id="vandal2", sink=lambda e: None)
    vandal.start(timeout=5)
    inside.start(timeout=5)
    try:
        junk = [b"", b"\xff\xfe", b"{", b"[]", b'{"c":"../#","t":"x","d":1}', b"null"]
        for payload in junk:
            for topic in ("ldm/p/vandal/up/session", "ldm/p/vandal/up/data/echo"):
                vandal.publish(topic, payload, qos=1)
            for topic in ("ldm/svc/echo/in/fake", "ldm/svc/echo/out/fake"):
                inside.publish(topic, payload, qos=1)
        assert wait_for(lambda: d.provider.stats.dropped_invalid >= len(junk) - 1, 5)
        assert wait_for(lambda: d.user_core.stats.dropped_invalid >= 2 * (len(junk) - 1), 5)
        assert session.request({"still": "fine"}) == {"echo": {"still": "fine"}}
        assert has_service(p, "echo")()
    finally:
        vandal.stop()
        inside.stop()


def test_a_vanished_core_takes_its_services_with_it(broker_factory) -> None:
    """The service core's last will on the backbone removes its services well before TTL."""
    user, backbone, service = broker_factory(), broker_factory(), broker_factory()
    slow = {**FAST, "service_ttl": 60.0}
    user_core = Core.create("u", user.url, backbone.url, **slow).start(timeout=5)
    service_core = Core.create("s", service.url, backbone.url, **slow).start(timeout=5)
    provider = echo_provider(service.url, EchoService())
    try:
        with Participant.create(user.url, client_id="lee-car") as p:
            assert wait_for(has_service(p, "echo"), 5)
            service_core.stop_dispatch()
            assert service_core.backbone is not None
            service_core.backbone.kill()  # a crash: the broker publishes the core's will
            assert wait_for(lacks_service(p, "echo"), 5)
            assert not user_core.services
    finally:
        provider.stop()
        service_core.cluster.stop()
        user_core.stop()


def test_a_batch_handler_gets_what_waited_and_answers_each_in_order(broker_factory) -> None:
    """A provider with a batch handler: while its first batch is being handled, the rest
    of a burst from three participants waits and arrives as larger batches; every request
    gets its own reply, and each participant's requests reach the handler in order."""
    d = deploy(broker_factory)
    batches: list[list[Request]] = []

    def handle_many(requests: Sequence[Request]) -> list[dict[str, Any]]:
        batches.append(list(requests))
        if len(batches) == 1:
            time.sleep(0.3)  # a slow first batch: the burst queues up behind it
        return [{"echo": r.payload, "batch": len(batches)} for r in requests]

    spec = ECHO.model_copy(update={"name": "becho"})
    provider = Provider.create(
        d.service.url,
        spec,
        lambda r: {"single": True},
        batch_handler=handle_many,
        announce_interval=0.3,
        max_age=FAST["max_age"],
        max_batch=16,
    ).start(timeout=5)
    try:
        participants = [d.participant(cid, user) for cid, user in CLIENTS]
        for p in participants:
            assert wait_for(has_service(p, "becho"), 5), "becho never listed"
        sessions = [p.open("becho") for p in participants]
        sent = [stream(s, cid, 20, 0.0) for s, (cid, _) in zip(sessions, CLIENTS, strict=True)]
        for stream_ in sent:
            for payload, future in stream_:
                reply = future.result(10)
                assert reply["echo"] == payload and "single" not in reply
        seen = [r for b in batches for r in b]
        assert len(seen) == 60
        assert max(len(b) for b in batches) > 1, "the burst should have waited in batches"
        assert max(len(b) for b in batches) <= 16
        for cid, _ in CLIENTS:
            order = [r.payload["i"] for r in seen if r.payload["who"] == cid]
            assert order == list(range(20)), f"{cid}'s requests were reordered"
    finally:
        provider.stop()
        d.close()
