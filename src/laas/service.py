"""The LaaS worker: the positioning engine offered as an LDM service named `laas`.

It takes every participant's `GpsMeasurement` through the provider's one wildcard
subscription, keeps a Kalman track per pseudonym (a rotated pseudonym simply starts a
new track; the common-error estimate, which is not per user, carries the group over),
and answers each accepted fix with a `CorrectedPosition`. A fix it cannot use gets an
error reply that names the field and the problem. The handler runs on the provider's
one worker thread, so the engine needs no lock.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib.metadata import version
from typing import Any

from pydantic import ValidationError

from laas.config import EngineConfig
from laas.engine import Engine
from laas.hdmap import HdMap
from laas.models import CorrectedPosition, GpsMeasurement
from ldm import BrokerSettings, Provider, Request, ServiceSpec

__all__ = ["SERVICE_NAME", "LaasService", "WorkerStats", "service_spec", "start_worker"]

SERVICE_NAME = "laas"

log = logging.getLogger(__name__)


def service_spec() -> ServiceSpec:
    """What the worker announces: name, version and the two wire schemas."""
    return ServiceSpec(
        name=SERVICE_NAME,
        version=version("laas"),
        description="Lane-level cooperative positioning: send GNSS fixes, get lane positions back.",
        input_schema=GpsMeasurement.model_json_schema(),
        output_schema=CorrectedPosition.model_json_schema(),
    )


@dataclass
class WorkerStats:
    """What the worker did with its input."""

    answered: int = 0
    invalid: int = 0
    refused: int = 0  # duplicates and fixes older than the track's last


def _error(kind: str, message: str, fields: list[dict[str, str]] | None = None) -> dict[str, Any]:
    return {"error": {"kind": kind, "message": message, "fields": fields or []}}


class LaasService:
    """Decode, correct, answer. `handle` is the provider's handler."""

    def __init__(
        self,
        hdmap: HdMap,
        config: EngineConfig | None = None,
        *,
        expire_every: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.engine = Engine(hdmap, config)
        self.stats = WorkerStats()
        self._clock = clock
        self._expire_every = expire_every
        self._next_expiry = clock() + expire_every
        self._latest_ms = 0

    def handle(self, request: Request) -> Mapping[str, Any]:
        """One fix of one pseudonym -> its corrected position, or an error reply."""
        try:
            measurement = GpsMeasurement.model_validate(request.payload)
        except ValidationError as exc:
            self.stats.invalid += 1
            fields = [
                {"field": ".".join(str(x) for x in e["loc"]) or "payload", "problem": e["msg"]}
                for e in exc.errors()
            ]
            summary = "; ".join(f"{f['field']}: {f['problem']}" for f in fields)
            return _error("invalid", f"measurement refused: {summary}", fields)
        answer = self.engine.process(request.pseudonym, measurement)
        self._latest_ms = max(self._latest_ms, measurement.timestamp)
        now = self._clock()
        if now >= self._next_expiry:
            self.engine.expire(self._latest_ms)
            self._next_expiry = now + self._expire_every
        if answer is None:
            self.stats.refused += 1
            return _error(
                "stale",
                f"timestamp {measurement.timestamp} is not newer than this session's last fix",
                [{"field": "timestamp", "problem": "not newer than the last fix"}],
            )
        self.stats.answered += 1
        return answer.model_dump()


def start_worker(
    cluster: BrokerSettings | str,
    hdmap: HdMap,
    config: EngineConfig | None = None,
    **provider_settings: Any,
) -> tuple[Provider, LaasService]:
    """Connect to a service-cluster broker, announce `laas` and serve until stopped."""
    service = LaasService(hdmap, config)
    provider = Provider.create(cluster, service_spec(), service.handle, **provider_settings)
    provider.start()
    log.info("laas worker serving map %s on %s", hdmap.source, BrokerSettings.of(cluster).url)
    return provider, service
