"""One Kalman track per road user (paper section IV-C).

State x = [e, n, v_e, v_n]: UTM easting and northing (m) and their velocities (m/s),
under a constant-velocity model with white-acceleration process noise. A fix
measures the position and, from speed s and heading h, the velocity:

    z = [e, n, s sin h, s cos h],    z = H x + v,    H = I (4x4)

A receiver spends a share pi of its time in multipath, its fixes then metres off for
seconds (a reflection, not noise). A plain Kalman filter takes such a fix at its stated
sigma, and at 10 Hz the track follows the reflection and keeps it for seconds after, while
its covariance says it is within decimetres. In default mode (`track_multipath` = pi > 0)
each fix is weighed by how likely it is to be in multipath given its position's
innovation y and S = P + R (the position's 2x2 blocks):

    rho = pi N(y; 0, S + s_mp^2 I) / ((1 - pi) N(y; 0, S) + pi N(y; 0, S + s_mp^2 I))

and taken with the variance it then has, R_pos + rho s_mp^2 I (s_mp = `MULTIPATH_SIGMA`):
a fix that fits the track counts in full, one metres off barely moves it. A reflection
lasts seconds; fixes that keep disagreeing with the track for longer than
`DOUBT_SECONDS` say that the track is the one that is off (it started, or was dragged,
in multipath, or missed a manoeuvre), so its position's covariance is widened by
s_mp^2 I and the fix taken at its own sigma: without this, a track a few metres off,
whose velocity the fixes keep measuring well, would weigh every later fix as a
reflection and never come back. Paper mode, and pi = 0, is the plain filter.

The filter is filterpy's `KalmanFilter` written out for this model (predict with
F = [[I, dt I], [0, I]], update with H = I and Joseph's form of P, as filterpy does) in a
few numpy calls on stacked (B, 4) states and (B, 4, 4) covariances: `kalman_steps` steps
a batch of tracks at once, and a single track (`Track.update`) is a batch of one. There
is no other copy of the step. filterpy's general predict and update cost about 150 us a
fix, most of it bookkeeping, a batch of one here about 30 us. `tests/test_tracking.py`
holds it to filterpy's own `KalmanFilter` and `Q_discrete_white_noise`, which stay the
reference.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from laas.config import EngineConfig

__all__ = [
    "DOUBT_SECONDS",
    "MULTIPATH_SIGMA",
    "Fix",
    "Track",
    "TrackUpdate",
    "kalman_steps",
    "measurement_noise",
    "multipath_weight",
]

_MIN_VELOCITY_VAR = 0.05**2  # m^2/s^2: a floor, so a stopped receiver's heading is not trusted
MULTIPATH_SIGMA = 3.0
"""m per axis: how far a receiver in multipath is off (the development families' jumps are
1-6 m; in cities it is the most common receiver fault). The lane filter uses the same."""
DOUBT_SECONDS = 2.0
"""s: how long fixes may keep disagreeing with a track (from a fix of rho > 1/2 until one
that clearly fits, rho < 0.1) before the track is doubted instead: a reflection lasts
seconds (in the development families 2-6 s on average, exponentially distributed), so by
2 s a disagreement that began as a reflection is as likely the track's own."""
_AGREES = 0.1  # a disagreement begins with a fix of rho > 1/2 and ends with one of rho < this


def multipath_weight(a: float, b: float, c: float, y0: float, y1: float, share: float) -> float:
    """rho of the module docstring for one fix: the posterior probability that it is in
    multipath, given its position's innovation y = (y0, y1) and S = [[a, b], [b, c]].
    In floats: numpy's call overhead on 2 x 2 arrays would double a track's step."""
    wide = MULTIPATH_SIGMA**2

    def log_density(a: float, c: float) -> float:
        det = a * c - b * b
        return -0.5 * (c * y0 * y0 - 2.0 * b * y0 * y1 + a * y1 * y1) / det - 0.5 * math.log(det)

    narrow = math.log(1.0 - share) + log_density(a, c)
    broad = math.log(share) + log_density(a + wide, c + wide)
    return 1.0 / (1.0 + math.exp(min(max(narrow - broad, -700.0), 700.0)))


