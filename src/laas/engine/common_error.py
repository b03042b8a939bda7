"""Default mode: the GNSS error that nearby receivers share, estimated cooperatively.

Receivers close together see almost the same satellite and atmosphere errors, so every
filtered fix is p_i = x_i + b + n_i with one common error b per area, a slowly drifting
2-D random walk (b_k = b_{k-1} + w, w ~ N(0, q dt I)).

A user on a lane observes b only across that lane. With n the unit normal of the road at
the user, d(b) = n . (p - b) its lateral offset once b is removed, o_l the lane centres
and pi_l the user's lane probabilities, one fix has the likelihood

    L(b) = eps + sum_l pi_l N(d(b) - o_l; 0, s^2)

which does not pick a lane: it keeps every lane the user might be on (and eps, a user off
every lane). A Gaussian filter would have to pick one and can lock onto a wrong lane for
good, so the posterior of b is kept on a grid (a point-mass filter, the discrete Bayes
filter of the paper applied to the common error):

    log p(b) <- log p(b) + log L(b)        prediction: a blur of variance q dt

Across one straight road the posterior is a ridge along the road: nothing is corrected
along it until some user drives a road of another direction, and the covariance of b
says so (and with it every answer's along-road accuracy).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CommonError", "CommonErrorField"]

_OFF_LANE = 1e-3  # eps: the likelihood floor of a user on no lane at all (a car park, say)
_DROP = 40.0  # cells this far below the maximum in log p hold no mass worth keeping


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
        self._drift_var = drift**2
        self._pending_var = 0.0
        self.t: float | None = None
        self.updates = 0
        self.b = np.zeros(2)
        self.P = np.eye(2) * prior_sigma**2
        self._moments()

    def _moments(self) -> None:
        """b = E[b], P = Cov[b] over the window (plus the cell's own spread, res^2 / 12)."""
        i0, i1, j0, j1 = self._win
        w = np.exp(self._log[i0:i1, j0:j1])
        w /= w.sum()
        ae, an = self._axis[i0:i1], self._axis[j0:j1]
        we, wn = w.sum(axis=1), w.sum(axis=0)
        me, mn = float(we @ ae), float(wn @ an)
        cee = float(we @ (ae - me) ** 2)
        cnn = float(wn @ (an - mn) ** 2)
        cen = float((ae - me) @ w @ (an - mn))
        self.b = np.array([me, mn])
        self.P = np.array([[cee, cen], [cen, cnn]]) + np.eye(2) * self._res**2 / 12.0

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

    def update(
        self,
        normal: np.ndarray,
        d0: float,
        offsets: np.ndarray,
        weights: np.ndarray,
        sigma: float,
    ) -> None:
        """Fold in one fix: lateral offset d0 with b = 0, lanes at `offsets` with `weights`.

        d(b) = d0 - n . b for every grid cell; the mixture is evaluated on a fine 1-D grid
        of n . b and gathered, so an update costs one pass over the window.
        """
        i0, i1, j0, j1 = self._win
        proj = self._axis[i0:i1, None] * normal[0] + self._axis[None, j0:j1] * normal[1]
        lo, hi = float(proj.min()), float(proj.max())
        step = min(self._res, sigma) / 4.0
        u = np.arange(lo, hi + step, step)
        r = (d0 - u)[:, None] - offsets[None, :]
        mix = (np.exp(-0.5 * (r / sigma) ** 2) * weights[None, :]).sum(axis=1)
        like = np.log(_OFF_LANE + mix / (math.sqrt(2 * math.pi) * sigma))
        idx = np.minimum(((proj - lo) / step + 0.5).astype(np.intp), u.size - 1)
        sub = self._log[i0:i1, j0:j1] + like[idx]
        self._log[i0:i1, j0:j1] = sub - sub.max()
        self.updates += 1
        self._shrink()
        self._moments()

    def sigma_along(self, direction: np.ndarray) -> float:
        """1-sigma of b along a unit direction, m."""
        return math.sqrt(max(float(direction @ self.P @ direction), 0.0))


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
