"""Signed identities: what a participant trusts, and what a core takes, on a real broker."""

from __future__ import annotations

import stat
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from ldm import ConfigError, Core, KeyPair, Participant, SigningKey, Trust, TrustError
from ldm.cli import main as ldm_main
from ldm.config import BrokerSettings
from ldm.local.brokers import RunningBroker, wait_for
from ldm.security.identity import endorse
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire.messages import Announcement, ServiceDescription, ServiceList, SessionNotice

from .deployment import EchoService, echo_provider, has_service


def _described(identity: SigningKey, name: str = "echo") -> ServiceDescription:
    unsigned = ServiceDescription(
        name=name, public_key=KeyPair().public, identity=identity.public, issued=time.time()
    )
    return unsigned.model_copy(update={"signature": identity.sign(unsigned.signed_text())})


def test_a_description_is_trusted_only_as_signed_and_pinned_or_endorsed() -> None:
    service, other, anchor = SigningKey(), SigningKey(), SigningKey()
    desc = _described(service)
    assert Trust({"echo": service.public}).trusts(desc)
    assert Trust().trusts(desc) and Trust().open  # nothing pinned: the old behaviour
    # A changed session key (what a core would substitute) breaks the signature.
    swapped = desc.model_copy(update={"public_key": KeyPair().public})
    assert "not signed" in (Trust({"echo": service.public}).problem(swapped) or "")
    # Signed, but by an identity pinned for nothing or for another service.
    assert "neither pinned" in (Trust({"echo": other.public}).problem(desc) or "")
    # An anchor's endorsement is for one service name and one identity.
    endorsed = desc.model_copy(update={"endorsement": endorse(anchor, "echo", service.public)})
    assert Trust(anchors=[anchor.public]).trusts(endorsed)
    wrong_name = desc.model_copy(update={"endorsement": endorse(anchor, "other", service.public)})
    assert not Trust(anchors=[anchor.public]).trusts(wrong_name)
    assert not Trust(anchors=[other.public]).trusts(endorsed)
    # An announcement's time is signed too.
    ann = Announcement(service=desc, t=time.time())
    signed = ann.model_copy(update={"sig": service.sign(ann.signed_text())})
    assert Trust({"echo": service.public}).announcement(signed)
    later = signed.model_copy(update={"t": signed.t + 3600})
    assert not Trust({"echo": service.public}).announcement(later)


