"""The GNSS error that nearby receivers share: a grid posterior per area.

Receivers close together see almost the same satellite and atmosphere errors, so every
fix is p_i = x_i + b + e_i with one common error b per area, a slowly drifting 2-D
random walk (b_k = b_{k-1} + w, w ~ N(0, q dt I)).

A user on a road observes b only across it: its evidence is a function of u = n . b,
with n the road's unit normal at the user. Such evidence can be many-peaked (one peak
per lane the user might be on), so the posterior of b is kept on a grid (a point-mass
filter: the discrete Bayes filter of the paper, applied to the common error):

    log p(b) <- log p(b) + log c(n . b)      update: c is given on a 1-D grid of u
    p(b)     <- p(b) * blur(q dt)             prediction: the random walk

Across one straight road the posterior is a ridge along the road: nothing is corrected
along it until some user drives a road of another direction, and the covariance of b
says so (and with it every answer's along-road accuracy). `UGrid` is the 1-D grid of
u = n . b shared by every direction n, and `project` gives the posterior of u.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CommonError", "CommonErrorField", "UGrid"]

_U_STEP = 0.1  # m: cell of the 1-D grid of u = n . b, well below any lane-evidence width
_DROP = 40.0  # cells this far below the maximum in log p hold no mass worth keeping


class UGrid:
    """A 1-D grid of u = n . b: `size` cells of width `step` from `lo` (cell centres)."""

    def __init__(self, half: float, step: float) -> None:
        self.step = step
        self.size = math.ceil(2.0 * half / step) + 1
        self.lo = -half
        self.values = self.lo + step * np.arange(self.size)

    def index(self, u: np.ndarray) -> np.ndarray:
        """The cell of each u (clipped to the grid)."""
        return np.clip(((u - self.lo) / self.step + 0.5).astype(np.intp), 0, self.size - 1)


class CommonError:
    """The common error of one area: a grid posterior with mean b (2,) and covariance P.

    Only a window of the grid holds mass worth keeping (log p > -`_DROP` below the
    maximum); updates touch only that window, which shrinks as evidence comes in and
    grows by the random-walk blur, so a settled estimate costs little per fix.
    """

    def __init__(
        self, centre: np.ndarray, prior_sigma: float, drift: float, resolution: float
    ) -> None:
        self.centre = centre.copy()
        half = 3.5 * prior_sigma  # wide enough that no ridge of likely values is clipped
        self._res = resolution
        self._axis = np.arange(-half, half + resolution / 2, resolution)
        n = self._axis.size
        sq = self._axis**2
        self._log = -0.5 * (sq[:, None] + sq[None, :]) / prior_sigma**2  # (n, n): [east, north]
        self._win = (0, n, 0, n)
        self.u = UGrid(half * math.sqrt(2.0), _U_STEP)
        self._cells_key: tuple[object, ...] = ()
        self._cells_idx = np.zeros((0, 0), dtype=np.intp)
        self._drift_var = drift**2
        self._pending_var = 0.0
        self.t: float | None = None
        self.updates = 0
        self.b = np.zeros(2)
        self.P = np.eye(2) * prior_sigma**2
        self._moments()

    def _moments(self) -> None:
        """The window's weights p(b), b = E[b] and P = Cov[b]."""
        i0, i1, j0, j1 = self._win
        w = np.exp(self._log[i0:i1, j0:j1])
        self._w = w / w.sum()
        self.b, self.P = self._stats(self._w)

    def _stats(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of b under window weights w (summing to 1), plus each
        cell's own spread res^2 / 12."""
        i0, i1, j0, j1 = self._win
        ae, an = self._axis[i0:i1], self._axis[j0:j1]
        we, wn = w.sum(axis=1), w.sum(axis=0)
        me, mn = float(we @ ae), float(wn @ an)
        cee = float(we @ (ae - me) ** 2)
        cnn = float(wn @ (an - mn) ** 2)
        cen = float((ae - me) @ w @ (an - mn))
        cov = np.array([[cee, cen], [cen, cnn]]) + np.eye(2) * self._res**2 / 12.0
        return np.array([me, mn]), cov

    def _shrink(self) -> None:
        """Drop the window's edges that hold no mass; keep two cells of margin."""
        i0, i1, j0, j1 = self._win
        sub = self._log[i0:i1, j0:j1]
        keep = sub > -_DROP
        rows, cols = np.flatnonzero(keep.any(axis=1)), np.flatnonzero(keep.any(axis=0))
        n = self._axis.size
        new = (
            max(0, i0 + int(rows[0]) - 2),
            min(n, i0 + int(rows[-1]) + 3),
            max(0, j0 + int(cols[0]) - 2),
            min(n, j0 + int(cols[-1]) + 3),
        )
        if new != self._win:
            outside = np.full_like(self._log, -2.0 * _DROP)
            outside[new[0] : new[1], new[2] : new[3]] = self._log[new[0] : new[1], new[2] : new[3]]
            self._log = outside
            self._win = new

    def predict(self, t: float) -> None:
        """Blur the grid by the random walk accumulated since the last call."""
        if self.t is not None and t > self.t:
            self._pending_var += self._drift_var * (t - self.t)
            a = self._pending_var / (2.0 * self._res**2)  # a walk of +-res steps, prob a each
            if a >= 0.05:
                a = min(a, 0.25)
                self._pending_var -= 2.0 * a * self._res**2
                n = self._axis.size
                i0, i1, j0, j1 = self._win
                i0, i1, j0, j1 = max(0, i0 - 1), min(n, i1 + 1), max(0, j0 - 1), min(n, j1 + 1)
                p = np.exp(self._log[i0:i1, j0:j1])
                for axis in (0, 1):
                    p = (1 - 2 * a) * p + a * (np.roll(p, 1, axis) + np.roll(p, -1, axis))
                self._log[i0:i1, j0:j1] = np.log(np.maximum(p, 1e-300))
                self._win = (i0, i1, j0, j1)
                self._moments()
        if self.t is None or t > self.t:
            self.t = t

    def weights_and_cells(self, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(window weights p(b), the u-grid cell of n . b for each window cell)."""
        return self._w, self._cells(normal)

    def _cells(self, normal: np.ndarray) -> np.ndarray:
        """The u-grid cell of n . b for each window cell (kept while the window and n are)."""
        key = (self._win, float(normal[0]), float(normal[1]))
        if key != self._cells_key:
            i0, i1, j0, j1 = self._win
            proj = self._axis[i0:i1, None] * normal[0] + self._axis[None, j0:j1] * normal[1]
            self._cells_key, self._cells_idx = key, self.u.index(proj)
        return self._cells_idx

    def project(self, normal: np.ndarray) -> np.ndarray:
        """The posterior of u = n . b on the u-grid: p_u[k] = sum of p(b) over n . b in k."""
        w, idx = self.weights_and_cells(normal)
        return np.bincount(idx.ravel(), weights=w.ravel(), minlength=self.u.size)

    def update(self, normal: np.ndarray, log_c: np.ndarray) -> None:
        """Fold in evidence about u = n . b: log p(b) += log_c[cell of n . b]."""
        i0, i1, j0, j1 = self._win
        sub = self._log[i0:i1, j0:j1] + log_c[self._cells(normal)]
        self._log[i0:i1, j0:j1] = sub - sub.max()
        self.updates += 1
        self._shrink()
        self._moments()

    def conditional(self, normal: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of b under p(b) weight[cell of n . b] (weight on the u-grid):
        the common error given what is known about u, for example a user's lane."""
        w = self._w * weight[self._cells(normal)]
        total = float(w.sum())
        if not total > 0.0:
            return self.b.copy(), self.P.copy()
        return self._stats(w / total)


class CommonErrorField:
    """One `CommonError` per area: a fix joins the nearest area centre within
    `size / 2`, else founds a new area there (no grid seams on a compact map). Areas are
    indexed by a coarse grid of cell `size`, so finding one looks at nine cells at most."""

    def __init__(self, size: float, prior_sigma: float, drift: float, resolution: float) -> None:
        self.size = size
        self._prior = prior_sigma
        self._drift = drift
        self._resolution = resolution
        self.areas: list[CommonError] = []
        self._cells: dict[tuple[int, int], list[CommonError]] = {}

    def _cell(self, xy: np.ndarray) -> tuple[int, int]:
        return math.floor(float(xy[0]) / self.size), math.floor(float(xy[1]) / self.size)

    def at(self, xy: np.ndarray) -> CommonError:
        """The area whose centre is nearest `xy`, created if none is within size / 2."""
        best: CommonError | None = None
        best_d = self.size / 2.0
        ci, cj = self._cell(xy)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                for area in self._cells.get((ci + di, cj + dj), ()):
                    dist = float(np.hypot(*(area.centre - xy)))
                    if dist <= best_d:
                        best, best_d = area, dist
        if best is None:
            best = CommonError(xy, self._prior, self._drift, self._resolution)
            self.areas.append(best)
            self._cells.setdefault((ci, cj), []).append(best)
        return best
