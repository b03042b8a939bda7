"""Long-term identities: Ed25519 keys that sign what a participant must be able to trust.

The brokers and the cores route every message, so neither may be able to change what a
participant acts on. Three things are signed:

- a service's *description* (its name, schemas and current X25519 session key) by the
  service's identity key, and each announcement of it (the description's signature
  and the announcement time), so a core cannot substitute a key of its own;
- optionally the service's identity by a deployment's *trust anchor* (an endorsement),
  so a participant can trust every service the anchor vouches for without pinning each;
- a core's session notices and service lists by the core's identity key, so a notice
  forged on the broker changes nothing for a participant that pinned the core's key.

Every signed text starts with a domain label (``ldm-service/1|`` …), so a signature
made for one purpose is never valid for another (a message's JSON made canonical by
`ldm.wire.messages.canonical`):

    description  Ed25519(identity, "ldm-service/1|" + JSON of all but the signature fields)
    announcement Ed25519(identity, "ldm-announce/2|" + description.signature + "|" + repr(t)
                                   + "|" + cluster)   ("ldm-announce/1|", no cluster: unbound)
    endorsement  Ed25519(anchor,   "ldm-endorse/1|" + service + "|" + identity)
    notice       Ed25519(core,     "ldm-notice/1|" + JSON of all but sig)
    service list Ed25519(core,     "ldm-list/1|" + JSON of all but sig)

Public keys and signatures travel as base64 (32 and 64 raw bytes). A private key is
stored as a PEM file with mode 0600 and is never logged.
"""

from __future__ import annotations

import base64
import binascii
import os
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.hazmat.primitives.serialization import (
    Encoding,
    NoEncryption,
    PrivateFormat,
    PublicFormat,
    load_pem_private_key,
)

from ldm.errors import ConfigError

__all__ = ["SigningKey", "endorse", "endorsement_text", "verify"]


class SigningKey:
    """An Ed25519 identity key: a service's, a core's or a deployment's trust anchor."""

    __slots__ = ("_private", "public")

    def __init__(self, private: Ed25519PrivateKey | None = None) -> None:
        self._private = private or Ed25519PrivateKey.generate()
        raw = self._private.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
        self.public: str = base64.b64encode(raw).decode()
        """The public key, base64 of the 32 raw bytes: what others pin."""

    @classmethod
    def generate(cls) -> SigningKey:
        return cls()

    @classmethod
    def load(cls, path: Path | str) -> SigningKey:
        """Read a PEM private key written by `save` (or ``openssl genpkey -algorithm ed25519``)."""
        path = Path(path)
        try:
            pem = path.read_bytes()
        except OSError as exc:
            raise ConfigError(
                f"identity key {path}: cannot read it ({exc.strerror}); "
                "create one with `ldm keys new FILE`"
            ) from None
        return cls.from_pem(pem, str(path))

    @classmethod
    def from_pem(cls, pem: bytes, what: str = "identity key") -> SigningKey:
        try:
            private = load_pem_private_key(pem, password=None)
        except (ValueError, TypeError):
            raise ConfigError(
                f"{what}: not an unencrypted PEM private key; create one with `ldm keys new FILE`"
            ) from None
        if not isinstance(private, Ed25519PrivateKey):
            raise ConfigError(f"{what}: not an Ed25519 key")
        return cls(private)

    @classmethod
    def load_or_create(cls, path: Path | str) -> SigningKey:
        """The key in ``path``, or a new one saved there if the file does not exist."""
        path = Path(path)
        if path.exists():
            return cls.load(path)
        key = cls()
        key.save(path)
        return key

    def save(self, path: Path | str) -> None:
        """Write the private key as PEM, readable by its owner only (mode 0600)."""
        pem = self.to_pem()
        path = Path(path)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as out:
            out.write(pem)

    def to_pem(self) -> bytes:
        """The private key as unencrypted PKCS#8 PEM: keep it secret."""
        return self._private.private_bytes(Encoding.PEM, PrivateFormat.PKCS8, NoEncryption())

    def derive(self, info: bytes) -> bytes:
        """A 32-byte secret for `info` that only holders of this key can compute:
        HKDF-SHA256(private key, info). The providers of one service's regions, which
        serve under one identity, share it (`ldm.security.crypto.region_cipher`)."""
        raw = self._private.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())
        return HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=info).derive(raw)

    def sign(self, data: bytes) -> str:
        """The base64 Ed25519 signature of ``data``."""
        return base64.b64encode(self._private.sign(data)).decode()

    def __repr__(self) -> str:
        return f"SigningKey(public={self.public!r})"


def verify(public: str, data: bytes, signature: str | None) -> bool:
    """True if ``signature`` is ``public``'s Ed25519 signature of ``data``.

    A malformed key or signature is simply not valid (False): both come off the wire.
    """
    if not signature:
        return False
    try:
        key = Ed25519PublicKey.from_public_bytes(base64.b64decode(public, validate=True))
        key.verify(base64.b64decode(signature, validate=True), data)
    except (InvalidSignature, ValueError, binascii.Error):
        return False
    return True


def endorsement_text(service: str, identity: str) -> bytes:
    return f"ldm-endorse/1|{service}|{identity}".encode()


def endorse(anchor: SigningKey, service: str, identity: str) -> str:
    """The anchor's endorsement of ``identity`` as the key of ``service``."""
    return anchor.sign(endorsement_text(service, identity))
