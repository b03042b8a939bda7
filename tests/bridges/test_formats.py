"""The bridges' decoders on the formats' own documented examples, and fuzzed.

Sources of the payloads:
- OwnTracks location: the OwnTracks Recorder's README ("Last position of a particular
  user", https://github.com/owntracks/recorder); the card and the encryption secret
  "mysecreTpass01": the OwnTracks booklet (features/card.md, features/encrypt.md).
- gpsd TPV: the protocol 3.4 example in gpsd_json(5) / Net::GPSD3 (Debian man page).
- NMEA RMC and GGA: the examples of gpsd's "NMEA Revealed" (https://gpsd.io/NMEA.html).
- CAM: the documented values ("examples", units) of its-client's cam_schema_2-1-0.json.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import logging
import math

import pyproj
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from laas.bridges.cam import (
    answer_cam,
    cam_fix,
    confidence_ellipse,
    etsi_lane_position,
    keeps_left,
    read_cam,
)
from laas.bridges.gpsd import paced, parse_address, tpv_epochs, tpv_fix
from laas.bridges.nmea import GPS_ROLLOVER, KNOT, nmea_fixes, nmea_sentences
from laas.bridges.owntracks import (
    LAAS_FIELD,
    answer_location,
    decrypt,
    encrypt,
    read_location,
    secret_key,
    to_measurement,
)
from laas.bridges.pool import LogLimiter, Malformed, device_name
from laas.errors import ConfigError
from laas.map.hdmap import HdMap
from laas.map.mapgen import LaneSpec
from laas.models import CorrectedPosition, GpsMeasurement

from ..helpers import Clock, small_map

RECORDER_EXAMPLE = {
    "tst": 1440405601,
    "acc": 10,
    "_type": "location",
    "alt": 262,
    "lon": 13.60279820860699,
    "vac": 6,
    "vel": 18,
    "lat": 51.06263391678321,
    "cog": 82,
    "tid": "NE",
    "batt": 99,
}
BOOKLET_CARD = {"_type": "card", "name": "Jane Jolie", "face": "iV1CFEVkMhmCIKBUKh3"}
BOOKLET_SECRET = "mysecreTpass01"
GPSD_TPV = {
    "class": "TPV",
    "tag": "0x0106",
    "device": "/dev/cuaU0",
    "time": "2011-03-20T06:51:59.12Z",
    "ept": 0.005,
    "lat": 37.371427205,
    "lon": -122.015179890,
    "alt": 25.789,
    "epx": 1.926,
    "epy": 1.808,
    "epv": 6.497,
    "track": 0.0000,
    "speed": 0.000,
    "climb": 0.000,
    "eps": 3.85,
    "mode": 3,
}
NMEA_RMC = "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A"
NMEA_GGA = "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"


def cam(**hf: int) -> dict[str, object]:
    return {
        "message_type": "cam",
        "source_uuid": "42",
        "timestamp": 1574778515424,
        "version": "2.1.0-dev",
        "message": {
            "protocol_version": 1,
            "station_id": 42,
            "generation_delta_time": 1245,
            "basic_container": {
                "station_type": 5,
                "reference_position": {
                    "latitude": 488417860,
                    "longitude": 23678940,
                    "altitude": {"value": 14000, "confidence": 15},
                    "position_confidence_ellipse": {
                        "semi_major_confidence": 500,
                        "semi_minor_confidence": 300,
                        "semi_major_orientation": 900,
                    },
                },
            },
            "high_frequency_container": {"heading": 900, "speed": 1389, **hf},
        },
    }


# --- OwnTracks ----------------------------------------------------------------------


def test_an_owntracks_location_maps_to_a_fix() -> None:
    location = read_location(json.dumps(RECORDER_EXAMPLE).encode())
    assert location is not None
    fix = to_measurement(location)
    assert fix.timestamp == 1440405601000  # s -> ms
    assert (fix.latitude, fix.longitude, fix.altitude) == (
        51.06263391678321,
        13.60279820860699,
        262,
    )
    assert fix.speed == pytest.approx(5.0)  # 18 km/h
    assert fix.heading == 82 and fix.accuracy == 10


def test_fields_the_app_leaves_out_when_zero_default_sanely() -> None:
    bare = {k: RECORDER_EXAMPLE[k] for k in ("_type", "tst", "lat", "lon")}
    location = read_location(json.dumps(bare).encode())
    assert location is not None
    fix = to_measurement(location)
    assert (fix.speed, fix.heading, fix.altitude, fix.accuracy) == (0.0, 0.0, 0.0, None)


def test_other_owntracks_types_are_not_fixes_and_bad_ones_say_why() -> None:
    assert read_location(json.dumps(BOOKLET_CARD).encode()) is None
    with pytest.raises(Malformed, match="lat"):
        read_location(json.dumps({**RECORDER_EXAMPLE, "lat": 91}).encode())
    with pytest.raises(Malformed, match="not JSON"):
        read_location(b"{")
    try:
        read_location(json.dumps({**RECORDER_EXAMPLE, "lat": 91.234567}).encode())
    except Malformed as exc:
        assert "91.23" not in str(exc)  # no position in a problem report


def test_owntracks_encryption_round_trips_with_the_apps_key() -> None:
    key = secret_key(BOOKLET_SECRET)
    assert key == b"mysecreTpass01" + b"\0" * 18  # padded with zeros to 32
    sealed = encrypt(json.dumps(RECORDER_EXAMPLE).encode(), key)
    envelope = json.loads(sealed)
    assert envelope["_type"] == "encrypted" and "51.06" not in sealed.decode()
    location = read_location(sealed, key)
    assert location is not None and location.tst == 1440405601
    with pytest.raises(Malformed, match="secret"):
        read_location(sealed, secret_key("another"))
    with pytest.raises(Malformed, match="no secret"):
        read_location(sealed, None)
    with pytest.raises(Malformed):
        decrypt("not base64!", key)
    with pytest.raises(ConfigError, match="32"):
        secret_key("x" * 33)


def test_an_answer_becomes_an_owntracks_location_with_the_lane() -> None:
    answer = CorrectedPosition(
        timestamp=1440405601000,
        latitude=51.0626,
        longitude=13.6028,
        segment="s1",
        lane=2,
        lane_type="driving",
        probability=0.9,
        accuracy=1.2,
        accuracy_cross=0.3,
        accuracy_along=1.16,
    )
    out = answer_location(answer)
    assert out["_type"] == "location" and out["tst"] == 1440405601 and out["acc"] == 2
    assert out[LAAS_FIELD]["lane"] == 2 and out[LAAS_FIELD]["lane_type"] == "driving"


@settings(max_examples=300, deadline=None)
@given(
    st.binary(max_size=300)
    | st.dictionaries(st.text(max_size=5), st.integers()).map(
        lambda d: json.dumps({"_type": "location", **d}).encode()
    )
)
def test_the_owntracks_decoder_never_fails_otherwise(payload: bytes) -> None:
    with contextlib.suppress(Malformed):
        read_location(payload, secret_key(BOOKLET_SECRET))


def test_device_names_are_one_topic_level_and_never_collide() -> None:
    assert device_name("ot.", "alice", "phone") == "ot.alice.phone"
    for bad in ("a.b", "a b", "", "é"):
        with pytest.raises(ValueError, match="cannot name a device"):
            device_name("ot.", bad, "phone")


def test_problems_are_logged_once_per_key_per_interval(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    limiter = LogLimiter(60.0, clock)
    with caplog.at_level(logging.WARNING, logger="laas.bridges.pool"):
        assert [limiter.warn("a", "device a: bad") for _ in range(5)] == [True] + [False] * 4
        assert limiter.warn("b", "device b: bad")  # another device is not held back
        clock.now += 60.0
        assert limiter.warn("a", "device a: bad")
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "device a: bad",
        "device b: bad",
        "device a: bad (4 more like it since the last report)",
    ]


# --- gpsd and NMEA ------------------------------------------------------------------


def test_a_gpsd_tpv_report_maps_to_a_fix() -> None:
    fix = tpv_fix(GPSD_TPV)
    assert fix is not None
    assert fix.timestamp == 1300603919120
    assert (fix.latitude, fix.longitude, fix.altitude) == (37.371427205, -122.015179890, 25.789)
    # epx, epy are 95 % per axis: sigma = ep / 1.96
    assert fix.accuracy == pytest.approx(math.hypot(1.926, 1.808) / 1.96)
    assert tpv_fix({**GPSD_TPV, "mode": 1}) is None  # no fix
    with pytest.raises(Malformed, match="lat"):
        tpv_fix({**GPSD_TPV, "lat": "north"})
    assert parse_address("localhost:2947") == ("localhost", 2947)
    with pytest.raises(ValueError, match="HOST:PORT"):
        parse_address("localhost:gps")


def test_nmea_rmc_and_gga_make_a_fix() -> None:
    alone = list(nmea_fixes([NMEA_RMC]))
    assert len(alone) == 1 and isinstance(alone[0], GpsMeasurement)
    fix = alone[0]
    assert fix.latitude == pytest.approx(48 + 7.038 / 60)
    assert fix.longitude == pytest.approx(11 + 31.0 / 60)
    assert fix.speed == pytest.approx(22.4 * KNOT) and fix.heading == 84.4
    assert fix.timestamp == 764426119000  # 1994-03-23 12:35:19 UTC
    (joined,) = nmea_fixes([NMEA_GGA, NMEA_RMC])
    assert isinstance(joined, GpsMeasurement) and joined.altitude == 545.4
    broken = list(nmea_fixes([NMEA_RMC[:-2] + "00", "$GPRMC,123519,V,,,,,,,230394,,*00", "junk"]))
    assert len(broken) == 2 and all(isinstance(b, Malformed) for b in broken)


def test_nmea_written_for_a_fix_reads_back() -> None:
    fix = GpsMeasurement(
        timestamp=1_800_000_000_120,
        latitude=53.55878,
        longitude=9.97607,
        altitude=10.0,
        heading=30.8,
        speed=5.1,
        accuracy=2.0,
    )
    (back,) = nmea_fixes(nmea_sentences(fix))
    assert isinstance(back, GpsMeasurement)
    assert back.timestamp == fix.timestamp
    assert back.latitude == pytest.approx(fix.latitude, abs=1e-7)
    assert back.longitude == pytest.approx(fix.longitude, abs=1e-7)
    assert back.speed == pytest.approx(fix.speed, abs=0.01)
    assert back.accuracy == pytest.approx(2.0, abs=0.02)


# --- CAM ----------------------------------------------------------------------------


def test_a_cam_maps_to_a_fix_in_its_units() -> None:
    parsed, _raw = read_cam(json.dumps(cam()).encode())
    fix = cam_fix(parsed)
    assert fix is not None
    assert fix.latitude == pytest.approx(48.841786) and fix.longitude == pytest.approx(2.367894)
    assert fix.altitude == 140.0 and fix.heading == 90.0 and fix.speed == pytest.approx(13.89)
    assert fix.accuracy == pytest.approx(math.hypot(5.0, 3.0) / 2.4477)
    unavailable = cam()
    unavailable["message"]["basic_container"]["reference_position"]["latitude"] = 900000001  # type: ignore[index]
    assert cam_fix(read_cam(json.dumps(unavailable).encode())[0]) is None
    with pytest.raises(Malformed, match="message_type"):
        read_cam(json.dumps({**cam(), "message_type": "denm"}).encode())


def test_etsi_lane_positions_count_driving_lanes_from_the_middle() -> None:
    hdmap = small_map()  # sidewalk (both), driving backward, driving forward, bicycle
    seg = sorted(hdmap.segments)[0]

    def answer(lane: int | None, segment: str | None = seg) -> CorrectedPosition:
        lane_type = None if lane is None else hdmap.segments[seg].lanes[lane].type
        return CorrectedPosition(
            timestamp=0,
            latitude=0.0,
            longitude=0.0,
            segment=segment,
            lane=lane,
            lane_type=lane_type,
            probability=1.0,
            accuracy=1.0,
            accuracy_cross=0.5,
            accuracy_along=0.8,
        )

    assert etsi_lane_position(hdmap, answer(2)) == 1  # the forward driving lane
    assert etsi_lane_position(hdmap, answer(1)) == 1  # the backward one, its own side
    assert etsi_lane_position(hdmap, answer(0)) == -1  # sidewalk: off the road
    assert etsi_lane_position(hdmap, answer(3)) is None  # bicycle lane: no ETSI number
    assert etsi_lane_position(hdmap, answer(None, None)) == -1
    out = answer_cam(cam(lane_position=7), answer(3), None)
    assert "lane_position" not in out["message"]["high_frequency_container"]
    out = answer_cam(cam(), answer(2), 1)
    assert out["message"]["high_frequency_container"]["lane_position"] == 1
    ellipse = out["message"]["basic_container"]["reference_position"]["position_confidence_ellipse"]
    assert ellipse["semi_major_confidence"] == round(1.0 / math.sqrt(2) * 2.4477 * 100)


def _answer_on(hdmap: HdMap, lane: int, s: float = 60.0, **fields: float) -> CorrectedPosition:
    """An answer at station `s` on `lane` of the map's first segment."""
    seg = hdmap.segments[sorted(hdmap.segments)[0]]
    x, y = seg.point(s, float(seg.lane_offsets(s)[lane]))
    lon, lat = hdmap.projection.to_wgs84(x, y)
    values = {"accuracy": 1.0, "accuracy_cross": 0.5, "accuracy_along": 0.8, **fields}
    return CorrectedPosition(
        timestamp=0,
        latitude=lat,
        longitude=lon,
        segment=seg.id,
        lane=lane,
        lane_type=seg.lanes[lane].type,
        probability=1.0,
        **values,
    )


