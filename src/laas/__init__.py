"""LaaS, Location as a Service: lane-level cooperative positioning at the mobile edge.

The engine (`Engine`) smooths each road user's GNSS track with a Kalman filter and
places the users of each road element on the lanes of an HD map (`HdMap`) with a
discrete Bayes filter over joint lane assignments. It knows no MQTT: the live worker,
`laas replay` and `laas evaluate` all drive the same engine.
"""

from laas.config import EngineConfig, Mode
from laas.engine import Engine, EngineStats
from laas.errors import ConfigError, LaasError, MapError, TraceError
from laas.map import HdMap, Lane, Segment
from laas.models import CorrectedPosition, ErrorReply, GpsMeasurement, LaneType, read_reply

__all__ = [
    "ConfigError",
    "CorrectedPosition",
    "Engine",
    "EngineConfig",
    "EngineStats",
    "ErrorReply",
    "GpsMeasurement",
    "HdMap",
    "LaasError",
    "Lane",
    "LaneType",
    "MapError",
    "Mode",
    "Segment",
    "TraceError",
    "read_reply",
]
