"""The lane-level HD map: GeoJSON loader, validation and the geometric queries the engine needs.

The file format is described in ``maps/README.md``. In short: a GeoJSON FeatureCollection whose
features are lanes (LineString centre lines, lon/lat) of road elements called *segments*; lane 0 is
the left-most lane looking along the segment's reference direction (the coordinate order).

After loading, everything is metric, in the UTM zone of the map's centroid (:mod:`laas.geo`).

The segment frame
-----------------
Each :class:`Segment` has a curvilinear frame ``(s, d)`` built on its *reference*, lane 0's centre
line, a polyline with vertices ``P_0 .. P_n`` and pieces ``i = 0 .. n-1``::

    T_i = (P_{i+1} - P_i) / |P_{i+1} - P_i|      unit tangent of piece i
    N_i = (T_i.y, -T_i.x)                       unit normal, pointing to the RIGHT
    M_j = (N_{j-1} + N_j) / (1 + N_{j-1}.N_j)   mitred vertex normal (M_j.N_{j-1} = M_j.N_j = 1),
                                                M_0 = N_0, M_n = N_{n-1}
    point(s, d) = P_i + u (P_{i+1} - P_i) + d ((1 - u) M_i + u M_{i+1})
    s = S_i + u |P_{i+1} - P_i|                 (S_i: station of P_i, 0 <= u <= 1)

so the curve ``d = const`` is exactly the mitred offset curve of the reference, and ``frame`` is the
exact inverse of ``point`` (a bijection within the local radius of curvature of the reference).
Before the start and after the end, the frame extrapolates along the end tangents. ``d`` is
positive to the right looking along the reference direction, so lane offsets increase with the
lane index.
"""

from __future__ import annotations

import json
import math
from bisect import bisect_right
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Literal, cast, get_args

import numpy as np
import numpy.typing as npt
import shapely
from shapely import LineString, Point, Polygon, STRtree

from laas.errors import MapError
from laas.geo import UtmProjection

__all__ = ["DIRECTIONS", "LANE_TYPES", "Direction", "HdMap", "Lane", "LaneType", "Segment"]

LaneType = Literal["driving", "parking", "bicycle", "sidewalk"]
Direction = Literal["forward", "backward", "both"]
LANE_TYPES: frozenset[str] = frozenset(get_args(LaneType))
DIRECTIONS: frozenset[str] = frozenset(get_args(Direction))

FloatArray = npt.NDArray[np.float64]

_KNOWN_PROPERTIES = frozenset({"segment", "lane", "type", "width", "direction", "successors"})
_MAX_TURN_DEG = 60.0  # sharpest turn allowed at one vertex of a reference line
_OFFSET_STEP = 1.0  # m, station spacing of the cached lane-offset table
_MIN_PIECE = 0.01  # m: reference vertices closer than this are merged
_U_EPS = 1e-9  # tolerance on the piece parameter u when accepting a frame solution


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
# The curvilinear frame of a polyline
# ----------------------------------------------------------------------------------------------


def _dedupe(coords: FloatArray, tol: float = 0.0) -> FloatArray:
    """Drop vertices within ``tol`` of the previously kept one (zero-length or sliver pieces
    have meaningless tangents); the last point is always kept."""
    if len(coords) < 2:
        return coords
    out = [coords[0]]
    for c in coords[1:-1]:
        if math.dist(c, out[-1]) > tol:
            out.append(c)
    last = coords[-1]
    if len(out) > 1 and math.dist(last, out[-1]) <= tol:
        out.pop()
    if math.dist(last, out[-1]) > tol or len(out) == 1:
        out.append(last)
    return np.asarray(out, dtype=np.float64)


def _sharpest_turn(coords: FloatArray) -> tuple[float, int]:
    """(largest turn angle in degrees at an interior vertex, that vertex's index)."""
    c = _dedupe(coords, _MIN_PIECE)
    if len(c) < 3:
        return 0.0, 0
    v = c[1:] - c[:-1]
    a = np.arctan2(v[:, 1], v[:, 0])
    turn = np.abs((np.diff(a) + math.pi) % (2 * math.pi) - math.pi)
    j = int(np.argmax(turn))
    return math.degrees(float(turn[j])), j + 1


