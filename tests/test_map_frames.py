"""Frames built together (`FrameStack`, `prepare`) give the values a frame built alone gives.

The reference here is the frame computed one polyline at a time, straight from the
equations in `laas.map.frame`'s docstring, and the lane-offset table computed one segment
at a time, as the loader did before it worked on whole maps: on every bundled map the
values must be the same, bit for bit.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest
import shapely

from laas.errors import MapError
from laas.map.bundled import bundled_map
from laas.map.frame import MIN_PIECE, Frame, FrameStack, _runs_cumsum, dedupe, sharpest_turn
from laas.map.geojson import read_geojson_file
from laas.map.hdmap import HdMap, Segment, prepare

MAPS = ["messe-hamburg", "melbourne-corner", "fabriksgatan", "karlsruhe", "helsinki"]
FloatArray = np.ndarray


@cache
def _map(name: str) -> HdMap:
    return read_geojson_file(bundled_map(name))


def _frame_alone(coords: FloatArray) -> dict[str, FloatArray | bool]:
    """The frame of one polyline, one array operation per equation."""
    p = dedupe(np.asarray(coords, dtype=np.float64), MIN_PIECE)
    v = p[1:] - p[:-1]
    lens = np.hypot(v[:, 0], v[:, 1])
    t = v / lens[:, None]  # T_i
    n = np.column_stack((t[:, 1], -t[:, 0]))  # N_i
    m = np.empty_like(p)  # M_j = (N_{j-1} + N_j) / (1 + N_{j-1}.N_j), M_0 = N_0, M_n = N_{n-1}
    m[0], m[-1] = n[0], n[-1]
    m[1:-1] = (n[:-1] + n[1:]) / (1.0 + np.sum(n[:-1] * n[1:], axis=1))[:, None]
    fwd = np.column_stack((-m[:, 1], m[:, 0]))
    fwd /= np.hypot(fwd[:, 0], fwd[:, 1])[:, None]
    heading = np.unwrap(np.arctan2(t[:, 1], t[:, 0]))
    return {
        "p": p,
        "v": v,
        "lens": lens,
        "t": t,
        "n": n,
        "m": m,
        "fwd": fwd,
        "cum": np.concatenate(([0.0], np.cumsum(lens))),
        "winds": bool(heading.max() - heading.min() > math.radians(150.0)),
    }


def _table_alone(seg: Segment) -> FloatArray:
    """Each lane's d(s) at 1 m stations, from its densified centre line, one lane at a time."""
    frame = Frame(np.asarray(seg.reference.coords)[:, :2])
    grid = np.linspace(0.0, frame.length, max(2, math.ceil(frame.length) + 1))
    table = np.zeros((len(grid), len(seg.lanes)))
    for k, lane in enumerate(seg.lanes[1:], start=1):
        dense = shapely.segmentize(lane.centerline, 1.0)
        sd = frame.frame_array(np.asarray(dense.coords)[:, :2])
        order = np.argsort(sd[:, 0], kind="stable")
        table[:, k] = np.interp(grid, sd[order, 0], sd[order, 1])
    return table


@pytest.mark.parametrize("name", MAPS)
def test_a_loaded_map_has_the_frames_of_its_references_alone(name: str) -> None:
    """The stacked frames of a load, and a Frame built on its own, against the equations."""
    for seg in _map(name).segments.values():
        alone = _frame_alone(np.asarray(seg.reference.coords)[:, :2])
        for frame in (seg._f, Frame(np.asarray(seg.reference.coords)[:, :2])):
            for key in ("p", "v", "lens", "t", "n", "m", "fwd", "cum"):
                np.testing.assert_array_equal(getattr(frame, key), alone[key], err_msg=key)
            assert frame.winds == alone["winds"]
        assert seg.length == float(alone["cum"][-1])  # type: ignore[index]


@pytest.mark.parametrize("name", MAPS)
def test_a_loaded_map_has_the_lane_offsets_of_its_segments_alone(name: str) -> None:
    rng = np.random.default_rng(7)
    for seg in _map(name).segments.values():
        table = _table_alone(seg)
        stations = np.concatenate(
            ([-3.0, 0.0, seg.length, seg.length + 3.0], rng.uniform(0.0, seg.length, 12))
        )
        many = seg.lane_offsets_many(stations)
        for s, row in zip(stations, many, strict=True):
            pos = min(max(float(s), 0.0), seg.length) / seg.length * (len(table) - 1)
            i = min(int(pos), len(table) - 2)
            expected = table[i] + (pos - i) * (table[i + 1] - table[i])
            np.testing.assert_array_equal(seg.lane_offsets(float(s)), expected)
            np.testing.assert_array_equal(row, expected)


