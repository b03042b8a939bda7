"""Moved to `laas.worker.processes` (the worker's package); `laas.run.workers` names the same
objects for the code that imports them from here."""

from laas.worker.processes import (
    child_argv,
    serve_processes,
)

__all__ = [
    "child_argv",
    "serve_processes",
]
