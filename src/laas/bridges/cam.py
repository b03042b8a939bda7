"""ETSI CAMs in the JSON of Orange's its-client, over MQTT.

its-client publishes a CAM (EN 302 637-2) as JSON (schema ``cam_schema_2-1-0.json`` of
https://github.com/Orange-OpenSource/its-client): ``message_type: "cam"``,
``source_uuid``, ``timestamp`` (ms) and ``message`` with ``station_id``, a
``basic_container`` (``station_type``, ``reference_position``) and a
``high_frequency_container`` (``heading``, ``speed``, ``lane_position``...). Units:

    latitude, longitude: 0.1 microdegree     deg = value * 1e-7   (unavailable 900000001,
                                                                   1800000001)
    altitude.value: cm                       m   = value / 100    (unavailable 800001)
    heading: 0.1 degree                      deg = value / 10     (unavailable 3601)
    speed: 0.01 m/s                          m/s = value / 100    (unavailable 16383)
    position_confidence_ellipse semi axes: cm, at 95 % confidence (2-D):
        sigma_axis = axis / 100 / 2.4477     (2.4477^2 = chi2 with 2 dof at 0.95)
        accuracy   = hypot(sigma_major, sigma_minor)   (a 1-sigma radius)
        (4094 out of range, 4095 unavailable: no accuracy)

The answer is the station's CAM again with the corrected ``reference_position``, its
``position_confidence_ellipse`` and ``lane_position``:

- the ellipse (`confidence_ellipse`) has the answer's two accuracies as its axes, along
  the road and across it, turned to the road's heading at the answer (true north,
  clockwise, 0.1 degree; the major axis is the along-road one unless the cross-road
  accuracy is the larger):

      semi_along = accuracy_along * 2.4477,  semi_cross = accuracy_cross * 2.4477  (95 %, m)
      orientation = road heading (grid) + meridian convergence  (of the major axis)

  off the map, a circle of radius accuracy / sqrt(2) * 2.4477, orientation 0;
- ``lane_position`` as ETSI counts lanes: innermostDrivingLane(1),
  secondLaneFromInside(2), ... among the driving lanes of the station's direction,
  from the middle of the road; offTheRoad(-1) off the map or on a sidewalk. On a
  bicycle or parking lane ETSI has no number, so ``lane_position`` is left out. The
  middle of a two-way road lies between its two directions; on a one-way road, on the
  driver's left in right-hand traffic and on the right in left-hand traffic, which the
  map's two-way roads tell (`keeps_left`).

The station type is a hint: road-side units (15) are not road users and are not
positioned.
"""

from __future__ import annotations

import copy
import json
import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from laas.bridges.mqtt import MqttBridge
from laas.bridges.pool import Answer, DevicePool, Malformed, device_name
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition, GpsMeasurement, problems
from ldm import BrokerSettings
from ldm.transport import Message

__all__ = [
    "STATION_TYPES",
    "Cam",
    "CamBridge",
    "CamConfig",
    "answer_cam",
    "cam_fix",
    "confidence_ellipse",
    "etsi_lane_position",
    "keeps_left",
    "read_cam",
]

CHI2_95 = 2.4477  # sqrt of chi-square, 2 degrees of freedom, 95 %
UNAVAILABLE_LAT, UNAVAILABLE_LON = 900_000_001, 1_800_000_001
UNAVAILABLE_ALT, UNAVAILABLE_HEADING, UNAVAILABLE_SPEED = 800_001, 3601, 16383
ROAD_SIDE_UNIT = 15
OFF_THE_ROAD = -1

STATION_TYPES = {
    0: "unknown",
    1: "pedestrian",
    2: "cyclist",
    3: "moped",
    4: "motorcycle",
    5: "passengerCar",
    6: "bus",
    7: "lightTruck",
    8: "heavyTruck",
    9: "trailer",
    10: "specialVehicles",
    11: "tram",
    15: "roadSideUnit",
}


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)


class Altitude(_Model):
    value: int = Field(default=UNAVAILABLE_ALT, ge=-100_000, le=800_001)


class ConfidenceEllipse(_Model):
    semi_major_confidence: int = Field(default=4095, ge=0, le=4095)
    semi_minor_confidence: int = Field(default=4095, ge=0, le=4095)
    semi_major_orientation: int = Field(default=3601, ge=0, le=3601)


class ReferencePosition(_Model):
    latitude: int = Field(ge=-900_000_000, le=UNAVAILABLE_LAT)
    longitude: int = Field(ge=-1_800_000_000, le=UNAVAILABLE_LON)
    altitude: Altitude | None = None
    position_confidence_ellipse: ConfidenceEllipse | None = None


class BasicContainer(_Model):
    station_type: int = Field(default=0, ge=0, le=255)
    reference_position: ReferencePosition


class HighFrequencyContainer(_Model):
    heading: int = Field(default=UNAVAILABLE_HEADING, ge=0, le=3601)
    speed: int = Field(default=UNAVAILABLE_SPEED, ge=0, le=16383)


