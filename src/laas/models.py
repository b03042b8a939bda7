"""The wire formats of LaaS: what a road user sends and what it gets back.

A `GpsMeasurement` in; a `CorrectedPosition` or an `ErrorReply` back (`read_reply`
tells them apart). All are pydantic models in strict mode. They are the only place where untrusted
input becomes typed values; everything inward takes these objects, never dicts.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

__all__ = [
    "CorrectedPosition",
    "ErrorKind",
    "ErrorReply",
    "FieldProblem",
    "GpsMeasurement",
    "LaneType",
    "ServiceError",
    "problems",
    "read_reply",
]

LaneType = Literal["driving", "parking", "bicycle", "sidewalk"]

HANDOVER_MAX = 32_000
"""Characters of a hand-over token at most (a user's track and lane table, sealed)."""

_STRICT = ConfigDict(strict=True, frozen=True, extra="forbid", allow_inf_nan=False)

# 0 .. 9999-12-31 in milliseconds since the Unix epoch.
Timestamp = Annotated[int, Field(ge=0, le=253_402_300_799_999)]
Latitude = Annotated[float, Field(ge=-90.0, le=90.0)]
Longitude = Annotated[float, Field(ge=-180.0, le=180.0)]


class GpsMeasurement(BaseModel):
    """One GNSS fix of one road user, as the receiver reports it.

    >>> GpsMeasurement(timestamp=0, latitude=53.56, longitude=9.98, altitude=10.0,
    ...                heading=30.0, speed=5.0).speed
    5.0
    """

    model_config = _STRICT

    timestamp: Timestamp = Field(description="time of the fix, ms since the Unix epoch")
    latitude: Latitude = Field(description="WGS84 latitude, degrees")
    longitude: Longitude = Field(description="WGS84 longitude, degrees")
    altitude: Annotated[float, Field(ge=-1_000.0, le=100_000.0)] = Field(
        default=0.0, description="height above the ellipsoid, m"
    )
    heading: Annotated[float, Field(ge=0.0, lt=360.0)] = Field(
        description="course over ground, degrees from north, clockwise"
    )
    speed: Annotated[float, Field(ge=0.0, le=150.0)] = Field(description="ground speed, m/s")
    accuracy: Annotated[float, Field(gt=0.0, le=10_000.0)] | None = Field(
        default=None,
        description=(
            "the receiver's own 1-sigma horizontal accuracy estimate, m (the radius: per axis "
            "it is accuracy / sqrt 2), if it gives one"
        ),
    )
    handover: Annotated[str, Field(max_length=HANDOVER_MAX)] | None = Field(
        default=None,
        exclude=True,  # never dumped: the worker and RoutedSession move it themselves
        description=(
            "the first fix to a regional worker: the last `handover` of the worker before "
            "(opaque, sealed for the workers; ldm.RoutedSession adds it)"
        ),
    )


class CorrectedPosition(BaseModel):
    """The lane-precise answer to one `GpsMeasurement`.

    `segment`, `lane` and `lane_type` are None when the user is off the map; the
    position is then the filtered (and, where known, bias-corrected) fix.
    `accuracy_cross` and `accuracy_along` are 1-sigma error estimates in metres
    across and along the road; `accuracy` is the horizontal 1-sigma radius. Across the
    road the position is the mean over the lanes the user may be on, and
    `accuracy_cross` counts the chance of each: an answer unsure of its lane says so in
    both `probability` and `accuracy_cross`.
    """

    model_config = _STRICT

    timestamp: Timestamp = Field(description="timestamp of the measurement this answers")
    latitude: Latitude
    longitude: Longitude
    segment: str | None = Field(description="road element (map segment) id")
    lane: Annotated[int, Field(ge=0)] | None = Field(description="lane index, 0 = leftmost")
    lane_type: LaneType | None
    probability: Annotated[float, Field(ge=0.0, le=1.0)] = Field(
        description=(
            "probability that the chosen lane is right (the lane posterior, calibrated on "
            "the development suite)"
        )
    )
    accuracy: Annotated[float, Field(ge=0.0)] = Field(description="horizontal 1-sigma, m")
    accuracy_cross: Annotated[float, Field(ge=0.0)] = Field(
        description="cross-road 1-sigma, m, the chance of every other lane included"
    )
    accuracy_along: Annotated[float, Field(ge=0.0)] = Field(description="along-road 1-sigma, m")
    handover: Annotated[str, Field(max_length=HANDOVER_MAX)] | None = Field(
        default=None,
        exclude=True,  # never dumped: the worker and RoutedSession move it themselves
        description=(
            "near a region's border: this user's state for the next regional worker "
            "(opaque, sealed for the workers; ldm.RoutedSession passes it on)"
        ),
    )


ErrorKind = Literal["invalid", "clock", "outside", "stale", "internal"]
"""Why a fix was refused: not a valid measurement; its timestamp too far from the service's
clock; outside the service area; not newer than the session's last fix; the service failed."""


class FieldProblem(BaseModel):
    """One field of a refused measurement and what is wrong with it."""

    model_config = _STRICT

    field: str
    problem: str


class ServiceError(BaseModel):
    """Why the service refused one measurement; `message` says what to do."""

    model_config = _STRICT

    kind: ErrorKind
    message: str
    fields: tuple[FieldProblem, ...] = ()


class ErrorReply(BaseModel):
    """The reply to a refused measurement: ``{"error": {"kind", "message", "fields"}}``.

    >>> read_reply({"error": {"kind": "stale", "message": "old", "fields": []}}).error.kind
    'stale'
    """

    model_config = _STRICT

    error: ServiceError

    @classmethod
    def of(cls, kind: ErrorKind, message: str, *fields: tuple[str, str]) -> ErrorReply:
        """An error reply with (field, problem) pairs."""
        found = tuple(FieldProblem(field=f, problem=p) for f, p in fields)
        return cls(error=ServiceError(kind=kind, message=message, fields=found))


def read_reply(payload: Mapping[str, Any]) -> CorrectedPosition | ErrorReply:
    """Decode a reply of the service; pydantic's ValidationError if it is neither kind.

    JSON carries lists where the models hold tuples, so replies are read in lax mode.
    """
    if "error" in payload:
        return ErrorReply.model_validate(payload, strict=False)
    return CorrectedPosition.model_validate(payload)


def problems(error: ValidationError, whole: str = "payload") -> list[tuple[str, str]]:
    """(field, problem) for each thing wrong in a refused input; `whole` names the input
    itself where the problem is not one field's."""
    return [(".".join(str(x) for x in e["loc"]) or whole, e["msg"]) for e in error.errors()]
