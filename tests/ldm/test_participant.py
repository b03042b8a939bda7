"""The participant library on a real broker: no future is left pending, resends are unlinkable."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import pytest

from ldm import (
    ConnectError,
    Core,
    Participant,
    Provider,
    Request,
    RequestTimeout,
    SessionError,
)
from ldm.local.brokers import MosquittoBroker, wait_for
from ldm.local.pytest_plugin import need_mosquitto
from ldm.transport.mqtt import Message
from ldm.wire.messages import Envelope

from .deployment import ECHO, Sniffer, has_service


@dataclass
class Holding:
    """Echoes, except the first input marked ``hold`` and every input marked ``never``:
    those get no reply."""

    requests: list[Request] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, request: Request) -> dict[str, Any] | None:
        with self.lock:
            self.requests.append(request)
            first = sum(r.payload == request.payload for r in self.requests) == 1
        if request.payload.get("never") or (request.payload.get("hold") and first):
            return None
        return {"echo": request.payload}

    def seen(self, payload: dict[str, Any]) -> list[Request]:
        with self.lock:
            return [r for r in self.requests if r.payload == payload]


@dataclass
class Cluster:
    broker: MosquittoBroker
    core: Core
    service: Holding
    provider: Provider
    sniffer: Sniffer

    def new_core(self) -> Core:
        self.core.stop()
        self.core = Core.create("edge", self.broker.url, data_qos=1).start(timeout=5)
        return self.core


@pytest.fixture
def cluster() -> Iterator[Cluster]:
    need_mosquitto()
    with MosquittoBroker() as broker:
        core = Core.create("edge", broker.url, data_qos=1).start(timeout=5)
        service = Holding()
        provider = Provider.create(broker.url, ECHO, service, announce_interval=0.3)
        provider.start(timeout=5)
        sniffer = Sniffer(broker.url, "edge")
        c = Cluster(broker, core, service, provider, sniffer)
        try:
            yield c
        finally:
            sniffer.stop()
            provider.stop()
            c.core.stop()


@pytest.mark.mosquitto
def test_no_future_is_left_pending_on_reopen_stop_or_cancel(
    cluster: Cluster, caplog: pytest.LogCaptureFixture
) -> None:
    p = Participant.create(cluster.broker.url, client_id="pia").start(timeout=5)
    stopped = False
    try:
        assert wait_for(has_service(p, "echo"), 5)
        first = p.open("echo")
        held = first.submit({"hold": 1})
        assert wait_for(lambda: cluster.service.seen({"hold": 1}), 5)
        # Opening the same service again replaces the session: its waiting requests fail
        # now instead of never; the ephemeral key (and pseudonym) is kept.
        second = p.open("echo")
        with pytest.raises(SessionError, match="opened again"):
            held.result(0)
        assert second.request({"n": 1}) == {"echo": {"n": 1}}
        assert len({r.pseudonym for r in cluster.service.requests}) == 1

        # A future its caller cancelled is skipped when the reply comes.
        caplog.set_level(logging.ERROR, logger="ldm")
        cancelled = second.submit({"n": 2})
        cancelled.cancel()
        assert wait_for(lambda: cluster.service.seen({"n": 2}), 5)
        assert second.request({"n": 3}) == {"echo": {"n": 3}}  # the reply to n=2 came first
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR]

        # Stopping the participant fails what still waits.
        waiting = second.submit({"hold": 2})
        assert wait_for(lambda: cluster.service.seen({"hold": 2}), 5)
        p.stop()
        stopped = True
        with pytest.raises(ConnectError, match="stopped"):
            waiting.result(0)
    finally:
        if not stopped:
            p.stop()


@pytest.mark.mosquitto
def test_a_resent_request_gets_a_new_correlation_id_and_qos_1_holds_on_every_hop(
    cluster: Cluster,
) -> None:
    p = Participant.create(cluster.broker.url, client_id="rex").start(timeout=5)
    try:
        assert wait_for(has_service(p, "echo"), 5)
        session = p.open("echo")
        held = session.submit({"hold": 1})
        assert wait_for(lambda: cluster.service.seen({"hold": 1}), 5)
        # A new core knows no session: the next input is answered nosession, the library
        # re-opens and re-sends both, each under a new correlation id and pseudonym.
        cluster.new_core()
        assert wait_for(lambda: bool(cluster.core.services), 5)
        assert session.request({"n": 1}, timeout=5) == {"echo": {"n": 1}}
        assert held.result(5) == {"echo": {"hold": 1}}
        first, again = cluster.service.seen({"hold": 1})
        assert first.pseudonym != again.pseudonym
        assert first.correlation_id != again.correlation_id

        # Core data_qos=1 holds on every hop (single messages and batches), though the
        # provider was given no QoS.
        def sniffed() -> list[Message]:
            return [
                m
                for m in cluster.sniffer.snapshot()
                if "/data/" in m.topic or "/echo/in" in m.topic or "/echo/out" in m.topic
            ]

        # The sniffer is another client: its copy of the last reply may trail the reply.
        hops = {"in", "out", "up", "down"}
        assert wait_for(lambda: {m.topic.split("/")[3] for m in sniffed()} == hops, 5)
        data = sniffed()
        assert {m.qos for m in data} == {1}
        c_ids = [Envelope.model_validate_json(m.payload).c for m in data if "/up/data/" in m.topic]
        assert len(c_ids) == len(set(c_ids))  # no correlation id was sent twice
    finally:
        p.stop()


@pytest.mark.mosquitto
def test_a_re_sent_request_times_out_as_long_after_its_submission_as_any_other(
    cluster: Cluster,
) -> None:
    """A new grant re-sends what waits, but the timeout (2 x max_age + 1 s = 3 s)
    counts from the submission: before, each re-send started it again, and a flooded
    participant's inputs failed only after 10 s (CI of stop 31)."""
    p = Participant.create(cluster.broker.url, client_id="tim", max_age=1.0).start(timeout=5)
    try:
        assert wait_for(has_service(p, "echo"), 5)
        session = p.open("echo")
        failed_at: dict[str, float] = {}

        def submit(name: str) -> Future[dict[str, Any]]:
            future = session.submit({"never": 1 if name == "never" else 2})  # unanswered
            future.add_done_callback(lambda _f: failed_at.setdefault(name, time.monotonic()))
            return future

        never = submit("never")
        time.sleep(2.0)
        before = session.grant.session
        p.reopen(session)
        assert wait_for(lambda: session.grant.session != before, 2), "no regrant"
        control = submit("control")  # submitted as `never` is re-sent: its 3 s start now
        assert wait_for(lambda: len(cluster.service.seen({"never": 1})) == 2, 2), "not re-sent"
        for future in (never, control):
            with pytest.raises(RequestTimeout, match="within 3 s"):
                future.result(10)
        # `never` failed 3 s after its submission, about 2 s before the control; counted
        # from its re-send it would fail with the control (an ordering of two timeouts
        # of one participant, not a bound on the machine's clock)
        assert failed_at["control"] - failed_at["never"] > 1.0, failed_at
    finally:
        p.stop()
