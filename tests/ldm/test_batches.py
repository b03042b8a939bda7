"""Batches between the cores and between a core and its provider (`ldm.wire.batch`):
order and replies kept per participant, a broker restart survived, a malformed line
costing only itself; and the hand-off of what waited. Real brokers (embedded and
Mosquitto), no mocks."""

from __future__ import annotations

import json
import threading
import time
from concurrent.futures import Future
from typing import Any

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from paho.mqtt.client import topic_matches_sub as paho_matches

from ldm import KeyPair, Provider, Request, ServiceSpec
from ldm.cli import main as ldm_main
from ldm.config import BrokerSettings
from ldm.local.brokers import wait_for
from ldm.local.pytest_plugin import need_mosquitto
from ldm.security.crypto import aad
from ldm.transport.intake import FairQueue
from ldm.transport.mqtt import Event, Message, Transport, matches
from ldm.wire import batch, topics
from ldm.wire.messages import Envelope

from .deployment import Deployment, deploy
from .test_faults import restart, works_again

PARTICIPANTS = 6
BURST = 15  # requests each participant sends at once, so that envelopes wait together
# Each participant's input budget: two bursts and their warm-up within a fraction of a
# second. At the default (100/s, burst 20), a burst that follows the last one's replies
# within ~100 ms is refused in part, as it should be: what the tests here hold is the
# batching, and the admission's rate is tests/ldm/test_intake.py's business.
INPUT_BURST = 4 * BURST


@pytest.fixture
def deployment(broker_factory):
    d = deploy(broker_factory, burst=INPUT_BURST)
    yield d
    d.close()


def burst(d: Deployment, sessions: list[Any], tag: str) -> list[tuple[int, int, Future[Any]]]:
    """Every participant sends BURST requests at once, numbered in order."""
    sent = []
    for n in range(BURST):
        for i, session in enumerate(sessions):
            payload = {"who": f"p{i}", "tag": tag, "n": n}
            sent.append((i, n, session.submit(payload)))
    return sent


def check_burst(d: Deployment, sent: list[tuple[int, int, Future[Any]]], tag: str) -> None:
    """Each request has its own reply, the service saw each once, and each pseudonym's
    in order. (The cores rotate every 0.5 s here: a burst that spans a change of
    pseudonym reaches the service in two lanes, and the service core serves its lanes
    round-robin, so the first input under the new pseudonym may overtake the last under
    the old one; docs/ldm.md says so.)"""
    for i, n, future in sent:
        assert future.result(10) == {"echo": {"who": f"p{i}", "tag": tag, "n": n}}
    with d.echo.lock:
        seen = [r for r in d.echo.requests if r.payload.get("tag") == tag]
    for i in range(PARTICIPANTS):
        mine = [r for r in seen if r.payload["who"] == f"p{i}"]
        assert sorted(r.payload["n"] for r in mine) == list(range(BURST)), f"p{i}: {mine}"
        for pseudonym in {r.pseudonym for r in mine}:
            order = [r.payload["n"] for r in mine if r.pseudonym == pseudonym]
            assert order == sorted(order), f"p{i} arrived out of order: {order}"


def open_sessions(d: Deployment) -> list[Any]:
    participants = [d.participant(f"batch-{i}") for i in range(PARTICIPANTS)]
    for p in participants:
        d.wait_listed(p)
    sessions = [p.open("echo") for p in participants]
    for s in sessions:
        assert s.request({"warm": 1}, timeout=5) == {"echo": {"warm": 1}}
    return sessions


def test_a_batch_mixing_participants_keeps_each_ones_order_and_replies(
    deployment: Deployment,
) -> None:
    d = deployment
    sessions = open_sessions(d)
    sent = burst(d, sessions, "mixed")
    check_burst(d, sent, "mixed")
    # The envelopes did travel in batches, each mixing participants (pseudonyms).
    mixed = 0
    for m in d.sniffers[0].snapshot():
        kind = topics.parse(m.topic).kind
        if kind in ("bb_input_batch", "bb_reply_batch"):
            entries, bad = batch.decode(m.payload)
            assert bad == 0 and entries  # a batch of one when an envelope travels alone
            mixed += len({p for p, _ in entries}) > 1
    assert mixed > 0, "no batch on the backbone mixed participants"
    assert d.user_core.stats.batches_sent > 0 and d.service_core.stats.batches_sent > 0
    assert d.user_core.stats.batched + d.service_core.stats.batched > PARTICIPANTS
    assert d.provider.stats.reply_batches > 0


def test_batches_survive_a_broker_restart(deployment: Deployment) -> None:
    d = deployment
    sessions = open_sessions(d)
    check_burst(d, burst(d, sessions, "before"), "before")
    before = d.service_core.stats.batches_sent
    restart(d.backbone)  # both cores reconnect; batches flow over the new connection
    for s in sessions:
        works_again(s)
    check_burst(d, burst(d, sessions, "after"), "after")
    assert d.service_core.stats.batches_sent > before


