"""Pure parts: crypto, wire models, settings, topic names, the public API."""

from __future__ import annotations

import base64
import json
import threading
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

import ldm
from ldm import ConfigError, CoreConfig, CryptoError, KeyPair, Provider, ServiceSpec
from ldm.config import BrokerSettings, build
from ldm.security.crypto import aad
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire.messages import Envelope, SessionNotice
from ldm.wire.topics import check_name


def test_public_api_is_pinned() -> None:
    assert sorted(ldm.__all__) == sorted(
        [
            "BatchHandler",
            "BrokerProcess",
            "BrokerSettings",
            "ConfigError",
            "ConnectError",
            "Core",
            "CoreConfig",
            "CoreStats",
            "CryptoError",
            "EmbeddedBroker",
            "Handler",
            "KeyPair",
            "LdmError",
            "Participant",
            "ParticipantConfig",
            "Provider",
            "ProviderConfig",
            "ProviderStats",
            "Request",
            "RequestRejected",
            "RequestTimeout",
            "RotationPolicy",
            "RoutedSession",
            "ServiceDescription",
            "ServiceNotFound",
            "ServiceSpec",
            "Session",
            "SigningKey",
            "Trust",
            "TrustError",
            "SessionError",
            "SessionSilent",
            "SessionGrant",
        ]
    )
    for name in ldm.__all__:
        assert getattr(ldm, name) is not None
    assert issubclass(ldm.RequestTimeout, ldm.LdmError)
    assert issubclass(ldm.RequestTimeout, TimeoutError)


def test_both_sides_derive_the_same_keys_and_directions_differ() -> None:
    service = KeyPair()
    eph = KeyPair()
    up = eph.cipher(service.public, initiator=True)
    down = service.cipher(eph.public, initiator=False)
    sealed = up.seal(b'{"x":1}', "c1")
    assert down.open(sealed, "c1") == b'{"x":1}'
    assert up.open(down.seal(b"reply", "c1"), "c1") == b"reply"
    with pytest.raises(CryptoError):
        up.open(sealed, "c1")  # a message never decrypts with its own direction's key


def test_tampering_wrong_key_and_wrong_correlation_fail() -> None:
    service, eph, other = KeyPair(), KeyPair(), KeyPair()
    sealed = eph.cipher(service.public, initiator=True).seal(b"secret", "c1")
    down = service.cipher(eph.public, initiator=False)
    with pytest.raises(CryptoError):
        down.open(sealed, "c2")
    with pytest.raises(CryptoError):
        service.cipher(other.public, initiator=False).open(sealed, "c1")
    raw = bytearray(base64.b64decode(sealed))
    raw[-1] ^= 1
    with pytest.raises(CryptoError):
        down.open(base64.b64encode(bytes(raw)).decode(), "c1")
    with pytest.raises(CryptoError):
        service.cipher("not-a-key", initiator=False)


def test_a_persisted_key_keeps_its_public_key() -> None:
    from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey
    from cryptography.hazmat.primitives.serialization import (
        Encoding,
        NoEncryption,
        PrivateFormat,
    )

    private = X25519PrivateKey.generate()
    raw = private.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())
    assert KeyPair.from_private_bytes(raw).public == KeyPair(private).public
    with pytest.raises(CryptoError):
        KeyPair.from_private_bytes(b"short")


@given(st.binary(max_size=300))
def test_envelope_decoder_rejects_garbage_cleanly(data: bytes) -> None:
    try:
        env = Envelope.model_validate_json(data)
    except ValidationError:
        return
    assert isinstance(env.c, str) and isinstance(env.t, float)


@given(
    c=st.from_regex(r"\A[A-Za-z0-9_-]{1,64}\Z"),
    t=st.floats(min_value=0, max_value=4e9),
)
def test_envelope_round_trips_and_is_compact(c: str, t: float) -> None:
    env = Envelope(c=c, t=t, d="AAAA")
    assert Envelope.model_validate_json(env.encode()) == env
    assert set(json.loads(env.encode())) == {"c", "t", "d"}


def test_unknown_fields_are_dropped_before_forwarding() -> None:
    raw = b'{"c":"a1","t":1.0,"d":"AAAA","client_id":"alice","username":"al"}'
    assert b"alice" not in Envelope.model_validate_json(raw).encode()
    with pytest.raises(ValidationError):
        SessionNotice.model_validate_json(b'{"kind":"bogus","service":"x"}')


def test_broker_settings_validate_urls_and_keep_passwords_secret(monkeypatch) -> None:
    s = BrokerSettings.of("mqtts://broker.example:8884")
    assert (s.tls, s.host, s.port) == (True, "broker.example", 8884)
    assert BrokerSettings.of("mqtt://h").port == 1883
    for bad in ("http://h:1", "mqtt://", "mqtt://u:p@h:1", "mqtt://h:99999"):
        with pytest.raises(ConfigError):
            BrokerSettings.of(bad)
    with pytest.raises(ConfigError, match="LDM_TEST_NOPE is not set"):
        build(BrokerSettings, url="mqtt://h:1", username="u", password_env="LDM_TEST_NOPE")
    monkeypatch.setenv("LDM_TEST_PW", "hunter2-secret")
    s = build(BrokerSettings, url="mqtt://h:1", username="u", password_env="LDM_TEST_PW")
    assert s.password is not None and s.password.get_secret_value() == "hunter2-secret"
    assert "hunter2" not in repr(s) and "hunter2" not in str(s.model_dump())


