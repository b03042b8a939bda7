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

import numpy as np
import numpy.typing as npt

from laas.errors import MapError

__all__ = ["MIN_PIECE", "Frame", "dedupe", "sharpest_turn"]

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
    """The (s, d) frame of a polyline (see the module docstring). Pure numbers, no shapely."""

    def __init__(self, coords: FloatArray) -> None:
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
        # Where the reference's heading spans more than _WINDING, vertex normal lines are
        # no longer ordered along it (a point can be past a later line and before an
        # earlier one), so the quad is not found by bisection: every quad between two
        # lines the point lies between is tried (`_frame_winding`).
        heading = np.unwrap(np.arctan2(t[:, 1], t[:, 0]))
        self.winds = bool(heading.max() - heading.min() > _WINDING)

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
        w0 = xy[before] - self.p[0]
        s[before], d[before] = w0 @ t0, w0[:, 0] * t0[1] - w0[:, 1] * t0[0]
        wn = xy[after] - self.p[-1]
        s[after], d[after] = self.length + wn @ t1, wn[:, 0] * t1[1] - wn[:, 1] * t1[0]
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
            (side[:, 0] < 0.0, w0 @ t0, w0[:, 0] * t0[1] - w0[:, 1] * t0[0]),
            (side[:, -1] >= 0.0, self.length + wn @ t1, wn[:, 0] * t1[1] - wn[:, 1] * t1[0]),
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
        """Solve the quad equation of :meth:`_solve` for point k in pieces i[k, :] (where
        `allowed`, of i's shape, says so).

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
