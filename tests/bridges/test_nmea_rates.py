"""A 10 Hz receiver (GGA at every epoch, RMC once a second, RMC first as u-blox sends
it): on the GGA-only epochs the speed and heading come from the positions, as gpsd
derives them, not from the last RMC repeated."""

from __future__ import annotations

import math

import pynmea2  # type: ignore[import-untyped]

from laas.bridges.nmea import nmea_fixes, nmea_sentences
from laas.models import GpsMeasurement

R = 6_371_000.0
START = 1_764_000_000_000  # ms, a whole second
LAT0, LON0, HEADING = 53.5600, 9.9800, 60.0
V0, ACCEL = 10.0, -2.0  # a car braking from 10 m/s at 2 m/s^2


def distance(t: float) -> float:
    return V0 * t + ACCEL * t * t / 2


def truth(t: float) -> GpsMeasurement:
    """The car at t s after START: on a straight line at HEADING."""
    s = distance(t)
    north, east = s * math.cos(math.radians(HEADING)), s * math.sin(math.radians(HEADING))
    return GpsMeasurement(
        timestamp=START + round(t * 1000),
        latitude=LAT0 + math.degrees(north / R),
        longitude=LON0 + math.degrees(east / (R * math.cos(math.radians(LAT0)))),
        altitude=10.0,
        heading=HEADING,
        speed=V0 + ACCEL * t,
    )


def ten_hz_log(seconds: int) -> list[str]:
    lines: list[str] = []
    for k in range(seconds * 10 + 1):
        gga, rmc = nmea_sentences(truth(k / 10))
        assert pynmea2.parse(gga).sentence_type == "GGA"
        lines += [rmc, gga] if k % 10 == 0 else [gga]
    return lines


def test_gga_only_epochs_of_a_10_hz_receiver_get_the_speed_of_their_positions() -> None:
    fixes = [f for f in nmea_fixes(ten_hz_log(3)) if isinstance(f, GpsMeasurement)]
    assert len(fixes) == 31
    checked = 0
    for k, fix in enumerate(fixes):
        t = k / 10
        assert fix.timestamp == START + round(t * 1000)
        if k % 10 == 0:  # an RMC epoch: the receiver's own speed (to 0.01 kn)
            assert abs(fix.speed - (V0 + ACCEL * t)) < 0.01
            continue
        last_rmc = V0 + ACCEL * (k // 10)  # what repeating the last RMC would give
        mean = (distance(t) - distance(t - 0.1)) / 0.1  # over the epoch's 0.1 s
        # positions to 1e-5 minutes (1.9 cm): the speed over 0.1 s to within 0.3 m/s
        assert abs(fix.speed - mean) < 0.3, (k, fix.speed, mean)
        assert abs(fix.heading - HEADING) < 6.0, (k, fix.heading)
        if abs(last_rmc - mean) > 0.6:
            checked += 1
            assert abs(fix.speed - mean) < abs(fix.speed - last_rmc)
    assert checked >= 12  # epochs where the last RMC's speed was wrong by 0.6 m/s or more
