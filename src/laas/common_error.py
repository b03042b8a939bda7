"""Default mode: the GNSS error that nearby receivers share, estimated cooperatively.

Receivers close together see almost the same satellite and atmosphere errors, so
every filtered fix is p_i = x_i + b + n_i with one common error b per area. b is a
2-D random walk,

    b_k = b_{k-1} + w,    w ~ N(0, q dt I),

and a user placed on a lane observes only its component across that lane: with n the
lane's unit normal and c the lane-centre point the user is placed on,

    z = n . (p_i - c) = n . b + v,    v ~ N(0, r).

So b is observable across every road that carries users; along a straight road it
stays at its prior (nothing is corrected along the road there) until some user drives
a road of another orientation. The scalar Kalman update is

    S = n' P n + r,   K = P n / S,   b <- b + K (z - n' b),   P <- (I - K n') P.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CommonError", "CommonErrorField"]


class CommonError:
    """The common error of one area: mean b (2,) and covariance P (2, 2), in metres."""

    def __init__(self, centre: np.ndarray, prior_sigma: float, drift: float) -> None:
        self.centre = centre.copy()
        self.b = np.zeros(2)
        self.P = np.eye(2) * prior_sigma**2
        self._prior_var = prior_sigma**2
        self._drift_var = drift**2
        self.t: float | None = None
        self.updates = 0

    def predict(self, t: float) -> None:
        """P <- P + q dt I, never past the prior (the error stays bounded)."""
        if self.t is not None and t > self.t:
            self.P = self.P + np.eye(2) * self._drift_var * (t - self.t)
            eig = np.linalg.eigvalsh(self.P)
            if eig[-1] > self._prior_var:
                self.P *= self._prior_var / eig[-1]
        if self.t is None or t > self.t:
            self.t = t

    def update(self, normal: np.ndarray, z: float, r: float) -> None:
        """Fold in one lateral observation z = n . b + v, v ~ N(0, r)."""
        pn = self.P @ normal
        s = float(normal @ pn) + r
        k = pn / s
        self.b = self.b + k * (z - float(normal @ self.b))
        self.P = self.P - np.outer(k, pn)
        self.P = 0.5 * (self.P + self.P.T)
        self.updates += 1

    def sigma_along(self, direction: np.ndarray) -> float:
        """1-sigma of b along a unit direction, m."""
        return math.sqrt(max(float(direction @ self.P @ direction), 0.0))


class CommonErrorField:
    """One `CommonError` per area: a fix joins the nearest area centre within
    `size / 2`, else founds a new area there (no grid seams on a compact map)."""

    def __init__(self, size: float, prior_sigma: float, drift: float) -> None:
        self.size = size
        self._prior = prior_sigma
        self._drift = drift
        self.areas: list[CommonError] = []

    def at(self, xy: np.ndarray) -> CommonError:
        """The area whose centre is nearest `xy`, created if none is within size / 2."""
        best: CommonError | None = None
        best_d = self.size / 2.0
        for area in self.areas:
            dist = float(np.hypot(*(area.centre - xy)))
            if dist <= best_d:
                best, best_d = area, dist
        if best is None:
            best = CommonError(xy, self._prior, self._drift)
            self.areas.append(best)
        return best
