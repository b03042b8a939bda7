"""The LDM on a cluster of three NATS servers (MQTT 3.1.1, state in JetStream), and
clients that fail over between the nodes of a cluster URL. Real nats-server processes
on free ports; the NATS tests skip when nats-server 2.10+ is missing."""

from __future__ import annotations

import socket
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import pytest

from ldm import (
    ConfigError,
    ConnectError,
    Core,
    LdmError,
    Participant,
    Provider,
    RequestRejected,
    RequestTimeout,
    ServiceNotFound,
)
from ldm.client.participant import Session
from ldm.config import BrokerSettings, build
from ldm.local.brokers import free_port, wait_for
from ldm.local.embedded import EmbeddedBroker
from ldm.local.nats import (
    NatsCluster,
)
from ldm.local.pytest_plugin import need_nats
from ldm.transport.mqtt import Event, Message, Transport, Will

from .deployment import ECHO, EchoService, has_service

ACCOUNTS = ("user", "backbone", "service")

# Patient enough to outlast a node failure: nothing is dropped as stale meanwhile, and
# what a participant held back while it moved to another node (then sends at once) fits
# in its burst, so a lost input is lost by the brokers, not by the LDM's own limits.
PATIENT = {
    "rotation_period": 60.0,
    "grace": 5.0,
    "idle_timeout": 60.0,
    "service_ttl": 30.0,
    "max_age": 20.0,
    "burst": 400.0,
}


@pytest.fixture
def cluster() -> Iterator[NatsCluster]:
    need_nats()
    with NatsCluster(3, accounts=ACCOUNTS, ack_wait=1.0) as c:
        yield c


class Inbox:
    """What one transport received, for assertions."""

    def __init__(self) -> None:
        self.messages: list[Message] = []
        self.lock = threading.Lock()

    def __call__(self, event: Event) -> None:
        if isinstance(event, Message):
            with self.lock:
                self.messages.append(event)

    def on(self, topic: str) -> list[Message]:
        with self.lock:
            return [m for m in self.messages if m.topic == topic]


def test_a_cluster_whose_port_another_process_took_starts_again_on_new_ports() -> None:
    """Ports are picked before the nodes bind them: a process that takes one in between
    (here a listener on node 1's route port) makes the first start fail, and the cluster
    starts again on fresh ports."""
    need_nats()
    cluster = NatsCluster(3, start_timeout=10.0)  # a node that cannot route waits it out
    taken = cluster.nodes[1].route_port
    squatter = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    squatter.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    squatter.bind(("0.0.0.0", taken))
    squatter.listen()
    try:
        with cluster:
            assert all(node.route_port != taken for node in cluster.nodes)
            assert all(cluster.running(i) for i in range(3))
            client = Transport(
                BrokerSettings(url=cluster.url), client_id="after-retry", sink=lambda _e: None
            )
            client.start(timeout=20)
            client.stop()
    finally:
        squatter.close()


# --- cluster URLs, on any broker --------------------------------------------------------


def test_a_cluster_url_lists_nodes_and_bad_ones_are_refused_with_the_form_to_use() -> None:
    one = BrokerSettings.of("mqtt://edge:1883")
    assert one.addresses == (("edge", 1883),) and one.clean_session
    three = BrokerSettings.of("mqtts://a:8001,b, [::1]:8003")
    assert three.addresses == (("a", 8001), ("b", 8883), ("::1", 8003))
    assert (three.host, three.port, three.tls) == ("a", 8001, True)
    assert not three.clean_session  # a cluster keeps the session while a client moves
    assert build(BrokerSettings, url=three.url, persistent_session=False).clean_session
    for url, says in [
        ("mqtt://a:1,", "names no host"),
        ("mqtt://a:1,b:x", "no valid port"),
        ("mqtt://a:1,a:1", "listed twice"),
        ("mqtt://u:pw@a:1,b:2", "credentials"),
        ("nats://a:4222", "mqtt://HOST:PORT,HOST:PORT"),
    ]:
        with pytest.raises(ConfigError, match=says):
            BrokerSettings.of(url)


