"""Moved to `laas.worker.regions` (the worker's package); `laas.regions` names the same
objects for the code that imports them from here."""

from laas.worker.regions import (
    Region,
    parse_region,
    split,
)

__all__ = [
    "Region",
    "parse_region",
    "split",
]