class _Frame:
    """The (s, d) frame of a polyline (see the module docstring). Pure numbers, no shapely."""

    def __init__(self, coords: FloatArray) -> None:
        p = _dedupe(np.asarray(coords, dtype=np.float64), _MIN_PIECE)
        if len(p) < 2 or (len(p) == 2 and math.dist(p[0], p[-1]) <= _MIN_PIECE):
            raise MapError(f"reference line is shorter than {_MIN_PIECE} m")
        v = p[1:] - p[:-1]
        lens = np.hypot(v[:, 0], v[:, 1])
        t = v / lens[:, None]
        nrm = np.column_stack((t[:, 1], -t[:, 0]))
        m = np.empty_like(p)
        m[0], m[-1] = nrm[0], nrm[-1]
        # M_j = (N_{j-1} + N_j) / (1 + N_{j-1}.N_j): the mitre vector, M_j.N = 1 on both sides
        m[1:-1] = (nrm[:-1] + nrm[1:]) / (1.0 + np.sum(nrm[:-1] * nrm[1:], axis=1))[:, None]
        # unit "forward" direction across each vertex normal line: perpendicular to M_j
        fwd = np.column_stack((-m[:, 1], m[:, 0]))
        fwd /= np.hypot(fwd[:, 0], fwd[:, 1])[:, None]
        self.p, self.v, self.lens, self.t, self.n, self.m, self.fwd = p, v, lens, t, nrm, m, fwd
        self.cum = np.concatenate(([0.0], np.cumsum(lens)))
        self.length = float(self.cum[-1])
        self.pieces = len(lens)
        # python-float copies for the scalar path (much faster than numpy scalars)
        self._p: list[list[float]] = p.tolist()
        self._v: list[list[float]] = v.tolist()
        self._m: list[list[float]] = m.tolist()
        self._fwd: list[list[float]] = fwd.tolist()
        self._cum: list[float] = self.cum.tolist()
        self._lens: list[float] = lens.tolist()
        self._t0: list[float] = t[0].tolist()
        self._t1: list[float] = t[-1].tolist()

    # -- scalar ------------------------------------------------------------------------------

    def _solve(self, i: int, x: float, y: float) -> tuple[float, float] | None:
        """(u, d) of the point in piece i's quad, or None if it is not in that quad.

        q = u V + d (M_i + u dM)  =>  cross(q - u V, M_i + u dM) = 0, a quadratic in u:
        a u^2 + b u + c = 0,  a = -V x dM,  b = q x dM - V x M_i,  c = q x M_i
        """
        px, py = self._p[i]
        vx, vy = self._v[i]
        m0x, m0y = self._m[i]
        m1x, m1y = self._m[i + 1]
        qx, qy = x - px, y - py
        dmx, dmy = m1x - m0x, m1y - m0y
        a = -(vx * dmy - vy * dmx)
        b = (qx * dmy - qy * dmx) - (vx * m0y - vy * m0x)
        c = qx * m0y - qy * m0x
        if a == 0.0:
            if b == 0.0:
                return None
            roots: tuple[float, ...] = (-c / b,)
        else:
            disc = b * b - 4.0 * a * c
            if disc < 0.0:
                return None
            h = -0.5 * (b + math.copysign(math.sqrt(disc), b))  # stable form
            roots = (h / a, c / h) if h != 0.0 else (h / a,)
        best: tuple[float, float] | None = None
        for u in roots:
            if -_U_EPS <= u <= 1.0 + _U_EPS:
                u = min(max(u, 0.0), 1.0)
                nx, ny = m0x + u * dmx, m0y + u * dmy
                d = ((qx - u * vx) * nx + (qy - u * vy) * ny) / (nx * nx + ny * ny)
                if best is None or abs(d) < abs(best[1]):
                    best = (u, d)
        return best

    def frame(self, x: float, y: float) -> tuple[float, float]:
        # which quad? the vertex normal lines are ordered along the reference: bisect over them
        def side(j: int) -> float:
            px, py = self._p[j]
            fx, fy = self._fwd[j]
            return (x - px) * fx + (y - py) * fy

        n = self.pieces
        if side(0) < 0.0:  # before the start: extrapolate along the first tangent
            px, py = self._p[0]
            tx, ty = self._t0
            return (x - px) * tx + (y - py) * ty, (x - px) * ty - (y - py) * tx
        if side(n) >= 0.0:  # after the end
            px, py = self._p[n]
            tx, ty = self._t1
            return self.length + (x - px) * tx + (y - py) * ty, (x - px) * ty - (y - py) * tx
        lo, hi = 0, n  # invariant: side(lo) >= 0 > side(hi)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if side(mid) >= 0.0:
                lo = mid
            else:
                hi = mid
        sol = self._solve(lo, x, y)
        if sol is None:  # far from the reference, where normal lines cross: search everything
            return self._frame_slow(x, y)
        u, d = sol
        return self._cum[lo] + u * self._lens[lo], d

    def point(self, s: float, d: float) -> tuple[float, float]:
        n = self.pieces
        if s <= 0.0:
            px, py = self._p[0]
            tx, ty = self._t0
            return px + s * tx + d * ty, py + s * ty - d * tx
        if s >= self.length:
            px, py = self._p[n]
            tx, ty = self._t1
            e = s - self.length
            return px + e * tx + d * ty, py + e * ty - d * tx
        i = min(max(bisect_right(self._cum, s) - 1, 0), n - 1)
        u = (s - self._cum[i]) / self._lens[i]
        px, py = self._p[i]
        vx, vy = self._v[i]
        m0x, m0y = self._m[i]
        m1x, m1y = self._m[i + 1]
        return (
            px + u * vx + d * (m0x + u * (m1x - m0x)),
            py + u * vy + d * (m0y + u * (m1y - m0y)),
        )

    def piece_at(self, s: float) -> int:
        return min(max(bisect_right(self._cum, s) - 1, 0), self.pieces - 1)

    # -- vectorised --------------------------------------------------------------------------

    def frame_array(self, xy: FloatArray, chunk: int = 2048) -> FloatArray:
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"expected an (n, 2) array, got shape {xy.shape}")
        out = np.empty_like(xy)
        for k in range(0, len(xy), chunk):
            out[k : k + chunk] = self._frame_chunk(xy[k : k + chunk])
        return out

    def _frame_chunk(self, xy: FloatArray) -> FloatArray:
        """The vectorised twin of :meth:`frame`: same quad choice, same extrapolation."""
        n = self.pieces
        # side of every vertex normal line, (k, n+1); the quad is the last line passed
        side = (xy[:, 0, None] - self.p[None, :, 0]) * self.fwd[None, :, 0] + (
            xy[:, 1, None] - self.p[None, :, 1]
        ) * self.fwd[None, :, 1]
        before = side[:, 0] < 0.0
        after = ~before & (side[:, -1] >= 0.0)
        i = np.clip(np.count_nonzero(side >= 0.0, axis=1) - 1, 0, n - 1)
        s, d = self._solve_rows(xy, i[:, None])
        inside = ~before & ~after
        lost = inside & np.isnan(s)
        if np.any(lost):  # far from the reference, where normal lines cross
            s[lost], d[lost] = self._search_all(xy[lost])
        t0, t1 = self.t[0], self.t[-1]
        w0 = xy[before] - self.p[0]
        s[before], d[before] = w0 @ t0, w0[:, 0] * t0[1] - w0[:, 1] * t0[0]
        wn = xy[after] - self.p[-1]
        s[after], d[after] = self.length + wn @ t1, wn[:, 0] * t1[1] - wn[:, 1] * t1[0]
        return np.column_stack((s, d))

    def _solve_rows(self, xy: FloatArray, i: npt.NDArray[np.intp]) -> tuple[FloatArray, FloatArray]:
        """Solve the quad equation of :meth:`_solve` for point k in pieces i[k, :].

        Returns (s, d) of the valid solution with the smallest |d| per point (NaN if none).
        """
        q = xy[:, None, :] - self.p[i]  # (k, c, 2)
        v = self.v[i]
        m0 = self.m[i]
        dm = self.m[i + 1] - m0

        def cross(a: FloatArray, b: FloatArray) -> FloatArray:
            return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

        a = -cross(v, dm)
        b = cross(q, dm) - cross(v, m0)
        c = cross(q, m0)
        disc = b * b - 4.0 * a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            h = -0.5 * (b + np.copysign(np.sqrt(np.where(disc >= 0.0, disc, np.nan)), b))
            lin = a == 0.0
            r1 = np.where(lin, -c / b, h / a)
            r2 = np.where(lin, np.nan, c / h)
        rows = np.arange(len(xy))
        best_s = np.full(len(xy), np.nan)
        best_d = np.full(len(xy), np.inf)
        for u in (r1, r2):
            ok = (u >= -_U_EPS) & (u <= 1.0 + _U_EPS)
            uc = np.clip(np.where(ok, u, 0.0), 0.0, 1.0)
            nv = m0 + uc[..., None] * dm
            r = q - uc[..., None] * v
            d = np.where(ok, np.sum(r * nv, axis=-1) / np.sum(nv * nv, axis=-1), np.inf)
            j = np.argmin(np.abs(d), axis=1)
            dj = d[rows, j]
            better = np.abs(dj) < np.abs(best_d)
            ij = i[rows, j]
            best_d = np.where(better, dj, best_d)
            best_s = np.where(better, self.cum[ij] + uc[rows, j] * self.lens[ij], best_s)
        best_d[np.isnan(best_s)] = np.nan
        return best_s, best_d

    def _search_all(self, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Try every quad; where none has a solution, fall back to the nearest point."""
        every = np.broadcast_to(np.arange(self.pieces), (len(xy), self.pieces))
        s, d = self._solve_rows(xy, every)
        none = np.isnan(s)
        if np.any(none):
            s[none], d[none] = self._nearest(xy[none])
        return s, d

    def _nearest(self, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Plain nearest-point projection: s of the foot, d = signed distance (+ right)."""
        q = xy[:, None, :] - self.p[None, :-1, :]
        u = np.clip(np.sum(q * self.v[None], axis=-1) / (self.lens**2)[None], 0.0, 1.0)
        r = q - u[..., None] * self.v[None]
        dist = np.hypot(r[..., 0], r[..., 1])
        j = np.argmin(dist, axis=1)
        rows = np.arange(len(xy))
        sign = np.where(np.sum(r[rows, j] * self.n[j], axis=-1) < 0.0, -1.0, 1.0)
        return self.cum[j] + u[rows, j] * self.lens[j], sign * dist[rows, j]

    def _frame_slow(self, x: float, y: float) -> tuple[float, float]:
        """The scalar fallback: every quad, then the nearest point."""
        s, d = self._search_all(np.array([[x, y]]))
        return float(s[0]), float(d[0])


# ----------------------------------------------------------------------------------------------
# Segment
# ----------------------------------------------------------------------------------------------


class Segment:
    """A road element: lanes side by side with a shared curvilinear frame (see module docstring)."""

    __slots__ = (
        "_area",
        "_frame",
        "_id",
        "_lane_d",
        "_lane_samples",
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
        self._frame = _Frame(np.asarray(self._reference.coords, dtype=np.float64)[:, :2])

        # Each lane's offset d(s) along the reference, sampled from its (densified) centre line.
        length = self._frame.length
        grid = np.linspace(0.0, length, max(2, math.ceil(length / _OFFSET_STEP) + 1))
        samples: list[FloatArray] = []
        table = np.zeros((len(grid), len(ordered)))
        for k, lane in enumerate(ordered):
            dense = shapely.segmentize(lane.centerline, _OFFSET_STEP)
            sd = self._frame.frame_array(np.asarray(dense.coords, dtype=np.float64)[:, :2])
            samples.append(sd)
            if k > 0:
                order = np.argsort(sd[:, 0], kind="stable")
                table[:, k] = np.interp(grid, sd[order, 0], sd[order, 1])
        self._lane_samples = tuple(samples)
        self._lane_d = table
        self._left = -ordered[0].width / 2.0

        self._area: Polygon | None = None

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

        Built on first use (the loader validates the lanes first, then builds it).
        """
        if self._area is None:
            self._area = self._build_area()
        return self._area

    def _build_area(self) -> Polygon:
        ordered = self._lanes
        parts = [
            shapely.buffer(lane.centerline, lane.width / 2.0, cap_style="flat") for lane in ordered
        ]
        area = shapely.union_all(parts)
        if not isinstance(area, Polygon) or len(area.interiors) > 0:
            # small gaps between lanes (tolerated by validation): close them morphologically
            gap = 0.75
            closed = shapely.buffer(
                shapely.buffer(area, gap, join_style="mitre"), -gap, join_style="mitre"
            )
            if isinstance(closed, Polygon) and not closed.is_empty:
                area = Polygon(closed.exterior)
        if not isinstance(area, Polygon):
            raise MapError(f"segment {self._id!r}: the lanes do not form one connected surface")
        return area

    @property
    def length(self) -> float:
        """Length of the reference line in metres."""
        return self._frame.length

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
        return self._frame.frame(x, y)

    def frame_array(self, xy: npt.ArrayLike) -> FloatArray:
        """Vectorised :meth:`frame`: (n, 2) UTM points -> (n, 2) of (s, d)."""
        return self._frame.frame_array(np.asarray(xy, dtype=np.float64).reshape(-1, 2))

    def point(self, s: float, d: float = 0.0) -> tuple[float, float]:
        """The UTM point at station s and lateral offset d; the inverse of :meth:`frame`."""
        s, d = float(s), float(d)
        if not (math.isfinite(s) and math.isfinite(d)):
            raise ValueError(f"station and offset must be finite, got ({s}, {d})")
        return self._frame.point(s, d)

    def tangent(self, s: float) -> FloatArray:
        """Unit (east, north) vector of the reference direction at station s."""
        return cast(FloatArray, self._frame.t[self._frame.piece_at(s)].copy())

    def heading(self, s: float) -> float:
        """Reference direction at s in degrees from (grid) north, clockwise, in [0, 360)."""
        tx, ty = self._frame.t[self._frame.piece_at(s)]
        h = math.degrees(math.atan2(tx, ty)) % 360.0
        return 0.0 if h >= 360.0 else h

    def lane_offsets(self, s: float) -> FloatArray:
        """d of every lane's centre line at station s, shape (L,); lane 0 is 0.0.

        Outside [0, length] the offsets at the nearer end are used.
        """
        if not math.isfinite(s):
            raise ValueError(f"station must be finite, got {s}")
        table = self._lane_d
        pos = min(max(s, 0.0), self.length) / self.length * (len(table) - 1)
        i = min(int(pos), len(table) - 2)
        f = pos - i
        return cast(FloatArray, table[i] + f * (table[i + 1] - table[i]))

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
        self._sorted = sorted(segs, key=lambda seg: seg.id)  # tree index order = id order
        self._tree = STRtree([seg.area for seg in self._sorted])
        b = np.array([seg.area.bounds for seg in segs])
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

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(min x, min y, max x, max y) of all surfaces, UTM metres."""
        return self._bounds

    def __repr__(self) -> str:
        return (
            f"HdMap({self.source!r}, {len(self._segments)} segments, EPSG:{self.projection.epsg})"
        )

    @classmethod
    def load(cls, path: str | Path) -> HdMap:
        """Load and validate a GeoJSON map file; raises :class:`MapError` naming the problem."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise MapError(f"{p}: cannot read the map file: {exc.strerror or exc}") from exc
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise MapError(
                f"{p}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}"
            ) from exc
        return cls.from_geojson(data, source=str(p))

    @classmethod
    def from_geojson(cls, data: Mapping[str, Any], source: str = "<memory>") -> HdMap:
        """Build a map from a parsed GeoJSON FeatureCollection (see ``maps/README.md``)."""
        return _build(data, source)

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
        """Segments whose surface is within ``radius`` metres of (x, y), nearest first."""
        pt = Point(x, y)
        idx = self._tree.query(pt, predicate="dwithin", distance=radius)
        found = [self._sorted[int(i)] for i in idx]
        return sorted(found, key=lambda seg: (float(seg.area.distance(pt)), seg.id))


# ----------------------------------------------------------------------------------------------
# Parsing and validation
# ----------------------------------------------------------------------------------------------


@dataclass
class _RawLane:
    feature: int
    segment: str
    index: int
    type: LaneType
    width: float
    direction: Direction
    lonlat: FloatArray
    successors: tuple[str, ...]
    extra: dict[str, Any]


def _where(source: str, i: int, segment: str | None = None, lane: int | None = None) -> str:
    where = f"{source}: feature {i}"
    if segment is not None and lane is not None:
        where += f" (segment {segment!r}, lane {lane})"
    elif segment is not None:
        where += f" (segment {segment!r})"
    return where


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _parse_feature(source: str, i: int, feature: object) -> _RawLane:
    if not isinstance(feature, Mapping):
        raise MapError(f"{_where(source, i)}: not a JSON object")
    if feature.get("type") != "Feature":
        raise MapError(
            f"{_where(source, i)}: 'type' must be 'Feature', got {feature.get('type')!r}"
        )
    props = feature.get("properties")
    if not isinstance(props, Mapping):
        raise MapError(f"{_where(source, i)}: 'properties' must be an object")

    seg = props.get("segment")
    if not isinstance(seg, str) or not seg:
        raise MapError(
            f"{_where(source, i)}: property 'segment' must be a non-empty string, got {seg!r}"
        )
    lane = props.get("lane")
    if not isinstance(lane, int) or isinstance(lane, bool):
        raise MapError(
            f"{_where(source, i, seg)}: property 'lane' must be an integer, got {lane!r}"
        )
    at = _where(source, i, seg, lane)
    if lane < 0:
        raise MapError(f"{at}: property 'lane' must be >= 0, got {lane}")

    ltype = props.get("type")
    if not isinstance(ltype, str):
        raise MapError(f"{at}: property 'type' must be a string, got {ltype!r}")
    if ltype not in LANE_TYPES:
        raise MapError(
            f"{at}: unknown lane type {ltype!r} (expected one of {', '.join(sorted(LANE_TYPES))})"
        )
    width = props.get("width")
    if not _is_number(width):
        raise MapError(f"{at}: property 'width' must be a number, got {width!r}")
    width_f = float(cast(float, width))
    if not math.isfinite(width_f) or width_f <= 0.0:
        raise MapError(f"{at}: property 'width' must be > 0 metres, got {width!r}")
    direction = props.get("direction")
    if not isinstance(direction, str):
        raise MapError(f"{at}: property 'direction' must be a string, got {direction!r}")
    if direction not in DIRECTIONS:
        raise MapError(
            f"{at}: unknown direction {direction!r} (expected one of "
            f"{', '.join(sorted(DIRECTIONS))})"
        )
    succ = props.get("successors", [])
    if succ is None:
        succ = []
    if not isinstance(succ, list) or not all(isinstance(s, str) and s for s in succ):
        raise MapError(f"{at}: property 'successors' must be a list of segment ids, got {succ!r}")

    geom = feature.get("geometry")
    if not isinstance(geom, Mapping):
        raise MapError(f"{at}: 'geometry' must be an object, got {geom!r}")
    if geom.get("type") != "LineString":
        raise MapError(f"{at}: geometry must be a LineString, got {geom.get('type')!r}")
    coords = geom.get("coordinates")
    if not isinstance(coords, list):
        raise MapError(f"{at}: LineString 'coordinates' must be a list")
    if len(coords) < 2:
        raise MapError(f"{at}: LineString needs at least 2 points, got {len(coords)}")
    lonlat = np.empty((len(coords), 2))
    for k, pos in enumerate(coords):
        if (
            not isinstance(pos, list)
            or not 2 <= len(pos) <= 3
            or not all(_is_number(c) for c in pos)
        ):
            raise MapError(f"{at}: coordinate {k} must be [lon, lat] numbers, got {pos!r}")
        lon, lat = float(pos[0]), float(pos[1])
        if not (
            math.isfinite(lon)
            and -180.0 <= lon <= 180.0
            and math.isfinite(lat)
            and -90.0 <= lat <= 90.0
        ):
            raise MapError(
                f"{at}: coordinate {k} [{pos[0]}, {pos[1]}] is out of lon/lat range "
                "(GeoJSON order is [longitude, latitude])"
            )
        lonlat[k] = lon, lat
    if not np.any(lonlat[1:] != lonlat[0]):
        raise MapError(f"{at}: LineString has fewer than 2 distinct points")
    line = LineString(lonlat)
    if line.is_closed:
        raise MapError(f"{at}: LineString is closed (first point equals last)")
    if not shapely.is_simple(line):
        raise MapError(f"{at}: LineString intersects itself")

    extra = {k: v for k, v in props.items() if k not in _KNOWN_PROPERTIES}
    return _RawLane(
        i,
        seg,
        lane,
        cast(LaneType, ltype),
        width_f,
        cast(Direction, direction),
        lonlat,
        tuple(succ),
        extra,
    )


def _build(data: Mapping[str, Any], source: str) -> HdMap:
    if not isinstance(data, Mapping) or data.get("type") != "FeatureCollection":
        got = data.get("type") if isinstance(data, Mapping) else type(data).__name__
        raise MapError(f"{source}: not a GeoJSON FeatureCollection (type is {got!r})")
    features = data.get("features")
    if not isinstance(features, list):
        raise MapError(f"{source}: FeatureCollection has no 'features' list")
    if not features:
        raise MapError(f"{source}: FeatureCollection has no features")

    raws = [_parse_feature(source, i, f) for i, f in enumerate(features)]
    by_seg: dict[str, dict[int, _RawLane]] = {}
    for raw in raws:
        lanes = by_seg.setdefault(raw.segment, {})
        if raw.index in lanes:
            first = lanes[raw.index].feature
            raise MapError(
                f"{_where(source, raw.feature, raw.segment, raw.index)}: duplicate "
                f"lane (segment {raw.segment!r}, lane {raw.index}) also in feature "
                f"{first}"
            )
        lanes[raw.index] = raw
    for seg_id, lanes in by_seg.items():
        expected = list(range(len(lanes)))
        got = sorted(lanes)
        if got != expected:
            missing = sorted(set(expected) - set(got))
            bad = min(i for i in got if i not in expected)
            raise MapError(
                f"{_where(source, lanes[bad].feature, seg_id, bad)}: lane indices of "
                f"segment {seg_id!r} must be contiguous from 0, got {got} "
                f"(missing {missing})"
            )
    for raw in raws:
        for succ in raw.successors:
            if succ not in by_seg:
                raise MapError(
                    f"{_where(source, raw.feature, raw.segment, raw.index)}: unknown "
                    f"successor segment {succ!r}"
                )

    all_ll = np.concatenate([r.lonlat for r in raws])
    projection = UtmProjection.for_location(
        float(np.mean(all_ll[:, 0])), float(np.mean(all_ll[:, 1]))
    )
    segments = []
    for seg_id, lanes in by_seg.items():
        ordered = [lanes[k] for k in range(len(lanes))]
        segments.append(_make_segment(source, projection, seg_id, ordered))
    return HdMap(segments, projection, source)


def _make_segment(
    source: str, proj: UtmProjection, seg_id: str, raws: Sequence[_RawLane]
) -> Segment:
    lanes = []
    for raw in raws:
        xy = proj.to_utm_array(raw.lonlat[:, 0], raw.lonlat[:, 1])
        lanes.append(
            Lane(
                seg_id,
                raw.index,
                raw.type,
                raw.width,
                raw.direction,
                LineString(xy),
                MappingProxyType(dict(raw.extra)),
            )
        )
    ref = raws[0]
    turn, vertex = _sharpest_turn(np.asarray(lanes[0].centerline.coords))
    if turn > _MAX_TURN_DEG:
        raise MapError(
            f"{_where(source, ref.feature, seg_id, 0)}: the reference centre line turns "
            f"by {turn:.0f} degrees at vertex {vertex} (at most {_MAX_TURN_DEG:.0f} "
            "allowed; add vertices along the curve)"
        )
    successors = [s for raw in raws for s in raw.successors]
    try:
        seg = Segment(seg_id, lanes, successors)
    except MapError as exc:
        raise MapError(f"{_where(source, ref.feature, seg_id)}: {exc}") from exc
    _check_side_by_side(source, seg, raws)
    try:
        _ = seg.area
    except MapError as exc:
        raise MapError(f"{_where(source, ref.feature, seg_id)}: {exc}") from exc
    return seg


def _check_side_by_side(source: str, seg: Segment, raws: Sequence[_RawLane]) -> None:
    """Lanes must follow the reference direction, cover it, and lie next to each other in order."""
    length = seg.length
    tol_s = max(5.0, 0.1 * length)
    samples = seg._lane_samples
    for raw, sd in zip(raws, samples, strict=True):
        at = _where(source, raw.feature, seg.id, raw.index)
        if raw.index == 0:
            continue
        if sd[-1, 0] <= sd[0, 0]:
            raise MapError(
                f"{at}: the centre line runs against the segment's reference direction "
                "(coordinates must follow lane 0's order; use direction 'backward' for "
                "travel against it)"
            )
        lo, hi = float(sd[:, 0].min()), float(sd[:, 0].max())
        if lo > tol_s or lo < -tol_s or hi < length - tol_s or hi > length + tol_s:
            raise MapError(
                f"{at}: the lane covers stations {lo:.1f}..{hi:.1f} m of the segment, "
                f"but lane 0 runs 0..{length:.1f} m (tolerance {tol_s:.1f} m)"
            )
    count = max(5, math.ceil(length / 10.0))
    stations = np.linspace(0.0, length, count + 2)[1:-1]
    for s in stations:
        offsets = seg.lane_offsets(float(s))
        for k in range(len(raws) - 1):
            a, b = raws[k], raws[k + 1]
            at = _where(source, b.feature, seg.id, b.index)
            gap = float(offsets[k + 1] - offsets[k])
            expected = (a.width + b.width) / 2.0
            tol = max(0.35 * expected, 0.75)
            if gap <= 0.0:
                raise MapError(
                    f"{at}: at station {s:.1f} m the lane is not to the right of lane "
                    f"{a.index} (lateral offset {offsets[k + 1]:.2f} m vs "
                    f"{offsets[k]:.2f} m); lanes are numbered from the left"
                )
            if abs(gap - expected) > tol:
                raise MapError(
                    f"{at}: at station {s:.1f} m the lane is {gap:.2f} m from lane "
                    f"{a.index}, expected {expected:.2f} ± {tol:.2f} m from the widths; "
                    "the lanes do not run side by side"
                )
