"""Hardening of LaaS on the LDM: faults, access control, overload, bounded memory.

The integration tests run against real Mosquitto processes on free ports, with the LaaS
worker as the service; the memory tests drive the decoders in-process.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from laas.map.hdmap import HdMap
from laas.models import ErrorReply, read_reply
from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate
from laas.worker.service import LaasService, start_worker
from ldm import (
    Core,
    KeyPair,
    LdmError,
    Participant,
    Provider,
    Request,
    RequestRejected,
    ServiceSpec,
    Session,
)
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, free_port, wait_for
from ldm.local.pytest_plugin import need_mosquitto
from ldm.security.crypto import aad
from ldm.transport import Event, Message, Transport
from ldm.wire.messages import (
    Announcement,
    Envelope,
    ServiceDescription,
    ServiceList,
    ServicesRequest,
    SessionRequest,
)

from .helpers import Clock
from .ldm.deployment import ECHO, EchoService, has_service
from .ldm.test_tls import make_certificates

ROOT = Path(__file__).resolve().parent.parent
SECURITY = ROOT / "deploy" / "security"
CORE: dict[str, float] = {
    "rotation_period": 60.0,
    "grace": 1.0,
    "idle_timeout": 3.0,
    "service_ttl": 3.0,
}
# The fault test's hops keep input this long (not the default 2 s): a broker restart on
# a busy machine must not turn a queued input into a stale one, so each can be required
# to arrive.
PATIENT_AGE = 20.0


@pytest.fixture(scope="module")
def fixes(hamburg_map: HdMap) -> dict[str, list[dict[str, Any]]]:
    """The Hamburg scenario's fixes per user, positions only (stamped when sent)."""
    trace = simulate(hamburg_map, hamburg_scenario(), ErrorModel(), 0)
    out: dict[str, list[dict[str, Any]]] = {}
    for f in trace.fixes:
        out.setdefault(f.user, []).append(f.measurement.model_dump())
    return out


@dataclass
class Road:
    """One participant driving its scenario fixes, stamped with the wall clock."""

    session: Session
    fixes: list[dict[str, Any]]
    i: int = 0
    last_ms: int = 0

    def next_fix(self) -> dict[str, Any]:
        fix = dict(self.fixes[self.i % len(self.fixes)])
        self.i += 1
        self.last_ms = max(self.last_ms + 1, int(time.time() * 1000))
        fix["timestamp"] = self.last_ms
        return fix

    def submit(self) -> Future[dict[str, Any]]:
        return self.session.submit(self.next_fix())

    def answered_again(self, within: float = 15.0) -> float:
        """Send fixes until one is answered with a position; how long that took."""
        start = time.monotonic()
        while True:
            try:
                reply = self.session.request(self.next_fix(), timeout=1.0)
                assert "error" not in reply, reply
                assert reply["segment"] is not None or reply["accuracy"] > 0
                return time.monotonic() - start
            except LdmError:
                if time.monotonic() - start > within:
                    raise
                time.sleep(0.05)


def restart(broker: MosquittoBroker, down: float = 0.5) -> None:
    broker.stop()
    time.sleep(down)
    broker.start()


# --- faults -------------------------------------------------------------------------


@dataclass
class LaasDeployment:
    user: MosquittoBroker
    backbone: MosquittoBroker
    service: MosquittoBroker
    hdmap: HdMap
    user_core: Core | None = None
    service_core: Core | None = None
    worker: Provider | None = None
    participants: list[Participant] = field(default_factory=list)

    def start_worker(self) -> Provider:
        self.worker, _ = start_worker(self.service.url, self.hdmap, data_qos=1, max_age=PATIENT_AGE)
        return self.worker

    def start_user_core(self) -> Core:
        self.user_core = Core.create(
            "user", self.user.url, self.backbone.url, data_qos=1, max_age=PATIENT_AGE, **CORE
        ).start(timeout=5)
        return self.user_core

    def close(self) -> None:
        for p in self.participants:
            p.stop()
        for part in (self.worker, self.user_core, self.service_core):
            if part is not None:
                part.stop()
        for broker in (self.user, self.backbone, self.service):
            broker.stop()


