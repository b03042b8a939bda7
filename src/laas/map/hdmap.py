"""The lane-level HD map: lanes, road elements (segments) and the queries the engine needs.

A map is a set of *segments*, road elements whose lanes run side by side; lane 0 is the
left-most lane looking along the segment's reference direction. Everything is metric, in
the UTM zone of the map's centroid (:mod:`laas.map.geo`), and each segment carries the
exact curvilinear frame of its reference line (:mod:`laas.map.frame`). Maps are read from
the GeoJSON lane format (:mod:`laas.map.geojson`, described in ``maps/README.md``); the
engine never knows where a map came from.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal, cast, get_args

import numpy as np
import numpy.typing as npt
import shapely
from shapely import LineString, Point, Polygon, STRtree

from laas.errors import MapError
from laas.map.frame import MIN_PIECE, Frame, FrameStack
from laas.map.geo import UtmProjection
from laas.models import LaneType

__all__ = [
    "DIRECTIONS",
    "LANE_TYPES",
    "SIDE_MARGIN",
    "Direction",
    "HdMap",
    "Lane",
    "LaneType",
    "Prepared",
    "Segment",
    "prepare",
]

Direction = Literal["forward", "backward", "both"]
LANE_TYPES: frozenset[str] = frozenset(get_args(LaneType))
DIRECTIONS: frozenset[str] = frozenset(get_args(Direction))

FloatArray = npt.NDArray[np.float64]

SIDE_MARGIN = 5.0
"""m: an element further than this from another's surface is not `HdMap.beside` it. Its
lanes' likelihood at a point inside the other (`laas.engine.elements`) is then below
exp(-0.5 (5 / 1.5)^2) = 0.4 % of what it is on its own lane, 1.5 m being about the
largest cross-road sigma of a corrected position once the common error is observed."""

_OFFSET_STEP = 1.0  # m, station spacing of the cached lane-offset table
# How many points or stations the `*_many` queries of a `Segment` take one by one: the
# arrays cost a fixed 270 us (frame), 160 us (point), 40 us (tangent) and 40 us (lane
# offsets) however few they are, one at a time 2-3, 2, 2 and 6 us (Messe Hamburg, one core)
_FEW_FRAMES = 96
_FEW_POINTS = 64
_FEW_TANGENTS = 16
_FEW_OFFSETS = 4


@dataclass(frozen=True)
class Lane:
    """One lane of one segment; the centre line is in UTM metres, in the reference direction."""

    segment: str
    index: int
    type: LaneType
    width: float
    direction: Direction
    centerline: LineString
    properties: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))


# ----------------------------------------------------------------------------------------------
# Segment
# ----------------------------------------------------------------------------------------------


class Segment:
    """A road element: lanes side by side with a shared curvilinear frame (see module docstring)."""

    __slots__ = (
        "_area",
        "_frame",
        "_from",
        "_id",
        "_lane_d",
        "_lanes",
        "_left",
        "_reference",
        "_successors",
    )

    def __init__(self, id: str, lanes: Iterable[Lane], successors: Iterable[str] = ()) -> None:
        ordered = tuple(sorted(lanes, key=lambda lane: lane.index))
        if not ordered:
            raise MapError(f"segment {id!r} has no lanes")
        indices = [lane.index for lane in ordered]
        if indices != list(range(len(ordered))):
            raise MapError(f"segment {id!r}: lane indices must be contiguous from 0, got {indices}")
        for lane in ordered:
            if lane.segment != id:
                raise MapError(f"lane {lane.index} belongs to {lane.segment!r}, not {id!r}")
        self._id = id
        self._lanes = ordered
        self._successors = tuple(dict.fromkeys(successors))
        self._reference = ordered[0].centerline
        self._left = -ordered[0].width / 2.0
        # The frame, the lane-offset table and the surface are built on first use, or for
        # a whole map at once by `prepare`. A reference too short for a frame is refused
        # here: it is one whose ends lie within MIN_PIECE (else two vertices survive).
        self._frame: Frame | None = None
        self._from: tuple[FrameStack, int] | None = None  # where `prepare` put the frame
        self._lane_d: FloatArray | None = None
        self._area: Polygon | None = None
        ref = shapely.get_coordinates(self._reference)
        if math.dist(ref[0], ref[-1]) <= MIN_PIECE:
            self._frame = Frame(ref)

    def _relinked(self, successors: Iterable[str]) -> Segment:
        """This segment with other successors, sharing what was built."""
        seg = Segment(self._id, self._lanes, successors)
        seg._frame, seg._from = self._frame, self._from
        seg._lane_d, seg._area = self._lane_d, self._area
        return seg

    @property
    def _f(self) -> Frame:
        """The frame, built on first use."""
        if self._frame is None:
            if self._from is not None:
                self._frame = self._from[0].frame(self._from[1])
            else:
                self._frame = Frame(shapely.get_coordinates(self._reference))
        return self._frame

    @property
    def _table(self) -> FloatArray:
        """d of each lane (columns) at equally spaced stations (rows); built on first use."""
        if self._lane_d is None:
            prepare([self], surfaces=False)
        return cast(FloatArray, self._lane_d)

    # -- attributes --------------------------------------------------------------------------

    @property
    def id(self) -> str:
        return self._id

    @property
    def lanes(self) -> tuple[Lane, ...]:
        return self._lanes

    @property
    def successors(self) -> tuple[str, ...]:
        return self._successors

    @property
    def reference(self) -> LineString:
        """Lane 0's centre line: the reference of the segment frame."""
        return self._reference

    @property
    def area(self) -> Polygon:
        """The element's surface: lane centre lines buffered by half their width, flat caps.

        Built on first use, or by the loader for the whole map at once (:func:`prepare`).
        """
        if self._area is None:
            self._area = self._build_area(_surfaces([self])[0])
        return self._area

    def settle_area(self, surface: Any) -> None:
        """Make the surface from the union of the lanes' buffers (:class:`Prepared`); raises
        :class:`MapError` if they do not form one."""
        self._area = self._build_area(surface)

    def _build_area(self, area: Any) -> Polygon:
        """The surface from :func:`_surfaces`; it must be one polygon."""
        if not isinstance(area, Polygon):
            raise MapError(f"segment {self._id!r}: the lanes do not form one connected surface")
        return area

    @property
    def length(self) -> float:
        """Length of the reference line in metres."""
        if self._frame is None and self._from is not None:
            return self._from[0].length(self._from[1])
        return self._f.length

    def __repr__(self) -> str:
        return (
            f"Segment({self._id!r}, lanes={len(self._lanes)}, length={self.length:.1f} m, "
            f"successors={list(self._successors)})"
        )

    # -- frame -------------------------------------------------------------------------------

    def frame(self, x: float, y: float) -> tuple[float, float]:
        """(s, d) of a UTM point: station along the reference, lateral offset (+ to the right)."""
        x, y = float(x), float(y)
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"point must be finite, got ({x}, {y})")
        return self._f.frame(x, y)

    def frame_array(self, xy: npt.ArrayLike) -> FloatArray:
        """Vectorised :meth:`frame`: (n, 2) UTM points -> (n, 2) of (s, d)."""
        return self._f.frame_array(np.asarray(xy, dtype=np.float64).reshape(-1, 2))

    def frame_many(self, xy: npt.ArrayLike) -> FloatArray:
        """Vectorised :meth:`frame`, the form a batch calls: (n, 2) UTM points -> (n, 2) of
        (s, d). (The same as :meth:`frame_array`; a few points go one by one, which
        costs less than setting up the arrays.)"""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(pts) <= _FEW_FRAMES:
            return np.array([self.frame(x, y) for x, y in pts.tolist()]).reshape(-1, 2)
        return self.frame_array(pts)

    def point_many(self, s: npt.ArrayLike, d: npt.ArrayLike = 0.0) -> FloatArray:
        """Vectorised :meth:`point`: (n,) stations and offsets -> (n, 2) UTM points, the same
        values as one at a time."""
        st = np.asarray(s, dtype=np.float64).reshape(-1)
        dt = np.broadcast_to(np.asarray(d, dtype=np.float64), st.shape)
        if not (np.isfinite(st).all() and np.isfinite(dt).all()):
            raise ValueError("stations and offsets must be finite")
        if len(st) <= _FEW_POINTS:
            points = [self._f.point(a, b) for a, b in zip(st.tolist(), dt.tolist(), strict=True)]
            return np.array(points, dtype=np.float64).reshape(-1, 2)
        return self._f.point_array(st, np.array(dt))

    def point(self, s: float, d: float = 0.0) -> tuple[float, float]:
        """The UTM point at station s and lateral offset d; the inverse of :meth:`frame`."""
        s, d = float(s), float(d)
        if not (math.isfinite(s) and math.isfinite(d)):
            raise ValueError(f"station and offset must be finite, got ({s}, {d})")
        return self._f.point(s, d)

    def tangent(self, s: float) -> FloatArray:
        """Unit (east, north) vector of the reference direction at station s."""
        f = self._f
        return np.array(f._t[f.piece_at(s)])

    def tangent_at(self, s: float) -> tuple[float, float]:
        """:meth:`tangent` as plain floats (the per-user arithmetic of a batch)."""
        f = self._f
        tx, ty = f._t[f.piece_at(s)]
        return tx, ty

    def tangent_many(self, s: npt.ArrayLike) -> FloatArray:
        """Vectorised :meth:`tangent`: (n,) stations -> (n, 2)."""
        f = self._f
        st = np.asarray(s, dtype=np.float64).reshape(-1)
        if len(st) <= _FEW_TANGENTS:
            return f.t[[f.piece_at(a) for a in st.tolist()]]
        return f.t[f.piece_array(st)]

    def heading(self, s: float) -> float:
        """Reference direction at s in degrees from (grid) north, clockwise, in [0, 360)."""
        f = self._f
        tx, ty = f._t[f.piece_at(s)]
        h = math.degrees(math.atan2(tx, ty)) % 360.0
        return 0.0 if h >= 360.0 else h

    def lane_offsets(self, s: float) -> FloatArray:
        """d of every lane's centre line at station s, shape (L,); lane 0 is 0.0.

        Outside [0, length] the offsets at the nearer end are used.
        """
        if not math.isfinite(s):
            raise ValueError(f"station must be finite, got {s}")
        if len(self._lanes) == 1:  # one lane: d = 0 everywhere
            return np.zeros(1)
        table = self._table
        length = self.length
        # pos = clamp(s, 0, length) / length * (rows - 1);  d = D_i + f (D_{i+1} - D_i)
        pos = min(max(s, 0.0), length) / length * (len(table) - 1)
        i = min(int(pos), len(table) - 2)
        f = pos - i
        lo = table[i]
        return cast(FloatArray, lo + f * (table[i + 1] - lo))

    def lane_offsets_many(self, s: npt.ArrayLike) -> FloatArray:
        """Vectorised :meth:`lane_offsets`: (n,) stations -> (n, L), the same values."""
        st = np.asarray(s, dtype=np.float64).reshape(-1)
        if len(st) <= _FEW_OFFSETS:  # each station checked by `lane_offsets`
            return np.array([self.lane_offsets(a) for a in st.tolist()]).reshape(len(st), -1)
        if not np.isfinite(st).all():
            raise ValueError("stations must be finite")
        table = self._table
        length = self.length
        # pos = clamp(s, 0, length) / length * (rows - 1);  d = D_i + f (D_{i+1} - D_i)
        pos = st.clip(0.0, length) / length * (len(table) - 1)
        i = pos.astype(np.intp)
        i[i > len(table) - 2] = len(table) - 2
        f = (pos - i)[:, None]
        lo = table[i]
        return lo + f * (table[i + 1] - lo)

    def lateral_bounds(self, s: float) -> tuple[float, float]:
        """(d of the left edge, d of the right edge) of the road element at station s."""
        right = float(self.lane_offsets(s)[-1]) + self._lanes[-1].width / 2.0
        return self._left, right

    def lane_point(self, lane: int, x: float, y: float) -> tuple[float, float]:
        """The point of lane ``lane``'s centre line nearest to the UTM point (x, y)."""
        if not 0 <= lane < len(self._lanes):
            raise IndexError(f"segment {self._id!r} has no lane {lane}")
        line = self._lanes[lane].centerline
        p = line.interpolate(line.project(Point(x, y)))
        return float(p.x), float(p.y)

    def _depth(self, x: float, y: float) -> float:
        """How far inside the element a point is (min distance to an edge in the frame)."""
        s, d = self.frame(x, y)
        left, right = self.lateral_bounds(s)
        return min(s, self.length - s, d - left, right - d)


