"""The core's session policy on a real broker: rotation notices, key churn, notices."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator

import pytest

from ldm import Core, KeyPair, Participant, Provider, RequestRejected
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, wait_for
from ldm.local.embedded import EmbeddedBroker
from ldm.local.pytest_plugin import need_mosquitto
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire import topics
from ldm.wire.messages import Envelope, SessionNotice, SessionRequest

from .deployment import ECHO, EchoService, has_service


class RawParticipant:
    """A participant without the library: it sends what a test says, keeps every notice."""

    def __init__(self, url: str, client_id: str) -> None:
        self.client_id = client_id
        self._lock = threading.Lock()
        self._notices: list[SessionNotice] = []
        self.transport = Transport(BrokerSettings(url=url), client_id=client_id, sink=self._sink)
        self.transport.subscribe(f"ldm/p/{client_id}/down/session", 1)
        self.transport.start(timeout=5)

    def _sink(self, event: Event) -> None:
        if isinstance(event, Message):
            with self._lock:
                self._notices.append(SessionNotice.model_validate_json(event.payload))

    def notices(self, kind: str) -> list[SessionNotice]:
        with self._lock:
            return [n for n in self._notices if n.kind == kind]

    def open(self, service: str) -> None:
        req = SessionRequest(c="open1", service=service, t=time.time())
        self.transport.publish(
            f"ldm/p/{self.client_id}/up/session", req.model_dump_json().encode(), 1
        )
        assert wait_for(lambda: self.notices("grant"), 5)

    def send(self, service: str, key: KeyPair, c: str) -> None:
        env = Envelope(c=c, t=time.time(), k=key.public, d="AAAA")
        self.transport.publish(f"ldm/p/{self.client_id}/up/data/{service}", env.encode(), 1)


@pytest.fixture
def edge() -> Iterator[tuple[MosquittoBroker, Core]]:
    need_mosquitto()
    with MosquittoBroker() as broker:
        core = Core.create(
            "edge", broker.url, rotation_period=0.3, grace=0.3, idle_timeout=10.0
        ).start(timeout=5)
        provider = Provider.create(broker.url, ECHO, EchoService(), announce_interval=0.3)
        provider.start(timeout=5)
        try:
            assert wait_for(lambda: bool(core.services), 5)
            yield broker, core
        finally:
            provider.stop()
            core.stop()


@pytest.mark.mosquitto
def test_rotate_is_repeated_until_a_new_key_comes_and_keys_cannot_churn(
    edge: tuple[MosquittoBroker, Core],
) -> None:
    broker, core = edge
    raw = RawParticipant(broker.url, "rolf")
    try:
        raw.open("echo")
        first = KeyPair()
        raw.send("echo", first, "a1")
        assert wait_for(lambda: core.stats.forwarded_in == 1, 5)
        # The participant ignores (or never got) the first rotate notice: it comes again
        # every rotation period, so a lost notice only delays the rotation.
        assert wait_for(lambda: len(raw.notices("rotate")) >= 3, 5)
        second = KeyPair()
        raw.send("echo", second, "a2")
        assert wait_for(lambda: core.stats.rotations == 1 and core.stats.forwarded_in == 2, 5)
        # A third key right away is one pseudonym too many: refused, counted, answered.
        raw.send("echo", KeyPair(), "a3")
        assert wait_for(lambda: core.stats.rejected_rekey == 1, 5)
        assert wait_for(lambda: any(n.c == "a3" for n in raw.notices("rejected")), 5)
        rejected = next(n for n in raw.notices("rejected") if n.c == "a3")
        assert rejected.reason == "rate_limited" and rejected.error and "k:" in rejected.error
        # The current key (and the old one, in its grace) still work.
        raw.send("echo", second, "a4")
        assert wait_for(lambda: core.stats.forwarded_in == 3, 5)
        assert core.stats.rotations == 1
    finally:
        raw.transport.stop()


@pytest.mark.mosquitto
def test_a_participant_restarted_under_its_name_is_answered_and_cannot_churn_keys() -> None:
    """A bridge restarted under the same client id within ``rekey_interval`` (30 s
    here) comes back with a new ephemeral key: its fresh grant lets that key in. A
    second restart at once is refused: fresh grants do not raise how many keys a
    session may take in the long run (one per ``rekey_interval``), only let one in early."""
    need_mosquitto()
    with MosquittoBroker() as broker:
        core = Core.create("edge", broker.url).start(timeout=5)
        provider = Provider.create(broker.url, ECHO, EchoService(), announce_interval=0.3)
        provider.start(timeout=5)
        try:
            answers: list[object] = []
            for run in range(3):
                p = Participant.create(broker.url, client_id="gpsd-1", max_age=2.0)
                p.start(timeout=5)
                try:
                    assert wait_for(has_service(p, "echo"), 5)
                    session = p.open("echo")
                    assert session.grant.rekey_interval == 30.0
                    try:
                        answers.append(session.request({"run": run}, timeout=5))
                    except RequestRejected as exc:
                        answers.append(exc.reason)
                finally:
                    p.stop()
            assert answers == [{"echo": {"run": 0}}, {"echo": {"run": 1}}, "rate_limited"]
            assert core.stats.rejected_rekey == 1
        finally:
            provider.stop()
            core.stop()


def test_input_on_its_way_when_its_provider_is_withdrawn_is_still_forwarded() -> None:
    """Input from another cluster that arrives just after the provider's withdrawal (a
    last will a NATS node sends while the provider only moves to another node) goes on
    to the provider's input topic, where its persistent session keeps it, for
    ``service_ttl`` s; dropped, it failed only by the participant's timeout (41 s in the
    NATS failover test). Later input is dropped as unroutable, as before."""
    cluster, backbone = EmbeddedBroker().start(), EmbeddedBroker().start()
    core = Core.create("svc", cluster.url, backbone.url, service_ttl=3.0).start(timeout=5)
    provider = Provider.create(cluster.url, ECHO, EchoService(), announce_interval=0.5)
    provider.start(timeout=5)
    inbox: list[Message] = []
    spy = Transport(BrokerSettings(url=cluster.url), client_id="spy", sink=_keep(inbox), name="spy")
    spy.subscribe(topics.provider_input_batch("echo"), 1)
    sender = Transport(BrokerSettings(url=backbone.url), client_id="user-core", sink=_keep([]))
    key = KeyPair()

    def send(c: str) -> None:
        env = Envelope(c=c, t=time.time(), k=key.public, d="AAAA")
        sender.publish(topics.bb_input("svc", "echo", "user-edge", "pseudo1"), env.encode(), 1)

    def forwarded(c: str) -> bool:
        return any(c.encode() in m.payload for m in list(inbox))

    try:
        spy.start(timeout=5)
        sender.start(timeout=5)
        assert wait_for(lambda: core.catalog.get("echo") is not None, 5)
        send("before")  # the positive control: a listed service's input is forwarded
        assert wait_for(lambda: forwarded("before"), 5)
        provider.kill()  # no goodbye: the broker sends its will, a withdrawal
        assert wait_for(lambda: core.catalog.get("echo") is None, 5)
        unroutable = core.stats.dropped_unroutable
        send("after")
        assert wait_for(lambda: forwarded("after"), 5)
        assert core.stats.dropped_unroutable == unroutable
        # service_ttl later the service is not this cluster's any more
        assert wait_for(lambda: not core.catalog.served_here("echo", time.time()), 10)
        send("late")
        assert wait_for(lambda: core.stats.dropped_unroutable == unroutable + 1, 5)
        assert not forwarded("late")
    finally:
        sender.stop()
        spy.stop()
        core.stop()
        cluster.stop()
        backbone.stop()


def _keep(into: list[Message]) -> Callable[[Event], None]:
    def sink(event: Event) -> None:
        if isinstance(event, Message):
            into.append(event)

    return sink
