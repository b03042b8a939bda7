"""Family notes: the providers of one family pass each other sealed notes through their
broker (`Provider.note`); no other key reads or forges one, and none is taken twice."""

from __future__ import annotations

import json
import time

import pytest

from ldm import CryptoError, Provider, ServiceSpec, SessionError
from ldm.config import BrokerSettings
from ldm.local.brokers import RunningBroker
from ldm.security.identity import SigningKey
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire import topics


def _wait(check: object, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():  # type: ignore[operator]
            return True
        time.sleep(0.02)
    return False


def test_a_note_reaches_the_family_sealed_once(mqtt_broker: RunningBroker) -> None:
    """laas-1of2's note reaches laas-2of2 (not itself); on the broker it is ciphertext;
    the same note replayed, and one sealed with another identity, are dropped."""
    identity = SigningKey.generate()
    got: list[tuple[str, bytes]] = []
    wire: list[bytes] = []

    def sink(event: Event) -> None:
        if isinstance(event, Message):
            wire.append(event.payload)

    def spec(name: str) -> ServiceSpec:
        return ServiceSpec(name=name, family="fam", coverage=[(0, 0), (1, 0), (1, 1)])

    one = Provider.create(mqtt_broker.url, spec("fam-1of2"), lambda r: {}, identity=identity)
    two = Provider.create(
        mqtt_broker.url,
        spec("fam-2of2"),
        lambda r: {},
        identity=identity,
        on_note=lambda sender, data: got.append((sender, data)),
    )
    stranger = Provider.create(
        mqtt_broker.url, spec("fam-3of2"), lambda r: {}, identity=SigningKey.generate()
    )
    spy = Transport(BrokerSettings(url=mqtt_broker.url), client_id="spy", sink=sink)
    spy.subscribe(topics.family_note_filter("fam"), 0)
    for p in (one, two, stranger):
        p.start()
    spy.start(timeout=5)
    try:
        time.sleep(0.2)
        one.note(b"secret evidence")
        assert _wait(lambda: got == [("fam-1of2", b"secret evidence")]), got
        assert _wait(lambda: len(wire) == 1)
        assert b"secret" not in wire[0] and set(json.loads(wire[0])) == {"t", "d"}
        spy.publish(topics.family_note("fam", "fam-1of2"), wire[0], 0)  # a replay
        stranger.note(b"forged")  # sealed with another identity's region key
        assert _wait(lambda: two.stats.dropped_notes == 2), two.stats
        assert got == [("fam-1of2", b"secret evidence")]
        assert one.stats.notes_sent == 1 and two.stats.notes_taken == 1
    finally:
        spy.stop()
        for p in (one, two, stranger):
            p.stop()


def test_the_providers_of_a_family_alone_open_what_they_seal_for_each_other() -> None:
    """`seal_shared`/`open_shared` (no broker needed): a provider of the family under the
    same identity opens it; another identity, another context or a provider in no
    family does not."""
    identity = SigningKey.generate()

    def provider(name: str, key: SigningKey, family: str | None = "fam") -> Provider:
        spec = ServiceSpec(name=name, family=family, coverage=[(0, 0), (1, 0), (1, 1)])
        return Provider.create("mqtt://127.0.0.1:1", spec, lambda r: {}, identity=key)

    one, two = provider("fam-1of2", identity), provider("fam-2of2", identity)
    sealed = one.seal_shared(b"a user's state", "handover/1")
    assert b"state" not in sealed.encode()
    assert two.open_shared(sealed, "handover/1") == b"a user's state"
    with pytest.raises(CryptoError):
        two.open_shared(sealed, "other/1")
    with pytest.raises(CryptoError):
        provider("fam-3of2", SigningKey.generate()).open_shared(sealed, "handover/1")
    with pytest.raises(SessionError, match="in no family"):
        provider("alone", identity, None).seal_shared(b"x", "handover/1")
