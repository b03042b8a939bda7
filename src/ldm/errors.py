"""The LDM error tree.

LdmError
├── ConfigError        an invalid setting (names the setting and what is allowed)
├── ConnectError       a broker could not be reached in time
├── ServiceNotFound    the requested service is not in the cluster's service list
├── SessionError       the core refused or lost a session
│   ├── RequestRejected  the core refused one input (malformed, too large, rate limit)
│   └── SessionSilent    the session keeps quiet after a change of pseudonym
├── RequestTimeout     no reply arrived in time (also a TimeoutError)
├── CryptoError        a payload could not be decrypted or a key is malformed
├── TrustError         a service's identity is neither pinned nor endorsed by an anchor
└── PasswordFileError  a user name, password or password file line Mosquitto cannot use
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "ConnectError",
    "CryptoError",
    "LdmError",
    "PasswordFileError",
    "RequestRejected",
    "RequestTimeout",
    "ServiceNotFound",
    "SessionError",
    "SessionSilent",
    "TrustError",
]


class LdmError(Exception):
    """Base class of every error the LDM raises on purpose."""


class ConfigError(LdmError, ValueError):
    """A configuration value is invalid; the message names the setting."""


class ConnectError(LdmError, ConnectionError):
    """A broker could not be reached; check the URL, the broker and the credentials."""


class ServiceNotFound(LdmError, LookupError):
    """The service is not announced in this cluster; list the services to see what is."""


class SessionError(LdmError):
    """The core refused a session or no longer knows it."""


class RequestRejected(SessionError):
    """The core refused one input; ``reason`` says why (see `ldm.wire.messages.Rejection`).

    ``rate_limited``: slow down (the core's per-participant rate and burst);
    ``too_large``: the payload is over the core's ``max_payload``; ``invalid``: the
    message was malformed; ``clock``: its time is too far ahead of the core's clock;
    ``unavailable``: the core cannot reach the service now (its backbone broker is
    unreachable), so send again later.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class SessionSilent(SessionError):
    """The session keeps quiet for a few seconds after a change of pseudonym (the core's
    rotation policy, `ldm.wire.rotation`): nothing was sent. Answer the application yourself
    until ``Session.silent`` is False (a positioning client dead-reckons)."""


class RequestTimeout(LdmError, TimeoutError):
    """No reply arrived before the timeout (the data may have been dropped as stale)."""


class CryptoError(LdmError):
    """A payload failed authentication or a key is malformed."""


class TrustError(LdmError):
    """The service's key is not signed by an identity the participant trusts.

    Pin the service's identity (``service_keys``, the key `ldm keys show` prints for
    its identity file) or a trust anchor that endorsed it (``anchors``).
    """


class PasswordFileError(LdmError, ValueError):
    """A user name, password or password file line is unusable; the message says why."""