@dataclass(frozen=True)
class Prepared:
    """What :func:`prepare` built for one segment that the loader checks: the (s, d) of each
    lane's densified centre line but lane 0's (one (n, 2) array per lane), and the union
    of the lanes' buffers, from which :meth:`Segment.settle_area` makes the surface."""

    samples: tuple[FloatArray, ...]
    surface: Any


def prepare(
    segments: Sequence[Segment], surfaces: bool = True, stack: FrameStack | None = None
) -> list[Prepared]:
    """Build the frames and lane-offset tables of many segments together, as a map load does.

    One :class:`FrameStack` holds every reference; every lane but lane 0 is densified to
    ``_OFFSET_STEP`` and put in its segment's frame in one call, and each lane's offset table
    column is ``d(s)`` interpolated at equally spaced stations. A segment alone builds the
    same on first use (through this function, with a list of one). Without `surfaces`,
    no surface is built (``Prepared.surface`` is None). `stack`: a :class:`FrameStack` of
    exactly these segments' references, in order, if the caller has one.
    """
    if not segments:
        return []
    if stack is None:
        stack = FrameStack([shapely.get_coordinates(seg.reference) for seg in segments])
    elif stack.count != len(segments):
        raise ValueError(f"a stack of {stack.count} frames for {len(segments)} segments")
    for k, seg in enumerate(segments):
        if seg._frame is None:
            seg._from = (stack, k)
    owner = np.array([k for k, seg in enumerate(segments) for _ in seg.lanes[1:]], np.intp)
    lines = np.array([lane.centerline for seg in segments for lane in seg.lanes[1:]], object)
    parts: list[FloatArray] = []
    if len(lines):
        dense = shapely.segmentize(lines, _OFFSET_STEP)
        xy, line_of = shapely.get_coordinates(dense, return_index=True)
        sd = stack.frame_many(xy, owner[line_of])
        cut = np.searchsorted(line_of, np.arange(len(lines) + 1)).tolist()
        parts = [sd[lo:hi] for lo, hi in itertools.pairwise(cut)]
    out: list[Prepared] = []
    made = _surfaces(segments) if surfaces else [None] * len(segments)
    j = 0
    for seg, surface in zip(segments, made, strict=True):
        mine = tuple(parts[j : j + len(seg.lanes) - 1])
        j += len(mine)
        out.append(Prepared(mine, surface))
        if seg._lane_d is not None:
            continue
        if not mine:  # one lane: its offset is 0 everywhere
            seg._lane_d = np.zeros((2, 1))
            continue
        length = seg.length
        grid = np.linspace(0.0, length, max(2, math.ceil(length / _OFFSET_STEP) + 1))
        table = np.zeros((len(grid), len(seg.lanes)))
        for c, lane_sd in enumerate(mine, start=1):
            order = np.argsort(lane_sd[:, 0], kind="stable")
            table[:, c] = np.interp(grid, lane_sd[order, 0], lane_sd[order, 1])
        seg._lane_d = table
    return out


