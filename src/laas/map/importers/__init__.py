"""Map importers: real HD maps into the GeoJSON lane-map format (``maps/README.md``).

common      lane drafts, the report of what was left out, writing a map the loader accepts
lanelet2    Lanelet2 OSM maps (Autoware, research), read with the ``lanelet2`` package
opendrive   ASAM OpenDRIVE roads (simulation, carmakers)
osm         OpenStreetMap ways with lane tags, read with ``osmium``

Each importer returns an `ImportResult` (the map as loaded, its GeoJSON, the report);
the engine never learns where a map came from. The readers are imported on use, since
they need the ``maps`` extra (``pip install laas[maps]``).
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, Literal

from laas.errors import ConfigError
from laas.map.importers.common import ImportReport, ImportResult, LaneDraft

__all__ = ["FORMATS", "ImportReport", "ImportResult", "LaneDraft", "import_map"]

Format = Literal["lanelet2", "opendrive", "osm"]
FORMATS: tuple[Format, ...] = ("lanelet2", "opendrive", "osm")


def import_map(fmt: Format, path: str | Path, **options: Any) -> ImportResult:
    """Import the map at `path` from format `fmt` with ``laas.map.importers.<fmt>``'s
    ``import_<fmt>``; options go to it. Raises `laas.MapError` naming the problem (and
    the source element); a missing ``maps`` extra is a `ConfigError` that says so."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown map format {fmt!r} (expected one of {', '.join(FORMATS)})")
    try:
        module = importlib.import_module(f"laas.map.importers.{fmt}")
    except ImportError as exc:
        raise ConfigError(
            f"the {fmt} importer needs {exc.name!r}: pip install 'laas[maps]'"
        ) from exc
    result: ImportResult = getattr(module, f"import_{fmt}")(path, **options)
    return result