@pytest.mark.parametrize("name", ["karlsruhe", "fabriksgatan"])
def test_a_segment_built_alone_equals_the_loaded_one(name: str) -> None:
    """Frame, lane offsets and surface built lazily, one segment at a time."""
    for seg in _map(name).segments.values():
        alone = Segment(seg.id, seg.lanes, seg.successors)
        assert shapely.equals_identical(alone.area, seg.area)
        np.testing.assert_array_equal(alone._table, seg._table)
        np.testing.assert_array_equal(alone._f.m, seg._f.m)
        xy = np.asarray(shapely.get_coordinates(seg.area))[::3]
        np.testing.assert_array_equal(alone.frame_array(xy), seg.frame_array(xy))


@pytest.mark.parametrize("name", MAPS)
def test_frame_many_gives_each_point_what_its_frame_gives(name: str) -> None:
    segs = list(_map(name).segments.values())
    stack = FrameStack([shapely.get_coordinates(seg.reference) for seg in segs])
    rng = np.random.default_rng(3)
    which = rng.integers(0, len(segs), 4000)
    lo = np.array([segs[k].area.bounds[:2] for k in which]) - 20.0  # near and far
    hi = np.array([segs[k].area.bounds[2:] for k in which]) + 20.0
    xy = rng.uniform(lo, hi)
    got = stack.frame_many(xy, which)
    for k in np.unique(which):
        sel = which == k
        np.testing.assert_array_equal(got[sel], segs[k].frame_array(xy[sel]))


def test_frame_many_on_frames_that_wind_and_frames_that_do_not() -> None:
    angle = np.radians(np.arange(0.0, 300.5, 2.0))
    arc = np.column_stack((30.0 * np.sin(angle), 30.0 - 30.0 * np.cos(angle)))
    line = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 5.0]])
    stack = FrameStack([arc, line, arc + 100.0])
    assert stack.winds.tolist() == [True, False, True]
    rng = np.random.default_rng(5)
    xy = rng.uniform(-40.0, 140.0, (600, 2))
    which = rng.integers(0, 3, 600)
    got = stack.frame_many(xy, which)
    for k, ref in enumerate((arc, line, arc + 100.0)):
        np.testing.assert_array_equal(got[which == k], Frame(ref).frame_array(xy[which == k]))


def test_a_reference_too_short_has_no_frame() -> None:
    short = np.array([[0.0, 0.0], [0.004, 0.0], [0.008, 0.0]])
    stack = FrameStack([np.array([[0.0, 0.0], [5.0, 0.0]]), short])
    assert stack.usable.tolist() == [True, False]
    with pytest.raises(MapError, match="shorter than"):
        stack.frame(1)
    with pytest.raises(MapError, match="shorter than"):
        Frame(short)
    with pytest.raises(MapError, match="shorter than"):
        stack.frame_many([[1.0, 1.0]], [1])
    np.testing.assert_array_equal(stack.frame_many([[1.0, 1.0]], [0]), [[1.0, -1.0]])  # left: d < 0


def test_close_vertices_are_merged_as_dedupe_merges_them() -> None:
    ref = np.array([[0.0, 0.0], [0.005, 0.0], [4.0, 0.0], [4.0, 0.001], [8.0, 2.0], [8.0, 2.009]])
    stack = FrameStack([ref, ref[::-1].copy()])
    for k, r in enumerate((ref, ref[::-1].copy())):
        np.testing.assert_array_equal(stack.frame(k).p, dedupe(r, MIN_PIECE))


@pytest.mark.parametrize("name", MAPS)
def test_sharpest_turns_of_a_stack(name: str) -> None:
    refs = [shapely.get_coordinates(seg.reference) for seg in _map(name).segments.values()]
    turns, vertex = FrameStack(refs).sharpest_turns()
    for ref, a, j in zip(refs, turns, vertex, strict=True):
        assert (math.degrees(float(a)), int(j)) == sharpest_turn(ref)


def test_runs_cumsum_sums_each_run_alone() -> None:
    rng = np.random.default_rng(11)
    lengths = rng.integers(0, 40, 200)
    lengths[:3] = [0, 1, 300]
    values = rng.uniform(0.0, 100.0, int(lengths.sum()))
    got = _runs_cumsum(values, lengths)
    start = 0
    for n in lengths:
        np.testing.assert_array_equal(got[start : start + n], np.cumsum(values[start : start + n]))
        start += n


def test_prepare_returns_the_samples_the_loader_checks() -> None:
    segs = list(_map("messe-hamburg").segments.values())
    fresh = [Segment(seg.id, seg.lanes, seg.successors) for seg in segs]
    for seg, prep in zip(fresh, prepare(fresh), strict=True):
        assert len(prep.samples) == len(seg.lanes) - 1
        for lane, sd in zip(seg.lanes[1:], prep.samples, strict=True):
            dense = shapely.segmentize(lane.centerline, 1.0)
            np.testing.assert_array_equal(sd, seg.frame_array(shapely.get_coordinates(dense)))
        seg.settle_area(prep.surface)
        assert shapely.equals_identical(seg.area, segs[fresh.index(seg)].area)
