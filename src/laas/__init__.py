"""LaaS, Location as a Service: lane-level cooperative positioning at the mobile edge.

A program that wants lane-precise positions uses `Client` (or `AsyncClient`): a
`GpsMeasurement` in, a `CorrectedPosition` out, over the deployment's brokers with the
LDM's pseudonyms and end-to-end encryption; failures are `ClientError`s that say what
to do. `load_map` reads a lane map (`HdMap`).

The engine (`Engine`) smooths each road user's GNSS track with a Kalman filter and
places the users of each road element on the lanes of an HD map with a discrete Bayes
filter over joint lane assignments. It knows no MQTT: the live worker, `laas replay`
and `laas evaluate` all drive the same engine.
"""

from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

from laas.config import EngineConfig, Mode
from laas.engine import Engine, EngineStats
from laas.errors import (
    ClientError,
    ConfigError,
    FixRefused,
    KeepingQuiet,
    LaasError,
    MapError,
    NoAnswer,
    ServiceUnavailable,
    TraceError,
    UntrustedService,
)
from laas.map import HdMap, Lane, Segment
from laas.map.bundled import load_map
from laas.models import CorrectedPosition, ErrorReply, GpsMeasurement, LaneType, read_reply

if TYPE_CHECKING:
    from laas.client import AsyncClient, Client

try:
    __version__ = version("laas")
except PackageNotFoundError:  # a source tree on sys.path, not installed
    __version__ = "0+unknown"


def __getattr__(name: str) -> Any:
    """`Client` and `AsyncClient`, imported on first use: importing laas (the engine, the
    maps, the models) loads no MQTT transport."""
    if name in ("AsyncClient", "Client"):
        from laas import client

        return getattr(client, name)
    raise AttributeError(f"module 'laas' has no attribute {name!r}")


__all__ = [
    "AsyncClient",
    "Client",
    "ClientError",
    "ConfigError",
    "CorrectedPosition",
    "Engine",
    "EngineConfig",
    "EngineStats",
    "ErrorReply",
    "FixRefused",
    "GpsMeasurement",
    "HdMap",
    "KeepingQuiet",
    "LaasError",
    "Lane",
    "LaneType",
    "MapError",
    "Mode",
    "NoAnswer",
    "Segment",
    "ServiceUnavailable",
    "TraceError",
    "UntrustedService",
    "__version__",
    "load_map",
    "read_reply",
]