def test_a_malformed_envelope_in_a_batch_costs_only_itself(mqtt_broker) -> None:
    """A batch to a provider with good envelopes around malformed lines: the good ones
    are each answered (in one batch of replies), each bad line is counted once."""
    service = KeyPair()
    seen: list[Request] = []

    def handler(request: Request) -> dict[str, Any]:
        seen.append(request)
        return {"n": request.payload["n"]}

    provider = Provider.create(
        mqtt_broker.url, ServiceSpec(name="echo"), handler, key=service
    ).start(timeout=5)
    replies: list[Message] = []
    lock = threading.Lock()

    def sink(event: Event) -> None:
        if isinstance(event, Message):
            with lock:
                replies.append(event)

    core = Transport(BrokerSettings(url=mqtt_broker.url), client_id="fake-core", sink=sink)
    core.subscribe("ldm/svc/echo/out/#", 1)
    core.start(timeout=5)
    try:

        def sealed(n: int) -> bytes:
            eph = KeyPair()
            cipher = eph.cipher(service.public, initiator=True)
            t, c = time.time(), f"c{n}"
            d = cipher.seal(f'{{"n":{n}}}'.encode(), aad(c, t))
            return Envelope(c=c, t=t, k=eph.public, d=d).encode()

        good = [(f"p{n}", sealed(n)) for n in range(3)]
        lines = [
            good[0],
            ("p-bad", b'{"c":"x","t":1.0,"d":"!!"}'),  # not an envelope
            good[1],
            ("p-bad2", sealed(9)[:-5]),  # cut short
            good[2],
        ]
        payload = batch.encode(lines) + b"\nno-envelope-here\n/+# {}"
        # connected is not subscribed: wait for the broker's SUBACK of the batch topic
        batch_topic = topics.provider_input_batch("echo")
        assert wait_for(lambda: batch_topic in provider.transport.granted, 5)
        core.publish(topics.provider_input_batch("echo"), payload, qos=1)
        assert wait_for(lambda: provider.stats.requests == 3, 5), provider.stats
        assert provider.stats.dropped_invalid == 4, provider.stats
        assert sorted(r.payload["n"] for r in seen) == [0, 1, 2]

        def answered() -> set[str]:
            with lock:
                got = list(replies)
            found = set()
            for m in got:
                t = topics.parse(m.topic)
                if t.kind == "provider_reply_batch":
                    found |= {p for p, _ in batch.decode(m.payload)[0]}
                elif t.kind == "provider_reply":
                    found.add(t.pseudonym)
            return found

        assert wait_for(lambda: answered() == {"p0", "p1", "p2"}, 5), answered()
        assert provider.stats.reply_batches >= 1
    finally:
        core.stop()
        provider.stop()


def test_a_core_forwards_the_good_envelopes_of_a_batch_with_bad_lines(
    deployment: Deployment,
) -> None:
    """A batch on the backbone to the service core with malformed lines among real
    envelopes: the core forwards the real ones to the provider, counts the bad ones."""
    d = deployment
    sessions = open_sessions(d)
    check_burst(d, burst(d, sessions, "warm"), "warm")
    forger = Transport(
        BrokerSettings(url=d.backbone.url), client_id="bb-forger", sink=lambda _e: None
    )
    forger.start(timeout=5)
    try:
        stats = d.service_core.stats
        invalid, forwarded = stats.dropped_invalid, stats.forwarded_in
        # Fresh, well-formed envelopes under new pseudonyms (the provider cannot open
        # them: that is its business; the core only routes).
        fake = Envelope(c="c1", t=time.time(), k="A" * 43 + "=", d="AAAA").encode()
        payload = batch.encode([("fresh-1", fake), ("fresh-2", fake)])
        payload += b"\nbroken line\n+/# " + fake + b"\nfresh-3 not json"
        topic = topics.bb_input_batch("svc-cluster", "echo", "user-edge")
        forger.publish(topic, payload, qos=1)
        assert wait_for(lambda: stats.forwarded_in == forwarded + 2, 5), stats
        assert wait_for(lambda: stats.dropped_invalid == invalid + 3, 5), stats
    finally:
        forger.stop()
    check_burst(d, burst(d, sessions, "after"), "after")  # nobody else paid for it


# --- the hand-off: what waited crosses the thread at once ------------------------------


def test_a_fair_queue_hands_over_what_waited_in_the_order_get_would() -> None:
    def fill() -> FairQueue[str]:
        q: FairQueue[str] = FairQueue()
        for key, n in (("a", 4), ("b", 1), ("c", 3)):
            for i in range(n):
                q.offer(f"{key}{i}", key)
        q.put("urgent")
        return q

    one_by_one = fill()
    expected = [one_by_one.get(0) for _ in range(9)]
    q = fill()
    assert q.take(5) + q.take(100) == expected
    assert q.take(10) == [] and len(q) == 0


_LEVEL = st.sampled_from(["a", "b", "", "$SYS", "+", "#"])


@given(st.lists(_LEVEL, min_size=1, max_size=4), st.lists(_LEVEL, min_size=1, max_size=4))
def test_topic_filters_match_as_paho_matches_them(
    topic_filter: list[str], topic: list[str]
) -> None:
    assume("#" not in topic_filter[:-1])
    assume(not any(level in ("+", "#") for level in topic))
    assume(not any(level.startswith("$") for level in topic[1:]))
    expected = paho_matches("/".join(topic_filter), "/".join(topic))
    assert matches(tuple(topic_filter), topic) == expected


def test_the_core_bench_answers_every_input_and_counts_the_cpu(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`ldm bench core` in short, its JSON report read back."""
    need_mosquitto()
    argv = ["bench", "core", "--participants", "5", "--rate", "4", "--duration", "1.5", "--json"]
    assert ldm_main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["answered"] == report["sent"] > 0, report
    # A short run: the brokers and the provider may use less than one clock tick (10 ms),
    # so only the cores' figure must be above 0.
    cpu = report["cpu_per_1000"]
    assert cpu.keys() == {"cores", "brokers", "provider"}, report
    assert cpu["cores"] > 0 and min(cpu.values()) >= 0, report
