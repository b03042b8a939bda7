"""Moved to `laas.worker.metrics` (the worker's package); `laas.metrics` names the same
objects for the code that imports them from here."""

from laas.worker.metrics import (
    ENGINE_COUNTERS,
    FIX_OUTCOMES,
    WorkerCollector,
    watch_worker,
)

__all__ = [
    "ENGINE_COUNTERS",
    "FIX_OUTCOMES",
    "WorkerCollector",
    "watch_worker",
]