def _weighs_multipath(config: EngineConfig) -> bool:
    """Whether the tracks weigh multipath: default mode with track_multipath > 0."""
    return config.track_multipath > 0.0 and config.mode == "default"


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
        self._x = np.zeros(4)  # [e, n, v_e, v_n]
        self._P = np.eye(4)
        self.t = fix.t
        self.dt = 0.0
        self.last_fix = fix
        self._doubted: float | None = None  # since when fixes disagree with the track
        self._start(fix)

    def _measurement_noise(self, fix: Fix) -> np.ndarray:
        """R of one fix (`measurement_noise`)."""
        r: np.ndarray = measurement_noise(self._config, [fix])[0]
        return r

    def _start(self, fix: Fix) -> None:
        r = self._measurement_noise(fix)
        self._x = np.array([fix.e, fix.n, *fix.velocity])
        self._P = r
        self.t = fix.t
        self.dt = 0.0
        self.last_fix = fix
        self._doubted = None

    def classify(self, fix: Fix) -> TrackUpdate:
        """What `update` would do with the fix, changing nothing."""
        dt = fix.t - self.t
        if dt == 0.0:
            return TrackUpdate.DUPLICATE
        if dt < 0.0:
            return TrackUpdate.OUT_OF_ORDER
        if dt > self._config.track_timeout:
            return TrackUpdate.RESTARTED
        return TrackUpdate.ACCEPTED

    def update(self, fix: Fix) -> TrackUpdate:
        """Fold one fix into the track; stale fixes are refused, long gaps restart it."""
        outcome = self.admit(fix)
        if outcome is TrackUpdate.ACCEPTED and self._config.kalman:
            kalman_steps([self], [fix])  # a batch of one
        return outcome

    def _weigh(self, rho: float, t: float, p: np.ndarray, r: np.ndarray) -> None:
        """In place on this step's predicted P and its R: the position's variance in R
        raised by rho s_mp^2, or, the track doubted, P's by s_mp^2 (module docstring)."""
        if self._doubt(rho, t):
            p[0, 0] += MULTIPATH_SIGMA**2
            p[1, 1] += MULTIPATH_SIGMA**2
        else:
            r[0, 0] += rho * MULTIPATH_SIGMA**2
            r[1, 1] += rho * MULTIPATH_SIGMA**2

    def _doubt(self, rho: float, t: float) -> bool:
        """Whether a fix of weight rho at time t ends a disagreement long enough to doubt
        the track (`DOUBT_SECONDS`); keeps the time the disagreement began."""
        if rho < _AGREES or (self._doubted is None and rho <= 0.5):
            self._doubted = None
            return False
        if self._doubted is None:
            self._doubted = t
        if t - self._doubted < DOUBT_SECONDS:
            return False
        self._doubted = None
        return True

    def admit(self, fix: Fix) -> TrackUpdate:
        """`update` but for the Kalman step of an accepted fix, which is left to the
        caller (`update`, or `kalman_steps` for a batch); a restart, or with the Kalman
        filter off any accepted fix, is taken here in full."""
        outcome = self.classify(fix)
        if outcome is TrackUpdate.RESTARTED:
            self._start(fix)
        elif outcome is TrackUpdate.ACCEPTED and not self._config.kalman:
            dt = fix.t - self.t
            self._start(fix)
            self.dt = dt
        return outcome

    def _accepted(self, fix: Fix, dt: float) -> None:
        self.t = fix.t
        self.dt = dt
        self.last_fix = fix

    @property
    def position(self) -> np.ndarray:
        """(e, n) at the time of the last fix, m."""
        return self._x[:2].copy()

    @property
    def velocity(self) -> np.ndarray:
        """(v_e, v_n) at the time of the last fix, m/s."""
        return self._x[2:].copy()

    @property
    def velocity_cov(self) -> np.ndarray:
        """2x2 covariance of the velocity, m^2/s^2."""
        return self._P[2:, 2:].copy()

    @property
    def position_cov(self) -> np.ndarray:
        """2x2 covariance of the position, m^2."""
        return self._P[:2, :2].copy()

    def moments(self) -> tuple[list[float], list[list[float]]]:
        """(x, P) as plain floats, for per-user arithmetic (no arrays made)."""
        x: list[float] = self._x.tolist()
        p: list[list[float]] = self._P.tolist()
        return x, p

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """(x (4,), P (4, 4)) copies: what a hand-over carries (`laas.engine.handover`)."""
        return self._x.copy(), self._P.copy()

    @classmethod
    def restore(
        cls, config: EngineConfig, x: np.ndarray, p: np.ndarray, last_fix: Fix, dt: float
    ) -> Track:
        """A track that goes on from state x, P after `last_fix` (a hand-over)."""
        track = cls(config, last_fix)
        track._x = np.asarray(x, dtype=float).copy()
        track._P = np.asarray(p, dtype=float).copy()
        track.dt = dt
        return track

    def position_at(self, t: float) -> np.ndarray:
        """(e, n) extrapolated to time t at constant velocity, without changing the track."""
        return self.position + self.velocity * (t - self.t)


_EYE4 = np.eye(4)
_Q_SCALE = np.array([0.25, 0.5, 1.0])  # Q = q [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]


