"""The LaaS error tree.

LaasError
├── MapError          a broken HD map (names the feature)
├── TraceError        a bad line in a recorded trace (names the line)
├── ConfigError       an invalid engine or scenario configuration
└── HandoverError     a hand-over between workers that cannot be read (laas.engine.handover)
"""

from __future__ import annotations

__all__ = ["ConfigError", "LaasError", "MapError", "TraceError"]


class LaasError(Exception):
    """Base class of every error LaaS raises on purpose."""


class MapError(LaasError):
    """The HD map cannot be used; the message names the feature and the problem."""


class TraceError(LaasError):
    """A recorded trace has a bad line; the message names the line and the problem."""


class ConfigError(LaasError):
    """A configuration value is invalid; the message names the setting."""