def test_etsi_lane_positions_on_a_left_hand_road_count_from_its_middle() -> None:
    """A left-hand 2 + 2 road (forward lanes on the left, as in Sydney): the middle lies
    between lanes 1 and 2, so lanes 1 and 2 are innermost (1) and 0 and 3 second (2)."""
    two = (LaneSpec("driving", 3.0, "forward"), LaneSpec("driving", 3.0, "forward"))
    back = (LaneSpec("driving", 3.0, "backward"), LaneSpec("driving", 3.0, "backward"))
    left_hand = small_map(lanes=(LaneSpec("sidewalk", 2.0, "both"), *two, *back))
    assert keeps_left(left_hand) and not keeps_left(small_map())
    numbers = [etsi_lane_position(left_hand, _answer_on(left_hand, k)) for k in range(5)]
    assert numbers == [-1, 2, 1, 1, 2]
    right_hand = small_map(lanes=(*back, *two))
    assert [etsi_lane_position(right_hand, _answer_on(right_hand, k)) for k in range(4)] == [
        2,
        1,
        1,
        2,
    ]
    # a one-way road: the middle is on the driver's left in right-hand traffic, right in left
    one_way = small_map(lanes=two)
    assert [etsi_lane_position(one_way, _answer_on(one_way, k), False) for k in (0, 1)] == [1, 2]
    assert [etsi_lane_position(one_way, _answer_on(one_way, k), True) for k in (0, 1)] == [2, 1]


