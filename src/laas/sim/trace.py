"""Recorded traces: JSON Lines, one `GpsMeasurement` per line plus a `user` field.

    {"user": "car", "timestamp": 1700000000000, "latitude": 53.5588, "longitude": 9.9761,
     "altitude": 10.0, "heading": 25.0, "speed": 5.1}

Reading never stops at a bad line: each one becomes a `TraceError` that names the line
and the problem, and the reader goes on with the next.

A trace that is still being written (a pipe, a terminal: `is_live`) is read with
`live_lines`, which says `IDLE` whenever no whole line is ready, so that `laas replay`
answers what it has instead of waiting for the next line (`laas.sim.batches`).
"""

from __future__ import annotations

import json
import os
import select
import stat
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Literal

from pydantic import ValidationError

from laas.errors import TraceError
from laas.models import CorrectedPosition, GpsMeasurement, problems
from laas.sim.batches import IDLE, Idle

__all__ = [
    "TraceLine",
    "format_answer",
    "format_measurement",
    "is_live",
    "live_lines",
    "read_trace",
]

MAX_LINE = 64 * 1024  # bytes; a longer line is refused, not parsed


@dataclass(frozen=True, slots=True)
class TraceLine:
    """One good line of a trace."""

    line: int
    user: str
    measurement: GpsMeasurement


def is_live(fd: int) -> bool:
    """Whether the file descriptor is not a regular file (a pipe, a terminal, a socket):
    its next line may be long in coming."""
    return not stat.S_ISREG(os.fstat(fd).st_mode)


def live_lines(fd: int, chunk: int = 65536) -> Iterator[str | Literal[Idle.IDLE]]:
    """The lines of a pipe or terminal as they come, and `IDLE` before each wait for
    more: whenever no whole line is ready. Bytes that are not UTF-8 become U+FFFD, and
    the line holding them fails to read as a trace line (or names a strange user)."""
    buffer = b""
    while True:
        end = buffer.find(b"\n")
        if end >= 0:
            line, buffer = buffer[: end + 1], buffer[end + 1 :]
            yield line.decode("utf-8", errors="replace")
            continue
        if not select.select([fd], [], [], 0)[0]:
            yield IDLE
        data = os.read(fd, chunk)  # blocks until more comes, or the writer closes
        if not data:
            if buffer:
                yield buffer.decode("utf-8", errors="replace")
            return
        buffer += data


def read_trace(
    lines: Iterable[str | Literal[Idle.IDLE]], source: str = "<trace>"
) -> Iterator[TraceLine | TraceError | Literal[Idle.IDLE]]:
    """Yield each line as a `TraceLine`, or as a `TraceError` naming `source:line`;
    `IDLE` among the lines is passed on."""
    number = 0
    for text in lines:
        if text is IDLE:
            yield IDLE
            continue
        number += 1
        if not text.strip():
            continue
        where = f"{source}:{number}"
        if len(text) > MAX_LINE:
            yield TraceError(f"{where}: line is longer than {MAX_LINE} bytes")
            continue
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            yield TraceError(f"{where}: not JSON ({exc.msg} at column {exc.colno})")
            continue
        if not isinstance(data, dict):
            yield TraceError(f"{where}: expected a JSON object, got {type(data).__name__}")
            continue
        user = data.pop("user", None)
        if not isinstance(user, str) or not user:
            yield TraceError(f"{where}: user: a non-empty string is required")
            continue
        try:
            measurement = GpsMeasurement.model_validate(data)
        except ValidationError as exc:
            found = problems(exc, whole="line")
            yield TraceError(f"{where}: " + "; ".join(f"{f}: {p}" for f, p in found))
            continue
        yield TraceLine(number, user, measurement)


def format_measurement(user: str, measurement: GpsMeasurement) -> str:
    """One trace line (no newline)."""
    return json.dumps({"user": user, **measurement.model_dump(exclude_none=True)})


def format_answer(user: str, answer: CorrectedPosition) -> str:
    """One output line of `laas replay` (no newline): the answer's fields plus `user`."""
    return json.dumps({"user": user, **answer.model_dump()})