@pytest.fixture
def laas(hamburg_map: HdMap) -> Iterator[LaasDeployment]:
    need_mosquitto()
    d = LaasDeployment(
        MosquittoBroker().start(),
        MosquittoBroker().start(),
        MosquittoBroker().start(),
        hamburg_map,
    )
    try:
        d.service_core = Core.create(
            "service", d.service.url, d.backbone.url, data_qos=1, max_age=PATIENT_AGE, **CORE
        ).start(timeout=5)
        d.start_user_core()
        d.start_worker()
        yield d
    finally:
        d.close()


def settle(futures: list[Future[dict[str, Any]]], within: float) -> list[dict[str, Any] | LdmError]:
    """Wait for every future: its reply or its LdmError, in order; a future still
    pending, or failing with anything else, fails the test."""
    outcomes: list[dict[str, Any] | LdmError] = []
    deadline = time.monotonic() + within
    for f in futures:
        try:
            outcomes.append(f.result(max(0.0, deadline - time.monotonic())))
        except LdmError as exc:
            outcomes.append(exc)
    return outcomes


@pytest.mark.mosquitto
def test_laas_survives_broker_worker_and_core_restarts(
    laas: LaasDeployment, fixes: dict[str, list[dict[str, Any]]]
) -> None:
    d = laas
    roads = []
    for user in ("car", "cyclist-1"):
        p = Participant.create(
            d.user.url,
            client_id=f"{user}-faults",
            data_qos=1,
            max_age=PATIENT_AGE,
            retry_after=0.5,
        ).start(timeout=5)
        d.participants.append(p)
        assert wait_for(has_service(p, "laas"), 10)
        roads.append(Road(p.open("laas"), fixes[user]))
    for road in roads:
        road.answered_again(within=5)

    # The user broker dies mid-stream: QoS 1 input sent meanwhile is held by the
    # participant's transport and sent after the reconnect; what the restarted broker
    # dropped (no subscriber yet: Mosquitto keeps no state here) is sent again by the
    # participant's retries (retry_after 0.5 s) while younger than max_age (20 s on every
    # hop), and the worker answers a retried input with the reply it made. So every one
    # of the 20 reaches the worker and is answered: its own corrected position, or, for a
    # fix that came after a later one of its user, the worker's "stale" error naming it.
    sent: list[tuple[int, Future[dict[str, Any]]]] = []  # (the fix's timestamp, its future)

    def submit_five_each() -> None:
        for road in roads:
            for _ in range(5):
                future = road.submit()
                sent.append((road.last_ms, future))

    submit_five_each()
    d.user.stop()
    submit_five_each()
    time.sleep(0.5)
    d.user.start()
    outcomes = settle([f for _, f in sent], within=60)
    positions = 0
    for (stamp, _), outcome in zip(sent, outcomes, strict=True):
        assert not isinstance(outcome, LdmError), repr(outcome)  # none lost, none failed
        reply = read_reply(outcome)
        if isinstance(reply, ErrorReply):
            assert reply.error.kind == "stale", outcome
            assert str(stamp) in reply.error.message, outcome
        else:
            assert reply.timestamp == stamp, outcome
            positions += 1
    assert positions >= 2, outcomes  # at least each user's newest fix is a position
    for road in roads:
        road.answered_again()
    assert wait_for(has_service(d.participants[0], "laas"), 5)  # the list came back

    for broker in (d.service, d.backbone):  # the cores and the worker reconnect
        restart(broker)
        for road in roads:
            road.answered_again()

    # The worker is killed (its last will withdraws it) and a new one starts, with a
    # new key: participants re-open their sessions by themselves.
    assert d.worker is not None
    d.worker.kill()
    assert wait_for(lambda: not has_service(d.participants[0], "laas")(), 5)
    d.start_worker()
    for road in roads:
        assert road.answered_again() < 10

    # The user core crashes; a new one knows no session, and participants re-request.
    assert d.user_core is not None
    d.user_core.stop_dispatch()
    d.user_core.cluster.kill()
    assert d.user_core.backbone is not None
    d.user_core.backbone.kill()
    new_core = d.start_user_core()
    for road in roads:
        road.answered_again()
    assert new_core.session_count == 2


