"""End-to-end payload encryption between a participant session and a service.

X25519 agreement between the participant's ephemeral key and the service's static key,
HKDF-SHA256 to two 32-byte keys (one per direction), ChaCha20-Poly1305 with a random
96-bit nonce per message. The correlation id and the send time are authenticated as
associated data, so neither can be changed in transit (a replay must keep both, and the
receiver drops an old ``t`` or a ``c`` it has seen).

    shared   = X25519(eph_private, service_public)
    up|down  = HKDF-SHA256(shared, salt=None, info="ldm/1" | eph_public | service_public, L=64)
    ad       = c | "|" | repr(t)
    d        = base64(nonce || ChaCha20Poly1305(key).encrypt(nonce, plaintext, ad))

Keys and plaintext are never logged.
"""

from __future__ import annotations

import base64
import binascii
import hmac
import os
from typing import TYPE_CHECKING

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from ldm.errors import CryptoError

if TYPE_CHECKING:
    from ldm.security.identity import SigningKey

__all__ = ["KeyPair", "SessionCipher", "aad", "input_tag", "region_cipher"]

_NONCE = 12


def aad(c: str, t: float) -> str:
    """The associated data of an envelope: its correlation id and its send time.

    ``repr`` of a float is its shortest round-trip form, and JSON carries the same
    value, so sender and receiver compute the same string.
    """
    return f"{c}|{t!r}"


class KeyPair:
    """An X25519 key pair: static for a service, ephemeral for a participant session."""

    __slots__ = ("_private", "public")

    def __init__(self, private: X25519PrivateKey | None = None) -> None:
        self._private = private or X25519PrivateKey.generate()
        raw = self._private.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
        self.public: str = base64.b64encode(raw).decode()
        """The public key, base64 of the 32 raw bytes."""

    @classmethod
    def from_private_bytes(cls, raw: bytes) -> KeyPair:
        """Load a persisted 32-byte private key."""
        try:
            return cls(X25519PrivateKey.from_private_bytes(raw))
        except ValueError as exc:
            raise CryptoError("a private key must be 32 raw bytes") from exc

    def session_secret(self, peer_public: str) -> bytes:
        """The secret a participant and its core share for one granted session.

        The participant sends a fresh public key with its session request; the core
        answers with one of its own in the grant:

            secret = HKDF-SHA256(X25519(own, peer), info="ldm-session/1" | both keys sorted)

        An observer of the broker sees both public keys and cannot compute it.
        """
        try:
            peer = X25519PublicKey.from_public_bytes(base64.b64decode(peer_public, validate=True))
            shared = self._private.exchange(peer)
        except (ValueError, binascii.Error) as exc:
            raise CryptoError("a public key must be base64 of 32 raw bytes") from exc
        first, second = sorted((self.public, peer_public))
        info = f"ldm-session/1|{first}|{second}".encode()
        return HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=info).derive(shared)

    def cipher(self, peer_public: str, *, initiator: bool) -> SessionCipher:
        """Derive the session cipher with a peer; the participant is the initiator."""
        try:
            peer_raw = base64.b64decode(peer_public, validate=True)
            shared = self._private.exchange(X25519PublicKey.from_public_bytes(peer_raw))
        except (ValueError, binascii.Error) as exc:
            raise CryptoError("a public key must be base64 of 32 raw bytes") from exc
        eph, svc = (self.public, peer_public) if initiator else (peer_public, self.public)
        info = b"ldm/1|" + eph.encode() + b"|" + svc.encode()
        okm = HKDF(algorithm=hashes.SHA256(), length=64, salt=None, info=info).derive(shared)
        up, down = okm[:32], okm[32:]
        return SessionCipher(up, down) if initiator else SessionCipher(down, up)


def region_cipher(identity: SigningKey, family: str) -> SessionCipher:
    """The region key: the cipher the providers of one service's regions (its
    ``family``, `ldm.wire.messages.ServiceSpec`) share, for what they pass each other
    (hand-overs through a participant, notes through their broker): the same
    ChaCha20-Poly1305 as a session's, keyed

        key = HKDF-SHA256(identity private key, info="ldm-family/1|" family)

    Only holders of the regions' identity key can read or make what it seals: not the
    brokers, not the cores, not the participants that carry it."""
    key = identity.derive(f"ldm-family/1|{family}".encode())
    return SessionCipher(key, key)


def input_tag(secret: bytes, c: str, t: float, k: str, d: str) -> str:
    """The participant's tag on one input envelope, which its core checks:

        m = base64(HMAC-SHA256(secret, c | repr(t) | k | d)[:16])

    It proves the input comes from the holder of the session's secret, so input forged
    on the participant's topics cannot change its key or reach the service under its
    pseudonym, even on a broker without ACL.
    """
    mac = hmac.digest(secret, f"{c}|{t!r}|{k}|{d}".encode(), "sha256")[:16]
    return base64.b64encode(mac).decode()


class SessionCipher:
    """Seals outgoing and opens incoming payloads of one session, seen from one side."""

    __slots__ = ("_rx", "_tx")

    def __init__(self, tx_key: bytes, rx_key: bytes) -> None:
        self._tx = ChaCha20Poly1305(tx_key)
        self._rx = ChaCha20Poly1305(rx_key)

    def seal(self, plaintext: bytes, aad: str) -> str:
        """Encrypt and authenticate; returns base64(nonce || ciphertext || tag)."""
        nonce = os.urandom(_NONCE)
        return base64.b64encode(nonce + self._tx.encrypt(nonce, plaintext, aad.encode())).decode()

    def open(self, sealed: str, aad: str) -> bytes:
        """Decrypt and check; raises CryptoError if the payload was altered or misdirected."""
        try:
            raw = base64.b64decode(sealed, validate=True)
            return self._rx.decrypt(raw[:_NONCE], raw[_NONCE:], aad.encode())
        except (InvalidTag, ValueError, binascii.Error) as exc:
            raise CryptoError("payload failed authentication (wrong key or altered)") from exc