def test_a_transport_moves_to_the_next_node_and_keeps_its_subscriptions() -> None:
    """Two embedded brokers behind one URL, the first address dead: the transport
    connects to the next, and when that one dies, goes round to the one after."""
    first, second = EmbeddedBroker().start(), EmbeddedBroker().start()
    dead = free_port()
    url = f"mqtt://127.0.0.1:{dead},127.0.0.1:{first.port},127.0.0.1:{second.port}"
    inbox = Inbox()
    settings = build(BrokerSettings, url=url, reconnect_max=0.5)
    t = Transport(settings, client_id="hopper", sink=inbox)
    t.subscribe("hop/#", 1)
    try:
        t.start(timeout=5)
        assert t.address == ("127.0.0.1", first.port)
        first.stop()
        assert wait_for(lambda: t.connected and t.address == ("127.0.0.1", second.port), 10)
        sender = Transport(BrokerSettings.of(second.url), client_id="sender", sink=Inbox())
        sender.start(timeout=5)
        sender.publish_and_wait("hop/1", b"after the move", qos=1)
        sender.stop()
        assert wait_for(lambda: inbox.on("hop/1"), 5)  # re-subscribed on the new node
    finally:
        t.stop()
        second.stop()


# --- what the LDM needs from NATS --------------------------------------------------------


def test_nats_keeps_what_the_ldm_needs_across_a_node_failure(cluster: NatsCluster) -> None:
    """Retained messages outlive the node they were published on; a client's last will
    is sent; a QoS 2 subscription is granted QoS 2 and gets QoS 2; '.' and ':' are fine
    inside a topic level; a client id with '.' is refused, with what to do."""
    on = [Inbox() for _ in range(3)]
    clients = []
    for node in range(3):
        t = Transport(cluster.settings("service", first=node), client_id=f"n{node}", sink=on[node])
        t.subscribe("ldm/svc/+/announce", 1)
        t.subscribe("ldm/svc/echo.v2:eu-1/in/+", 2)
        t.start(timeout=10)
        assert cluster.node_of(t) == node
        clients.append(t)
    assert wait_for(lambda: all(len(t.granted) == 2 for t in clients), 10)  # SUBACKs
    assert all(t.granted["ldm/svc/echo.v2:eu-1/in/+"] == 2 for t in clients)

    clients[0].publish_and_wait("ldm/svc/echo.v2:eu-1/announce", b"hello", qos=1, retain=True)
    clients[1].publish_and_wait("ldm/svc/echo.v2:eu-1/in/p.1", b"exactly once", qos=2)
    assert wait_for(lambda: all(i.on("ldm/svc/echo.v2:eu-1/in/p.1") for i in on), 10)
    assert [m.qos for m in on[2].on("ldm/svc/echo.v2:eu-1/in/p.1")] == [2]

    will = Will("ldm/svc/gone/announce", b"", qos=1, retain=True)
    doomed = Transport(
        cluster.settings("service", first=1), client_id="doomed", sink=Inbox(), will=will
    )
    doomed.start(timeout=10)
    doomed.kill()  # no DISCONNECT: node 1 publishes the will
    assert wait_for(lambda: on[2].on("ldm/svc/gone/announce"), 10)

    for t in clients:
        t.stop()
    cluster.kill(0)  # the node the retained message was published on
    kept = _read_retained(cluster, "ldm/svc/echo.v2:eu-1/announce", within=40)
    assert (kept.payload, kept.retain) == (b"hello", True)

    dotted = Transport(cluster.settings("service", first=1), client_id="car.17", sink=Inbox())
    with pytest.raises(ConnectError, match=r"client id 'car\.17'.*choose one without"):
        dotted.start(timeout=3)


