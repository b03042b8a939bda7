"""The broker helpers: embedded amqtt, Mosquitto, and the transport's socket settings."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ldm import BrokerProcess, EmbeddedBroker
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, free_port, wait_for
from ldm.transport.mqtt import Connected, Event, Message, Transport


def client(url: str, name: str, events: list[Event]) -> Transport:
    t = Transport(BrokerSettings(url=url), client_id=name, sink=events.append)
    t.start(timeout=5)
    return t


def test_every_client_socket_has_tcp_nodelay(mqtt_broker) -> None:
    events: list[Event] = []
    t = client(mqtt_broker.url, "nodelay-check", events)
    try:
        sock = t._client.socket()
        assert isinstance(sock, socket.socket)
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
    finally:
        t.stop()


def test_transport_reconnects_and_resubscribes_after_a_restart(mqtt_broker) -> None:
    got: list[Event] = []
    sub = client(mqtt_broker.url, "resub", got)
    sub.subscribe("t/#", 1)
    pub = client(mqtt_broker.url, "pub", [])
    try:
        assert wait_for(lambda: sum(isinstance(e, Connected) for e in got) == 1, 2)
        mqtt_broker.stop()
        assert wait_for(lambda: not sub.connected, 10)
        mqtt_broker.start()
        assert wait_for(lambda: sum(isinstance(e, Connected) for e in got) == 2, 10)
        assert wait_for(lambda: pub.connected, 10)

        def delivered() -> bool:
            pub.publish("t/x", b"after-restart", qos=1)
            return wait_for(
                lambda: any(isinstance(e, Message) and e.payload == b"after-restart" for e in got),
                0.3,
            )

        assert wait_for(delivered, 10)
    finally:
        sub.stop()
        pub.stop()


def test_embedded_broker_picks_a_free_port_and_restarts_on_it() -> None:
    broker = EmbeddedBroker().start()
    try:
        port = broker.port
        assert port > 0 and broker.url == f"mqtt://127.0.0.1:{port}"
        broker.stop()
        assert not broker.running
        broker.start()
        assert broker.port == port
        with socket.create_connection(("127.0.0.1", port), timeout=2):
            pass
    finally:
        broker.stop()


def test_broker_process_serves_and_restarts_on_its_port() -> None:
    events: list[Event] = []
    with BrokerProcess() as broker:
        port = broker.port
        t = client(broker.url, "proc-client", events)
        try:
            broker.stop()
            assert wait_for(lambda: not t.connected, 5)
            broker.start()
            assert broker.port == port
            assert wait_for(lambda: t.connected, 10)
        finally:
            t.stop()


@pytest.mark.mosquitto
def test_mosquitto_config_has_nodelay_and_a_free_port() -> None:
    from ldm.local.pytest_plugin import need_mosquitto

    need_mosquitto()
    with MosquittoBroker() as broker:
        text = broker.config_file.read_text()
        assert "set_tcp_nodelay true" in text
        assert f"listener {broker.port} 127.0.0.1" in text
        with socket.create_connection(("127.0.0.1", broker.port), timeout=2):
            pass


def test_missing_mosquitto_skips_or_fails_when_required(tmp_path: Path) -> None:
    """With LDM_REQUIRE_MOSQUITTO=1 (as in CI) a missing mosquitto fails the tests."""
    test_file = tmp_path / "test_needs_mosquitto.py"
    test_file.write_text(
        textwrap.dedent(
            """
            from ldm.local.pytest_plugin import broker_kind  # noqa: F401

            def test_kind(broker_kind):
                assert broker_kind in ("embedded", "mosquitto")
            """
        )
    )
    base = {**os.environ, "LDM_MOSQUITTO": str(tmp_path / "no-such-mosquitto")}
    args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test_file)]
    args += ["-o", "addopts=", "--rootdir", str(tmp_path), "-W", "ignore"]

    relaxed = subprocess.run(args, env={**base, "LDM_REQUIRE_MOSQUITTO": ""}, capture_output=True)
    assert relaxed.returncode == 0, relaxed.stdout.decode()
    assert b"1 passed, 1 skipped" in relaxed.stdout

    strict = subprocess.run(args, env={**base, "LDM_REQUIRE_MOSQUITTO": "1"}, capture_output=True)
    assert strict.returncode != 0
    assert b"LDM_REQUIRE_MOSQUITTO=1 but mosquitto is not installed" in strict.stdout


def test_free_port_is_bindable() -> None:
    port = free_port()
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))


def test_embedded_restart_waits_for_its_port_to_be_released() -> None:
    import socket
    import threading

    from ldm import EmbeddedBroker

    broker = EmbeddedBroker().start()
    port = broker.port
    broker.stop()
    holder = socket.socket()
    holder.bind(("127.0.0.1", port))  # someone still holds the port for a moment
    holder.listen()
    threading.Timer(0.5, holder.close).start()
    try:
        broker.start()
        assert broker.port == port
    finally:
        broker.stop()
        holder.close()