def _surfaces(segments: Sequence[Segment]) -> list[Any]:
    """Each segment's surface, all at once: the union of its lane centre lines buffered by
    half their width, flat caps (a lane alone: its buffer). Where that is not one polygon
    without holes (small gaps between lanes, which validation tolerates), it is closed
    morphologically: the exterior of ``buffer(buffer(union, g), -g)``, mitred, g = 0.75 m,
    if that is a polygon."""
    lanes = [lane for seg in segments for lane in seg.lanes]
    buffers = shapely.buffer(
        np.array([lane.centerline for lane in lanes], object),
        np.array([lane.width / 2.0 for lane in lanes]),
        cap_style="flat",
    )
    # the union of a segment's buffers; one lane's buffer is its surface as it is
    width = np.array([len(seg.lanes) for seg in segments])
    first = np.cumsum(width) - width
    union = buffers[first]
    multi = np.flatnonzero(width > 1)
    if len(multi):
        table = np.full((len(multi), int(width.max())), None, object)
        rows = np.repeat(np.arange(len(multi)), width[multi])
        cols = np.concatenate([np.arange(w) for w in width[multi]])
        table[rows, cols] = buffers[np.repeat(first[multi], width[multi]) + cols]
        union[multi] = shapely.union_all(table, axis=1)
    polygon = shapely.get_type_id(union) == 3
    holes = np.zeros(len(union), np.intp)
    holes[polygon] = shapely.get_num_interior_rings(union[polygon])
    gappy = np.flatnonzero(~polygon | (holes > 0))
    out = list(union)
    if len(gappy):
        gap = 0.75
        closed = shapely.buffer(
            shapely.buffer(union[gappy], gap, join_style="mitre"), -gap, join_style="mitre"
        )
        for k, c in zip(gappy, closed, strict=True):
            if isinstance(c, Polygon) and not c.is_empty:
                out[k] = Polygon(c.exterior)
    return out