def _read_retained(cluster: NatsCluster, topic: str, within: float) -> Message:
    """Subscribe afresh on the surviving nodes until the retained message comes. Right
    after a node failure a SUBSCRIBE can wait seconds while the survivors elect new
    JetStream leaders (docs/brokers.md); a new client each try gets the replay anew."""
    deadline = time.monotonic() + within
    attempt = 0
    while True:
        attempt += 1
        inbox = Inbox()
        settings = cluster.settings("service", first=1 + attempt % 2, persistent_session=False)
        reader = Transport(settings, client_id=f"late-{attempt}", sink=inbox)
        reader.subscribe(topic, 0)  # QoS 0: no JetStream consumer to place
        try:
            reader.start(timeout=5)
            if wait_for(lambda inbox=inbox: inbox.on(topic), 5):  # type: ignore[misc]
                return inbox.on(topic)[0]
        except ConnectError:
            pass
        finally:
            reader.stop()
        assert time.monotonic() < deadline, f"{topic}: no retained message within {within} s"


# --- the LDM on the cluster ----------------------------------------------------------------


@dataclass
class NatsDeployment:
    """Three LDM brokers as three accounts of one NATS cluster: user cluster,
    backbone, service cluster. ``first`` says which node each client tries first."""

    cluster: NatsCluster
    data_qos: int
    user_core: Core = field(init=False)
    service_core: Core = field(init=False)
    echo: EchoService = field(init=False)
    provider: Provider = field(init=False)
    participants: list[Participant] = field(default_factory=list)

    def __post_init__(self) -> None:
        c = self.cluster
        self.user_core = Core.create(
            "user-edge",
            c.settings("user", 1),
            c.settings("backbone", 2),
            data_qos=self.data_qos,
            **PATIENT,
        ).start(timeout=15)
        self.service_core = Core.create(
            "svc-cluster",
            c.settings("service", 2),
            c.settings("backbone", 0),
            data_qos=self.data_qos,
            **PATIENT,
        ).start(timeout=15)
        self.echo = EchoService()
        self.provider = Provider.create(
            c.settings("service", 0),
            ECHO,
            self.echo,
            announce_interval=1.0,
            max_age=PATIENT["max_age"],
        ).start(timeout=15)

    def participant(self, client_id: str, first: int, **settings: Any) -> Participant:
        # Patient by default: a participant whose node died may wait for JetStream's new
        # leaders (5-11 s) before it is connected again; with unreachable_after at its
        # default (1.5 s) its requests would fail meanwhile instead (ConnectError).
        settings.setdefault("unreachable_after", PATIENT["max_age"])
        p = Participant.create(
            self.cluster.settings("user", first),
            client_id=client_id,
            max_age=PATIENT["max_age"],
            **settings,
        ).start(timeout=15)
        self.participants.append(p)
        assert wait_for(has_service(p, "echo"), 15), "echo never listed"
        return p

    def close(self) -> None:
        for p in self.participants:
            p.stop()
        self.provider.stop()
        self.user_core.stop()
        self.service_core.stop()


def test_the_ldm_round_trip_runs_on_a_nats_cluster(cluster: NatsCluster) -> None:
    """participant -> user core -> backbone -> service core -> provider and back, each
    hop on its own account of the cluster, at QoS 2 (the provider's subscription)."""
    d = NatsDeployment(cluster, data_qos=2)
    try:
        session = d.participant("car-17", first=0).open("echo", timeout=10)
        assert session.request({"hello": "nats"}, timeout=10) == {"echo": {"hello": "nats"}}
        futures = [session.submit({"i": i}) for i in range(20)]
        assert [f.result(10) for f in futures] == [{"echo": {"i": i}} for i in range(20)]
        assert d.provider.transport.granted["ldm/svc/echo/in/+"] == 2
        assert d.user_core.stats.forwarded_in >= 21 and d.service_core.stats.forwarded_in >= 21
        assert d.echo.pseudonyms() and "car-17" not in str(d.echo.requests)
    finally:
        d.close()


