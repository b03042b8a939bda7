"""One Kalman track per road user (paper section IV-C).

State x = [e, n, v_e, v_n]: UTM easting and northing (m) and their velocities (m/s),
under a constant-velocity model with white-acceleration process noise. A fix
measures the position and, from speed s and heading h, the velocity:

    z = [e, n, s sin h, s cos h],    z = H x + v,    H = I (4x4)

filterpy's `KalmanFilter` is the only filterpy object, and it stays inside `Track`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from laas.config import EngineConfig

__all__ = ["Fix", "Track", "TrackUpdate"]

_MIN_VELOCITY_VAR = 0.05**2  # m^2/s^2: a floor, so a stopped receiver's heading is not trusted


class TrackUpdate(enum.Enum):
    """What a fix did to its track."""

    ACCEPTED = "accepted"
    RESTARTED = "restarted"
    DUPLICATE = "duplicate"
    OUT_OF_ORDER = "out_of_order"


@dataclass(frozen=True, slots=True)
class Fix:
    """A measurement in the projected frame: time (s), position (m), speed (m/s), heading (rad)."""

    t: float
    e: float
    n: float
    speed: float
    heading: float
    accuracy: float | None = None  # the receiver's own 1-sigma per axis, m, if it gives one

    @property
    def velocity(self) -> np.ndarray:
        """(v_e, v_n) from speed and heading (heading clockwise from north)."""
        return np.array([self.speed * math.sin(self.heading), self.speed * math.cos(self.heading)])


class Track:
    """A road user's smoothed state. With `config.kalman` off it holds the last raw fix."""

    def __init__(self, config: EngineConfig, fix: Fix) -> None:
        self._config = config
        self._kf = KalmanFilter(dim_x=4, dim_z=4)
        self._kf.H = np.eye(4)
        self.t = fix.t
        self.dt = 0.0
        self.last_fix = fix
        self._start(fix)

    def _measurement_noise(self, fix: Fix) -> np.ndarray:
        """R: sigma_pos^2 on the position; on the velocity, speed noise along the heading
        and across it the heading's error s sigma_h plus the speed noise again, since a GNSS
        course over ground comes from a velocity vector whose every component carries it
        (so a slow user's heading is worth little):  R_v = sigma_v^2 I + s^2 sigma_h^2 n n'."""
        c = self._config
        nrm = np.array([math.cos(fix.heading), -math.sin(fix.heading)])
        sigma_h = math.radians(c.sigma_heading)
        r_v = c.sigma_vel**2 * np.eye(2) + (fix.speed * sigma_h) ** 2 * np.outer(nrm, nrm)
        r = np.zeros((4, 4))
        sigma_pos = fix.accuracy if fix.accuracy is not None else c.sigma_pos
        r[0, 0] = r[1, 1] = sigma_pos**2
        r[2:, 2:] = r_v + _MIN_VELOCITY_VAR * np.eye(2)
        return r

    def _start(self, fix: Fix) -> None:
        r = self._measurement_noise(fix)
        self._kf.x = np.array([fix.e, fix.n, *fix.velocity]).reshape(4, 1)
        self._kf.P = r.copy()
        self.t = fix.t
        self.dt = 0.0
        self.last_fix = fix

    def update(self, fix: Fix) -> TrackUpdate:
        """Fold one fix into the track; stale fixes are refused, long gaps restart it."""
        dt = fix.t - self.t
        if dt == 0.0:
            return TrackUpdate.DUPLICATE
        if dt < 0.0:
            return TrackUpdate.OUT_OF_ORDER
        if dt > self._config.track_timeout:
            self._start(fix)
            return TrackUpdate.RESTARTED
        if not self._config.kalman:
            self._start(fix)
            self.dt = dt
            return TrackUpdate.ACCEPTED
        # x = F x,  P = F P F' + Q
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        q = Q_discrete_white_noise(
            dim=2, dt=dt, var=self._config.sigma_accel**2, block_size=2, order_by_dim=False
        )
        self._kf.predict(F=f, Q=q)
        # K = P H' (H P H' + R)^-1,  x = x + K (z - H x),  P = (I - K H) P
        z = np.array([fix.e, fix.n, *fix.velocity])
        self._kf.update(z, R=self._measurement_noise(fix))
        self.t = fix.t
        self.dt = dt
        self.last_fix = fix
        return TrackUpdate.ACCEPTED

    @property
    def position(self) -> np.ndarray:
        """(e, n) at the time of the last fix, m."""
        return np.asarray(self._kf.x[:2, 0], dtype=float)

    @property
    def velocity(self) -> np.ndarray:
        """(v_e, v_n) at the time of the last fix, m/s."""
        return np.asarray(self._kf.x[2:, 0], dtype=float)

    @property
    def velocity_cov(self) -> np.ndarray:
        """2x2 covariance of the velocity, m^2/s^2."""
        return np.asarray(self._kf.P[2:, 2:], dtype=float)

    @property
    def position_cov(self) -> np.ndarray:
        """2x2 covariance of the position, m^2."""
        return np.asarray(self._kf.P[:2, :2], dtype=float)

    def position_at(self, t: float) -> np.ndarray:
        """(e, n) extrapolated to time t at constant velocity, without changing the track."""
        return self.position + self.velocity * (t - self.t)