# --- access control and TLS ---------------------------------------------------------


def password_file(directory: Path, *users: str) -> tuple[Path, dict[str, str]]:
    """Run deploy/security/make-passwd.sh as documented; return the file and passwords."""
    path = directory / "passwd"
    out = subprocess.run(
        ["bash", str(SECURITY / "make-passwd.sh"), str(path), *users],
        check=True,
        capture_output=True,
        text=True,
        env={"PATH": "/usr/bin:/bin:/usr/sbin", "MODE": "0644"},
    ).stdout
    passwords = dict(line.split("=", 1) for line in out.splitlines())
    assert set(passwords) == set(users)
    text = path.read_text()
    entries = dict(line.split(":", 1) for line in text.splitlines())
    assert set(entries) == set(users)  # one line per user, USER:HASH
    assert all(h.startswith("$") for h in entries.values())  # a hash, never the password
    assert all(pw not in text for pw in passwords.values())
    return path, passwords


@dataclass
class Spy:
    """A hostile client's inbox."""

    events: list[Event] = field(default_factory=list)

    def messages(self) -> list[Message]:
        return [e for e in list(self.events) if isinstance(e, Message)]


@pytest.mark.mosquitto
def test_a_hostile_participant_gets_nothing_over_tls_with_passwords(
    hamburg_map: HdMap, fixes: dict[str, list[dict[str, Any]]]
) -> None:
    need_mosquitto()
    tls_port = free_port()
    broker = MosquittoBroker(allow_anonymous=False, acl=(SECURITY / "acl-user-cluster").read_text())
    ca, cert, key = make_certificates(broker.directory)
    service_acl = (SECURITY / "acl-service-cluster").read_text()
    (broker.directory / "acl").write_text((broker.directory / "acl").read_text() + service_acl)
    passwd, passwords = password_file(
        broker.directory, "ldm-core-user", "laas-worker", "alice", "bob", "mallory"
    )
    broker.config_file.write_text(
        broker.config_file.read_text()
        + f"password_file {passwd}\nuse_username_as_clientid true\n"
        + f"listener {tls_port} 127.0.0.1\ncafile {ca}\ncertfile {cert}\nkeyfile {key}\n"
        + "use_username_as_clientid true\n"  # a per-listener setting: repeat it for each
    )
    url = f"mqtts://127.0.0.1:{tls_port}"

    def account(user: str, password: str | None = None) -> BrokerSettings:
        pw = passwords[user] if password is None else password
        return BrokerSettings(url=url, ca_file=ca, username=user, password=pw)

    with broker:
        # Anonymous and wrong-password clients are refused.
        for settings in (BrokerSettings(url=url, ca_file=ca), account("alice", "wrong")):
            with pytest.raises(LdmError):
                Transport(settings, client_id="x", sink=lambda e: None).start(timeout=1.5)

        core = Core.create("single", account("ldm-core-user"), None, **CORE).start(timeout=5)
        worker, service = start_worker(account("laas-worker"), hamburg_map)
        parts: list[Participant] = []
        spy = Spy()
        mallory = Transport(account("mallory"), client_id="alice", sink=spy.events.append)
        try:
            for user in ("alice", "bob"):
                parts.append(Participant.create(account(user)).start(timeout=5))
            assert [p.client_id for p in parts] == ["alice", "bob"]
            assert wait_for(has_service(parts[0], "laas"), 10)
            roads = [
                Road(p.open("laas"), fixes[u])
                for p, u in zip(parts, ("car", "cyclist-1"), strict=True)
            ]
            for road in roads:
                road.answered_again(within=5)

            # mallory asks for alice's client id, then for everything it should not see.
            for flt in ("#", "ldm/p/alice/#", "ldm/p/+/down/#", "$SYS/#", "ldm/svc/#"):
                mallory.subscribe(flt, 1)
            mallory.start(timeout=5)
            # Its own service list (it may read no other) comes once the subscriptions
            # are in place.
            asked = ServicesRequest(t=time.time()).model_dump_json().encode()
            mallory.publish("ldm/p/mallory/up/services", asked, 1)
            assert wait_for(
                lambda: any(m.topic == "ldm/p/mallory/down/services" for m in spy.messages()), 5
            )
            # ... and writes where it must not: alice's input, a forged service
            # announcement with its own key, a forged service list.
            fake = ServiceDescription(
                **ECHO.model_dump(exclude={"name"}), name="laas", public_key=KeyPair().public
            )
            forged = Announcement(service=fake, t=time.time()).model_dump_json().encode()
            mallory.publish("ldm/svc/laas/announce", forged, 1, retain=True)
            mallory.publish(
                "ldm/services",
                ServiceList(t=time.time(), services=[fake]).model_dump_json().encode(),
                1,
                retain=True,
            )
            k, t = KeyPair(), time.time()
            cipher = k.cipher(roads[0].session.service.public_key, initiator=True)
            env = Envelope(c="m1", t=t, k=k.public, d=cipher.seal(b"{}", aad("m1", t)))
            forwarded = core.stats.forwarded_in
            mallory.publish("ldm/p/alice/up/data/laas", env.encode(), 1)
            # Then a request on mallory's own topic, on the same connection: once the
            # core has answered it, the forged input had its turn (MQTT keeps the order).
            own = SessionRequest(c="m2", service="laas", t=time.time()).model_dump_json()
            mallory.publish("ldm/p/mallory/up/session", own.encode(), 1)
            requests_before = worker.stats.requests

            for _ in range(5):
                for road in roads:
                    road.answered_again(within=5)
            assert wait_for(
                lambda: any(m.topic == "ldm/p/mallory/down/session" for m in spy.messages()), 5
            )
            assert core.stats.forwarded_in == forwarded + 10, "mallory wrote as alice"
            assert worker.stats.requests == requests_before + 10
            assert [p.transport.disconnects for p in parts] == [0, 0], "client id taken over"
            seen = {m.topic for m in spy.messages()}
            assert seen == {t for t in seen if t.startswith("ldm/p/mallory/")}, seen
            real = worker.key.public
            assert [s.public_key for s in core.services] == [real], "forged announcement used"
            assert all(s.public_key == real for p in parts for s in p.services())
            assert service.stats.answered >= 12
        finally:
            mallory.stop()
            for p in parts:
                p.stop()
            worker.stop()
            core.stop()