def test_a_key_file_round_trips_and_bad_files_are_named(tmp_path: Path) -> None:
    key = SigningKey()
    path = tmp_path / "laas.key"
    key.save(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert SigningKey.load(path).public == key.public
    assert SigningKey.load_or_create(tmp_path / "new.key").public != key.public
    assert (tmp_path / "new.key").exists()
    (tmp_path / "bad.key").write_text("not a key")
    with pytest.raises(ConfigError, match=r"bad\.key: not an unencrypted PEM"):
        SigningKey.load(tmp_path / "bad.key")
    with pytest.raises(ConfigError, match="cannot read it"):
        SigningKey.load(tmp_path / "missing.key")


def test_ldm_keys_makes_shows_and_endorses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, anchor = tmp_path / "svc.key", tmp_path / "anchor.key"
    assert ldm_main(["keys", "new", str(path)]) == 0
    public = capsys.readouterr().out.strip()
    assert len(public) == 44  # the public key and nothing else: no private key on stdout
    assert ldm_main(["keys", "new", str(path)]) == 2  # never overwrites a key
    assert "exists" in capsys.readouterr().err
    assert ldm_main(["keys", "show", str(path)]) == 0
    assert capsys.readouterr().out.strip() == public == SigningKey.load(path).public
    assert ldm_main(["keys", "new", str(anchor)]) == 0
    anchor_public = capsys.readouterr().out.strip()
    assert ldm_main(["keys", "endorse", str(anchor), "echo", public]) == 0
    endorsement = capsys.readouterr().out.strip()
    desc = _described(SigningKey.load(path)).model_copy(update={"endorsement": endorsement})
    assert Trust(anchors=[anchor_public]).trusts(desc)


class _Raw:
    """A client on the cluster broker that publishes what a test says and keeps what it sees."""

    def __init__(self, url: str, subscribe: str) -> None:
        self.seen: list[Message] = []
        self.transport = Transport(
            BrokerSettings(url=url), client_id=f"raw-{time.monotonic_ns()}", sink=self._sink
        )
        self.transport.subscribe(subscribe, 1)
        self.transport.start(timeout=5)

    def _sink(self, event: Event) -> None:
        if isinstance(event, Message):
            self.seen.append(event)

    def publish(self, topic: str, payload: bytes, retain: bool = False) -> None:
        self.transport.publish_and_wait(topic, payload, qos=1, retain=retain)


def test_pinned_participants_act_only_on_what_is_signed(
    broker_factory: Callable[[], RunningBroker],
) -> None:
    """One cluster: the core takes only the pinned identity's announcements; a pinned
    participant ignores unsigned notices and lists; a tampered list is put back."""
    broker = broker_factory()
    identity = SigningKey()
    core = Core.create("solo", broker.url, service_keys={"echo": identity.public}).start(5)
    echo = EchoService()
    provider = echo_provider(broker.url, echo, identity=identity)
    pinned = {"service_keys": {"echo": identity.public}, "core_key": core.public_key}
    alice = Participant.create(broker.url, client_id="alice", **pinned).start(timeout=5)
    mallory = _Raw(broker.url, "ldm/services")
    try:
        assert wait_for(has_service(alice, "echo"), 5)
        session = alice.open("echo")
        assert session.request({"n": 1}) == {"echo": {"n": 1}}
        # A forged announcement of "echo" under another identity: dropped by the core.
        forger = SigningKey()
        ann = Announcement(service=_described(forger), t=time.time())
        ann = ann.model_copy(update={"sig": forger.sign(ann.signed_text())})
        mallory.publish("ldm/svc/echo/announce", ann.model_dump_json().encode(), retain=True)
        assert wait_for(lambda: core.stats.dropped_untrusted >= 1, 5)
        assert core.services[0].public_key == provider.key.public
        # Clearing the retained topic is no withdrawal: only the provider's signed one is.
        mallory.publish("ldm/svc/echo/announce", b"", retain=True)
        # Unsigned notices change nothing for a participant that pinned the core.
        ignored = alice.ignored
        for kind in ("rotate", "nosession"):
            notice = SessionNotice(kind=kind, service="echo", to="alice", t=time.time())
            mallory.publish("ldm/p/alice/down/session", notice.model_dump_json().encode())
        assert wait_for(lambda: alice.ignored >= ignored + 2, 5)
        assert session.rotations == 0
        assert session.request({"n": 2}) == {"echo": {"n": 2}}
        # A forged empty list: the core puts its own back, which alice still trusts.
        forged = ServiceList(t=time.time() + 10, services=[]).model_dump_json().encode()
        mallory.publish("ldm/services", forged, retain=True)
        assert wait_for(lambda: core.stats.repaired_list >= 1, 5)  # after the empty payload
        assert [s.public_key for s in core.services] == [provider.key.public]

        def repaired() -> bool:  # the core's list came after the forged one
            payloads = [m.payload for m in mallory.seen]
            return forged in payloads and payloads[-1] == core.catalog.list_payload

        # The repair is counted before the core's list reaches the broker: wait for it.
        assert wait_for(repaired, 5)
        fresh = _Raw(broker.url, "ldm/services")
        assert wait_for(lambda: bool(fresh.seen), 5)
        assert fresh.seen[0].payload == core.catalog.list_payload  # what the broker retained
        fresh.transport.stop()
        assert [s.name for s in alice.services()] == ["echo"]
        # A participant pinning another identity for echo does not trust it.
        bob = Participant.create(
            broker.url, client_id="bob", service_keys={"echo": forger.public}
        ).start(timeout=5)
        try:
            assert wait_for(lambda: bob._have_list.is_set(), 5)
            assert bob.services() == []
            with pytest.raises(TrustError, match="neither pinned"):
                bob.open("echo", timeout=1.0)
        finally:
            bob.stop()
    finally:
        mallory.transport.stop()
        alice.stop()
        provider.stop()
        core.stop()


@pytest.mark.parametrize("end", ["stop", "kill"])
def test_a_pinned_core_takes_the_providers_signed_goodbye(
    broker_factory: Callable[[], RunningBroker], end: str
) -> None:
    """A provider's stop and its last will (a killed provider) withdraw it at once."""
    broker = broker_factory()
    identity = SigningKey()
    core = Core.create("solo", broker.url, service_keys={"echo": identity.public}).start(5)
    provider = echo_provider(broker.url, EchoService(), identity=identity)
    try:
        assert wait_for(lambda: len(core.services) == 1, 5)
        provider.stop() if end == "stop" else provider.kill()
        assert wait_for(lambda: not core.services, 5)
    finally:
        core.stop()
