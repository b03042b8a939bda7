"""NMEA 0183 from a receiver (a serial device or a log file), read with pynmea2.

`nmea_fixes` turns sentences into fixes: a fix per valid RMC (time, date, position,
speed, course), with the altitude of the GGA and the error estimate of the GST of the
same second when they came first. `nmea_sentences` writes a fix as GGA, RMC and, with
an accuracy, GST: the logs `gpsfake` replays in the tests.

    RMC speed is in knots:          v [m/s] = knots * 1852 / 3600
    GST gives 1-sigma errors of latitude and longitude in metres:
                                    accuracy = hypot(sd_lat, sd_lon)  (a 1-sigma radius)
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Iterator
from pathlib import Path

import pynmea2  # type: ignore[import-untyped]

from laas.bridges.pool import Malformed
from laas.models import GpsMeasurement

__all__ = ["KNOT", "nmea_fixes", "nmea_sentences", "read_nmea_file"]

KNOT = 1852.0 / 3600.0  # m/s per knot


def nmea_fixes(lines: Iterable[str]) -> Iterator[GpsMeasurement | Malformed]:
    """A fix per valid RMC; a Malformed per sentence that does not parse or check."""
    altitude: tuple[dt.time, float] | None = None
    error: tuple[dt.time, float] | None = None
    for line in lines:
        line = line.strip()
        if not line.startswith(("$", "!")):
            continue
        try:
            msg = pynmea2.parse(line, check=True)
        except (pynmea2.ParseError, ValueError) as exc:
            yield Malformed(f"NMEA sentence does not parse: {type(exc).__name__}")
            continue
        try:
            if isinstance(msg, pynmea2.GGA):
                if msg.gps_qual and msg.altitude is not None and msg.timestamp is not None:
                    altitude = (msg.timestamp, float(msg.altitude))
            elif isinstance(msg, pynmea2.GST):
                sd_lat, sd_lon = msg.std_dev_latitude, msg.std_dev_longitude
                if msg.timestamp is not None and sd_lat and sd_lon:
                    error = (msg.timestamp, math.hypot(float(sd_lat), float(sd_lon)))
            elif isinstance(msg, pynmea2.RMC):
                fix = _rmc_fix(msg, altitude, error)
                if fix is not None:
                    yield fix
        except (ValueError, TypeError, AttributeError) as exc:
            yield Malformed(f"NMEA {msg.sentence_type} has a bad field: {type(exc).__name__}")


def _rmc_fix(
    msg: pynmea2.RMC, altitude: tuple[dt.time, float] | None, error: tuple[dt.time, float] | None
) -> GpsMeasurement | None:
    if msg.status != "A" or msg.timestamp is None or msg.datestamp is None:
        return None  # V = void: no fix
    when = dt.datetime.combine(msg.datestamp, msg.timestamp)
    if when.tzinfo is None:
        when = when.replace(tzinfo=dt.UTC)
    speed = float(msg.spd_over_grnd or 0.0) * KNOT
    course = float(msg.true_course or 0.0) % 360.0
    same = msg.timestamp.replace(tzinfo=None)
    return GpsMeasurement(
        timestamp=round(when.timestamp() * 1000),
        latitude=msg.latitude,
        longitude=msg.longitude,
        altitude=altitude[1] if altitude and altitude[0].replace(tzinfo=None) == same else 0.0,
        heading=course,
        speed=min(speed, 150.0),
        accuracy=error[1] if error and error[0].replace(tzinfo=None) == same else None,
    )


def read_nmea_file(path: Path) -> Iterator[GpsMeasurement | Malformed]:
    """`nmea_fixes` of a file or a serial device (set its baud rate first: ``stty``)."""
    with open(path, encoding="ascii", errors="replace") as f:
        yield from nmea_fixes(f)


def _angle(value: float, positive: str, negative: str, degree_digits: int) -> tuple[str, str]:
    """NMEA's ddmm.mmmmm (or dddmm.mmmmm) and its hemisphere."""
    a = abs(value)
    degrees = int(a)
    minutes = (a - degrees) * 60.0
    return f"{degrees:0{degree_digits}d}{minutes:08.5f}", positive if value >= 0 else negative


def nmea_sentences(fix: GpsMeasurement, talker: str = "GP") -> list[str]:
    """GGA, then GST (with an accuracy), then RMC of one fix, with checksums."""
    when = dt.datetime.fromtimestamp(fix.timestamp / 1000.0, dt.UTC)
    hhmmss = when.strftime("%H%M%S.") + f"{when.microsecond // 10_000:02d}"
    lat, ns = _angle(fix.latitude, "N", "S", 2)
    lon, ew = _angle(fix.longitude, "E", "W", 3)
    gga = (
        hhmmss,
        lat,
        ns,
        lon,
        ew,
        "1",
        "08",
        "0.9",
        f"{fix.altitude:.1f}",
        "M",
        "0.0",
        "M",
        "",
        "",
    )
    sentences = [pynmea2.GGA(talker, "GGA", gga)]
    if fix.accuracy is not None:
        sd = fix.accuracy / math.sqrt(2.0)  # per axis
        gst = (hhmmss, f"{fix.accuracy:.2f}", "", "", "", f"{sd:.2f}", f"{sd:.2f}", "")
        sentences.append(pynmea2.GST(talker, "GST", gst))
    rmc = (
        hhmmss,
        "A",
        lat,
        ns,
        lon,
        ew,
        f"{fix.speed / KNOT:.2f}",
        f"{fix.heading:.1f}",
        when.strftime("%d%m%y"),
        "",
        "",
        "A",
    )
    sentences.append(pynmea2.RMC(talker, "RMC", rmc))
    return [str(s) for s in sentences]