@dataclass
class Sent:
    """One input: who sent it, its number, when, and when its answer came."""

    who: str
    i: int
    at: float
    future: Future[dict[str, Any]]
    answered: list[float] = field(default_factory=list)

    @classmethod
    def of(cls, who: str, i: int, session: Session) -> Sent:
        item = cls(who, i, time.monotonic(), session.submit({"who": who, "i": i}))
        item.future.add_done_callback(item._done)
        return item

    def _done(self, _future: Future[dict[str, Any]]) -> None:
        self.answered.append(time.monotonic())


def _moved_at(transport: Transport, cluster: NatsCluster) -> Future[float]:
    """When `transport` is connected to a node other than node 0 (a watching thread)."""
    when: Future[float] = Future()

    def watch() -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if transport.connected and cluster.node_of(transport) != 0:
                when.set_result(time.monotonic())
                return
            time.sleep(0.005)
        when.set_exception(TimeoutError(f"{transport.name} stayed away for 30 s"))

    threading.Thread(target=watch, daemon=True).start()
    return when


def _send_killing_node_0(
    cluster: NatsCluster,
    people: list[Participant],
    sessions: list[Session],
    seconds: float,
    on_kill: Callable[[], None] | None = None,
) -> tuple[list[Sent], float]:
    """Every participant sends 20 inputs/s for `seconds`; node 0 is killed 2 s in (then
    `on_kill` runs). Returns the inputs sent and the time of the kill."""
    sent: list[Sent] = []
    killed_at = 0.0
    start = time.monotonic()
    i = 0
    while time.monotonic() - start < seconds:
        for p, s in zip(people, sessions, strict=True):
            sent.append(Sent.of(p.client_id, i, s))
        i += 1
        if not killed_at and time.monotonic() - start > 2.0:
            cluster.kill(0)
            killed_at = time.monotonic()
            if on_kill is not None:
                on_kill()
        time.sleep(0.05)
    return sent, killed_at