class CamMessage(_Model):
    station_id: int = Field(ge=0, le=4_294_967_295)
    basic_container: BasicContainer
    high_frequency_container: HighFrequencyContainer = HighFrequencyContainer()


class Cam(_Model):
    """The fields of an its-client CAM the bridge reads."""

    message_type: Literal["cam"]
    source_uuid: str = Field(min_length=1, max_length=128)
    timestamp: int = Field(ge=0, le=253_402_300_799_999, description="ms since 1970")
    message: CamMessage


def read_cam(payload: bytes) -> tuple[Cam, dict[str, Any]]:
    """The CAM and its JSON object; Malformed if it is not a CAM."""
    try:
        raw = json.loads(payload)
    except (ValueError, RecursionError):
        raise Malformed("not JSON") from None
    if not isinstance(raw, dict):
        raise Malformed("not a JSON object")
    try:
        return Cam.model_validate(raw), raw
    except ValidationError as exc:
        raise Malformed("; ".join(f"{f}: {p}" for f, p in problems(exc, "cam"))) from None


def cam_fix(cam: Cam) -> GpsMeasurement | None:
    """The fix a CAM describes; None when it has no position (unavailable)."""
    basic = cam.message.basic_container
    ref = basic.reference_position
    if ref.latitude == UNAVAILABLE_LAT or ref.longitude == UNAVAILABLE_LON:
        return None
    hf = cam.message.high_frequency_container
    altitude = 0.0
    if ref.altitude is not None and ref.altitude.value != UNAVAILABLE_ALT:
        altitude = ref.altitude.value / 100.0  # cm -> m
    accuracy = None
    e = ref.position_confidence_ellipse
    if e is not None and 0 < e.semi_major_confidence < 4094 and 0 < e.semi_minor_confidence < 4094:
        major = e.semi_major_confidence / 100.0 / CHI2_95  # 95 % semi axis, cm -> 1 sigma, m
        minor = e.semi_minor_confidence / 100.0 / CHI2_95
        accuracy = math.hypot(major, minor)
    return GpsMeasurement(
        timestamp=cam.timestamp,
        latitude=ref.latitude * 1e-7,
        longitude=ref.longitude * 1e-7,
        altitude=altitude,
        heading=0.0 if hf.heading == UNAVAILABLE_HEADING else (hf.heading / 10.0) % 360.0,
        speed=0.0 if hf.speed == UNAVAILABLE_SPEED else min(hf.speed / 100.0, 150.0),
        accuracy=accuracy,
    )


def keeps_left(hdmap: HdMap) -> bool:
    """Whether the map's traffic keeps left: on most of its two-way segments, the forward
    driving lanes lie left of the backward ones (lanes count left to right along the
    segment). A map without two-way segments keeps right."""
    left = right = 0
    for segment in hdmap.segments.values():
        driving = [x for x in segment.lanes if x.type == "driving"]
        forward = [x.index for x in driving if x.direction == "forward"]
        backward = [x.index for x in driving if x.direction == "backward"]
        if forward and backward:
            if max(forward) < min(backward):
                left += 1
            elif max(backward) < min(forward):
                right += 1
    return left > right


def etsi_lane_position(
    hdmap: HdMap, answer: CorrectedPosition, keep_left: bool | None = None
) -> int | None:
    """ETSI's LanePosition of an answer: driving lanes of the same direction counted from
    the middle of the road (1 = innermost); -1 off the map or on a sidewalk; None on a
    lane ETSI does not number (bicycle, parking). `keep_left`: the map's traffic side
    (None: `keeps_left`, which a caller with many answers computes once)."""
    if answer.segment is None or answer.lane is None or answer.segment not in hdmap.segments:
        return OFF_THE_ROAD
    lanes = hdmap.segments[answer.segment].lanes
    if answer.lane >= len(lanes):
        return OFF_THE_ROAD
    lane = lanes[answer.lane]
    if lane.type == "sidewalk":
        return OFF_THE_ROAD
    if lane.type != "driving":
        return None
    # Lanes are numbered left to right looking along the segment. The middle of a two-way
    # road lies towards the other direction's lanes; of a one-way road, on the driver's
    # left in right-hand traffic (lower indices for forward lanes, whose drivers look
    # along the segment; higher for backward ones) and on the right in left-hand traffic.
    backward = lane.direction == "backward"
    other = "forward" if backward else "backward"
    driving = [x for x in lanes if x.type == "driving"]
    same = [x for x in driving if x.direction != other]
    opposite = [x.index for x in driving if x.direction == other]
    if opposite:
        middle_low = sum(opposite) / len(opposite) < lane.index
    else:
        if keep_left is None:
            keep_left = keeps_left(hdmap)
        middle_low = backward == keep_left
    inner_first = sorted(same, key=lambda x: x.index if middle_low else -x.index)
    position = 1 + [x.index for x in inner_first].index(lane.index)
    return min(position, 13)


def _axis_cm(sigma: float) -> int:
    """A 95 % semi axis in cm from a 1-sigma error in m; 4094 (outOfRange) past 40.93 m."""
    cm = round(sigma * CHI2_95 * 100.0)
    return 4094 if cm > 4093 else max(cm, 1)


