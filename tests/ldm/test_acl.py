"""Mosquitto ACLs can confine a participant to its own topics (client id in the topic)."""

from __future__ import annotations

import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from ldm import Core, KeyPair, Participant, Provider
from ldm.config import BrokerSettings
from ldm.local.brokers import (
    MosquittoBroker,
    find_mosquitto,
    free_port,
    mosquitto_acl,
    wait_for,
)
from ldm.local.pytest_plugin import need_mosquitto
from ldm.ops.passwd import password_line, random_password
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire.messages import Envelope, SessionRequest

from .deployment import ECHO, EchoService, has_service


@pytest.mark.mosquitto
def test_a_participant_cannot_read_or_write_another_participants_topics() -> None:
    need_mosquitto()
    acl = mosquitto_acl("ldm-core", {"svc-echo": "echo"})
    with MosquittoBroker(acl=acl) as broker:

        def as_user(user: str) -> BrokerSettings:
            return BrokerSettings(url=broker.url, username=user)

        echo = EchoService()
        core = Core.create("single", as_user("ldm-core"), idle_timeout=5).start(timeout=5)
        provider = Provider.create(as_user("svc-echo"), ECHO, echo, announce_interval=0.3)
        provider.start(timeout=5)
        alice = Participant.create(broker.url, client_id="alice").start(timeout=5)
        seen: list[Event] = []
        mallory = Transport(BrokerSettings(url=broker.url), client_id="mallory", sink=seen.append)
        mallory.subscribe("ldm/p/alice/#", 1)  # accepted by the broker, never delivered
        mallory.subscribe("ldm/svc/#", 1)
        mallory.subscribe("ldm/p/mallory/down/#", 1)  # its own: allowed
        mallory.start(timeout=5)
        try:
            assert wait_for(has_service(alice, "echo"), 5)
            session = alice.open("echo")
            assert session.request({"n": 1}) == {"echo": {"n": 1}}
            # mallory sends valid input in alice's name: the broker must drop it.
            before = core.stats.forwarded_in
            key = KeyPair()
            sealed = key.cipher(session.service.public_key, initiator=True).seal(b"{}", "m1")
            forged = Envelope(c="m1", t=time.time(), k=key.public, d=sealed)
            mallory.publish(session.grant.input_topic, forged.encode(), 1)
            # Then a request on mallory's own topic: once the core has answered it, the
            # forged input had its turn (MQTT keeps one client's messages in order).
            own = SessionRequest(c="m2", service="echo", t=time.time()).model_dump_json()
            mallory.publish("ldm/p/mallory/up/session", own.encode(), 1)
            assert session.request({"n": 2}) == {"echo": {"n": 2}}

            def answered() -> list[Message]:
                return [e for e in list(seen) if isinstance(e, Message)]

            assert wait_for(lambda: answered(), 5), "mallory's own request went unanswered"
            assert core.stats.forwarded_in == before + 1, "ACL let mallory write"
            assert {m.topic for m in answered()} == {"ldm/p/mallory/down/session"}, (
                "ACL let mallory read"
            )
            assert len(echo.requests) == 2
        finally:
            mallory.stop()
            alice.stop()
            provider.stop()
            core.stop()


ROOT = Path(__file__).resolve().parents[2]


def _listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


def shipped_user_broker(
    directory: Path, port: int, accounts: dict[str, str], acl_extra: str = ""
) -> Path:
    """The user-cluster broker as compose runs it: the shipped mosquitto.conf and
    deploy/security/acl-user-cluster (plus `acl_extra`), on `port` of 127.0.0.1, its
    files in `directory`."""
    acl = (ROOT / "deploy/security/acl-user-cluster").read_text() + acl_extra
    (directory / "acl").write_text(acl)
    lines = [password_line(user, password) for user, password in accounts.items()]
    (directory / "passwd").write_text("\n".join(lines) + "\n")
    config = (ROOT / "mosquitto.conf").read_text()
    assert "\nlistener 1883\n" in config and "/mosquitto/config/" in config
    config = config.replace("\nlistener 1883\n", f"\nlistener {port} 127.0.0.1\n")
    config = config.replace("/mosquitto/config/", f"{directory}/")
    path = directory / "mosquitto.conf"
    path.write_text(config)
    (directory / "listeners.d").mkdir(exist_ok=True)  # as compose mounts: no further listener
    for file in directory.iterdir():
        file.chmod(0o755 if file.is_dir() else 0o644)
    directory.chmod(0o755)  # mosquitto started as root reads them as "mosquitto"
    return path


@pytest.mark.mosquitto
def test_the_shipped_user_broker_starts_without_warnings_and_lists_services() -> None:
    """Mosquitto with the shipped config and ACL says nothing at start (it warned about
    a pattern for ``ldm/services`` naming no %u), and a participant, which may read
    only its own topics there, still gets the service list: its core sends it there,
    also to a participant that asked before the core was up."""
    need_mosquitto()
    binary = find_mosquitto()
    assert binary is not None
    port = free_port()
    accounts = {name: random_password() for name in ("ldm-core-user", "svc-echo", "alice")}
    # A provider in this cluster, for something to list, with the rights the service
    # cluster's ACL gives its worker.
    provider_acl = "user svc-echo\ntopic readwrite ldm/svc/echo/#\ntopic read ldm/services\n"
    # Not pytest's tmp_path: mosquitto started as root reads its files as "mosquitto",
    # which cannot enter pytest's private folder.
    directory = Path(tempfile.mkdtemp(prefix="ldm-shipped-"))
    config = shipped_user_broker(directory, port, accounts, provider_acl)
    broker = subprocess.Popen(
        [binary, "-c", str(config)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    url = f"mqtt://127.0.0.1:{port}"

    def account(name: str) -> BrokerSettings:
        return BrokerSettings(url=url, username=name, password=accounts[name])

    started: list[Core | Provider | Participant] = []
    try:
        assert wait_for(lambda: _listening(port), 10), "mosquitto did not start"
        core = Core.create("user", account("ldm-core-user"))
        # alice connects first: she asks again (after 1 s, 2 s, ...) until the core answers
        alice = Participant.create(account("alice"), core_key=core.public_key)
        started.append(alice.start(timeout=5))
        time.sleep(0.5)
        started.append(core.start(timeout=5))
        provider = Provider.create(account("svc-echo"), ECHO, EchoService(), announce_interval=0.3)
        started.append(provider.start(timeout=5))
        assert wait_for(has_service(alice, "echo"), 5), "the list never reached alice"
        assert alice.open("echo").request({"n": 1}) == {"echo": {"n": 1}}
    finally:
        for part in reversed(started):
            part.stop()
        broker.terminate()
        log = broker.communicate(timeout=10)[0].decode()
        shutil.rmtree(directory, ignore_errors=True)
    assert "Warning" not in log and "Error" not in log, log
