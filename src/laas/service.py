"""Moved to `laas.worker.service` (the worker's package); `laas.service` names the same
objects for the code that imports them from here."""

from laas.worker.service import (
    SERVICE_NAME,
    LaasService,
    Observation,
    WorkerConfig,
    WorkerStats,
    service_spec,
    start_worker,
)

__all__ = [
    "SERVICE_NAME",
    "LaasService",
    "Observation",
    "WorkerConfig",
    "WorkerStats",
    "service_spec",
    "start_worker",
]