def test_the_cam_confidence_ellipse_lies_along_the_road_with_both_accuracies() -> None:
    """0.25 m across and 10 m along the road: a 95 % ellipse of 0.61 m by 24.48 m whose
    major axis points along the road (true north bearing, from the WGS84 ellipsoid)."""
    hdmap = small_map()  # its first segment heads 100 degrees (grid)
    answer = _answer_on(hdmap, 2, accuracy=10.0, accuracy_cross=0.25, accuracy_along=10.0)
    ellipse = confidence_ellipse(hdmap, answer)
    assert ellipse.semi_major_confidence == round(10.0 * 2.4477 * 100)
    assert ellipse.semi_minor_confidence == round(0.25 * 2.4477 * 100)
    seg = hdmap.segments[answer.segment or ""]
    a = hdmap.projection.to_wgs84(*seg.point(50.0))
    b = hdmap.projection.to_wgs84(*seg.point(70.0))
    bearing = pyproj.Geod(ellps="WGS84").inv(a[0], a[1], b[0], b[1])[0] % 360.0
    assert ellipse.semi_major_orientation / 10.0 == pytest.approx(bearing, abs=0.15)
    out = answer_cam(cam(), answer, 1, ellipse)
    ref = out["message"]["basic_container"]["reference_position"]
    assert ref["position_confidence_ellipse"] == ellipse.model_dump()
    # wider across than along: the major axis lies across the road
    across = _answer_on(hdmap, 2, accuracy_cross=3.0, accuracy_along=1.0)
    turned = confidence_ellipse(hdmap, across)
    assert turned.semi_major_confidence == round(3.0 * 244.77)
    assert (turned.semi_major_orientation / 10.0 - bearing) % 180.0 == pytest.approx(90.0, abs=0.15)
    off = confidence_ellipse(hdmap, across.model_copy(update={"segment": None, "lane": None}))
    assert off.semi_major_confidence == off.semi_minor_confidence == round(244.77 / math.sqrt(2))


