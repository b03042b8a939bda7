"""The curvilinear frame ``(s, d)`` of a polyline: exact, pure numbers, no shapely.

A segment's frame is built on its *reference*, lane 0's centre line, a polyline with
vertices ``P_0 .. P_n`` and pieces ``i = 0 .. n-1``::

    T_i = (P_{i+1} - P_i) / |P_{i+1} - P_i|      unit tangent of piece i
    N_i = (T_i.y, -T_i.x)                       unit normal, pointing to the RIGHT
    M_j = (N_{j-1} + N_j) / (1 + N_{j-1}.N_j)   mitred vertex normal (M_j.N_{j-1} = M_j.N_j = 1),
                                                M_0 = N_0, M_n = N_{n-1}
    point(s, d) = P_i + u (P_{i+1} - P_i) + d ((1 - u) M_i + u M_{i+1})
    s = S_i + u |P_{i+1} - P_i|                 (S_i: station of P_i, 0 <= u <= 1)

so the curve ``d = const`` is exactly the mitred offset curve of the reference, and ``frame`` is
the exact inverse of ``point`` (a bijection within the local radius of curvature of the
reference). Before the start and after the end, the frame extrapolates along the end tangents.
``d`` is positive to the right looking along the reference direction, so lane offsets increase
with the lane index.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from typing import Protocol, cast

import numpy as np
import numpy.typing as npt

from laas.errors import MapError

__all__ = ["MIN_PIECE", "Frame", "FrameStack", "dedupe", "sharpest_turn"]

FloatArray = npt.NDArray[np.float64]

MIN_PIECE = 0.01  # m: reference vertices closer than this are merged
_U_EPS = 1e-9  # tolerance on the piece parameter u when accepting a frame solution
_WINDING = math.radians(150.0)  # heading span beyond which the quad search tries them all


def dedupe(coords: FloatArray, tol: float = 0.0) -> FloatArray:
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


def sharpest_turn(coords: FloatArray) -> tuple[float, int]:
    """(largest turn angle in degrees at an interior vertex, that vertex's index)."""
    c = dedupe(coords, MIN_PIECE)
    if len(c) < 3:
        return 0.0, 0
    v = c[1:] - c[:-1]
    a = np.arctan2(v[:, 1], v[:, 0])
    turn = np.abs((np.diff(a) + math.pi) % (2 * math.pi) - math.pi)
    j = int(np.argmax(turn))
    return math.degrees(float(turn[j])), j + 1


class Frame:
    """The (s, d) frame of a polyline (see the module docstring). Pure numbers, no shapely.

    Arrays: ``p``, ``m``, ``fwd``, ``cum`` per vertex (n + 1, ...); ``v``, ``lens``, ``t``,
    ``n`` per piece (n, ...). Many frames at once: :class:`FrameStack`.
    """

    def __init__(self, coords: npt.ArrayLike) -> None:
        p = dedupe(np.asarray(coords, dtype=np.float64), MIN_PIECE)
        if len(p) < 2 or (len(p) == 2 and math.dist(p[0], p[-1]) <= MIN_PIECE):
            raise MapError(f"reference line is shorter than {MIN_PIECE} m")
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
        cum = np.concatenate(([0.0], np.cumsum(lens)))
        heading = np.unwrap(np.arctan2(t[:, 1], t[:, 0]))
        self._set(p, v, lens, t, nrm, m, fwd, cum, bool(heading.max() - heading.min() > _WINDING))

    @classmethod
    def _of(cls, stack: FrameStack, k: int) -> Frame:
        frame = cls.__new__(cls)
        frame._take(stack, k)
        return frame

    def _take(self, stack: FrameStack, k: int) -> None:
        """Become frame k of `stack`: views of its rows, no arithmetic."""
        if not stack.usable[k]:
            raise MapError(f"reference line is shorter than {MIN_PIECE} m")
        a, b = int(stack.first[k]), int(stack.first[k + 1])
        self._set(
            stack.p[a:b],
            stack.v[a : b - 1],
            stack.lens[a : b - 1],
            stack.t[a : b - 1],
            stack.n[a : b - 1],
            stack.m[a:b],
            stack.fwd[a:b],
            stack.cum[a:b],
            bool(stack.winds[k]),
        )

    def _set(
        self,
        p: FloatArray,
        v: FloatArray,
        lens: FloatArray,
        t: FloatArray,
        n: FloatArray,
        m: FloatArray,
        fwd: FloatArray,
        cum: FloatArray,
        winds: bool,
    ) -> None:
        self.p, self.v, self.lens, self.t, self.n, self.m, self.fwd = p, v, lens, t, n, m, fwd
        self.cum = cum
        self.length = float(cum[-1])
        self.pieces = len(lens)
        # Where the reference's heading spans more than _WINDING, vertex normal lines are
        # no longer ordered along it (a point can be past a later line and before an
        # earlier one), so the quad is not found by bisection: every quad between two
        # lines the point lies between is tried (`_frame_winding`).
        self.winds = winds
        # python-float copies for the scalar path (much faster than numpy scalars)
        self._p: list[list[float]] = self.p.tolist()
        self._v: list[list[float]] = self.v.tolist()
        self._m: list[list[float]] = self.m.tolist()
        self._fwd: list[list[float]] = self.fwd.tolist()
        self._cum: list[float] = self.cum.tolist()
        self._lens: list[float] = self.lens.tolist()
        self._t: list[list[float]] = self.t.tolist()
        self._t0: list[float] = self._t[0]
        self._t1: list[float] = self._t[-1]

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
        if self.winds:
            return self._frame_winding_scalar(x, y)

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

    def _frame_winding_scalar(self, x: float, y: float) -> tuple[float, float]:
        """:meth:`frame` for a winding reference, in plain floats (see `_frame_winding`)."""
        n = self.pieces
        sides = [
            (x - px) * fx + (y - py) * fy
            for (px, py), (fx, fy) in zip(self._p, self._fwd, strict=True)
        ]
        best: tuple[float, float] | None = None
        for j in range(n):
            if sides[j] >= 0.0 > sides[j + 1]:
                sol = self._solve(j, x, y)
                if sol is not None and (best is None or abs(sol[1]) < abs(best[1])):
                    best = (self._cum[j] + sol[0] * self._lens[j], sol[1])
        if sides[0] < 0.0:
            px, py = self._p[0]
            tx, ty = self._t0
            d = (x - px) * ty - (y - py) * tx
            if best is None or not abs(best[1]) <= abs(d):
                best = ((x - px) * tx + (y - py) * ty, d)
        if sides[n] >= 0.0:
            px, py = self._p[n]
            tx, ty = self._t1
            d = (x - px) * ty - (y - py) * tx
            if best is None or not abs(best[1]) <= abs(d):
                best = (self.length + (x - px) * tx + (y - py) * ty, d)
        return best if best is not None else self._frame_slow(x, y)

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

    def piece_array(self, s: FloatArray) -> npt.NDArray[np.intp]:
        """Vectorised :meth:`piece_at`."""
        i = np.searchsorted(self.cum, s, side="right") - 1
        return cast(npt.NDArray[np.intp], np.clip(i, 0, self.pieces - 1))

    def point_array(self, s: FloatArray, d: FloatArray) -> FloatArray:
        """Vectorised :meth:`point`: (n,) stations and offsets -> (n, 2), the same values."""
        i = self.piece_array(s)
        u = (s - self.cum[i]) / self.lens[i]
        m0, m1 = self.m[i], self.m[i + 1]
        # P_i + u V_i + d (M_i + u (M_{i+1} - M_i))
        x = self.p[i, 0] + u * self.v[i, 0] + d * (m0[:, 0] + u * (m1[:, 0] - m0[:, 0]))
        y = self.p[i, 1] + u * self.v[i, 1] + d * (m0[:, 1] + u * (m1[:, 1] - m0[:, 1]))
        # before the start and after the end: along the end tangents
        t0, t1, n = self.t[0], self.t[-1], self.pieces
        lo, hi = s <= 0.0, s >= self.length
        x[lo] = self.p[0, 0] + s[lo] * t0[0] + d[lo] * t0[1]
        y[lo] = self.p[0, 1] + s[lo] * t0[1] - d[lo] * t0[0]
        e = s[hi] - self.length
        x[hi] = self.p[n, 0] + e * t1[0] + d[hi] * t1[1]
        y[hi] = self.p[n, 1] + e * t1[1] - d[hi] * t1[0]
        return np.column_stack((x, y))

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
        if self.winds:
            return self._frame_winding(xy, side)
        before = side[:, 0] < 0.0
        after = ~before & (side[:, -1] >= 0.0)
        i = np.clip(np.count_nonzero(side >= 0.0, axis=1) - 1, 0, n - 1)
        s, d = self._solve_rows(xy, i[:, None])
        inside = ~before & ~after
        lost = inside & np.isnan(s)
        if np.any(lost):  # far from the reference, where normal lines cross
            s[lost], d[lost] = self._search_all(xy[lost])
        t0, t1 = self.t[0], self.t[-1]
        w0 = xy[before] - self.p[0]  # summed as the scalar path sums, not a BLAS product
        s[before] = w0[:, 0] * t0[0] + w0[:, 1] * t0[1]
        d[before] = w0[:, 0] * t0[1] - w0[:, 1] * t0[0]
        wn = xy[after] - self.p[-1]
        s[after] = self.length + (wn[:, 0] * t1[0] + wn[:, 1] * t1[1])
        d[after] = wn[:, 0] * t1[1] - wn[:, 1] * t1[0]
        return np.column_stack((s, d))

    def _frame_winding(self, xy: FloatArray, side: FloatArray) -> FloatArray:
        """:meth:`_frame_chunk` for a winding reference: the candidates are every quad
        whose two normal lines the point lies between (side(j) >= 0 > side(j + 1)), and
        the extrapolations before the start (side(0) < 0) and after the end
        (side(n) >= 0); the one with the smallest |d| is the point's place."""
        between = (side[:, :-1] >= 0.0) & (side[:, 1:] < 0.0)
        every = np.broadcast_to(np.arange(self.pieces), (len(xy), self.pieces))
        s, d = self._solve_rows(xy, every, between)
        t0, t1 = self.t[0], self.t[-1]
        w0, wn = xy - self.p[0], xy - self.p[-1]
        ends = (
            (
                side[:, 0] < 0.0,
                w0[:, 0] * t0[0] + w0[:, 1] * t0[1],
                w0[:, 0] * t0[1] - w0[:, 1] * t0[0],
            ),
            (
                side[:, -1] >= 0.0,
                self.length + (wn[:, 0] * t1[0] + wn[:, 1] * t1[1]),
                wn[:, 0] * t1[1] - wn[:, 1] * t1[0],
            ),
        )
        for candidate, s_end, d_end in ends:
            take = candidate & ~(np.abs(d) <= np.abs(d_end))  # also where d is NaN
            s, d = np.where(take, s_end, s), np.where(take, d_end, d)
        lost = np.isnan(s)
        if np.any(lost):
            s[lost], d[lost] = self._search_all(xy[lost])
        return np.column_stack((s, d))

    def _solve_rows(
        self,
        xy: FloatArray,
        i: npt.NDArray[np.intp],
        allowed: npt.NDArray[np.bool_] | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        return _solve_rows(self, xy, i, allowed)

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


def _solve_rows(
    f: _Pieces,
    xy: FloatArray,
    i: npt.NDArray[np.intp],
    allowed: npt.NDArray[np.bool_] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Solve the quad equation of :meth:`Frame._solve` for point k in pieces i[k, :] (where
    `allowed`, of i's shape, says so).

    Returns (s, d) of the valid solution with the smallest |d| per point (NaN if none).
    """
    q = xy[:, None, :] - f.p[i]  # (k, c, 2)
    v = f.v[i]
    m0 = f.m[i]
    dm = f.m[i + 1] - m0

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
        if allowed is not None:
            ok &= allowed
        uc = np.clip(np.where(ok, u, 0.0), 0.0, 1.0)
        nv = m0 + uc[..., None] * dm
        r = q - uc[..., None] * v
        d = np.where(ok, np.sum(r * nv, axis=-1) / np.sum(nv * nv, axis=-1), np.inf)
        j = np.argmin(np.abs(d), axis=1)
        dj = d[rows, j]
        better = np.abs(dj) < np.abs(best_d)
        ij = i[rows, j]
        best_d = np.where(better, dj, best_d)
        best_s = np.where(better, f.cum[ij] + uc[rows, j] * f.lens[ij], best_s)
    best_d[np.isnan(best_s)] = np.nan
    return best_s, best_d


class _Pieces(Protocol):
    """The arrays :func:`_solve_rows` reads, indexed by vertex (a piece by its first vertex)."""

    p: FloatArray
    v: FloatArray
    m: FloatArray
    cum: FloatArray
    lens: FloatArray


class FrameStack:
    """The frames of many polylines in one set of arrays: built together, queried together.

    Vertex ``g`` of the stack is vertex ``g - first[k]`` of frame ``k``. Arrays of pieces
    (``v``, ``lens``, ``t``, ``n``) are indexed by the vertex that starts the piece, so the
    last vertex of each frame has a row of NaN there. Every value comes from the same
    elementwise arithmetic as :class:`Frame` uses for one polyline (sums run in order within
    each frame, np.unwrap's steps are repeated), so ``stack.frame(k)`` equals
    ``Frame(refs[k])`` bit for bit (tests/test_map_frames.py holds it to that). A reference
    shorter than :data:`MIN_PIECE` has no frame: ``usable[k]`` is False and ``frame(k)``
    raises :class:`MapError`.
    """

    def __init__(self, refs: Sequence[npt.ArrayLike]) -> None:
        arrays = [np.asarray(r, dtype=np.float64) for r in refs]
        for c in arrays:
            if c.ndim != 2 or c.shape[1] != 2:
                raise ValueError(f"a reference must be an (n, 2) array, got shape {c.shape}")
        p, counts = _dedupe_all(arrays)
        self.count = len(counts)
        self.usable: npt.NDArray[np.bool_] = counts > 0
        first = np.zeros(self.count + 1, dtype=np.intp)
        np.cumsum(counts, out=first[1:])
        self.first = first  # the vertices of frame k: first[k] .. first[k + 1] - 1
        total = int(first[-1])
        starts, ends = first[:-1][self.usable], first[1:][self.usable] - 1
        pieces = counts[self.usable] - 1
        # V_g = P_{g+1} - P_g,  T = V / |V|,  N = (T.y, -T.x)   (NaN past each frame's end)
        v = np.full((total, 2), np.nan)
        v[:-1] = p[1:] - p[:-1]
        v[ends] = np.nan
        lens = np.hypot(v[:, 0], v[:, 1])
        t = v / lens[:, None]
        nrm = np.column_stack((t[:, 1], -t[:, 0]))
        m = np.empty_like(p)
        # M_j = (N_{j-1} + N_j) / (1 + N_{j-1}.N_j): the mitre vector, M_j.N = 1 on both sides
        m[1:] = (nrm[:-1] + nrm[1:]) / (1.0 + np.sum(nrm[:-1] * nrm[1:], axis=1))[:, None]
        m[starts], m[ends] = nrm[starts], nrm[ends - 1]  # M_0 = N_0, M_n = N_{n-1}
        # unit "forward" direction across each vertex normal line: perpendicular to M_j
        fwd = np.column_stack((-m[:, 1], m[:, 0]))
        fwd /= np.hypot(fwd[:, 0], fwd[:, 1])[:, None]
        # S_j = |V_0| + .. + |V_{j-1}|, summed in order within each frame
        is_piece = ~np.isnan(lens)
        cum = np.zeros(total)
        cum[np.flatnonzero(is_piece) + 1] = _runs_cumsum(lens[is_piece], pieces)
        self.p, self.v, self.lens, self.t, self.n = p, v, lens, t, nrm
        self.m, self.fwd, self.cum = m, fwd, cum
        self.winds = np.zeros(self.count, dtype=np.bool_)
        self.winds[self.usable] = self._heading_span(is_piece, pieces) > _WINDING
        self._frames: list[Frame | None] = [None] * self.count

    def _heading_span(
        self, is_piece: npt.NDArray[np.bool_], pieces: npt.NDArray[np.intp]
    ) -> FloatArray:
        """max - min of each usable frame's unwrapped tangent heading (np.unwrap's arithmetic:
        a jump dd is corrected by mod(dd + pi, 2 pi) - pi - dd where |dd| >= pi)."""
        heading = np.arctan2(self.t[:, 1], self.t[:, 0])
        pair = is_piece[:-1] & is_piece[1:]  # piece g followed by piece g + 1 of its frame
        dd = heading[1:][pair] - heading[:-1][pair]
        ddmod = np.mod(dd + np.pi, 2 * np.pi) - np.pi
        np.copyto(ddmod, np.pi, where=(ddmod == -np.pi) & (dd > 0))
        correct = ddmod - dd
        np.copyto(correct, 0, where=np.abs(dd) < np.pi)
        if np.any(correct != 0.0):
            heading[np.flatnonzero(pair) + 1] += _runs_cumsum(correct, pieces - 1)
        run = heading[is_piece]
        if not len(run):
            return np.zeros(0)
        at = np.cumsum(pieces) - pieces
        return cast(FloatArray, np.maximum.reduceat(run, at) - np.minimum.reduceat(run, at))

    def length(self, k: int) -> float:
        """The length of reference k."""
        return float(self.cum[self.first[k + 1] - 1])

    def frame(self, k: int) -> Frame:
        """Frame k on its own (views of the stack's rows; built once)."""
        f = self._frames[k]
        if f is None:
            f = self._frames[k] = Frame._of(self, k)
        return f

    def sharpest_turns(self) -> tuple[FloatArray, npt.NDArray[np.intp]]:
        """:func:`sharpest_turn` of every reference: (radians, vertex) per frame, (0, 0)
        for a frame of fewer than two pieces or none."""
        turns = np.zeros(self.count)
        vertex = np.zeros(self.count, dtype=np.intp)
        heading = np.arctan2(self.v[:, 1], self.v[:, 0])
        is_piece = ~np.isnan(self.lens)
        pair = is_piece[:-1] & is_piece[1:]
        turn = np.abs((heading[1:][pair] - heading[:-1][pair] + math.pi) % (2 * math.pi) - math.pi)
        runs = np.where(self.usable, np.diff(self.first) - 2, 0)
        has = runs > 0
        if np.any(has):
            at = (np.cumsum(runs) - runs)[has]
            top = np.maximum.reduceat(turn, at)
            local = np.arange(len(turn)) - np.repeat(np.cumsum(runs) - runs, runs)
            first_top = np.where(turn == np.repeat(top, runs[has]), local, len(turn))
            turns[has] = top
            vertex[has] = np.minimum.reduceat(first_top, at) + 1
        return turns, vertex

    def frame_many(self, xy: npt.ArrayLike, which: npt.ArrayLike) -> FloatArray:
        """(s, d) of point k in frame which[k]: (n, 2) points, (n,) frame indices -> (n, 2).

        Each point gets exactly what ``frame(which[k]).frame_array`` gives it.
        """
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        idx = np.asarray(which, dtype=np.intp).reshape(-1)
        if len(idx) != len(pts):
            raise ValueError(f"{len(pts)} points but {len(idx)} frame indices")
        if len(idx) and (idx.min() < 0 or idx.max() >= self.count):
            raise IndexError(f"frame indices must lie in 0..{self.count - 1}")
        if not np.all(self.usable[idx]):
            raise MapError(f"reference line is shorter than {MIN_PIECE} m")
        out = np.empty_like(pts)
        winding = self.winds[idx]
        for k in np.unique(idx[winding]):
            sel = idx == k
            out[sel] = self.frame(int(k)).frame_array(pts[sel])
        plain = np.flatnonzero(~winding)
        # in chunks of about _PAIRS (point, vertex) pairs
        pairs = np.cumsum(np.diff(self.first)[idx[plain]])
        lo = 0
        while lo < len(plain):
            base = int(pairs[lo - 1]) if lo else 0
            hi = max(lo + 1, int(np.searchsorted(pairs, base + _PAIRS, side="right")))
            rows = plain[lo:hi]
            out[rows] = self._frame_plain(pts[rows], idx[rows])
            lo = hi
        return out

    def _frame_plain(self, xy: FloatArray, which: npt.NDArray[np.intp]) -> FloatArray:
        """:meth:`Frame._frame_chunk` for points in frames that do not wind."""
        a = self.first[which]
        nv = self.first[which + 1] - a
        grp = np.cumsum(nv) - nv  # the first (point, vertex) pair of each point
        pt = np.repeat(np.arange(len(xy)), nv)
        g = np.arange(int(nv.sum())) - np.repeat(grp, nv) + np.repeat(a, nv)
        # side of every vertex normal line of the point's frame; the quad is the last passed
        side = (xy[pt, 0] - self.p[g, 0]) * self.fwd[g, 0] + (xy[pt, 1] - self.p[g, 1]) * self.fwd[
            g, 1
        ]
        passed = np.add.reduceat((side >= 0.0).astype(np.intp), grp)
        before = side[grp] < 0.0
        after = ~before & (side[grp + nv - 1] >= 0.0)
        i = a + np.clip(passed - 1, 0, nv - 2)
        s, d = _solve_rows(self, xy, i[:, None])
        lost = ~before & ~after & np.isnan(s)
        for k in np.unique(which[lost]):  # far from the reference, where normal lines cross
            sel = lost & (which == k)
            s[sel], d[sel] = self.frame(int(k))._search_all(xy[sel])
        j = a[before]  # before the start: along the first tangent
        w, tj = xy[before] - self.p[j], self.t[j]
        s[before] = w[:, 0] * tj[:, 0] + w[:, 1] * tj[:, 1]
        d[before] = w[:, 0] * tj[:, 1] - w[:, 1] * tj[:, 0]
        j = (a + nv - 1)[after]  # after the end: along the last tangent
        w, tj = xy[after] - self.p[j], self.t[j - 1]
        s[after] = self.cum[j] + (w[:, 0] * tj[:, 0] + w[:, 1] * tj[:, 1])
        d[after] = w[:, 0] * tj[:, 1] - w[:, 1] * tj[:, 0]
        return np.column_stack((s, d))


_PAIRS = 1 << 20  # (point, vertex) pairs per chunk of FrameStack.frame_many


def _dedupe_all(refs: Sequence[FloatArray]) -> tuple[FloatArray, npt.NDArray[np.intp]]:
    """Every reference deduplicated as by :func:`dedupe` (MIN_PIECE), concatenated; and the
    vertex count of each, 0 for one too short for a frame.

    A reference whose consecutive vertices are all clearly farther apart than MIN_PIECE is
    kept as it is (what `dedupe` does with it); only the others go through `dedupe`.
    """
    if not refs:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.intp)
    raw = np.concatenate(refs)
    n = np.array([len(r) for r in refs], dtype=np.intp)
    last = np.cumsum(n) - 1  # the last vertex of each reference
    inner = n >= 2
    close = ~inner
    if np.any(inner):  # the closest consecutive pair of each reference
        gap = np.hypot(*(raw[1:] - raw[:-1]).T)
        within = np.ones(len(gap), dtype=np.bool_)
        within[last[(n >= 1) & (last < len(gap))]] = False
        runs = n[inner] - 1
        nearest = np.minimum.reduceat(gap[within], np.cumsum(runs) - runs)
        close[inner] = ~(nearest > MIN_PIECE * (1.0 + 1e-9))
    kept: list[FloatArray] = []
    counts = n.copy()
    for k in range(len(refs)):
        if not close[k]:
            kept.append(refs[k])
            continue
        p = dedupe(refs[k], MIN_PIECE)
        if len(p) < 2 or (len(p) == 2 and math.dist(p[0], p[-1]) <= MIN_PIECE):
            counts[k] = 0
            continue
        kept.append(p)
        counts[k] = len(p)
    return (np.concatenate(kept) if kept else np.zeros((0, 2))), counts


def _runs_cumsum(values: FloatArray, lengths: npt.NDArray[np.intp]) -> FloatArray:
    """np.cumsum of each run of `values` (consecutive runs of `lengths`), each summed in
    order from its start, exactly as np.cumsum of the run alone: runs of about the same
    length share a zero-padded table that is summed along its rows."""
    if len(lengths) == 1:  # one run: the plain sum
        return cast(FloatArray, np.cumsum(values))
    out = np.empty_like(values)
    starts = np.cumsum(lengths) - lengths
    size = np.ceil(np.log2(np.maximum(lengths, 1))).astype(np.intp)
    for b in np.unique(size[lengths > 0]):
        runs = np.flatnonzero((size == b) & (lengths > 0))
        n = lengths[runs]
        rows = np.repeat(np.arange(len(runs)), n)
        cols = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        at = starts[runs][rows] + cols
        table = np.zeros((len(runs), int(n.max())))
        table[rows, cols] = values[at]
        out[at] = np.cumsum(table, axis=1)[rows, cols]
    return out
