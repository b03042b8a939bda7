"""UTM projection: zone choice, known coordinates, round trips, value-type behaviour."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from laas.map.geo import UtmProjection, utm_zone


@pytest.mark.parametrize(
    ("place", "lon", "lat", "epsg"),
    [
        ("Hamburg, Messe", 9.980, 53.561, 32632),
        ("Sydney", 151.209, -33.868, 32756),
        ("New York", -74.006, 40.713, 32618),
        ("Sao Paulo", -46.633, -23.550, 32723),
        ("Bergen (Norway exception)", 5.322, 60.391, 32632),
        ("Longyearbyen (Svalbard exception)", 15.63, 78.22, 32633),
        ("antimeridian east", 180.0, 10.0, 32660),
        ("antimeridian west", -180.0, -10.0, 32701),
        ("equator at Greenwich", 0.0, 0.0, 32631),
    ],
)
def test_zone_for_location(place: str, lon: float, lat: float, epsg: int) -> None:
    proj = UtmProjection.for_location(lon, lat)
    assert proj.epsg == epsg, place
    assert proj.zone == epsg % 100
    assert proj.south == (lat < 0)


def test_zone_numbers_at_boundaries() -> None:
    assert utm_zone(-180.0, 0.0) == 1
    assert utm_zone(-174.0, 0.0) == 2
    assert utm_zone(5.999, 45.0) == 31
    assert utm_zone(6.0, 45.0) == 32
    assert utm_zone(179.999, 0.0) == 60


def test_known_coordinates() -> None:
    # On a zone's central meridian at the equator: easting 500 km, northing 0 (north) or 10000 km.
    north = UtmProjection(32632)
    x, y = north.to_utm(9.0, 0.0)
    assert x == pytest.approx(500_000.0, abs=1e-6)
    assert y == pytest.approx(0.0, abs=1e-6)
    south = UtmProjection(32756)
    x, y = south.to_utm(153.0, -1e-9)
    assert x == pytest.approx(500_000.0, abs=1e-6)
    assert y == pytest.approx(10_000_000.0, abs=1e-3)
    # Hamburg Messe is ~66 km east of 9 E and ~5935 km north of the equator.
    x, y = north.to_utm(9.980, 53.561)
    assert 564_000 < x < 566_000
    assert 5_934_000 < y < 5_936_000


@pytest.mark.parametrize(
    ("lon", "lat"),
    [(9.980, 53.561), (151.209, -33.868), (-74.006, 40.713), (-179.9, -79.0), (24.9, 83.9)],
)
def test_round_trip_below_a_millimetre(lon: float, lat: float) -> None:
    proj = UtmProjection.for_location(lon, lat)
    x, y = proj.to_utm(lon, lat)
    lon2, lat2 = proj.to_wgs84(x, y)
    x2, y2 = proj.to_utm(lon2, lat2)
    assert math.hypot(x2 - x, y2 - y) < 1e-3
    assert lon2 == pytest.approx(lon, abs=1e-8)
    assert lat2 == pytest.approx(lat, abs=1e-8)


@given(
    lon=st.floats(-180.0, 180.0, allow_nan=False),
    lat=st.floats(-80.0, 84.0, allow_nan=False),
)
def test_round_trip_anywhere(lon: float, lat: float) -> None:
    proj = UtmProjection.for_location(lon, lat)
    x, y = proj.to_utm(lon, lat)
    lon2, lat2 = proj.to_wgs84(x, y)
    back = proj.to_utm(lon2, lat2)
    assert math.hypot(back[0] - x, back[1] - y) < 1e-3


def test_arrays_match_scalars() -> None:
    proj = UtmProjection.for_location(9.98, 53.56)
    lon = np.array([9.97, 9.98, 9.99])
    lat = np.array([53.55, 53.56, 53.57])
    xy = proj.to_utm_array(lon, lat)
    assert xy.shape == (3, 2)
    for k in range(3):
        assert tuple(xy[k]) == pytest.approx(proj.to_utm(lon[k], lat[k]), abs=1e-9)
    ll = proj.to_wgs84_array(xy[:, 0], xy[:, 1])
    np.testing.assert_allclose(ll, np.column_stack((lon, lat)), atol=1e-10)
    with pytest.raises(ValueError, match="differ in length"):
        proj.to_utm_array(lon, lat[:2])


def test_convergence_converts_grid_to_true_bearing() -> None:
    proj = UtmProjection.for_location(9.98, 53.561)
    assert proj.convergence(9.0, 53.561) == pytest.approx(0.0, abs=1e-9)
    # a line due true north has grid bearing -convergence
    a = proj.to_utm(9.98, 53.561)
    b = proj.to_utm(9.98, 53.571)
    grid = math.degrees(math.atan2(b[0] - a[0], b[1] - a[1]))
    assert grid + proj.convergence(9.98, 53.566) == pytest.approx(0.0, abs=1e-3)
    assert 0.7 < proj.convergence(9.98, 53.561) < 0.9


def test_value_type() -> None:
    a = UtmProjection(32632)
    assert a == UtmProjection.for_location(9.98, 53.56)
    assert hash(a) == hash(UtmProjection(32632))
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.epsg = 32633  # type: ignore[misc]


@pytest.mark.parametrize("epsg", [4326, 32600, 32661, 32700, 32761, 25832])
def test_rejects_non_utm_codes(epsg: int) -> None:
    with pytest.raises(ValueError, match="not a WGS84 UTM zone"):
        UtmProjection(epsg)


@pytest.mark.parametrize(("lon", "lat"), [(181.0, 0.0), (0.0, 91.0), (math.nan, 0.0)])
def test_rejects_bad_locations(lon: float, lat: float) -> None:
    with pytest.raises(ValueError):
        UtmProjection.for_location(lon, lat)