def test_core_config_validates_and_names_the_setting() -> None:
    cfg = build(CoreConfig, name="user", cluster="mqtt://h:1", rotation_period=1, grace=0.5)
    assert cfg.backbone is None and 0.02 <= cfg.tick <= 0.5
    with pytest.raises(ConfigError, match="grace"):
        build(CoreConfig, name="user", cluster="mqtt://h:1", grace=-1)
    with pytest.raises(ConfigError, match="name"):
        build(CoreConfig, name="a/b", cluster="mqtt://h:1")
    with pytest.raises(ConfigError, match="data_qos"):
        build(CoreConfig, name="a", cluster="mqtt://h:1", data_qos=3)


@pytest.mark.parametrize("bad", ["", "a/b", "+", "#", "a b", "-x", "x" * 129])
def test_topic_names_reject_wildcards_and_separators(bad: str) -> None:
    with pytest.raises(ConfigError, match="cannot be used in a topic"):
        check_name(bad, "client id")
    assert check_name("car-17.a_b:c", "client id") == "car-17.a_b:c"


def test_the_provider_drops_replays_and_altered_times() -> None:
    service = KeyPair()
    provider = Provider.create(
        "mqtt://127.0.0.1:9", ServiceSpec(name="echo"), lambda r: {"ok": 1}, key=service
    )
    try:
        eph = KeyPair()
        cipher = eph.cipher(service.public, initiator=True)
        t = time.time()
        env = Envelope(c="c1", t=t, k=eph.public, d=cipher.seal(b"{}", aad("c1", t)))

        def deliver(e: Envelope) -> None:
            provider.handle(Message("ldm/svc/echo/in/p1", e.encode(), 1, False, "svc"))

        deliver(env)
        deliver(env)  # the same message again, within max_age: the same reply again
        stats = provider.stats
        assert (stats.requests, stats.answered_again, stats.dropped_replay) == (1, 1, 0)
        deliver(env.model_copy(update={"t": t + 0.5}))  # a fresher time is not authentic
        deliver(env.model_copy(update={"c": "c2"}))  # nor another correlation id
        assert (provider.stats.requests, provider.stats.dropped_invalid) == (1, 2)
    finally:
        provider.transport.stop()


def test_a_topic_that_is_not_utf8_is_counted_not_raised_on_pahos_thread() -> None:
    import paho.mqtt.client as mqtt  # only to build the message paho would hand over

    got: list[Event] = []
    transport = Transport(BrokerSettings.of("mqtt://127.0.0.1:9"), client_id="t", sink=got.append)
    transport.subscribe("ldm/#", 1)  # not connected: noted, sent on connecting
    bad = mqtt.MQTTMessage(topic=b"ldm/p/\xff/up/session")
    good = mqtt.MQTTMessage(topic=b"ldm/services")
    transport._on_message(transport._client, None, bad)
    transport._on_message(transport._client, None, good)
    assert transport.dropped_topics == 1
    assert [e.topic for e in got if isinstance(e, Message)] == ["ldm/services"]


def test_a_message_on_a_topic_not_subscribed_to_never_reaches_the_owner() -> None:
    """A broker that delivers a message to a client that did not subscribe to its topic
    (amqtt was seen doing it with the retained service list) is not believed."""
    import paho.mqtt.client as mqtt  # only to build the message paho would hand over

    got: list[Event] = []
    transport = Transport(BrokerSettings.of("mqtt://127.0.0.1:9"), client_id="t", sink=got.append)
    transport.subscribe("laas/cam/+", 1)
    for topic in (b"laas/cam/car_1", b"ldm/services", b"laas/cam/car_1/extra"):
        transport._on_message(transport._client, None, mqtt.MQTTMessage(topic=topic))
    assert [e.topic for e in got if isinstance(e, Message)] == ["laas/cam/car_1"]
    assert transport.dropped_foreign == 2


def test_stopping_a_dispatcher_under_a_backlog_ends_before_the_next_item() -> None:
    from ldm.local.brokers import wait_for
    from ldm.transport.dispatch import Dispatcher

    entered, release = threading.Event(), threading.Event()

    class Blocking(Dispatcher[int]):
        handled = 0

        def handle(self, item: int) -> None:
            entered.set()
            assert release.wait(5), "never released"
            self.handled += 1

    dispatcher = Blocking("blocking", 1.0)
    for i in range(1_000):
        dispatcher.put(i)
    dispatcher.start_dispatch()
    assert entered.wait(5)  # inside the first item, 999 waiting behind it
    stopper = threading.Thread(target=dispatcher.stop_dispatch)
    stopper.start()
    assert wait_for(dispatcher._stopping.is_set, 5)  # the stop is asked for ...
    release.set()  # ... before the first item ends
    stopper.join(5)
    assert not stopper.is_alive() and not dispatcher._thread.is_alive()
    assert dispatcher.handled == 1  # the stop did not wait for the backlog


def test_a_full_dispatcher_still_takes_a_reconnect_and_counts_what_it_drops() -> None:
    from ldm.transport.dispatch import Dispatcher
    from ldm.transport.mqtt import Connected, Event, Message

    class Recorder(Dispatcher[Event]):
        dropped = 0
        seen: list[Event]

        def handle(self, item: Event) -> None:
            self.seen.append(item)

        def overflowed(self) -> None:
            self.dropped += 1

    dispatcher = Recorder("full", 1.0, limit=1)
    dispatcher.seen = []
    message = Message(topic="t", payload=b"x", qos=0, retain=False, source="broker")
    dispatcher.sink(message)
    dispatcher.sink(message)  # past the limit: dropped and counted
    dispatcher.sink(Connected("broker"))  # a reconnect is never dropped
    dispatcher.start_dispatch()
    from ldm.local.brokers import wait_for

    assert wait_for(lambda: len(dispatcher.seen) == 2, 5)
    dispatcher.stop_dispatch()
    assert dispatcher.dropped == 1
    assert isinstance(dispatcher.seen[-1], Connected)
