"""Recorded traces: JSON Lines, one `GpsMeasurement` per line plus a `user` field.

    {"user": "car", "timestamp": 1700000000000, "latitude": 53.5588, "longitude": 9.9761,
     "altitude": 10.0, "heading": 25.0, "speed": 5.1}

Reading never stops at a bad line: each one becomes a `TraceError` that names the line
and the problem, and the reader goes on with the next.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from pydantic import ValidationError

from laas.errors import TraceError
from laas.models import CorrectedPosition, GpsMeasurement, problems

__all__ = ["TraceLine", "format_answer", "format_measurement", "read_trace"]

MAX_LINE = 64 * 1024  # bytes; a longer line is refused, not parsed


@dataclass(frozen=True, slots=True)
class TraceLine:
    """One good line of a trace."""

    line: int
    user: str
    measurement: GpsMeasurement


def read_trace(lines: Iterable[str], source: str = "<trace>") -> Iterator[TraceLine | TraceError]:
    """Yield each line as a `TraceLine`, or as a `TraceError` naming `source:line`."""
    for number, text in enumerate(lines, start=1):
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