def confidence_ellipse(hdmap: HdMap, answer: CorrectedPosition) -> ConfidenceEllipse:
    """The answer's 95 % confidence ellipse (the module docstring): its along-road and
    cross-road axes, turned to the road's heading; a circle off the map."""
    segment = hdmap.segments.get(answer.segment) if answer.segment is not None else None
    if segment is None:
        axis = _axis_cm(answer.accuracy / math.sqrt(2.0))
        return ConfidenceEllipse(
            semi_major_confidence=axis, semi_minor_confidence=axis, semi_major_orientation=0
        )
    x, y = hdmap.projection.to_utm(answer.longitude, answer.latitude)
    s, _d = segment.frame(x, y)
    heading = segment.heading(s) + hdmap.projection.convergence(answer.longitude, answer.latitude)
    along, cross = answer.accuracy_along, answer.accuracy_cross
    if cross > along:  # the major axis lies across the road
        along, cross, heading = cross, along, heading + 90.0
    return ConfidenceEllipse(
        semi_major_confidence=_axis_cm(along),
        semi_minor_confidence=_axis_cm(cross),
        semi_major_orientation=round(heading * 10.0) % 3600,  # 0.1 degree from true north
    )


def answer_cam(
    raw: dict[str, Any],
    answer: CorrectedPosition,
    lane_position: int | None,
    ellipse: ConfidenceEllipse | None = None,
) -> dict[str, Any]:
    """The station's CAM with the corrected position, its confidence ellipse (None: a
    circle from the answer's accuracy, as off the map) and the lane position."""
    out = copy.deepcopy(raw)
    basic = out["message"]["basic_container"]
    ref = basic["reference_position"]
    ref["latitude"] = round(answer.latitude * 1e7)  # deg -> 0.1 microdegree
    ref["longitude"] = round(answer.longitude * 1e7)
    if ellipse is None:
        axis = _axis_cm(answer.accuracy / math.sqrt(2.0))
        ellipse = ConfidenceEllipse(
            semi_major_confidence=axis, semi_minor_confidence=axis, semi_major_orientation=0
        )
    ref["position_confidence_ellipse"] = ellipse.model_dump()
    hf = out["message"].setdefault("high_frequency_container", {})
    if lane_position is None:
        hf.pop("lane_position", None)
    else:
        hf["lane_position"] = lane_position
    return out


class CamConfig(BaseModel):
    """Where CAMs come from and where the answers go."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    topic_filter: str = "v2x/cam/#"
    answer_topic: str = "laas/cam/{source_uuid}"
    """Template of the answer's topic; ``{source_uuid}`` and ``{station_id}`` are filled."""
    prefix: str = Field(default="cam.", pattern=r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,20}$")


class CamBridge(MqttBridge):
    """``laas cam``: every CAM station on the broker as an LDM participant."""

    def __init__(
        self,
        broker: BrokerSettings,
        pool: DevicePool,
        hdmap: HdMap,
        config: CamConfig | None = None,
    ) -> None:
        self.config = config or CamConfig()
        super().__init__(broker, pool, [self.config.topic_filter], name="laas-cam")
        self.hdmap = hdmap
        self.keep_left = keeps_left(hdmap)
        self.ignored = 0  # retained CAMs, road-side units, CAMs without a position
        self.station_types: dict[str, str] = {}  # device -> the kind of road user it says

    def handle(self, message: Message) -> None:
        if message.retain or message.topic.startswith(self.config.answer_topic.split("{")[0]):
            self.ignored += 1
            return
        try:
            cam, raw = read_cam(message.payload)
        except Malformed as exc:
            self.pool.malformed(f"topic {message.topic}", str(exc))
            return
        try:
            name = device_name(self.config.prefix, cam.source_uuid, str(cam.message.station_id))
        except ValueError as exc:
            self.pool.malformed(f"topic {message.topic}", str(exc))
            return
        station = cam.message.basic_container.station_type
        if station == ROAD_SIDE_UNIT:
            self.ignored += 1
            return
        self.station_types[name] = STATION_TYPES.get(station, "unknown")
        fix = cam_fix(cam)
        if fix is None:
            self.ignored += 1
            return
        topic = self.config.answer_topic.format(
            source_uuid=cam.source_uuid, station_id=cam.message.station_id
        )
        self.pool.submit(name, fix, lambda a: self._answer(topic, raw, a))

    def _answer(self, topic: str, raw: dict[str, Any], answer: Answer) -> None:
        if not isinstance(answer, CorrectedPosition):
            return
        lane = etsi_lane_position(self.hdmap, answer, self.keep_left)
        ellipse = confidence_ellipse(self.hdmap, answer)
        out = answer_cam(raw, answer, lane, ellipse)
        payload = json.dumps(out, separators=(",", ":")).encode()
        self.publish(topic, payload, qos=0)

    def forgotten(self, names: list[str]) -> None:
        for name in names:
            self.station_types.pop(name, None)
