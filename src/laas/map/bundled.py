"""The maps that ship with LaaS, and where to find them.

Looked for in this order: the folder named by ``$LAAS_MAPS``; the checkout's ``maps/``
(an editable install or a source tree); the installed copy under
``<prefix>/share/laas/maps`` (``pip install .`` puts it there, see ``pyproject.toml``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from laas.errors import MapError

__all__ = ["bundled_map", "maps_dir"]


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
