"""An open broker: what an attacker with full access to every broker,
and no private key, did to availability, each against real Mosquitto without ACL.

Each test stages one attack and asserts what it must not do: every honest participant
answered (at least 95 % of its requests, none taken for forged, no run of refused or
lost requests longer than 2 s: a lock-out), a forged list repaired after any burst, no
older key taken back. How many were answered within 2 s is printed: on a loaded machine
a late answer is the machine's, not the attack's. The toolkit and the
deployment are tests/ldm/hostile.py; the issue-11 attacks are tests/ldm/test_hostile.py.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from ldm import Participant
from ldm.local.brokers import wait_for
from ldm.local.pytest_plugin import need_mosquitto
from ldm.wire.messages import Announcement, SessionRequest

from .hostile import (
    PROBE,
    HostileDeployment,
    Load,
    Recorder,
    Repeater,
    Window,
    drive,
    forged_list,
    read_retained,
)

pytestmark = pytest.mark.mosquitto

DEADLINE = 2.0
"""The answer time the tests print the share of (and the single requests' timeout)."""

MIN_ANSWERED = 0.95
"""Every honest participant: at least 95 % of its requests answered, genuinely."""

LOCKOUT = 2.0
"""No honest participant's requests are refused or lost for longer than 2 s in a row."""

SETTLE = 15.0
"""How long the tests wait for the last requests' answers or errors at most (the
requests' own timeout is 2 x max_age + 1 s); they go on as soon as all have one."""

LIST_REPAIR = 15.0
"""A forged retained service list is the core's own again after any burst (before the
fix the last forgery of a burst stayed for good). About 0.2 s plus a tick, which the
test prints; it waits this long, generous for a loaded machine, as what it checks is
that the list is repaired."""

ATTACK_SECONDS = 3.0
"""How long each attack runs: longer than the participant's request timeout (2 x
max_age + 1 s = 5 s under FAST would be longer still; 3 s is six FAST rotations)."""


@pytest.fixture
def d() -> Iterator[HostileDeployment]:
    need_mosquitto()
    with HostileDeployment("open") as deployment:
        yield deployment


def assert_served(load: Load, window: Window) -> None:
    """The target of every phase: >= 95 % answered, no lock-out over 2 s (a run of
    requests refused, lost or forged), nothing forged; the share answered within 2 s
    is printed."""
    load.settle(SETTLE)
    ever = float("inf")  # answered at all: a late answer is the machine's load
    fraction = load.answered_fraction(window, ever)
    assert fraction >= MIN_ANSWERED, load.summary(window, ever)
    outage = load.longest_outage(window, ever)
    assert outage <= LOCKOUT, f"locked out {outage:.2f} s: {load.summary(window, ever)}"
    assert load.forged() == [], load.summary()
    print(f"\n{load.summary(window, DEADLINE)} (answered: within {DEADLINE:g} s)")


def test_forged_session_requests_lock_no_one_out(d: HostileDeployment) -> None:
    """A well-formed session request with the attacker's key on alice's topic every
    0.5 s: before the fix each replaced her session's secret, her tagged input was
    dropped as unauthentic until her request timed out (22-26 % answered)."""
    alice = d.participant("alice")
    d.wait_listed(alice)
    load = Load(alice.open("echo"), "alice")
    drive([load], 0.3)

    def forge() -> None:
        keys = d.attacker.keys
        request = SessionRequest(c=f"x{time.monotonic_ns()}", service="echo", t=time.time())
        request = request.model_copy(update={"k": keys.public})
        d.attacker.publish("ldm/p/alice/up/session", request.model_dump_json().encode())

    forger = Repeater(0.5, forge).start()
    try:
        window = drive([load], ATTACK_SECONDS, interval=0.1)
    finally:
        forger.stop()
    assert forger.runs >= 5
    assert_served(load, window)
    assert d.user_core.stats.dropped_unauthentic == 0, "alice's own input was taken for forged"


def test_a_replayed_genuine_announcement_diverts_nothing(d: HostileDeployment) -> None:
    """The provider's genuine announcement (from the service broker) and its backbone
    copy, replayed retained on the user broker's announce topic every 0.2 s: before the
    fix the user core took echo for a local service and sent every input to a topic no
    one serves. The cores keep echo where it is, and alice is served."""
    alice = d.participant("alice")
    d.wait_listed(alice)
    load = Load(alice.open("echo"), "alice")
    drive([load], 0.3)
    service = d.account(d.service, PROBE)
    backbone = d.account(d.backbone, PROBE)

    def replay() -> None:
        for settings, topic in (
            (service, "ldm/svc/echo/announce"),
            (backbone, "ldm/bb/announce/echo"),
        ):
            payload = read_retained(settings, topic, 0.1)
            if payload:
                d.attacker.publish("ldm/svc/echo/announce", payload, retain=True)

    replayer = Repeater(0.2, replay).start()
    try:
        window = drive([load], ATTACK_SECONDS, interval=0.1)
    finally:
        replayer.stop()
    assert replayer.runs >= 3
    origins = {(s.name, e.origin) for s in [d.user_core] for e in s.catalog.entries()}
    assert origins == {("user-edge", "svc-cluster")}, origins
    assert_served(load, window)
    cleared = [m for m in d.backbone_witness.messages("ldm/bb/announce/echo") if not m.payload]
    assert cleared == [], "the service's backbone announcement was cleared"
    payload = read_retained(backbone, "ldm/bb/announce/echo")
    assert payload and Announcement.model_validate_json(payload).origin == "svc-cluster"


def test_an_older_announcement_never_comes_back() -> None:
    """The provider restarts with a new key; its old (genuine, fresh) announcements are
    then replayed on the service broker and the backbone: before the fix the cores put
    the old key back and a new participant was granted it (its first request timed
    out). The cores keep the newer key, and a participant that arrives is served.
    ``service_ttl`` is the default 30 s here, so the old announcement is still fresh."""
    need_mosquitto()
    with HostileDeployment("open", core={"service_ttl": 30.0}) as d:
        _older_announcement(d)


def _older_announcement(d: HostileDeployment) -> None:
    old_local = read_retained(d.account(d.service, PROBE), "ldm/svc/echo/announce")
    old_backbone = read_retained(d.account(d.backbone, PROBE), "ldm/bb/announce/echo")
    assert old_local and old_backbone
    old_key = Announcement.model_validate_json(old_local).service.public_key
    cores = (d.user_core, d.service_core)
    replayers = [
        Recorder(d.account(broker, PROBE), f"replayer-{i}", filters=()).start()
        for i, broker in enumerate((d.service, d.backbone))
    ]

    def replay_and_watch(seconds: float) -> list[str]:
        """Replay both old announcements every 0.1 s; the cores that took the old key."""
        took: list[str] = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            replayers[0].transport.publish("ldm/svc/echo/announce", old_local, qos=1, retain=True)
            replayers[1].transport.publish("ldm/bb/announce/echo", old_backbone, qos=1, retain=True)
            for _ in range(5):
                time.sleep(0.02)
                took += [c.name for c in cores if old_key in [s.public_key for s in c.services]]
        return took

    try:
        d.provider.kill()  # dies: its last will withdraws the old key
        assert wait_for(lambda: all(c.services == [] for c in cores), 5), "never withdrawn"
        took = replay_and_watch(1.0)
        assert took == [], f"the dead provider's key came back at {sorted(set(took))}"
        d.restart_provider()
        new_key = d.provider.description.public_key
        assert wait_for(
            lambda: all([s.public_key for s in c.services] == [new_key] for c in cores), 5
        ), "the restarted provider was never taken"
        took = replay_and_watch(1.0)
        assert took == [], f"the old key replaced the new one at {sorted(set(took))}"
        carol = d.participant("carol")
        assert wait_for(lambda: d.listed(carol), 5)
        session = carol.open("echo")
        assert session.service.public_key == new_key
        answer = session.request({"hello": "carol"}, timeout=DEADLINE)
        assert answer == {"echo": {"hello": "carol"}}
    finally:
        for r in replayers:
            r.stop()


def test_a_burst_of_forged_lists_is_repaired(d: HostileDeployment) -> None:
    """20 forged lists at 100/s, retained: before the fix the core repaired 5 a second
    and never came back to the ones it skipped, so the last forgery stayed. The core's
    list is retained again after the burst (how soon is printed), and a new participant
    finds echo."""
    alice = d.participant("alice")
    d.wait_listed(alice)
    for _ in range(2):  # twice: a second burst right after the first repair
        for _ in range(20):
            d.attacker.publish("ldm/services", forged_list(d.attacker, []), retain=True)
            time.sleep(0.01)
        ended = time.monotonic()
        d.attacker.fence(d.witness)
        assert wait_for(d.list_is_genuine, LIST_REPAIR), "the forged list stayed"
        print(f"\nlist repaired {time.monotonic() - ended:.2f} s after the burst")
    carol = Participant.create(d.account(d.user, "carol"), client_id="carol").start(timeout=5)
    try:
        assert wait_for(lambda: d.listed(carol), LIST_REPAIR), "carol could not find echo"
    finally:
        carol.stop()


def test_a_forged_list_is_not_parsed_before_its_signature(d: HostileDeployment) -> None:
    """A pinned participant drops an oversized list, and a list not signed by its core,
    before it validates it: both are counted as ignored and echo stays listed."""
    alice = d.participant("alice")
    d.wait_listed(alice)
    before = alice.ignored
    real = d.real()
    big = forged_list(d.attacker, [real] * 3000)  # about 1.5 MB
    assert len(big) > 1_000_000
    invalid = b'{"t": 1, "services": [{"name": 5}], "sig": "AAAA"}'  # unsigned, invalid
    for payload in (big, invalid):
        d.attacker.publish("ldm/services", payload, retain=True)
    assert wait_for(lambda: alice.ignored >= before + 2, 3), alice.ignored - before
    assert d.listed(alice)


def test_retained_junk_is_cleared_as_it_arrives() -> None:
    """A participant publishes 300 retained 32 KiB messages on topics of its own that
    are no LDM topic: the core clears each as it arrives, not at a sweep (none comes
    here: retain_sweep is an hour), so a fresh subscriber finds none of them.

    A live subscriber sees each junk message (the positive control: it reached the
    broker; QoS 1, so none is dropped on the way); a fresh subscriber's look ends at a
    message published after it subscribed, which the broker delivers after anything
    retained, and is repeated until it finds no junk (the clearing's time is not
    bounded here; nothing but the core clears them)."""
    need_mosquitto()
    junk_topics = "ldm/p/mallory/up/junk/#"
    junk = b"j" * 32 * 1024
    with HostileDeployment("open", core={"retain_sweep": 3600.0}) as d:
        live = Recorder(d.account(d.user, PROBE), "junk-live", filters=(junk_topics,))
        live.start()
        try:
            assert wait_for(lambda: junk_topics in live.transport.granted, 10)  # subscribed
            for i in range(300):
                d.attacker.publish(f"ldm/p/mallory/up/junk/{i}", junk, retain=True, qos=1)

            def seen() -> int:
                return len({m.topic for m in live.messages(junk_topics) if m.payload == junk})

            assert wait_for(lambda: seen() == 300, 30), seen()
        finally:
            live.stop()

        def retained_junk() -> list[str]:
            fresh = Recorder(
                d.account(d.user, PROBE),
                f"junk-probe-{time.monotonic_ns()}",
                filters=(junk_topics,),
            )
            fresh.start()
            try:
                assert wait_for(lambda: junk_topics in fresh.transport.granted, 10)
                d.attacker.publish("ldm/p/mallory/up/junk/fence", b"fence", qos=1)
                assert wait_for(lambda: fresh.messages(junk_topics), 10), "no fence"
                return [m.topic for m in fresh.messages(junk_topics) if m.payload == junk]
            finally:
                fresh.stop()

        found = retained_junk()
        deadline = time.monotonic() + 30
        while found and time.monotonic() < deadline:
            found = retained_junk()
        assert found == [], f"{len(found)} junk messages still retained"


def test_an_older_grant_never_replaces_a_newer_key(d: HostileDeployment) -> None:
    """`Session.regrant` with a description older (``issued``) than the session's: the
    session keeps its newer key (before the fix it went back)."""
    alice = d.participant("alice")
    d.wait_listed(alice)
    session = alice.open("echo")
    newer = session.grant
    older = newer.model_copy(
        update={
            "service": newer.service.model_copy(
                update={"issued": newer.service.issued - 10, "public_key": d.attacker.keys.public}
            )
        }
    )
    session.regrant(older, None)
    assert session.service.public_key == newer.service.public_key
    assert session.request({"still": "here"}, timeout=DEADLINE) == {"echo": {"still": "here"}}


def test_a_regrant_soon_after_a_rotation_is_not_refused() -> None:
    """The participant rotates, sends its first input under the new key 0.8 s later,
    and its session is granted again 0.3 s after that: before the fix it counted
    rekey_interval (1 s) from the rotation, made a new key at the regrant, and the
    core, counting from that first input, refused it (``rate_limited``)."""
    need_mosquitto()
    with HostileDeployment("open", core={"rotation_period": 4.0}) as d:
        alice = d.participant("alice")
        d.wait_listed(alice)
        session = alice.open("echo")
        assert session.grant.rekey_interval == 1.0
        answers = [session.request({"i": 0}, timeout=DEADLINE)]
        time.sleep(1.4)
        assert session.rotate(time.time())
        time.sleep(0.8)
        answers.append(session.request({"i": 1}, timeout=DEADLINE))  # the new key's first
        time.sleep(0.3)
        before = session.grant.session
        alice.reopen(session)
        assert wait_for(lambda: session.grant.session != before, 2), "no regrant"
        answers += [session.request({"i": i}, timeout=DEADLINE) for i in range(2, 6)]
        assert answers == [{"echo": {"i": i}} for i in range(6)]
        assert d.user_core.stats.rejected_rekey == 0