# --- overload -----------------------------------------------------------------------


@pytest.mark.mosquitto
def test_a_flooding_participant_is_rate_limited_without_slowing_others() -> None:
    need_mosquitto()
    with MosquittoBroker() as broker:
        core = Core.create("edge", broker.url, None, rate=20.0, burst=20.0, **CORE).start(timeout=5)
        echo = EchoService()
        provider = Provider.create(broker.url, ECHO, echo, announce_interval=0.5).start(timeout=5)
        flooder = Participant.create(broker.url, client_id="flooder").start(timeout=5)
        calm = Participant.create(broker.url, client_id="calm").start(timeout=5)
        try:
            assert wait_for(has_service(calm, "echo"), 5)
            flood, quiet = flooder.open("echo"), calm.open("echo")
            futures = [flood.submit({"i": i}) for i in range(400)]
            # The calm participant, during the flood: every request answered, none
            # refused for the flooder's rate. How much the flood delays others is the
            # figure of `ldm bench flood` (docs/security.md); a
            # wall-clock bound here measured the machine.
            for i in range(20):
                assert quiet.request({"calm": i}, timeout=10.0) == {"echo": {"calm": i}}
                time.sleep(0.05)
            outcomes = settle(futures, within=10)
            answered = sum(isinstance(o, dict) for o in outcomes)
            errors = [str(o) for o in outcomes if isinstance(o, LdmError)]
            rejected = [e for e in errors if "rate" in e or "second" in e]
            assert answered < 200 and rejected, (answered, errors[:3])
            assert core.stats.rejected_rate >= 400 - answered - 5
            with pytest.raises(RequestRejected) as info:
                for i in range(100):
                    flood.request({"again": i}, timeout=2.0)
            assert info.value.reason == "rate_limited"
        finally:
            flooder.stop()
            calm.stop()
            provider.stop()
            core.stop()


