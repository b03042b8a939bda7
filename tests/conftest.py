"""Shared pytest configuration: a report header with the versions that matter."""

from __future__ import annotations

import numpy
import pyproj
import shapely


def pytest_report_header() -> list[str]:
    return [
        f"numpy {numpy.__version__}, shapely {shapely.__version__} "
        f"(GEOS {shapely.geos_version_string}), "
        f"pyproj {pyproj.__version__} (PROJ {pyproj.proj_version_str})"
    ]
