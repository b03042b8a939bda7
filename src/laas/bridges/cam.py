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

The answer is the station's CAM again with the corrected ``reference_position``, a
circular ``position_confidence_ellipse`` from the answer's accuracy and
``lane_position`` filled as ETSI counts lanes: innermostDrivingLane(1),
secondLaneFromInside(2), ... among the driving lanes of the station's direction, from
the middle of the road; offTheRoad(-1) off the map or on a sidewalk. On a bicycle or
parking lane ETSI has no number, so ``lane_position`` is left out. The station type
is a hint: road-side units (15) are not road users and are not positioned.
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
    "etsi_lane_position",
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


def etsi_lane_position(hdmap: HdMap, answer: CorrectedPosition) -> int | None:
    """ETSI's LanePosition of an answer: driving lanes of the same direction counted from
    the middle of the road (1 = innermost); -1 off the map or on a sidewalk; None on a
    lane ETSI does not number (bicycle, parking)."""
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
    # Lanes are numbered left to right looking along the segment; the middle of the road
    # is left of forward lanes and right of backward ones.
    if lane.direction == "backward":
        same = [x for x in lanes if x.type == "driving" and x.direction != "forward"]
        inner_first = sorted(same, key=lambda x: -x.index)
    else:
        same = [x for x in lanes if x.type == "driving" and x.direction != "backward"]
        inner_first = sorted(same, key=lambda x: x.index)
    position = 1 + [x.index for x in inner_first].index(lane.index)
    return min(position, 13)


def answer_cam(
    raw: dict[str, Any], answer: CorrectedPosition, lane_position: int | None
) -> dict[str, Any]:
    """The station's CAM with the corrected position, accuracy and lane position."""
    out = copy.deepcopy(raw)
    basic = out["message"]["basic_container"]
    ref = basic["reference_position"]
    ref["latitude"] = round(answer.latitude * 1e7)  # deg -> 0.1 microdegree
    ref["longitude"] = round(answer.longitude * 1e7)
    axis = min(round(answer.accuracy / math.sqrt(2.0) * CHI2_95 * 100.0), 4093)  # 95 %, cm
    ref["position_confidence_ellipse"] = {
        "semi_major_confidence": max(axis, 1),
        "semi_minor_confidence": max(axis, 1),
        "semi_major_orientation": 0,
    }
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
        lane = etsi_lane_position(self.hdmap, answer)
        payload = json.dumps(answer_cam(raw, answer, lane), separators=(",", ":")).encode()
        self.publish(topic, payload, qos=0)

    def forgotten(self, names: list[str]) -> None:
        for name in names:
            self.station_types.pop(name, None)
