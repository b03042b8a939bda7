"""WGS84 <-> UTM projection: the one place where pyproj is used.

Everything metric in LaaS (Kalman states, the HD map, lane offsets) lives in one UTM zone, chosen
from a location with :meth:`UtmProjection.for_location`. pyproj objects never leave this module:
callers see floats, tuples and numpy arrays.

Conventions: longitude first (x, y order, as in GeoJSON), degrees; UTM easting/northing in metres.
UTM "grid north" differs from true north by the meridian convergence (about 0.8 degrees in
Hamburg); :meth:`UtmProjection.convergence` gives it for converting grid bearings to true ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt
from pyproj import Proj, Transformer

__all__ = ["UtmProjection", "utm_zone"]

_WGS84 = "EPSG:4326"


def _check_lonlat(lon: float, lat: float) -> None:
    if not (math.isfinite(lon) and math.isfinite(lat)):
        raise ValueError(f"longitude/latitude must be finite, got ({lon}, {lat})")
    if not -180.0 <= lon <= 180.0:
        raise ValueError(f"longitude {lon} is outside [-180, 180]")
    if not -90.0 <= lat <= 90.0:
        raise ValueError(f"latitude {lat} is outside [-90, 90]")


def utm_zone(lon: float, lat: float) -> int:
    """The UTM zone number (1..60) of a location, with the Norway and Svalbard exceptions."""
    _check_lonlat(lon, lat)
    zone = math.floor((lon + 180.0) / 6.0) + 1
    zone = min(max(zone, 1), 60)  # lon == 180 belongs to zone 60
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:  # south-western Norway
        return 32
    if 72.0 <= lat <= 84.0 and 0.0 <= lon < 42.0:  # Svalbard: zones 31, 33, 35, 37
        if lon < 9.0:
            return 31
        if lon < 21.0:
            return 33
        if lon < 33.0:
            return 35
        return 37
    return zone


@lru_cache(maxsize=64)
def _transformers(epsg: int) -> tuple[Any, Any]:
    """(WGS84 -> UTM, UTM -> WGS84), built once per zone (pyproj >= 3.1: thread-safe)."""
    crs = f"EPSG:{epsg}"
    forward = Transformer.from_crs(_WGS84, crs, always_xy=True)
    inverse = Transformer.from_crs(crs, _WGS84, always_xy=True)
    return forward, inverse


@lru_cache(maxsize=64)
def _proj(epsg: int) -> Any:
    return Proj(f"EPSG:{epsg}")


@dataclass(frozen=True)
class UtmProjection:
    """A WGS84 UTM zone (EPSG 32601-32660 north, 32701-32760 south) with cached transformers.

    >>> p = UtmProjection.for_location(9.98, 53.561)
    >>> p.epsg, p.zone, p.south
    (32632, 32, False)
    """

    epsg: int

    def __post_init__(self) -> None:
        if isinstance(self.epsg, bool) or not isinstance(self.epsg, int):
            raise TypeError(f"epsg must be an int, got {self.epsg!r}")
        if not (32601 <= self.epsg <= 32660 or 32701 <= self.epsg <= 32760):
            raise ValueError(f"EPSG:{self.epsg} is not a WGS84 UTM zone (32601-32660, 32701-32760)")

    @classmethod
    def for_location(cls, lon: float, lat: float) -> UtmProjection:
        """The zone of a location; southern hemisphere (lat < 0) gives the 327xx codes."""
        zone = utm_zone(lon, lat)
        return cls((32700 if lat < 0.0 else 32600) + zone)

    @property
    def zone(self) -> int:
        return self.epsg % 100

    @property
    def south(self) -> bool:
        return self.epsg >= 32701

    def to_utm(self, lon: float, lat: float) -> tuple[float, float]:
        """(easting, northing) in metres."""
        x, y = _transformers(self.epsg)[0].transform(lon, lat)
        return float(x), float(y)

    def to_utm_array(self, lon: npt.ArrayLike, lat: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Vectorised :meth:`to_utm`: shape (n, 2) of (easting, northing)."""
        return _transform_array(_transformers(self.epsg)[0], lon, lat, ("lon", "lat"))

    def to_wgs84(self, x: float, y: float) -> tuple[float, float]:
        """(lon, lat) in degrees."""
        lon, lat = _transformers(self.epsg)[1].transform(x, y)
        return float(lon), float(lat)

    def to_wgs84_array(self, x: npt.ArrayLike, y: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Vectorised :meth:`to_wgs84`: shape (n, 2) of (lon, lat)."""
        return _transform_array(_transformers(self.epsg)[1], x, y, ("x", "y"))

    def convergence(self, lon: float, lat: float) -> float:
        """Meridian convergence in degrees: true bearing = grid bearing + convergence.

        (PROJ's sign convention: the angle from true north to grid north, clockwise positive.)
        """
        factors = _proj(self.epsg).get_factors(lon, lat)
        return float(factors.meridian_convergence)


def _transform_array(
    transformer: Any, a: npt.ArrayLike, b: npt.ArrayLike, names: tuple[str, str]
) -> npt.NDArray[np.float64]:
    """Run a pyproj transformer over two equally long coordinate arrays: shape (n, 2)."""
    a_arr = np.asarray(a, dtype=np.float64).reshape(-1)
    b_arr = np.asarray(b, dtype=np.float64).reshape(-1)
    if a_arr.shape != b_arr.shape:
        raise ValueError(
            f"{names[0]} and {names[1]} differ in length: {a_arr.size} != {b_arr.size}"
        )
    if a_arr.size <= _FEW:  # pyproj's array call costs ~10 us before the first point
        out = np.empty((a_arr.size, 2))
        for k, (x, y) in enumerate(zip(a_arr.tolist(), b_arr.tolist(), strict=True)):
            out[k] = transformer.transform(x, y)
        return out
    u, v = transformer.transform(a_arr, b_arr)
    return np.column_stack((np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)))


_FEW = 4
"""Up to this many points are transformed one by one: pyproj's scalar call is about
1.5 us a point, its array call about 10 us however few the points (the same PROJ
operation either way, so the same result)."""