# --- NMEA as real receivers send it ---------------------------------------------------


def _drive(n: int, step_ms: int = 1000, t0_ms: int = 1_700_000_000_000) -> list[GpsMeasurement]:
    """`n` fixes of a car heading north-east at 10 m/s, `step_ms` apart."""
    step = step_ms / 1000.0 * 10.0 / math.sqrt(2.0)  # m north and east per step
    return [
        GpsMeasurement(
            timestamp=t0_ms + i * step_ms,
            latitude=53.55 + i * step / 111_195.0,
            longitude=9.97 + i * step / (111_195.0 * math.cos(math.radians(53.55))),
            altitude=12.5,
            heading=45.0,
            speed=10.0,
            accuracy=1.5,
        )
        for i in range(n)
    ]


def _sentences(fix: GpsMeasurement) -> dict[str, str]:
    return {s[3:6]: s for s in nmea_sentences(fix)}


def test_gga_and_gst_after_the_rmc_of_their_epoch_are_kept() -> None:
    """u-blox, Garmin and NaviLock send RMC first, then GGA and GST of the same epoch."""
    fixes = _drive(3)
    lines = [_sentences(f)[k] for f in fixes for k in ("RMC", "GGA", "GST")]
    read = list(nmea_fixes(lines))
    assert [r.timestamp for r in read if isinstance(r, GpsMeasurement)] == [
        f.timestamp for f in fixes
    ]
    assert all(isinstance(r, GpsMeasurement) and r.altitude == 12.5 for r in read)
    assert all(
        isinstance(r, GpsMeasurement) and r.accuracy == pytest.approx(1.5, abs=0.01) for r in read
    )


