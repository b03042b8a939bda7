"""The maps that ship with LaaS, where to find them, and `load_map`: a map by file or name.

Looked for in this order: the folder named by ``$LAAS_MAPS``; the checkout's ``maps/``
(an editable install or a source tree); the installed copy under
``<prefix>/share/laas/maps`` (``pip install .`` puts it there, see ``pyproject.toml``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from laas.errors import MapError
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap

__all__ = ["bundled_map", "load_map", "maps_dir"]


def maps_dir() -> Path:
    """The folder of the bundled maps."""
    chosen = os.environ.get("LAAS_MAPS")
    if chosen:
        return Path(chosen)
    checkout = Path(__file__).resolve().parents[3] / "maps"
    if checkout.is_dir():
        return checkout
    return Path(sys.prefix) / "share" / "laas" / "maps"


def bundled_map(name: str) -> Path:
    """The path of bundled map `name` (without ``.geojson``); MapError if it is missing."""
    path = maps_dir() / f"{name}.geojson"
    if not path.is_file():
        raise MapError(
            f"bundled map {name!r} not found at {path}; set LAAS_MAPS to the folder that "
            "holds the project's maps/"
        )
    return path


def load_map(source: str | os.PathLike[str]) -> HdMap:
    """A lane map from a GeoJSON file (`laas map import` makes one), or the bundled map of
    that name (``"messe-hamburg"``); MapError names the file or feature at fault.

    >>> load_map("messe-hamburg").segments["messe-0"].lanes[0].type
    'driving'
    """
    path = Path(source)
    if isinstance(source, str) and path.suffix == "" and len(path.parts) == 1:
        path = bundled_map(source)
    if not path.is_file():
        raise MapError(f"no map file at {path}; give a GeoJSON lane map or a bundled map's name")
    return read_geojson_file(path)