def test_the_provider_sheds_load_past_its_queue_and_counts_it() -> None:
    provider = Provider.create("mqtt://127.0.0.1:9", ECHO, EchoService(), max_queue=50)
    try:
        for i in range(1_000):  # the dispatch thread is not running: nothing drains
            provider.sink(Message(f"ldm/svc/echo/in/p{i}", b"{}", 0, False, "svc"))
        assert provider.stats.dropped_overload == 950
        assert provider._queue.qsize() == 50
    finally:
        provider.transport.stop()


# --- bounded memory with many idle pseudonyms ---------------------------------------


IDLE = 1_000  # pseudonyms: enough to show that memory does not grow with them


def test_a_thousand_idle_pseudonyms_are_forgotten(hamburg_map: HdMap) -> None:
    wall, tick = Clock(1_700_000_000.0), Clock(0.0)
    service = LaasService(hamburg_map, wall_clock=wall, clock=tick)
    base = {
        "latitude": 53.55876,
        "longitude": 9.97610,
        "altitude": 10.0,
        "heading": 30.8,
        "speed": 5.4,
    }
    for i in range(IDLE):
        fix = {**base, "timestamp": int(wall.now * 1000)}
        assert "error" not in service.handle(Request(f"p{i}", "c", fix, wall.now, True))
        if i % 20 == 19:  # a new group on the segment every 4 s (group_timeout 3 s)
            wall.now += 4.0
    assert service.sessions == IDLE
    assert service.engine.users == IDLE  # no expiry yet: the pacing clock stood still
    wall.now += 60.0
    tick.now += 60.0
    fix = {**base, "timestamp": int(wall.now * 1000)}
    assert "error" not in service.handle(Request("last", "c", fix, wall.now, True))
    assert service.engine.users == 1 and service.sessions == 1
    assert service.engine.stats.expired == IDLE


def test_core_sessions_and_provider_ciphers_stay_bounded() -> None:
    spec = ServiceSpec(name="echo")
    key = KeyPair()
    provider = Provider.create("mqtt://127.0.0.1:9", spec, EchoService(), key=key, cipher_cache=100)
    core = Core.create(
        "edge", "mqtt://127.0.0.1:9", idle_timeout=1.0, rate=1e9, burst=1e9, service_ttl=600
    )
    try:
        description = ServiceDescription(**spec.model_dump(), public_key=key.public)
        ann = Announcement(service=description, t=time.time()).model_dump_json().encode()
        core.handle(Message("ldm/svc/echo/announce", ann, 1, False, "cluster"))
        for i in range(10_000):
            req = f'{{"c":"c{i}","service":"echo","t":{time.time()}}}'.encode()
            core.handle(Message(f"ldm/p/p{i}/up/session", req, 1, False, "cluster"))
            env = Envelope(
                c=f"c{i}", t=time.time(), k=KeyPair().public if i < 300 else key.public, d="AAAA"
            )
            core.handle(Message(f"ldm/p/p{i}/up/data/echo", env.encode(), 1, False, "cluster"))
        assert core.session_count == 10_000 and core.pseudonym_count == 10_000
        core.tick(time.time() + 5.0)
        assert core.session_count == 0 and not core.pseudonym_count and not core.admission.clients

        for i in range(300):  # 300 participants' ephemeral keys, cache of 100
            k = KeyPair()
            t = time.time()
            sealed = k.cipher(key.public, initiator=True).seal(b"{}", aad("c", t))
            env = Envelope(c="c", t=t, k=k.public, d=sealed)
            provider.handle(Message(f"ldm/svc/echo/in/p{i}", env.encode(), 0, False, "svc"))
        assert provider.stats.requests == 300
        assert provider.cached_ciphers == 100 and len(provider._by_pseudonym) == 100
    finally:
        core.cluster.stop()
        provider.transport.stop()
