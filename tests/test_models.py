"""The wire models accept what a receiver can report and name what they refuse."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from laas.models import CorrectedPosition, GpsMeasurement

GOOD = {
    "timestamp": 1_700_000_000_000,
    "latitude": 53.56,
    "longitude": 9.98,
    "altitude": 12.0,
    "heading": 30.0,
    "speed": 5.0,
}


@settings(max_examples=300)
@given(
    timestamp=st.integers(0, 253_402_300_799_999),
    latitude=st.floats(-90, 90),
    longitude=st.floats(-180, 180),
    heading=st.floats(0, 360, exclude_max=True),
    speed=st.floats(0, 150),
)
def test_valid_measurements_round_trip_through_json(
    timestamp: int, latitude: float, longitude: float, heading: float, speed: float
) -> None:
    m = GpsMeasurement(
        timestamp=timestamp,
        latitude=latitude,
        longitude=longitude,
        heading=heading,
        speed=speed,
    )
    assert GpsMeasurement.model_validate_json(m.model_dump_json()) == m


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("latitude", 90.5),
        ("latitude", -91.0),
        ("longitude", 180.01),
        ("heading", 360.0),
        ("heading", -0.1),
        ("speed", -1.0),
        ("timestamp", -1),
        ("timestamp", 1.5),
        ("timestamp", True),
        ("latitude", "53.5"),
        ("altitude", float("inf")),
    ],
)
def test_out_of_range_or_wrong_type_is_refused_naming_the_field(field: str, value: object) -> None:
    with pytest.raises(ValidationError) as info:
        GpsMeasurement.model_validate({**GOOD, field: value})
    assert info.value.errors()[0]["loc"] == (field,)


@settings(max_examples=300)
@given(st.sampled_from(["latitude", "longitude", "heading", "speed", "altitude"]))
def test_nan_is_refused_in_every_float_field(field: str) -> None:
    text = json.dumps({**GOOD, field: math.nan})  # json.dumps writes NaN
    with pytest.raises(ValidationError) as info:
        GpsMeasurement.model_validate_json(text)
    assert field in str(info.value)


def test_missing_and_unknown_fields_are_refused() -> None:
    with pytest.raises(ValidationError, match="speed"):
        GpsMeasurement.model_validate({k: v for k, v in GOOD.items() if k != "speed"})
    with pytest.raises(ValidationError, match="colour"):
        GpsMeasurement.model_validate({**GOOD, "colour": "red"})


def test_schemas_export() -> None:
    schema = GpsMeasurement.model_json_schema()
    assert set(schema["required"]) == {"timestamp", "latitude", "longitude", "heading", "speed"}
    assert schema["properties"]["heading"]["exclusiveMaximum"] == 360.0
    assert "probability" in CorrectedPosition.model_json_schema()["properties"]