def test_a_10_hz_receiver_with_rmc_once_a_second_gets_every_epoch_through() -> None:
    """GGA at every epoch (10 Hz), RMC at whole seconds: 40 epochs, 40 fixes; the
    GGA-only epochs get the speed and course of their positions (positions to 1e-5
    minutes: within 0.3 m/s and 3 degrees over 0.1 s; tests/bridges/test_nmea_rates.py
    has a car that brakes)."""
    fixes = _drive(40, step_ms=100)
    lines = []
    for f in fixes:
        s = _sentences(f)
        lines += [s["GGA"]] + ([s["RMC"]] if f.timestamp % 1000 == 0 else [])
    read = [r for r in nmea_fixes(lines) if isinstance(r, GpsMeasurement)]
    assert [r.timestamp for r in read] == [f.timestamp for f in fixes]
    assert all(r.speed == pytest.approx(10.0, abs=0.3) for r in read), [r.speed for r in read]
    assert all(r.heading == pytest.approx(45.0, abs=3.0) for r in read)


def test_a_gga_only_receiver_is_dated_by_the_clock_and_its_motion_derived() -> None:
    fixes = _drive(5)
    lines = [_sentences(f)["GGA"] for f in fixes]
    now = fixes[-1].timestamp / 1000.0 + 0.5
    read = [r for r in nmea_fixes(lines, now=now) if isinstance(r, GpsMeasurement)]
    assert [r.timestamp for r in read] == [f.timestamp for f in fixes]
    assert read[0].speed == 0.0  # nothing before it to derive from
    assert all(r.speed == pytest.approx(10.0, rel=0.01) for r in read[1:])
    assert all(r.heading == pytest.approx(45.0, abs=0.5) for r in read[1:])
    # without a clock a GGA alone has no date: said, not guessed
    (problem, *_rest) = list(nmea_fixes(lines))
    assert isinstance(problem, Malformed) and "date" in str(problem)


