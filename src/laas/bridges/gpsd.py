"""A GNSS receiver on in-car Linux as one LaaS participant: gpsd's TPV reports, or NMEA.

`gpsd_fixes` connects to a gpsd daemon, asks for JSON reports (``?WATCH``) and turns
each TPV report into a fix (gpsd_json(5), https://gpsd.io/gpsd_json.html):

    time (ISO 8601, UTC)  -> timestamp, ms
    lat, lon, alt (m)     -> position
    track (deg from true north), speed (m/s) -> heading, speed
    epx, epy: longitude and latitude errors, m, 95 % confidence per axis
        sigma_x = epx / 1.96, sigma_y = epy / 1.96
        accuracy = hypot(sigma_x, sigma_y)            (a 1-sigma horizontal radius)
    mode < 2              -> no fix, skipped

gpsd reports an epoch several times as its sentences arrive, the least complete first
(13 TPVs for 9 epochs of one receiver). `tpv_epochs` keeps one report per epoch (per
`time`): the first complete one (mode 3 with every field above), else the last, which
gpsd has merged the most into, once the next epoch begins.

`paced` sends a recorded log's fixes at the pace of their own timestamps, moved to the
wall clock (the worker refuses fixes 10 minutes old, and the user core a burst of
more than 20), and `run_receiver` sends a stream of fixes as one device of a
`DevicePool` and hands each answer to a callback (`laas gpsd` prints them as JSON Lines).
"""

from __future__ import annotations

import datetime as dt
import json
import math
import socket
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from laas.bridges.pool import Answer, DevicePool, Malformed
from laas.models import GpsMeasurement, problems

__all__ = [
    "Tpv",
    "gpsd_fixes",
    "paced",
    "parse_address",
    "run_receiver",
    "tpv_epochs",
    "tpv_fix",
]

Z95 = 1.96  # a normal variable is within 1.96 sigma 95 % of the time
WATCH = b'?WATCH={"enable":true,"json":true};\n'


class Tpv(BaseModel):
    """The fields of a gpsd TPV report the bridge reads; the others are ignored."""

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)

    class_: Literal["TPV"] = Field(alias="class")
    mode: int = Field(ge=0, le=3)
    time: dt.datetime | None = None
    lat: float | None = Field(default=None, ge=-90.0, le=90.0)
    lon: float | None = Field(default=None, ge=-180.0, le=180.0)
    alt: float | None = Field(default=None, ge=-1_000.0, le=100_000.0)
    track: float | None = Field(default=None, ge=0.0, le=360.0)
    speed: float | None = Field(default=None, ge=0.0)
    epx: float | None = Field(default=None, gt=0.0)
    epy: float | None = Field(default=None, gt=0.0)


def tpv_fix(report: dict[str, object]) -> GpsMeasurement | None:
    """The fix of one TPV report; None without a fix; Malformed if it is broken."""
    try:
        tpv = Tpv.model_validate(report)
    except ValidationError as exc:
        raise Malformed("; ".join(f"{f}: {p}" for f, p in problems(exc, "TPV"))) from None
    if tpv.mode < 2 or tpv.time is None or tpv.lat is None or tpv.lon is None:
        return None
    when = tpv.time if tpv.time.tzinfo is not None else tpv.time.replace(tzinfo=dt.UTC)
    accuracy = None
    if tpv.epx is not None and tpv.epy is not None:
        accuracy = math.hypot(tpv.epx / Z95, tpv.epy / Z95)
    return GpsMeasurement(
        timestamp=round(when.timestamp() * 1000),
        latitude=tpv.lat,
        longitude=tpv.lon,
        altitude=tpv.alt or 0.0,
        heading=(tpv.track or 0.0) % 360.0,
        speed=min(tpv.speed or 0.0, 150.0),
        accuracy=min(accuracy, 10_000.0) if accuracy else None,
    )


_COMPLETE = ("lat", "lon", "alt", "track", "speed", "epx", "epy")


