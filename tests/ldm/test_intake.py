"""Fair intake at the core (issue 11, item 3) and no retained participant messages (item 2).

The fair queue and the core's intake are tested in-process first (deterministic); then
on real brokers, the embedded one and Mosquitto with the shipped ACL: a flooder is
refused at intake while everyone else is answered, retained participant messages are
cleared within the stated bound and never taken as input, and other users' latency
under a flood (`ldm bench flood`, short phases; its figures are printed, the assertions
are structural and loose: a 2-core machine shared with other jobs cannot promise p99).
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict

import pytest

from ldm import Core, KeyPair, Participant, Provider
from ldm.cli import main as ldm_main
from ldm.config import BrokerSettings
from ldm.core.stats import CoreStats
from ldm.local.brokers import MosquittoBroker, RunningBroker, mosquitto_acl, start_broker, wait_for
from ldm.local.pytest_plugin import need_mosquitto
from ldm.transport.dispatch import Dispatcher
from ldm.transport.intake import FairQueue
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire.messages import Announcement, Envelope, ServiceDescription, SessionRequest

from .deployment import ECHO, EchoService, has_service

UNREACHABLE = "mqtt://127.0.0.1:9"  # never connected: the core's publishes only queue

# --- the fair queue -------------------------------------------------------------------


def drain(q: FairQueue[str]) -> list[str]:
    out: list[str] = []
    while q.qsize():
        out.append(q.get(timeout=0))
    return out


def test_keys_are_served_round_robin_behind_the_urgent_lane() -> None:
    q: FairQueue[str] = FairQueue()
    for item in ("a1", "a2", "a3", "a4"):
        q.offer(item, "a")
    q.offer("b1", "b")
    q.offer("b2", "b")
    q.offer("u1")  # key None: the urgent lane
    q.offer("c1", "c")
    q.put("u2")
    assert drain(q) == ["u1", "u2", "a1", "b1", "c1", "a2", "b2", "a3", "a4"]
    # a key that ran empty joins the ring again at its tail
    q.offer("a5", "a")
    q.offer("b3", "b")
    q.offer("a6", "a")
    assert drain(q) == ["a5", "b3", "a6"]


def test_a_newcomer_waits_at_most_one_item_per_other_key() -> None:
    q: FairQueue[str] = FairQueue()
    for i in range(1000):
        q.offer(f"flood{i}", "mallory")
    for i in range(3):
        q.offer(f"busy{i}", f"busy{i}")
    assert q.get(timeout=0) == "flood0"
    q.offer("alice", "alice")  # arrives behind 999 of mallory's and 3 others
    order = [q.get(timeout=0) for _ in range(6)]
    assert "alice" in order[:5], order  # at most one of each other waiting key first
    assert q.waiting("mallory") == 999 - order.count("mallory") - sum(
        x.startswith("flood") for x in order
    )


def test_offer_keeps_the_limit_and_put_does_not() -> None:
    q: FairQueue[str] = FairQueue(limit=3)
    assert q.offer("a1", "a") and q.offer("b1", "b") and q.offer("u1")
    assert not q.offer("a2", "a") and not q.offer("u2")
    q.put("stop")  # control items are never lost
    assert q.qsize() == len(q) == 4
    assert drain(q) == ["u1", "stop", "a1", "b1"]
    with pytest.raises(queue.Empty):
        q.get(timeout=0.01)


def test_producers_on_several_threads_keep_each_keys_order() -> None:
    q: FairQueue[tuple[str, int]] = FairQueue()
    keys = [f"k{i}" for i in range(4)]

    def produce(key: str) -> None:
        for n in range(2000):
            assert q.offer((key, n), key)

    threads = [threading.Thread(target=produce, args=(k,)) for k in keys]
    got: list[tuple[str, int]] = []
    for t in threads:
        t.start()
    while len(got) < 8000:
        got.append(q.get(timeout=5))
    for t in threads:
        t.join()
    for key in keys:
        assert [n for k, n in got if k == key] == list(range(2000))


def test_a_dispatcher_takes_its_items_from_a_fair_inbox() -> None:
    seen: list[str] = []
    done = threading.Event()

    class Recorder(Dispatcher[str]):
        def handle(self, item: str) -> None:
            seen.append(item)
            if len(seen) == 5:
                done.set()

    inbox: FairQueue[object] = FairQueue()
    dispatcher = Recorder("recorder", 0.05, inbox=inbox)
    for item, key in (("m1", "m"), ("m2", "m"), ("m3", "m"), ("a1", "a")):
        inbox.offer(item, key)
    dispatcher.put("ctl")
    dispatcher.start_dispatch()
    try:
        assert done.wait(5)
        assert seen == ["ctl", "m1", "a1", "m2", "m3"]
    finally:
        dispatcher.stop_dispatch()


# --- the core's intake, in-process ------------------------------------------------------


def outcomes(s: CoreStats) -> int:
    """Every participant message ends in exactly one of these counters."""
    return sum(
        n
        for name, n in asdict(s).items()
        if name in ("forwarded_in", "granted")
        or name.startswith(("dropped_", "rejected_", "answered_"))
    )


@pytest.fixture
def edge() -> Iterator[Core]:
    """A core that knows `echo` and holds alice's session (key ALICE, no secret); never
    connected, its dispatch thread not running: a test hands it messages through `sink` (what
    paho's thread calls) and handles the queued items itself, in the queue's order."""
    core = Core.create("edge", UNREACHABLE, rate=10.0, burst=10.0)
    description = ServiceDescription(**ECHO.model_dump(), public_key=KeyPair().public)
    ann = Announcement(service=description, t=time.time())
    payload = ann.model_dump_json().encode()
    core.handle(Message("ldm/svc/echo/announce", payload, 1, False, "cluster"))
    yield core
    core.cluster.stop()


ALICE = KeyPair()


def up(core: Core, client: str, kind: str, payload: bytes, retain: bool = False) -> None:
    core.sink(Message(f"ldm/p/{client}/up/{kind}", payload, 0, retain, "cluster"))


def request(c: str) -> bytes:
    return SessionRequest(c=c, service="echo", t=time.time()).model_dump_json().encode()


def data(key: KeyPair, c: str) -> bytes:
    return Envelope(c=c, t=time.time(), k=key.public, d="AAAA").encode()


def handle_all(core: Core) -> list[str]:
    """Handle what waits in the intake, in order; the client of each participant item."""
    clients: list[str] = []
    while core._intake.qsize():
        item = core._intake.get(timeout=0)
        assert isinstance(item, Message)
        if item.topic.startswith("ldm/p/"):
            clients.append(item.topic.split("/")[2])
        core.handle(item)
    return clients


def test_a_flood_is_refused_at_intake_and_others_go_first(edge: Core) -> None:
    up(edge, "alice", "session", request("a0"))
    up(edge, "alice", "data/echo", data(ALICE, "a1"))
    assert handle_all(edge) == ["alice", "alice"]
    assert edge.stats.granted == 1 and edge.stats.forwarded_in == 1
    before = outcomes(edge.stats)
    flood = [data(KeyPair(), f"m{i}") for i in range(1000)]  # made first: buckets refill
    for payload in flood:  # mallory floods, then alice and bob send one each
        up(edge, "mallory", "data/echo", payload)
    up(edge, "alice", "data/echo", data(ALICE, "a2"))
    up(edge, "bob", "session", request("b1"))
    # The bucket (burst 10) refused all but 10 before anything was queued; the next
    # 10 of mallory's wait only to have their `rejected` notices sent (10/s).
    assert edge.stats.rejected_rate == 990
    assert edge.stats.notices_suppressed == 980
    assert edge._intake.waiting("mallory") == 20
    order = handle_all(edge)
    assert order.index("alice") <= 1 and order.index("bob") <= 2, order
    assert outcomes(edge.stats) == before + 1002  # each message in exactly one counter
    assert edge.stats.forwarded_in == 2 and edge.stats.granted == 2


def test_forged_input_on_an_open_broker_leaves_the_sessions_budget(edge: Core) -> None:
    up(edge, "alice", "session", request("a0"))
    up(edge, "alice", "data/echo", data(ALICE, "a1"))
    handle_all(edge)
    forged = [data(KeyPair(), f"f{i}") for i in range(200)]
    for payload in forged:  # forged: other keys, garbage, malformed session requests
        up(edge, "alice", "data/echo", payload)
        up(edge, "alice", "data/echo", b"{")
        up(edge, "alice", "session", b"[]")
    refused = edge.stats.rejected_rate
    assert refused >= 590
    for i in range(5):  # alice's own input and a session request still get through
        up(edge, "alice", "data/echo", data(ALICE, f"a{i + 2}"))
    up(edge, "alice", "session", request("a9"))
    assert edge.stats.rejected_rate == refused
    handle_all(edge)
    assert edge.stats.forwarded_in == 6 and edge.stats.granted == 2


def test_retained_and_empty_participant_messages_are_dropped_at_intake(edge: Core) -> None:
    up(edge, "mallory", "data/echo", data(KeyPair(), "r1"), retain=True)
    up(edge, "mallory", "data/echo", b"")  # the echo of the core's own clearing
    assert edge.stats.dropped_retained == 2
    assert edge._intake.qsize() == 0 and not edge.admission.clients  # not input: no bucket charged


def test_the_tick_forgets_full_buckets_and_gone_sessions(edge: Core) -> None:
    up(edge, "alice", "session", request("a0"))
    up(edge, "alice", "data/echo", data(ALICE, "a1"))
    handle_all(edge)
    assert "alice" in edge.admission.clients and ("alice", "echo") in edge.admission.sessions
    edge.tick(time.time() + 3600.0)  # idle: the session expires, the buckets refill
    assert not edge.admission.clients and not edge.admission.sessions


# --- real brokers ---------------------------------------------------------------------


def test_a_flooder_is_refused_at_intake_and_others_are_all_answered(
    broker_factory: Callable[[], RunningBroker],
) -> None:
    url = broker_factory().url
    core = Core.create("edge", url, rate=20.0, burst=20.0).start(timeout=5)
    provider = Provider.create(url, ECHO, EchoService(), announce_interval=0.3).start(timeout=5)
    people = {n: Participant.create(url, client_id=n).start(timeout=5) for n in ("a", "b", "m")}
    stop = threading.Event()
    waiting = [0]

    def flood() -> None:
        sessions = people["m"].open("echo")
        while not stop.is_set():  # a few thousand a second, in this process
            for i in range(20):
                sessions.send({"flood": i})
            waiting[0] = max(waiting[0], core._intake.waiting("m"))
            time.sleep(0.005)

    try:
        assert wait_for(has_service(people["a"], "echo"), 5)
        a, b = people["a"].open("echo"), people["b"].open("echo")
        flooder = threading.Thread(target=flood)
        flooder.start()
        start = time.monotonic()
        assert wait_for(lambda: core.stats.rejected_rate > 500, 10), "no flood"
        # while the flood goes on, each honest request is answered (how fast belongs to
        # `ldm bench flood`: on a loaded machine the embedded broker, which
        # carries the flood on the same cores, took more than 3 s once)
        for i in range(5):
            assert a.request({"a": i}, timeout=10.0) == {"echo": {"a": i}}
            assert b.request({"b": i}, timeout=10.0) == {"echo": {"b": i}}
        stop.set()
        flooder.join()
        elapsed = time.monotonic() - start
        s = core.stats
        assert s.dropped_overload == 0
        # refused at intake: the flooder's share of the forwarded input is its bucket's
        assert s.forwarded_in <= 20 + 20 + 20.0 * elapsed + 2, (asdict(s), elapsed)
        assert waiting[0] <= 40, waiting  # its admitted messages and notices, no backlog
    finally:
        stop.set()
        for p in people.values():
            p.stop()
        provider.stop()
        core.stop()


SWEEP = 0.5  # s, CoreConfig.retain_sweep in these tests
# s: how long the tests wait for a clearing. A sweep, a tick and the round trips take
# about SWEEP + 1 s (docs/security.md; the test prints it); the wait is generous, as
# nothing but the core clears these messages, so the outcome is what is checked.
PATIENCE = 30.0


def retained_on(settings: BrokerSettings) -> list[Message]:
    """What a fresh subscriber to ``ldm/p/#`` is sent as retained there."""
    seen: list[Event] = []
    probe = Transport(settings, client_id=f"probe-{time.monotonic_ns()}", sink=seen.append)
    probe.subscribe("ldm/p/#", 1)
    probe.start(timeout=5)
    time.sleep(0.3)
    probe.stop()
    # (amqtt 0.12 also sends the subscriber retained messages of other filters)
    return [e for e in seen if isinstance(e, Message) and e.retain and e.topic.startswith("ldm/p/")]


def check_retained_hygiene(participant: BrokerSettings, core_side: BrokerSettings) -> None:
    mallory = Transport(participant, client_id="mallory", sink=lambda _e: None)
    mallory.start(timeout=5)
    try:
        big = json.dumps({"c": "r0", "t": time.time(), "pad": "x" * 20_000}).encode()
        for i in range(10):  # left on the broker before the core starts
            mallory.publish_and_wait(f"ldm/p/mallory/up/data/echo{i}", big, retain=True)
        assert len(retained_on(core_side)) == 10
        core = Core.create("edge", core_side, retain_sweep=SWEEP).start(timeout=5)
        try:
            assert wait_for(lambda: not retained_on(core_side), PATIENCE)
            s = core.stats
            assert s.dropped_retained >= 10  # each delivered flagged at the subscription
            assert outcomes(s) == s.dropped_retained  # none of them taken as input
            assert wait_for(lambda: s.dropped_retained >= 20, PATIENCE)  # the clearings' echoes
            # now while the core runs: the broker hides the flag on live delivery, the
            # core takes these as (invalid) input, and the sweep clears them
            for i in range(10):
                mallory.publish_and_wait(f"ldm/p/mallory/up/session/x{i}", big, retain=True)
            published = time.monotonic()
            assert wait_for(lambda: not retained_on(core_side), PATIENCE)
            print(f"cleared {time.monotonic() - published:.2f} s after publishing")
        finally:
            core.stop()
    finally:
        mallory.stop()


def test_retained_participant_messages_are_cleared_on_the_embedded_broker() -> None:
    broker = start_broker("embedded")
    try:
        settings = BrokerSettings(url=broker.url)
        check_retained_hygiene(settings, settings)
    finally:
        broker.stop()


@pytest.mark.mosquitto
def test_retained_participant_messages_are_cleared_on_mosquitto_with_the_acl() -> None:
    need_mosquitto()
    with MosquittoBroker(acl=mosquitto_acl("ldm-core", {"svc-echo": "echo"})) as broker:
        check_retained_hygiene(
            BrokerSettings(url=broker.url), BrokerSettings(url=broker.url, username="ldm-core")
        )


@pytest.mark.mosquitto
def test_other_users_latency_under_a_flood_with_the_shipped_acl(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The flood bench in short (`ldm bench flood`, its JSON report read back): baseline,
    then a 3,000 msg/s flood, in one run: every honest request answered in both phases,
    the flood refused at intake."""
    need_mosquitto()
    argv = ["bench", "flood", "--participants", "3", "--hz", "10", "--rate", "3000"]
    assert ldm_main([*argv, "--phase", "1.5", "--json"]) == 0
    out = capsys.readouterr().out
    print(out)
    report = json.loads(out)
    base, flood, settings = report["baseline"], report["flood"], report["settings"]
    assert base["answered"] == base["sent"] and flood["answered"] == flood["sent"], out
    assert report["flood_sent"] > 2000, "no flood"
    # structural: the flood is refused at intake, before it queues
    assert report["flooder_waiting"] <= 2 * settings["core_burst"]
    # At most a burst and the rate over the time the core can have been taking the flood
    # are admitted (a bound in 1.5 s failed by one message when the broker delivered
    # the flood over 2.5 s); the 100 are what may still be on the way when it is read.
    admitted = settings["core_burst"] + settings["core_rate"] * report["flood_span"]
    assert report["core"]["rejected_rate"] >= report["flood_sent"] - admitted - 100
    # How much the flood slows the others (the old shared queue made the typical request
    # 10-20 times slower) is the bench's figure, printed above and quoted from `ldm bench
    # flood` in docs/security.md: a latency bound here failed on a machine
    # at load 8 (39 ms against 6.6 ms). What keeps the others fast is checked above: the
    # flood is refused at intake and never queues past the flooder's burst.