def measurement_noise(config: EngineConfig, fixes: Sequence[Fix]) -> np.ndarray:
    """R of each fix, (B, 4, 4): sigma_pos^2 on the position (the receiver's own accuracy
    if it gives one); on the velocity, speed noise along the heading and across it the
    heading's error s sigma_h plus the speed noise again, since a GNSS course over ground
    comes from a velocity vector whose every component carries it (so a slow user's
    heading is worth little):  R_v = sigma_v^2 I + s^2 sigma_h^2 n n',  n = (cos h, -sin h)."""
    sigma_h = math.radians(config.sigma_heading)
    v2 = config.sigma_vel**2 + _MIN_VELOCITY_VAR
    rows = []
    for fix in fixes:
        n_e, n_n = math.cos(fix.heading), -math.sin(fix.heading)
        h2 = (fix.speed * sigma_h) ** 2
        p2 = (fix.accuracy if fix.accuracy is not None else config.sigma_pos) ** 2
        en = h2 * n_e * n_n
        # fmt: off
        rows.append((
            p2, 0.0, 0.0, 0.0,
            0.0, p2, 0.0, 0.0,
            0.0, 0.0, v2 + h2 * n_e * n_e, en,
            0.0, 0.0, en, v2 + h2 * n_n * n_n,
        ))
        # fmt: on
    return np.array(rows).reshape(-1, 4, 4)


def kalman_steps(tracks: list[Track], fixes: list[Fix]) -> None:
    """`Track.update`'s Kalman step for fix i of track i, all at once (each fix admitted
    by its track with `Track.admit`, one fix per track), on stacked (B, 4) states and
    (B, 4, 4) covariances; a single track is a batch of one.

    predict   x = F x,  P = F P F' + Q,  F = [[I, dt I], [0, I]], and the white
              acceleration of variance q gives (filterpy's Q_discrete_white_noise(dim=2,
              block_size=2))  Q = q [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]
    weigh     in default mode, rho of each fix and `Track._weigh` (module docstring)
    update    H = I:  S = P + R,  K = P S^-1,  x = x + K (z - x),
              P = (I - K) P (I - K)' + K R K'  (Joseph's form, which stays symmetric and
              positive; filterpy's update)
    """
    if not tracks:
        return
    config = tracks[0]._config
    x = np.array([tr._x for tr in tracks])
    p = np.array([tr._P for tr in tracks])
    steps = [f.t - tr.t for tr, f in zip(tracks, fixes, strict=True)]
    dts = np.array(steps)
    # F x and F P F', F = [[I, dt I], [0, I]]: the velocity's rows, then its columns,
    # added dt times to the position's (what the products with F's ones and zeros do)
    dt = dts[:, None]
    x[:, :2] += dt * x[:, 2:]
    p[:, :2, :] += dt[:, :, None] * p[:, 2:, :]
    p[:, :, :2] += dt[:, None, :] * p[:, :, 2:]
    # + Q: its three coefficients q dt^4 / 4, q dt^3 / 2, q dt^2
    q4, q3, q2 = (config.sigma_accel**2 * _Q_SCALE).tolist()
    q = []
    for step in steps:
        a, b, c = q4 * step**4.0, q3 * step**3.0, q2 * step**2.0
        q.append((a, 0.0, b, 0.0, 0.0, a, 0.0, b, b, 0.0, c, 0.0, 0.0, b, 0.0, c))
    p += np.array(q).reshape(-1, 4, 4)
    z = np.array(
        [
            [fx.e, fx.n, fx.speed * math.sin(fx.heading), fx.speed * math.cos(fx.heading)]
            for fx in fixes
        ]
    )
    r = measurement_noise(config, fixes)
    if _weighs_multipath(config):
        share = config.track_multipath
        y = (z[:, :2] - x[:, :2]).tolist()
        s = (p[:, :2, :2] + r[:, :2, :2]).tolist()
        for i, (track, fix) in enumerate(zip(tracks, fixes, strict=True)):
            (s00, s01), (_, s11) = s[i]
            rho = multipath_weight(s00, s01, s11, y[i][0], y[i][1], share)
            track._weigh(rho, fix.t, p[i], r[i])
    k = np.linalg.solve(p + r, p).transpose(0, 2, 1)  # P S^-1 = (S^-1 P)', P, S symmetric
    x = x + np.matmul(k, (z - x)[:, :, None])[:, :, 0]
    i_k = _EYE4 - k
    p = i_k @ p @ i_k.transpose(0, 2, 1) + k @ r @ k.transpose(0, 2, 1)
    for i, (track, fix) in enumerate(zip(tracks, fixes, strict=True)):
        track._x = x[i]
        track._P = p[i]
        track._accepted(fix, float(dts[i]))
