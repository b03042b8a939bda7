"""OwnTracks phones as LaaS participants, with no app of our own.

The OwnTracks app (iOS, Android) publishes ``_type: location`` JSON to
``owntracks/<user>/<device>`` (https://owntracks.org/booklet/tech/json/). The bridge
subscribes to ``owntracks/+/+`` on the user-cluster broker, makes each device its own
LDM participant (`DevicePool`), and publishes each answer back where the app shows
friends (it subscribes to ``owntracks/+/+`` and ``owntracks/+/+/info``):

- ``owntracks/<user>/<device>-lane/info``: a retained ``_type: card`` named
  "my lane position", so the app labels the friend;
- ``owntracks/<user>/<device>-lane``: a retained ``_type: location`` at the corrected
  position, with the lane in the extra field ``laas`` (`LAAS_FIELD`).

With the shipped ACL (``pattern readwrite owntracks/%u/#``) a phone reads only its own
user's topics, so only its own answers. Retained device messages (old fixes) are not
taken, as the OwnTracks Recorder does by default.

Payload encryption (https://owntracks.org/booklet/features/encrypt/): the app seals the
JSON with libsodium's secretbox (XSalsa20-Poly1305) under its secret, "up to 32
characters which the apps pad with binary zeroes", and sends
``{"_type": "encrypted", "data": base64(nonce(24) || box)}``. The bridge keeps one
secret per ``user-device`` (lowercased, as the Recorder's ``ocat --load=keys``), opens
such messages with it and seals the answers for that device with the same secret.
"""

from __future__ import annotations

import base64
import binascii
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import nacl.exceptions
import nacl.secret
import nacl.utils
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from laas.bridges.mqtt import MqttBridge
from laas.bridges.pool import Answer, DevicePool, Malformed, device_name
from laas.errors import ConfigError
from laas.models import CorrectedPosition, GpsMeasurement, problems
from ldm import BrokerSettings
from ldm.transport import Message

__all__ = [
    "ANSWER_SUFFIX",
    "CARD_NAME",
    "LAAS_FIELD",
    "OwnTracksBridge",
    "OwnTracksConfig",
    "OwnTracksLocation",
    "answer_card",
    "answer_location",
    "decrypt",
    "encrypt",
    "read_location",
    "read_secrets",
    "secret_key",
    "to_measurement",
]

log = logging.getLogger(__name__)

TOPIC_FILTER = "owntracks/+/+"
ANSWER_SUFFIX = "-lane"
"""A device's answers go to ``owntracks/<user>/<device>-lane``; the bridge never takes a
device whose name ends in it as input (its own answers)."""
CARD_NAME = "my lane position"
ANSWER_TID = "LP"
"""The tracker id of the answers: the two letters the app shows on the map."""
LAAS_FIELD = "laas"
"""The extra field of an answer location: segment, lane, lane_type, probability,
accuracy_cross, accuracy_along (as in `CorrectedPosition`)."""

KMH = 1000.0 / 3600.0  # m/s per km/h


class OwnTracksLocation(BaseModel):
    """The fields of an OwnTracks ``_type: location`` that the bridge reads.

    The app leaves out ``acc``, ``alt``, ``cog`` and ``vel`` when they are zero (booklet,
    "Notes"), so each defaults to 0 (``acc``: unknown). Other fields are ignored.
    """

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)

    type: Literal["location"] = Field(alias="_type")
    tst: int = Field(ge=0, le=253_402_300_799, description="time of the fix, Unix s")
    lat: float = Field(ge=-90.0, le=90.0)
    lon: float = Field(ge=-180.0, le=180.0)
    alt: float = Field(default=0.0, ge=-1_000.0, le=100_000.0, description="m")
    vel: float = Field(default=0.0, ge=0.0, le=540.0, description="km/h")
    cog: float = Field(default=0.0, ge=0.0, le=360.0, description="degrees from north")
    acc: float = Field(default=0.0, ge=0.0, le=10_000.0, description="m; 0 = unknown")
    tid: str | None = None


def to_measurement(loc: OwnTracksLocation) -> GpsMeasurement:
    """The fix an OwnTracks location describes.

    timestamp = tst * 1000 (s -> ms); speed = vel * 1000 / 3600 (km/h -> m/s);
    heading = cog mod 360; accuracy = acc, the radius the phone's location API reports
    (iOS horizontalAccuracy, Android getAccuracy: about one sigma), None when 0.
    """
    return GpsMeasurement(
        timestamp=loc.tst * 1000,
        latitude=loc.lat,
        longitude=loc.lon,
        altitude=loc.alt,
        heading=loc.cog % 360.0,
        speed=min(loc.vel * KMH, 150.0),
        accuracy=loc.acc if loc.acc > 0 else None,
    )


# --- payload encryption --------------------------------------------------------------


def secret_key(secret: str) -> bytes:
    """OwnTracks' key: the secret's UTF-8 bytes padded with zeros to 32 (secretbox's size)."""
    raw = secret.encode()
    if not raw or len(raw) > nacl.secret.SecretBox.KEY_SIZE:
        raise ConfigError("an OwnTracks secret has 1 to 32 bytes (the app pads it to 32)")
    return raw.ljust(nacl.secret.SecretBox.KEY_SIZE, b"\0")


def decrypt(data: str, key: bytes) -> bytes:
    """Open ``data`` = base64(nonce || box); Malformed if it does not authenticate."""
    try:
        sealed = base64.b64decode(data, validate=True)
        return nacl.secret.SecretBox(key).decrypt(sealed)  # nonce: its first 24 bytes
    except (binascii.Error, ValueError, nacl.exceptions.CryptoError):
        raise Malformed("encrypted payload does not open with the device's secret") from None


