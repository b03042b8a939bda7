"""The TLS overlay on a real Mosquitto: the certificate made as docs/operations.md says
(deploy/security/make-tls-cert.sh, openssl), the user-cluster broker's own config with
the listener docker-compose.tls.yml mounts, and a participant's connection with the CA:
it publishes and receives; without the CA, or in plain MQTT, it gets nowhere."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from ldm import LdmError
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, free_port
from ldm.local.pytest_plugin import need_mosquitto
from ldm.transport import Event, Message, Transport

from .test_compose import SETTINGS, TLS, load_compose, mounts

ROOT = Path(__file__).resolve().parent.parent
SECURITY = ROOT / "deploy" / "security"
MOSQUITTO_UID = 1883  # eclipse-mosquitto's user, which reads the key in the container


def in_container_paths(text: str, paths: dict[str, Path]) -> str:
    for in_image, host in paths.items():
        text = re.sub(rf"(?m)^(\w+) {re.escape(in_image)}\s*$", rf"\1 {host}", text)
    return text


@pytest.mark.mosquitto
@pytest.mark.timeout(60)
def test_a_participant_publishes_and_receives_over_the_tls_overlay(tmp_path: Path) -> None:
    need_mosquitto()
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed (apt-get install openssl)")
    if os.geteuid() != 0:
        pytest.skip("starts mosquitto as uid 1883, as in its container: run as root")
    plain, secure = free_port(), free_port()
    broker = MosquittoBroker(port=plain, allow_anonymous=False, run_as=MOSQUITTO_UID)
    certs = broker.directory / "tls"
    made = subprocess.run(
        ["bash", str(SECURITY / "make-tls-cert.sh"), "localhost", str(certs)],
        capture_output=True,
        text=True,
        check=True,
        env={"PATH": "/usr/bin:/bin"},
    )
    assert "server certificate for DNS:localhost" in made.stderr
    assert (certs / "server.key").stat().st_mode & 0o777 == 0o400
    # compose mounts the two files themselves; here mosquitto reaches them in the folder
    certs.chmod(0o755)
    passwd = broker.directory / "passwd"
    accounts = subprocess.run(
        ["bash", str(SECURITY / "make-passwd.sh"), str(passwd), "alice"],
        capture_output=True,
        text=True,
        check=True,
        env={"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin"},
    )
    password = accounts.stdout.strip().split("=", 1)[1]
    # the overlay's mounts, as docker-compose.tls.yml merged over docker-compose.yml has them
    service = load_compose({**SETTINGS, "LAAS_TLS_DIR": str(certs)}, TLS)["broker-user"]
    mounted = mounts(service)
    listeners = broker.directory / "listeners.d"
    listeners.mkdir()
    for conf in mounted["/mosquitto/config/listeners.d"].glob("*.conf"):
        text = conf.read_text().replace("listener 8883", f"listener {secure} 127.0.0.1")
        (listeners / conf.name).write_text(in_container_paths(text, mounted))
    assert mounted["/mosquitto/certs/server.key"] == certs / "server.key"
    acl = broker.directory / "acl"
    shutil.copyfile(mounted["/mosquitto/config/acl"], acl)
    config = (ROOT / "mosquitto.conf").read_text()
    config = config.replace("listener 1883\n", f"listener {plain} 127.0.0.1\n")
    config = in_container_paths(
        config,
        {
            "/mosquitto/config/listeners.d": listeners,
            "/mosquitto/config/passwd": passwd,
            "/mosquitto/config/acl": acl,
        },
    )
    broker.config_file.write_text(config.replace("log_dest stdout", "log_dest stderr"))
    for path in (listeners, *listeners.iterdir(), acl, broker.config_file):
        path.chmod(0o755 if path.is_dir() else 0o644)

    url = f"mqtts://localhost:{secure}"
    got: list[bytes] = []
    received = threading.Event()

    def sink(e: Event) -> None:
        if isinstance(e, Message) and e.topic == "owntracks/alice/phone":
            got.append(e.payload)
            received.set()

    def connect(settings: BrokerSettings) -> bool:
        t = Transport(settings, client_id="alice", sink=lambda e: None)
        try:
            t.start(timeout=3)
        except LdmError:
            return False
        t.stop()
        return True

    with broker:
        settings = BrokerSettings(
            url=url, ca_file=certs / "ca.crt", username="alice", password=password
        )
        phone = Transport(settings, client_id="alice", sink=sink, name="alice")
        phone.subscribe("owntracks/alice/#", 1)
        phone.start(timeout=5)
        try:
            phone.publish("owntracks/alice/phone", b'{"_type":"location"}', 1)
            assert received.wait(5), "nothing came back over TLS"
        finally:
            phone.stop()
        assert got == [b'{"_type":"location"}']
        # a client that does not trust the CA, or speaks plain MQTT to 8883, gets nowhere
        assert not connect(settings.model_copy(update={"ca_file": None}))
        assert not connect(settings.model_copy(update={"url": f"mqtt://127.0.0.1:{secure}"}))
