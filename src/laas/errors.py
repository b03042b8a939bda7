"""The LaaS error tree.

LaasError
├── MapError          a broken HD map (names the feature)
├── TraceError        a bad line in a recorded trace (names the line)
├── ConfigError       an invalid engine or scenario configuration
├── HandoverError     a hand-over between workers that cannot be read (laas.engine.handover)
└── ClientError       the service gave `laas.Client` no corrected position for a fix
    ├── ServiceUnavailable  no broker, core or worker to answer (the message says which)
    ├── UntrustedService    the service or the core is not the one whose key is pinned
    ├── FixRefused          the service refused the fix (`kind`, `fields`: why)
    ├── NoAnswer            no reply in time (also a TimeoutError)
    └── KeepingQuiet        silent after a change of pseudonym, with no answer to go on from
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from laas.models import ErrorKind, FieldProblem

__all__ = [
    "ClientError",
    "ConfigError",
    "FixRefused",
    "KeepingQuiet",
    "LaasError",
    "MapError",
    "NoAnswer",
    "ServiceUnavailable",
    "TraceError",
    "UntrustedService",
]


class LaasError(Exception):
    """Base class of every error LaaS raises on purpose."""


class MapError(LaasError):
    """The HD map cannot be used; the message names the feature and the problem."""


class TraceError(LaasError):
    """A recorded trace has a bad line; the message names the line and the problem."""


class ConfigError(LaasError):
    """A configuration value is invalid; the message names the setting."""


class ClientError(LaasError):
    """`laas.Client` got no corrected position for a fix; the message says what to do."""


class ServiceUnavailable(ClientError):
    """No broker, LDM core or laas worker to answer, or none whose area holds the fix;
    check the URL, the credentials, and that the deployment runs."""


class UntrustedService(ClientError):
    """The service's or the user core's key is not the one pinned (``LAAS_SERVICE_KEY``,
    ``LAAS_CORE_KEY``): pin the keys the operator published, or ask them which changed."""


class NoAnswer(ClientError, TimeoutError):
    """No reply in time: the service is busy or gone, or the fix was dropped as stale."""


class KeepingQuiet(ClientError):
    """The session keeps quiet after a change of pseudonym and has no earlier answer to
    dead-reckon from; the message says for how long: send again after that."""


class FixRefused(ClientError):
    """The service refused the fix: `kind` says why (``invalid``, ``clock``, ``outside``,
    ``stale``, ``internal``), `fields` which fields and what is wrong with each."""

    def __init__(
        self, message: str, kind: ErrorKind, fields: tuple[FieldProblem, ...] = ()
    ) -> None:
        super().__init__(message)
        self.kind = kind
        self.fields = fields
