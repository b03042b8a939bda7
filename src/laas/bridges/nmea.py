"""NMEA 0183 from a receiver (a serial device or a log file), read with pynmea2.

`nmea_fixes` turns sentences into fixes, one per epoch (the sentences that share a time
of day): receivers send an epoch's RMC, GGA, GST and VTG in an order of their own
(u-blox, Garmin and NaviLock put GGA and GST after RMC), and some send GGA alone, or
GGA at 10 Hz and RMC at 1 Hz. An epoch makes a fix when its RMC is valid (``A``) or its
GGA has a fix (quality > 0):

    position           RMC, else GGA
    date               RMC, else the last date seen (the next day after midnight), else
                       the reference clock's (`now`)
    altitude           GGA (0 without one)
    accuracy           GST: hypot(sd_lat, sd_lon), 1-sigma latitude and longitude errors, m
    speed, heading     RMC, else VTG, else from the position change since the previous
                       fix (at most 5 s back), as gpsd does, else those of the last 2 s,
                       else 0
    RMC and VTG speed are in knots:  v [m/s] = knots * 1852 / 3600

A 10 Hz receiver that sends GGA at every epoch and RMC once a second gets, on the GGA-only
epochs, the speed and heading of its own positions (a car braking is seen braking), not
the last RMC's repeated. A fix that did not move keeps the last heading.

An epoch is complete, and its fix sent, once it holds every sentence type the previous
epoch held, or else when the next epoch begins (or the input ends): a receiver's first
epoch waits for its second.

GPS week rollover: receivers that count GPS weeks in 10 bits report dates 1024 weeks
(19.6 years) back once their epoch has passed (1999 in 2019). Given a reference clock
`now`, a fix dated more than 512 weeks before it is moved forward by 1024 weeks until it
is not, as gpsd does; without `now` (a historical log read as it is) dates are kept.

`nmea_sentences` writes a fix as GGA, GST (with an accuracy) and RMC: the logs `gpsfake`
and the tests replay.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pynmea2  # type: ignore[import-untyped]

from laas.bridges.pool import Malformed
from laas.models import GpsMeasurement

__all__ = ["GPS_ROLLOVER", "KNOT", "NmeaReader", "nmea_fixes", "nmea_sentences", "read_nmea_file"]

KNOT = 1852.0 / 3600.0  # m/s per knot
GPS_ROLLOVER = dt.timedelta(weeks=1024)
_MOTION_MAX_AGE = 2.0  # s: the last RMC/VTG speed and course still stand for a fix
_DERIVE_MAX_GAP = 5.0  # s: speed and heading from the position change since the last fix
_EARTH_RADIUS = 6_371_000.0  # m, for the position change (an equirectangular step)


@dataclass
class _Epoch:
    """The sentences of one time of day."""

    time: dt.time
    sentences: dict[str, Any] = field(default_factory=dict)  # sentence type -> message
    sent: bool = False  # its fix has gone out (later sentences of it are ignored)


class NmeaReader:
    """Assembles sentences into fixes, epoch by epoch (the module docstring).

    `feed` takes one line and returns what it completed; `flush` ends the input.
    `now` is the reference clock (Unix s) for the week rollover and for a GGA-only
    receiver's date; None keeps the receiver's dates and needs an RMC date.
    """

    def __init__(self, now: float | None = None) -> None:
        self.now = None if now is None else dt.datetime.fromtimestamp(now, dt.UTC)
        self._epoch: _Epoch | None = None
        self._expected: frozenset[str] = frozenset()
        self._date: dt.date | None = None  # of the last fix (or RMC)
        self._last_time: dt.datetime | None = None  # of the last fix
        self._last_position: tuple[float, float] | None = None
        self._motion: tuple[dt.datetime, float, float] | None = None  # when, speed, course
        self._last_course = 0.0  # of the last fix

    def feed(self, line: str) -> list[GpsMeasurement | Malformed]:
        """One line of the receiver: the fixes (and problems) it completes."""
        line = line.strip()
        if not line.startswith(("$", "!")):
            return []
        try:
            msg = pynmea2.parse(line, check=True)
        except (pynmea2.ParseError, ValueError) as exc:
            return [Malformed(f"NMEA sentence does not parse: {type(exc).__name__}")]
        kind = getattr(msg, "sentence_type", "")
        if kind not in ("RMC", "GGA", "GST", "VTG"):
            return []
        out: list[GpsMeasurement | Malformed] = []
        when = getattr(msg, "timestamp", None)
        if kind == "VTG":  # no time of its own: it belongs to the epoch under way
            if self._epoch is not None and not self._epoch.sent:
                self._epoch.sentences.setdefault(kind, msg)
            return out
        if not isinstance(when, dt.time):
            return out
        when = when.replace(tzinfo=None)
        epoch = self._epoch
        if epoch is None or epoch.time != when:
            if epoch is not None:
                out += self._finish(epoch, learn=True)
            epoch = self._epoch = _Epoch(when)
        if epoch.sent:  # late for its epoch's fix; its speed and course serve the next
            self._expected = self._expected | {kind}
            if kind == "RMC" and msg.status == "A" and self._last_time is not None:
                self._note_motion(self._last_time, {"RMC": msg})
            return out
        epoch.sentences.setdefault(kind, msg)
        if self._expected and self._expected <= epoch.sentences.keys():
            out += self._finish(epoch, learn=False)
        return out

    def flush(self) -> list[GpsMeasurement | Malformed]:
        """The end of the input: the fix of the epoch under way, if any."""
        epoch, self._epoch = self._epoch, None
        return [] if epoch is None else self._finish(epoch, learn=True)

    def _finish(self, epoch: _Epoch, *, learn: bool) -> list[GpsMeasurement | Malformed]:
        if learn:
            self._expected = frozenset(epoch.sentences)
        if epoch.sent:
            return []
        epoch.sent = True
        try:
            fix = self._fix(epoch)
        except (ValueError, TypeError, AttributeError) as exc:
            kinds = "/".join(sorted(epoch.sentences))
            return [Malformed(f"NMEA {kinds} has a bad field: {type(exc).__name__}")]
        return [] if fix is None else [fix]

    def _fix(self, epoch: _Epoch) -> GpsMeasurement | Malformed | None:
        s = epoch.sentences
        rmc: Any = s.get("RMC")
        gga: Any = s.get("GGA")
        rmc_ok = rmc is not None and rmc.status == "A" and rmc.latitude is not None
        gga_ok = gga is not None and bool(gga.gps_qual) and gga.latitude is not None
        if not (rmc_ok or gga_ok):
            return None  # RMC void and GGA without a fix: no fix this epoch
        when = self._when(epoch.time, rmc.datestamp if rmc_ok else None)
        if when is None:
            return Malformed(
                "NMEA GGA without a date (no RMC yet): give a reference clock to date it"
            )
        lat, lon = (rmc.latitude, rmc.longitude) if rmc_ok else (gga.latitude, gga.longitude)
        altitude = float(gga.altitude) if gga_ok and gga.altitude is not None else 0.0
        accuracy = None
        gst = s.get("GST")
        if gst is not None and gst.std_dev_latitude and gst.std_dev_longitude:
            accuracy = math.hypot(float(gst.std_dev_latitude), float(gst.std_dev_longitude))
        speed, heading = self._motion_of(when, s, (lat, lon))
        self._date, self._last_time, self._last_position = when.date(), when, (lat, lon)
        self._last_course = heading % 360.0
        return GpsMeasurement(
            timestamp=round(when.timestamp() * 1000),
            latitude=lat,
            longitude=lon,
            altitude=altitude,
            heading=heading % 360.0,
            speed=min(speed, 150.0),
            accuracy=accuracy,
        )

    def _when(self, time_of_day: dt.time, date: dt.date | None) -> dt.datetime | None:
        """The epoch's UTC date and time, corrected for the GPS week rollover."""
        if date is None and self._date is not None and self._last_time is not None:
            date = self._date
            candidate = dt.datetime.combine(date, time_of_day, dt.UTC)
            if candidate < self._last_time - dt.timedelta(hours=12):  # past midnight
                date = date + dt.timedelta(days=1)
        elif date is None and self.now is not None:  # the day of the reference clock
            now = self.now
            days = [now.date() + dt.timedelta(days=k) for k in (-1, 0, 1)]
            date = min(days, key=lambda d: abs(dt.datetime.combine(d, time_of_day, dt.UTC) - now))
        if date is None:
            return None
        when = dt.datetime.combine(date, time_of_day, dt.UTC)
        if self.now is not None:
            while when < self.now - GPS_ROLLOVER / 2:
                when += GPS_ROLLOVER
        return when

    def _motion_of(
        self, when: dt.datetime, s: dict[str, Any], position: tuple[float, float]
    ) -> tuple[float, float]:
        """Speed (m/s) and course (degrees) of the epoch (the module docstring's order)."""
        motion = self._note_motion(when, s) or self._derived(when, position)
        if motion is not None:
            return motion
        if self._motion is not None:
            at, speed, course = self._motion
            if 0.0 <= (when - at).total_seconds() <= _MOTION_MAX_AGE:
                return speed, course
        return 0.0, 0.0

    def _note_motion(self, when: dt.datetime, s: dict[str, Any]) -> tuple[float, float] | None:
        """The speed (m/s) and course of an epoch's valid RMC, else its VTG, noted as the
        latest; None without either."""
        rmc, vtg = s.get("RMC"), s.get("VTG")
        if rmc is not None and rmc.status == "A" and rmc.spd_over_grnd is not None:
            motion = (float(rmc.spd_over_grnd) * KNOT, float(rmc.true_course or 0.0))
        elif vtg is not None and vtg.spd_over_grnd_kts is not None:
            motion = (float(vtg.spd_over_grnd_kts) * KNOT, float(vtg.true_track or 0.0))
        else:
            return None
        self._motion = (when, *motion)
        return motion

    def _derived(
        self, when: dt.datetime, position: tuple[float, float]
    ) -> tuple[float, float] | None:
        """Speed and course from the position change since the last fix; None without a
        fix 0-5 s before. A fix that did not move keeps the last course.

        dx = R * dlon * cos(lat), dy = R * dlat (radians); v = hypot(dx, dy) / dt;
        course = atan2(dx, dy) from north, clockwise.
        """
        if self._last_time is None or self._last_position is None:
            return None
        gap = (when - self._last_time).total_seconds()
        if not 0.0 < gap <= _DERIVE_MAX_GAP:
            return None
        lat0, lon0 = self._last_position
        dy = math.radians(position[0] - lat0) * _EARTH_RADIUS
        dx = math.radians(position[1] - lon0) * _EARTH_RADIUS * math.cos(math.radians(lat0))
        if dx == 0.0 and dy == 0.0:
            return 0.0, self._last_course
        return math.hypot(dx, dy) / gap, math.degrees(math.atan2(dx, dy)) % 360.0


def nmea_fixes(
    lines: Iterable[str], *, now: float | None = None
) -> Iterator[GpsMeasurement | Malformed]:
    """A fix per epoch; a Malformed per sentence that does not parse or check
    (`NmeaReader`; `now`: the reference clock, Unix s)."""
    reader = NmeaReader(now)
    for line in lines:
        yield from reader.feed(line)
    yield from reader.flush()


def read_nmea_file(path: Path, *, now: float | None = None) -> Iterator[GpsMeasurement | Malformed]:
    """`nmea_fixes` of a file or a serial device (set its baud rate first: ``stty``)."""
    with open(path, encoding="ascii", errors="replace") as f:
        yield from nmea_fixes(f, now=now)


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
