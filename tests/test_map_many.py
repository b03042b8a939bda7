"""The map's queries for many points at once give each point the answer it gets alone."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from shapely import Point

from laas.map.bundled import bundled_map
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap, Segment

MAPS = ["messe-hamburg", "fabriksgatan", "karlsruhe", "helsinki"]


@cache
def _map(name: str) -> HdMap:
    return read_geojson_file(bundled_map(name))


def _points(hdmap: HdMap, n: int, seed: int) -> np.ndarray:
    """Points on lane centre lines, on seams between elements, and anywhere near the map."""
    rng = np.random.default_rng(seed)
    segs = list(hdmap.segments.values())
    on = []
    for k in rng.integers(0, len(segs), n):
        lane = segs[k].lanes[int(rng.integers(len(segs[k].lanes)))]
        p = lane.centerline.interpolate(
            float(rng.choice([0.0, rng.uniform(), 1.0])), normalized=True
        )
        on.append((p.x, p.y))
    x0, y0, x1, y1 = hdmap.bounds
    anywhere = np.column_stack(
        (rng.uniform(x0 - 40.0, x1 + 40.0, n), rng.uniform(y0 - 40.0, y1 + 40.0, n))
    )
    return np.concatenate((np.array(on), anywhere))


@pytest.mark.parametrize("name", MAPS)
@pytest.mark.parametrize("max_distance", [15.0, 2.0, 0.0])
def test_locate_many_answers_as_locate(name: str, max_distance: float) -> None:
    hdmap = _map(name)
    xy = _points(hdmap, 600, seed=1)
    many = hdmap.locate_many(xy, max_distance)
    alone = [hdmap.locate(float(x), float(y), max_distance) for x, y in xy]
    assert [s.id if s else None for s in many] == [s.id if s else None for s in alone]
    assert any(s is None for s in alone) and sum(s is not None for s in alone) > 400
    assert hdmap.locate_many(np.zeros((0, 2))) == []


@pytest.mark.parametrize("name", MAPS)
def test_segments_near_sorts_by_distance_then_id(name: str) -> None:
    hdmap = _map(name)
    for x, y in _points(hdmap, 100, seed=2):
        near = hdmap.segments_near(float(x), float(y), 12.0)
        pt = Point(x, y)
        keys = [(seg.area.distance(pt), seg.id) for seg in near]
        assert keys == sorted(keys)
        assert all(d <= 12.0 + 1e-9 for d, _ in keys)
        within = {seg.id for seg in hdmap.segments.values() if seg.area.distance(pt) <= 12.0}
        assert {seg.id for seg in near} == within


@pytest.mark.parametrize("name", MAPS)
def test_frame_many_of_the_map_is_each_segments_frame(name: str) -> None:
    hdmap = _map(name)
    xy = _points(hdmap, 400, seed=3)
    segs = hdmap.locate_many(xy, 30.0)
    kept = [k for k, s in enumerate(segs) if s is not None]
    on: list[Segment] = [s for s in segs if s is not None]
    got = hdmap.frame_many(xy[kept], on)
    for row, seg, (x, y) in zip(got, on, xy[kept], strict=True):
        np.testing.assert_array_equal(row, seg.frame_array([[x, y]])[0])
        assert seg.frame(float(x), float(y)) == pytest.approx(tuple(row), abs=1e-9)


@pytest.mark.parametrize("name", MAPS)
def test_point_tangent_and_offsets_many_are_the_single_values(name: str) -> None:
    rng = np.random.default_rng(4)
    for seg in list(_map(name).segments.values())[:200]:
        s = np.concatenate(
            ([0.0, seg.length, -2.0, seg.length + 2.0], rng.uniform(0, seg.length, 8))
        )
        d = rng.uniform(-6.0, 6.0, len(s))
        np.testing.assert_array_equal(
            seg.point_many(s, d), [seg.point(float(a), float(b)) for a, b in zip(s, d, strict=True)]
        )
        np.testing.assert_array_equal(seg.tangent_many(s), [seg.tangent(float(a)) for a in s])
        np.testing.assert_array_equal(
            seg.lane_offsets_many(s), [seg.lane_offsets(float(a)) for a in s]
        )
        xy = seg.point_many(s, d)
        # a few points go one by one (`frame`); many go as arrays (`frame_array`, held to
        # `frame` by test_frame_many_of_the_map_is_each_segments_frame above)
        np.testing.assert_array_equal(seg.frame_many(xy), [seg.frame(x, y) for x, y in xy])


def test_many_refuses_what_one_refuses() -> None:
    seg = next(iter(_map("messe-hamburg").segments.values()))
    with pytest.raises(ValueError, match="finite"):
        seg.point_many([1.0, np.nan])
    with pytest.raises(ValueError, match="finite"):
        seg.lane_offsets_many([np.inf])