def test_killing_a_node_while_qos1_traffic_flows(cluster: NatsCluster) -> None:
    """Three participants, one per node, send 20 inputs/s each at QoS 1; node 0 (one
    participant, the provider and the service core's backbone link) is killed 2 s in.
    Every input reaches the provider and every reply its participant, or the user core
    refuses it, with a notice, while it lost sight of the service; not settled: in a run
    where the provider's will withdrew it, a few may be lost (docs/brokers.md);
    the clients of node 0 continue on the others; a newcomer finds the retained list."""
    d = NatsDeployment(cluster, data_qos=1)
    try:
        people = [d.participant(f"car-{n}", first=n) for n in range(3)]
        sessions = [p.open("echo", timeout=10) for p in people]
        moved = {"participant": people[0].transport, "provider": d.provider.transport}
        back: dict[str, Future[float]] = {}

        def watch() -> None:
            back.update({name: _moved_at(t, cluster) for name, t in moved.items()})

        sent, killed_at = _send_killing_node_0(cluster, people, sessions, 6.0, watch)

        # Every input is answered (by the service, or by the user core's explicit
        # refusal while it saw the service withdrawn: see docs/brokers.md), or lost: a
        # lost one fails only by RequestTimeout, 2 x max_age + 1 = 41 s after it was
        # sent, so the wait outlasts that.
        assert wait_for(lambda: all(item.future.done() for item in sent), 60)
        answered = [x for x in sent if x.future.exception() is None]
        refused = [x for x in sent if x.future.exception() is not None]
        kinds = sorted({type(x.future.exception()).__name__ for x in refused})
        timeouts = [x for x in refused if isinstance(x.future.exception(), RequestTimeout)]
        withdrawn = [x for x in refused if isinstance(x.future.exception(), ServiceNotFound)]
        assert len(timeouts) + len(withdrawn) == len(refused), kinds
        # Not settled (docs/brokers.md, "Refusals, and lost inputs"): with the provider's
        # last will sent while it moved, some inputs are still lost (11 of 348 in one run
        # at load 8). Without that withdrawal none may be; with it, few.
        assert not timeouts or (withdrawn and len(timeouts) <= len(sent) // 20), (
            f"{len(timeouts)} of {len(sent)} inputs lost (timed out): {kinds}"
        )
        for item in answered:
            assert item.future.result() == {"echo": {"who": item.who, "i": item.i}}
        seen = {(r.payload["who"], r.payload["i"]) for r in d.echo.requests}
        assert {(x.who, x.i) for x in answered} <= seen
        assert len(refused) <= len(sent) // 4, kinds  # a refusal window, if any, is short
        # Each answer came within 2 x max_age of its input: every hop drops an input, and
        # then its reply, older than max_age. A later one could only be an input sent
        # again after its session was re-opened, which a lost input's timeout does (the
        # 41 s answer was one): so only in a run without losses.
        worst = max(item.answered[0] - item.at for item in answered)
        if not timeouts:
            assert worst <= 2 * PATIENT["max_age"], f"an input answered only after {worst:.1f} s"

        assert cluster.node_of(people[0].transport) != 0 and people[0].transport.connected
        assert cluster.node_of(d.provider.transport) != 0 and d.provider.transport.connected
        newcomer = Participant.create(cluster.settings("user", first=2), client_id="late-car")
        newcomer.start(timeout=15)
        d.participants.append(newcomer)
        # the retained list may wait for JetStream's new leaders and a repair (one run in
        # six after issue 25 needed more than 15 s; the cause is not yet known)
        assert wait_for(has_service(newcomer, "echo"), 40)

        reconnect = {name: f"{f.result(1) - killed_at:.2f} s" for name, f in back.items()}
        print(
            f"\nNATS failover: {len(sent)} inputs at QoS 1, node 0 killed; lost "
            f"{len(timeouts)}, refused by the user core {len(refused)} {kinds}; on another "
            f"node after {reconnect}; slowest reply {worst:.2f} s; duplicates dropped by the "
            f"provider {d.provider.stats.dropped_replay}, answered again "
            f"{d.provider.stats.answered_again}"
        )
        # How soon answers flow again is printed (the figures docs/brokers.md quotes) and
        # bounded only by 2 x max_age (above): the seconds of a leader election are
        # NATS's, and a loaded machine adds to them.
    finally:
        d.close()


def test_the_cluster_tells_an_operator_each_nodes_process_and_monitoring_port(
    cluster: NatsCluster,
) -> None:
    """What `ldm nats-cluster` prints per node: its process id and a monitoring URL that
    answers."""
    lines = cluster.describe()
    assert len(lines) == len(cluster.nodes)
    for node, line in zip(cluster.nodes, lines, strict=True):
        assert node.process is not None
        assert f"pid {node.process.pid}," in line
        url = f"http://127.0.0.1:{node.monitor_port}/healthz"
        assert url in line
        with urllib.request.urlopen(url, timeout=10) as reply:
            assert reply.status == 200