def tpv_epochs(reports: Iterable[dict[str, Any]]) -> Iterator[dict[str, Any]]:
    """One TPV report per epoch (per ``time``), in order: the first complete one, else
    the last of its epoch (emitted when the next epoch's first report arrives, or at the
    end). Reports without a time pass through."""
    pending: dict[str, Any] | None = None
    sent_time: object = None
    for report in reports:
        when = report.get("time")
        if when is None:
            yield report
            continue
        if when == sent_time:
            continue  # its epoch already went out complete
        if pending is not None and pending.get("time") != when:
            yield pending
        pending = report
        if report.get("mode") == 3 and all(report.get(k) is not None for k in _COMPLETE):
            yield report
            sent_time, pending = when, None
    if pending is not None:
        yield pending


def paced(
    fixes: Iterable[GpsMeasurement | Malformed],
    *,
    speedup: float = 1.0,
    clock: Callable[[], float] = time.time,
    sleep: Callable[[float], None] = time.sleep,
) -> Iterator[GpsMeasurement | Malformed]:
    """A recorded log's fixes, each when its time comes: the first now, a later one
    (t - t_first) / speedup seconds after it, its timestamp moved by the same offset as
    the first's to now (the spacing kept). A Malformed passes at once."""
    start: float | None = None
    first = 0
    for item in fixes:
        if isinstance(item, Malformed):
            yield item
            continue
        if start is None:
            start, first = clock(), item.timestamp
        due = start + (item.timestamp - first) / 1000.0 / speedup
        wait = due - clock()
        if wait > 0:
            sleep(wait)
        shift = round(start * 1000.0) - first
        yield item.model_copy(update={"timestamp": item.timestamp + shift})


def parse_address(address: str) -> tuple[str, int]:
    """``HOST:PORT`` (gpsd's default port 2947 when left out)."""
    host, _, port = address.rpartition(":") if ":" in address else (address, "", "2947")
    if not host or not port.isdigit():
        raise ValueError(f"{address!r}: give gpsd as HOST:PORT, e.g. localhost:2947")
    return host, int(port)


def gpsd_fixes(
    host: str, port: int, *, timeout: float = 10.0
) -> Iterator[GpsMeasurement | Malformed]:
    """Fixes from a gpsd daemon until it closes the connection (or `timeout` s of silence)."""
    problems: list[Malformed] = []
    with socket.create_connection((host, port), timeout=timeout) as sock:
        sock.sendall(WATCH)
        with sock.makefile("r", encoding="utf-8", errors="replace") as lines:
            for report in tpv_epochs(_tpv_reports(_until_silent(lines), problems)):
                yield from problems
                problems.clear()
                try:
                    fix = tpv_fix(report)
                except Malformed as exc:
                    yield exc
                    continue
                if fix is not None:
                    yield fix
            yield from problems


def _tpv_reports(lines: Iterable[str], problems: list[Malformed]) -> Iterator[dict[str, Any]]:
    """The TPV reports among gpsd's lines; a line that is not JSON goes to `problems`."""
    for line in lines:
        try:
            report = json.loads(line)
        except ValueError:
            problems.append(Malformed("gpsd sent a line that is not JSON"))
            continue
        if isinstance(report, dict) and report.get("class") == "TPV":
            yield report  # not VERSION, DEVICES, WATCH, SKY, ...


def _until_silent(lines: Iterator[str]) -> Iterator[str]:
    """The lines, until the socket's timeout passes without one (the receiver is quiet)."""
    try:
        yield from lines
    except TimeoutError:
        return


def run_receiver(
    fixes: Iterable[GpsMeasurement | Malformed],
    pool: DevicePool,
    name: str,
    on_answer: Callable[[Answer], None],
) -> int:
    """Send every fix as device `name`; count a Malformed and go on. The fixes sent."""
    sent = 0
    for item in fixes:
        if isinstance(item, Malformed):
            pool.malformed(name, str(item))
            continue
        pool.submit(name, item, on_answer)
        sent += 1
        pool.expire()
    return sent
