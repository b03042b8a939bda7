"""Log lines for operators: plain text, or one JSON object per line.

    configure("json", component="ldm-core-user", level=logging.INFO)

Each JSON line holds ``ts`` (UTC, ISO 8601), ``level``, ``component`` (the process:
which core, the worker), ``event`` (a short name for what happened: the log call's
``extra={"event": ...}``, else made from its message template), ``logger``,
``thread`` and ``message``. A logged exception adds ``error`` (its type) and
``stack`` (file, line and function of each frame), never the exception's text: that
may quote the input it failed on (pydantic's errors quote the values), such as a
position.

What the LDM and LaaS log never holds a key, a password or a participant's position
(docs/operations.md lists the log calls): passwords are `SecretStr`, keys stay in
their objects, and positions travel only inside encrypted payloads and the engine.
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import traceback
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal, get_args

from ldm.errors import ConfigError

__all__ = ["ENV", "LOG_FORMATS", "JsonFormatter", "LogFormat", "configure", "event_of"]

LogFormat = Literal["text", "json"]
LOG_FORMATS: tuple[str, ...] = get_args(LogFormat)
ENV = "LDM_LOG_FORMAT"
"""The environment variable that chooses the format when no option does."""

_PLACEHOLDER = re.compile(r"%(\([^)]*\))?[-#0 +]*\d*(\.\d+)?[sdifrxXeEgGc%]")
_WORD = re.compile(r"[a-z0-9]+")
_EVENT_WORDS = 6


def event_of(record: logging.LogRecord) -> str:
    """The record's event: ``extra={"event": ...}`` if the call gave one, else the first
    words of its message template with the placeholders left out (stable across calls:
    ``"%s: disconnected (%s), reconnecting"`` -> ``disconnected_reconnecting``)."""
    given = getattr(record, "event", None)
    if isinstance(given, str) and given:
        return given
    template = _PLACEHOLDER.sub(" ", str(record.msg)).lower()
    return "_".join(_WORD.findall(template)[:_EVENT_WORDS]) or "log"


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (see the module docstring)."""

    def __init__(self, component: str) -> None:
        super().__init__()
        self.component = component

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, object] = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "component": self.component,
            "event": event_of(record),
            "logger": record.name,
            "thread": record.threadName,
            "message": record.getMessage(),
        }
        if record.exc_info and record.exc_info[0] is not None:
            kind, _error, tb = record.exc_info
            line["error"] = kind.__name__
            line["stack"] = [
                f"{Path(frame.filename).name}:{frame.lineno} in {frame.name}"
                for frame in traceback.extract_tb(tb)
            ]
        return json.dumps(line, ensure_ascii=False, default=str)


def configure(
    log_format: str | None,
    *,
    component: str,
    level: int = logging.WARNING,
    text_format: str = "%(asctime)s %(name)s %(levelname)s %(message)s",
) -> LogFormat:
    """Send the process's log to stderr as text or JSON lines (None: ``LDM_LOG_FORMAT``,
    else text); replaces any handler set before. Returns the format chosen."""
    chosen = (log_format or os.environ.get(ENV) or "text").strip().lower()
    if chosen not in LOG_FORMATS:
        raise ConfigError(
            f"log format {chosen!r}: use text or json (--log-format, or the variable {ENV})"
        )
    handler = logging.StreamHandler(sys.stderr)
    if chosen == "json":
        handler.setFormatter(JsonFormatter(component))
    else:
        handler.setFormatter(logging.Formatter(text_format))
    logging.basicConfig(level=level, handlers=[handler], force=True)
    return "json" if chosen == "json" else "text"