# ----------------------------------------------------------------------------------------------
# The map
# ----------------------------------------------------------------------------------------------


class HdMap:
    """Segments in one UTM projection, with an STRtree over their surfaces."""

    def __init__(
        self, segments: Iterable[Segment], projection: UtmProjection, source: str = "<memory>"
    ) -> None:
        segs = list(segments)
        if not segs:
            raise MapError(f"{source}: the map has no segments")
        by_id: dict[str, Segment] = {}
        for seg in segs:
            if seg.id in by_id:
                raise MapError(f"{source}: duplicate segment {seg.id!r}")
            by_id[seg.id] = seg
        for seg in segs:
            for succ in seg.successors:
                if succ not in by_id:
                    raise MapError(f"{source}: segment {seg.id!r} names unknown successor {succ!r}")
        self.projection = projection
        self.source = source
        self._segments = MappingProxyType(by_id)
        before: dict[str, list[str]] = {}
        for seg in segs:
            for succ in seg.successors:
                before.setdefault(succ, []).append(seg.id)
        self._predecessors = {k: tuple(v) for k, v in before.items()}
        self._sorted = sorted(segs, key=lambda seg: seg.id)  # tree index order = id order
        self._areas = np.array([seg.area for seg in self._sorted], object)
        self._tree = STRtree(self._areas)
        self._index = {seg.id: k for k, seg in enumerate(self._sorted)}
        self._stack: FrameStack | None = None  # every frame, for frame_many; on first use
        self._beside: dict[str, tuple[Segment, ...]] = {}  # `beside`, on first use
        self._beside_areas: dict[str, npt.NDArray[np.object_]] = {}  # their surfaces
        b = shapely.bounds(np.array([seg.area for seg in segs], object))
        self._bounds = (
            float(b[:, 0].min()),
            float(b[:, 1].min()),
            float(b[:, 2].max()),
            float(b[:, 3].max()),
        )

    @property
    def segments(self) -> Mapping[str, Segment]:
        """Segments by id, in file order."""
        return self._segments

    def predecessors(self, segment: str) -> tuple[str, ...]:
        """The segments that name `segment` among their successors, in file order."""
        return self._predecessors.get(segment, ())

    def beside(self, segment: str) -> tuple[Segment, ...]:
        """The elements whose surface comes within `SIDE_MARGIN` of `segment`'s and that
        are not joined to it at a seam (its successors and predecessors): the lanelets a
        junction overlaps it with, a footway beside its road. Worked out on first use."""
        found = self._beside.get(segment)
        if found is None:
            seg = self._segments[segment]
            joined = {segment, *seg.successors, *self.predecessors(segment)}
            idx = self._tree.query(seg.area, predicate="dwithin", distance=SIDE_MARGIN)
            near = (self._sorted[int(i)] for i in sorted(idx))
            found = self._beside[segment] = tuple(e for e in near if e.id not in joined)
            self._beside_areas[segment] = np.array([e.area for e in found], object)
        return found

    def beside_near(self, segment: str, x: float, y: float, distance: float) -> list[Segment]:
        """The elements `beside` `segment` whose surface lies within `distance` of the
        point (x, y), in the order of `beside`: one array query, not one per element."""
        others = self.beside(segment)
        if not others:
            return []
        near = shapely.dwithin(self._beside_areas[segment], Point(x, y), distance)
        return [e for e, ok in zip(others, near, strict=True) if ok]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(min x, min y, max x, max y) of all surfaces, UTM metres."""
        return self._bounds

    def __repr__(self) -> str:
        return (
            f"HdMap({self.source!r}, {len(self._segments)} segments, EPSG:{self.projection.epsg})"
        )

    # -- queries -----------------------------------------------------------------------------

    def locate(self, x: float, y: float, max_distance: float = 15.0) -> Segment | None:
        """The segment whose surface contains the UTM point (x, y).

        Several: the one the point is deepest inside (largest distance to the element's edges
        in its frame), ties by id. None contains it: the nearest within ``max_distance``
        (ties by id). Otherwise None.
        """
        pt = Point(x, y)
        hits = self._tree.query(pt, predicate="intersects")
        if len(hits) == 1:
            return self._sorted[int(hits[0])]
        if len(hits) > 1:
            cands = [self._sorted[int(i)] for i in hits]
            return min(cands, key=lambda seg: (-seg._depth(x, y), seg.id))
        if max_distance <= 0.0:
            return None
        near = self._tree.query_nearest(pt, max_distance=max_distance, all_matches=True)
        if len(near) == 0:
            return None
        return self._sorted[int(np.min(near))]

    def segments_near(self, x: float, y: float, radius: float) -> list[Segment]:
        """Segments whose surface is within ``radius`` metres of (x, y), nearest first (ties
        by id)."""
        pt = Point(x, y)
        idx = self._tree.query(pt, predicate="dwithin", distance=radius)
        if len(idx) == 0:
            return []
        dist = shapely.distance(self._areas[idx], pt)
        order = np.lexsort((idx, dist))  # tree index order is id order
        return [self._sorted[int(i)] for i in idx[order]]

    # -- many points at once -----------------------------------------------------------------

    def locate_many(self, xy: npt.ArrayLike, max_distance: float = 15.0) -> list[Segment | None]:
        """:meth:`locate` of each of (n, 2) UTM points, the same answers, the tree searched
        once for all of them."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out: list[Segment | None] = [None] * len(pts)
        if not len(pts):
            return out
        if len(pts) == 1:  # the tree's array query costs more than one point's own
            return [self.locate(float(pts[0, 0]), float(pts[0, 1]), max_distance)]
        geoms = shapely.points(pts)
        inp, hit = self._tree.query(geoms, predicate="intersects")
        order = np.lexsort((hit, inp))
        inp, hit = inp[order], hit[order]
        count = np.bincount(inp, minlength=len(pts))
        first = np.searchsorted(inp, np.arange(len(pts)))  # hits of point k: first[k]..
        for k in np.flatnonzero(count == 1).tolist():
            out[k] = self._sorted[int(hit[first[k]])]
        for k in np.flatnonzero(count > 1).tolist():  # the deepest, ties by id
            x, y = float(pts[k, 0]), float(pts[k, 1])
            cands = [self._sorted[int(i)] for i in hit[first[k] : first[k] + count[k]]]
            out[k] = min(cands, key=lambda seg: (-seg._depth(x, y), seg.id))
        none = np.flatnonzero(count == 0)
        if max_distance > 0.0 and len(none):
            near_in, near = self._tree.query_nearest(
                geoms[none], max_distance=max_distance, all_matches=True
            )
            best = np.full(len(none), len(self._sorted))
            np.minimum.at(best, near_in, near)  # the nearest, ties by id
            for k, b in zip(none.tolist(), best.tolist(), strict=True):
                if b < len(self._sorted):
                    out[k] = self._sorted[b]
        return out

    def frame_many(self, xy: npt.ArrayLike, segments: Sequence[Segment]) -> FloatArray:
        """(s, d) of point k in the frame of segments[k]: (n, 2) -> (n, 2), each the value of
        ``segments[k].frame_array``, all frames in one pass (:class:`FrameStack`)."""
        if self._stack is None:
            self._stack = FrameStack([shapely.get_coordinates(s.reference) for s in self._sorted])
        which = [self._index[seg.id] for seg in segments]
        return self._stack.frame_many(xy, which)