def test_with_its_quorum_lost_the_cluster_gives_a_clear_error_soon(
    cluster: NatsCluster,
) -> None:
    """Two of three nodes killed (JetStream has no quorum): a participant's request
    fails with an error that says what is wrong (after unreachable_after, 1.5 s; the
    printed figure), instead of nothing (before:
    no answer and no error for 2 x max_age + 1 s, 41 s with max_age 20)."""
    d = NatsDeployment(cluster, data_qos=1)
    try:
        p = d.participant("car-q", first=2, unreachable_after=1.5)
        session = p.open("echo", timeout=10)
        assert session.request({"before": 1}, timeout=10) == {"echo": {"before": 1}}
        cluster.kill(0)
        cluster.kill(1)
        lost = time.monotonic()
        sent: list[Sent] = []
        while time.monotonic() - lost < 3.0:
            sent.append(Sent.of("car-q", len(sent), session))
            time.sleep(0.1)
        assert wait_for(lambda: all(x.future.done() for x in sent), 10), "requests left waiting"
        errors = [x.future.exception() for x in sent]
        kinds = sorted({type(e).__name__ for e in errors})
        assert all(isinstance(e, ConnectError) for e in errors), kinds
        # Each failed by unreachable_after (1.5 s) of the loss, or of being sent after it:
        # the figure is printed (docs/brokers.md quotes it); the test requires that each
        # fails long before the 41 s a request waited in silence before, not that the
        # machine is quick (10 s: 1.5 s plus the participant's 0.25 s ticks, with room).
        waits = [x.answered[0] - max(x.at, lost) for x in sent]
        print(f"\nquorum lost: {len(sent)} requests, all {kinds}; longest wait {max(waits):.2f} s")
        print(f"  {errors[0]}")
        assert max(waits) <= 10.0, waits
    finally:
        d.close()


def test_killing_a_node_with_data_at_qos0_and_retries(cluster: NatsCluster) -> None:
    """As the QoS 1 test above, with data at QoS 0 and end-to-end retries (issue 25):
    each participant sends an unanswered input again after 0.5 s and fails a request
    at once when no node takes or acknowledges its messages for 1.5 s. Every input is
    answered or failed with an error (none is lost silently); prints how long after the
    kill answers flowed again for each participant."""
    d = NatsDeployment(cluster, data_qos=0)
    try:
        people = [
            d.participant(f"car-{n}", first=n, retry_after=0.5, unreachable_after=1.5)
            for n in range(3)
        ]
        sessions = [p.open("echo", timeout=10) for p in people]
        sent, killed_at = _send_killing_node_0(cluster, people, sessions, 8.0)
        assert wait_for(lambda: all(x.future.done() for x in sent), 45), "requests left waiting"
        kinds: dict[str, int] = {}
        for x in sent:
            error = x.future.exception()
            name = "answered" if error is None else type(error).__name__
            if isinstance(error, RequestRejected):
                name += f" ({error.reason})"
            kinds[name] = kinds.get(name, 0) + 1
        # After the kill: for each participant, the first input sent after which every
        # later input was answered; how long after the kill it was sent.
        back = {}
        for p in people:
            mine = [x for x in sent if x.who == p.client_id and x.at >= killed_at]
            ok = [x.future.exception() is None for x in mine]
            first = next((k for k in range(len(ok)) if all(ok[k:])), None)
            back[p.client_id] = "never" if first is None else f"{mine[first].at - killed_at:.2f} s"
        retries = sum(s.retries for s in sessions)
        print(
            f"\nNATS failover at QoS 0 with retries: {len(sent)} inputs {kinds}; answered "
            f"again for good after {back}; retries {retries}; answered again by the provider "
            f"{d.provider.stats.answered_again}"
        )
        slowest = max(x.answered[0] - x.at for x in sent if x.future.exception() is None)
        print(
            f"  slowest answer {slowest:.2f} s; inputs forwarded by the user core "
            f"{d.user_core.stats.forwarded_in}, taken by the provider "
            f"{d.provider.stats.requests}"
        )
        # Every input answered, or failed with an LdmError (none left waiting, no other
        # exception). A RequestTimeout is an input lost on the way: at QoS 0 that is not
        # yet excluded (docs/brokers.md): in one run at load 8 the provider's last will
        # withdrew it while it moved (36 refusals, ServiceNotFound) and 3 of 450 inputs
        # were lost. So losses are allowed only with such a withdrawal, and few.
        errors = [x.future.exception() for x in sent]
        assert all(e is None or isinstance(e, LdmError) for e in errors), kinds
        lost = sum(isinstance(e, RequestTimeout) for e in errors)
        withdrawn = any(isinstance(e, ServiceNotFound) for e in errors)
        assert lost == 0 or (withdrawn and lost <= len(sent) // 50), kinds
    finally:
        d.close()
