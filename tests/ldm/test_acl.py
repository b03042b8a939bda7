"""Mosquitto ACLs can confine a participant to its own topics (client id in the topic)."""

from __future__ import annotations

import time

import pytest

from ldm import Core, KeyPair, Participant, Provider
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, mosquitto_acl, wait_for
from ldm.local.pytest_plugin import need_mosquitto
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire.messages import Envelope, SessionRequest

from .deployment import ECHO, EchoService, has_service


@pytest.mark.mosquitto
def test_a_participant_cannot_read_or_write_another_participants_topics() -> None:
    need_mosquitto()
    acl = mosquitto_acl("ldm-core", {"svc-echo": "echo"})
    with MosquittoBroker(acl=acl) as broker:

        def as_user(user: str) -> BrokerSettings:
            return BrokerSettings(url=broker.url, username=user)

        echo = EchoService()
        core = Core.create("single", as_user("ldm-core"), idle_timeout=5).start(timeout=5)
        provider = Provider.create(as_user("svc-echo"), ECHO, echo, announce_interval=0.3)
        provider.start(timeout=5)
        alice = Participant.create(broker.url, client_id="alice").start(timeout=5)
        seen: list[Event] = []
        mallory = Transport(BrokerSettings(url=broker.url), client_id="mallory", sink=seen.append)
        mallory.subscribe("ldm/p/alice/#", 1)  # accepted by the broker, never delivered
        mallory.subscribe("ldm/svc/#", 1)
        mallory.subscribe("ldm/p/mallory/down/#", 1)  # its own: allowed
        mallory.start(timeout=5)
        try:
            assert wait_for(has_service(alice, "echo"), 5)
            session = alice.open("echo")
            assert session.request({"n": 1}) == {"echo": {"n": 1}}
            # mallory sends valid input in alice's name: the broker must drop it.
            before = core.stats.forwarded_in
            key = KeyPair()
            sealed = key.cipher(session.service.public_key, initiator=True).seal(b"{}", "m1")
            forged = Envelope(c="m1", t=time.time(), k=key.public, d=sealed)
            mallory.publish(session.grant.input_topic, forged.encode(), 1)
            # Then a request on mallory's own topic: once the core has answered it, the
            # forged input had its turn (MQTT keeps one client's messages in order).
            own = SessionRequest(c="m2", service="echo", t=time.time()).model_dump_json()
            mallory.publish("ldm/p/mallory/up/session", own.encode(), 1)
            assert session.request({"n": 2}) == {"echo": {"n": 2}}

            def answered() -> list[Message]:
                return [e for e in list(seen) if isinstance(e, Message)]

            assert wait_for(lambda: answered(), 5), "mallory's own request went unanswered"
            assert core.stats.forwarded_in == before + 1, "ACL let mallory write"
            assert {m.topic for m in answered()} == {"ldm/p/mallory/down/session"}, (
                "ACL let mallory read"
            )
            assert len(echo.requests) == 2
        finally:
            mallory.stop()
            alice.stop()
            provider.stop()
            core.stop()