def encrypt(plaintext: bytes, key: bytes) -> bytes:
    """``{"_type": "encrypted", "data": base64(nonce || box)}`` with a random nonce."""
    sealed = nacl.secret.SecretBox(key).encrypt(plaintext, nacl.utils.random(24))
    return json.dumps({"_type": "encrypted", "data": base64.b64encode(sealed).decode()}).encode()


def read_secrets(path: Path) -> dict[str, str]:
    """``user-device secret`` per line (the Recorder's key format; ``#`` comments)."""
    found: dict[str, str] = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        device, _, secret = line.partition(" ")
        if not secret.strip() or "-" not in device:
            raise ConfigError(f"{path}:{number}: write `user-device secret`")
        secret_key(secret.strip())  # checks its length
        found[device.lower()] = secret.strip()
    return found


def read_location(payload: bytes, key: bytes | None = None) -> OwnTracksLocation | None:
    """The location a device message holds; None for other ``_type``s; Malformed if bad.

    An encrypted message is opened with `key` (Malformed without one).
    """
    try:
        data = json.loads(payload)
    except (ValueError, RecursionError):
        raise Malformed("not JSON") from None
    if not isinstance(data, dict):
        raise Malformed("not a JSON object")
    if data.get("_type") == "encrypted":
        if key is None:
            raise Malformed("encrypted, but the bridge has no secret for this device")
        if not isinstance(data.get("data"), str):
            raise Malformed("encrypted without a `data` string")
        return read_location(decrypt(data["data"], key), None)
    if data.get("_type") != "location":
        return None  # lwt, transition, card, ...: nothing to position
    try:
        return OwnTracksLocation.model_validate(data)
    except ValidationError as exc:
        raise Malformed("; ".join(f"{f}: {p}" for f, p in problems(exc, "location"))) from None


def answer_card(name: str = CARD_NAME) -> dict[str, Any]:
    """The card that names the answers in the app."""
    return {"_type": "card", "name": name, "tid": ANSWER_TID}


def answer_location(answer: CorrectedPosition) -> dict[str, Any]:
    """An OwnTracks location at the corrected position; the lane in `LAAS_FIELD`.

    ``acc`` is the answer's horizontal 1-sigma radius, rounded up to whole metres (the
    app's integers); ``tst`` the fix's time, s.
    """
    return {
        "_type": "location",
        "tid": ANSWER_TID,
        "tst": answer.timestamp // 1000,
        "lat": round(answer.latitude, 7),
        "lon": round(answer.longitude, 7),
        "acc": max(1, int(-(-answer.accuracy // 1))),
        LAAS_FIELD: {
            "segment": answer.segment,
            "lane": answer.lane,
            "lane_type": answer.lane_type,
            "probability": round(answer.probability, 3),
            "accuracy_cross": round(answer.accuracy_cross, 2),
            "accuracy_along": round(answer.accuracy_along, 2),
        },
    }


class OwnTracksConfig(BaseModel):
    """What the bridge subscribes to and how it names and unlocks devices."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    topic_filter: str = TOPIC_FILTER
    prefix: str = Field(default="ot.", pattern=r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,20}$")
    """Device client ids are prefix + user + "." + device: ``ot.alice.phone``."""
    secrets: Mapping[str, str] = Field(default_factory=dict, repr=False)
    """``user-device`` (lowercase) -> the OwnTracks secret of that device."""
    card_name: str = CARD_NAME


class OwnTracksBridge(MqttBridge):
    """``laas owntracks``: every OwnTracks device on the broker as an LDM participant."""

    def __init__(
        self, broker: BrokerSettings, pool: DevicePool, config: OwnTracksConfig | None = None
    ) -> None:
        self.config = config or OwnTracksConfig()
        super().__init__(broker, pool, [self.config.topic_filter], name="laas-owntracks")
        self._keys = {d: secret_key(s) for d, s in self.config.secrets.items()}
        self._carded: set[str] = set()
        self.ignored = 0  # messages of other types, retained ones, our own answers

    def handle(self, message: Message) -> None:
        levels = message.topic.split("/")
        if len(levels) != 3 or levels[2].endswith(ANSWER_SUFFIX) or message.retain:
            self.ignored += 1
            return
        user, device = levels[1], levels[2]
        try:
            name = device_name(self.config.prefix, user, device)
        except ValueError as exc:
            self.pool.malformed(f"{user}/{device}", str(exc))
            return
        key = self._keys.get(f"{user}-{device}".lower())
        try:
            location = read_location(message.payload, key)
        except Malformed as exc:
            self.pool.malformed(name, str(exc))
            return
        if location is None:
            self.ignored += 1
            return
        fix = to_measurement(location)
        self.pool.submit(name, fix, lambda a: self._answer(user, device, name, key, a))

    def _answer(self, user: str, device: str, name: str, key: bytes | None, a: Answer) -> None:
        """Runs on the device participant's thread: publish, never block."""
        if not isinstance(a, CorrectedPosition):
            return  # refused: counted and logged by the pool
        topic = f"owntracks/{user}/{device}{ANSWER_SUFFIX}"
        if name not in self._carded:
            self._carded.add(name)
            self.publish(
                f"{topic}/info", self._seal(answer_card(self.config.card_name), key), retain=True
            )
        self.publish(topic, self._seal(answer_location(a), key), retain=True)

    @staticmethod
    def _seal(message: dict[str, Any], key: bytes | None) -> bytes:
        plain = json.dumps(message, separators=(",", ":")).encode()
        return plain if key is None else encrypt(plain, key)

    def forgotten(self, names: list[str]) -> None:
        self._carded.difference_update(names)
