"""Broker connections over TLS (mqtts://) with a CA file, on Mosquitto."""

from __future__ import annotations

import datetime
import ipaddress
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from ldm import Core, Participant, Provider
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, free_port, wait_for
from ldm.local.pytest_plugin import need_mosquitto

from .deployment import ECHO, EchoService, has_service


def make_certificates(directory: Path) -> tuple[Path, Path, Path]:
    """A throw-away CA and a server certificate for 127.0.0.1."""
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ldm test CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=1))
        .not_valid_after(now + datetime.timedelta(hours=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=1))
        .not_valid_after(now + datetime.timedelta(hours=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    paths = directory / "ca.pem", directory / "server.pem", directory / "server.key"
    paths[0].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    paths[1].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    paths[2].write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    for p in paths:
        p.chmod(0o644)  # mosquitto started as root reads them as user "mosquitto"
    return paths


@pytest.mark.mosquitto
def test_core_provider_and_participant_over_tls() -> None:
    need_mosquitto()
    tls_port = free_port()
    broker = MosquittoBroker()
    ca, cert, key = make_certificates(broker.directory)
    broker.config_file.write_text(
        broker.config_file.read_text()
        + f"listener {tls_port} 127.0.0.1\ncafile {ca}\ncertfile {cert}\nkeyfile {key}\n"
    )
    with broker:
        settings = BrokerSettings(url=f"mqtts://127.0.0.1:{tls_port}", ca_file=ca)
        core = Core.create("tls", settings).start(timeout=5)
        provider = Provider.create(settings, ECHO, EchoService()).start(timeout=5)
        try:
            with Participant.create(settings, client_id="tls-car") as p:
                assert wait_for(has_service(p, "echo"), 5)
                assert p.open("echo").request({"over": "tls"}) == {"echo": {"over": "tls"}}
        finally:
            provider.stop()
            core.stop()