def test_the_gps_week_rollover_is_corrected_against_the_clock() -> None:
    """A receiver whose 10-bit week count rolled over in April 2019 reports 1999: moved
    1024 weeks forward against the clock, as gpsd does; a historical log read without a
    clock keeps its date (the 1994 example of "NMEA Revealed")."""
    true = dt.datetime(2019, 7, 1, 9, 30, tzinfo=dt.UTC)
    reported = true - GPS_ROLLOVER  # 1999-11-15
    assert reported.year == 1999
    fix = _drive(1, t0_ms=round(reported.timestamp() * 1000))[0]
    lines = list(_sentences(fix).values())
    now = (true + dt.timedelta(seconds=2)).timestamp()
    (read,) = nmea_fixes(lines, now=now)
    assert isinstance(read, GpsMeasurement)
    assert read.timestamp == round(true.timestamp() * 1000)
    (kept,) = nmea_fixes(lines)
    assert isinstance(kept, GpsMeasurement) and kept.timestamp == fix.timestamp
    (old,) = nmea_fixes([NMEA_RMC])
    assert isinstance(old, GpsMeasurement) and old.timestamp == 764426119000


def test_gpsd_reports_of_one_epoch_are_sent_once_the_most_complete() -> None:
    """gpsd reports an epoch as its sentences arrive, the least complete first."""
    full = {**GPSD_TPV}
    partial = {k: v for k, v in GPSD_TPV.items() if k not in ("epx", "epy", "alt")}
    later = {**GPSD_TPV, "time": "2011-03-20T06:52:00.12Z"}
    later_partial = {k: v for k, v in later.items() if k != "track"}
    kept = list(tpv_epochs([partial, full, full, later_partial, {**later_partial, "epx": 3.0}]))
    assert kept == [full, {**later_partial, "epx": 3.0}]


def test_a_recorded_log_is_paced_by_its_own_timestamps_moved_to_now() -> None:
    clock = Clock(1_800_000_000.0)
    waits: list[float] = []

    def sleep(s: float) -> None:
        waits.append(s)
        clock.now += s

    fixes = _drive(4, step_ms=1000)
    out = list(paced([fixes[0], Malformed("x"), *fixes[1:]], clock=clock, sleep=sleep))
    sent = [f for f in out if isinstance(f, GpsMeasurement)]
    assert [f.timestamp for f in sent] == [1_800_000_000_000 + 1000 * i for i in range(4)]
    assert waits == pytest.approx([1.0, 1.0, 1.0])
    clock.now, waits[:] = 1_800_000_100.0, []
    list(paced(fixes, speedup=4.0, clock=clock, sleep=sleep))
    assert waits == pytest.approx([0.25, 0.25, 0.25])
