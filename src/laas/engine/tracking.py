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
F = [[I, dt I], [0, I]], update with H = I and Joseph's form of P, as filterpy does) on
stacked (B, 4) states and (B, 4, 4) covariances, compiled (`_kalman`, `laas.engine.jit`):
`kalman_steps` steps a batch of tracks at once, and a single track (`Track.update`) is a
batch of one. There is no other copy of the step. filterpy's general predict and update
cost about 40 us a fix, most of it bookkeeping; a batch of one here about 10 us, a track
in a batch of 64 about 4 us (the development machine).
`tests/test_tracking.py` holds it to filterpy's own `KalmanFilter` and
`Q_discrete_white_noise`, which stay the reference.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from laas.config import EngineConfig
from laas.engine.jit import jit

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


@jit
def multipath_weight(a: float, b: float, c: float, y0: float, y1: float, share: float) -> float:
    """rho of the module docstring for one fix: the posterior probability that it is in
    multipath, given its position's innovation y = (y0, y1) and S = [[a, b], [b, c]]."""
    wide = MULTIPATH_SIGMA**2
    det = a * c - b * b
    narrow = math.log(1.0 - share) - 0.5 * (
        (c * y0 * y0 - 2.0 * b * y0 * y1 + a * y1 * y1) / det + math.log(det)
    )
    a, c = a + wide, c + wide
    det = a * c - b * b
    broad = math.log(share) - 0.5 * (
        (c * y0 * y0 - 2.0 * b * y0 * y1 + a * y1 * y1) / det + math.log(det)
    )
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


def measurement_noise(config: EngineConfig, fixes: Sequence[Fix]) -> np.ndarray:
    """R of each fix, (B, 4, 4) (`_noise`)."""
    sigma_h = math.radians(config.sigma_heading)
    v2 = config.sigma_vel**2 + _MIN_VELOCITY_VAR
    r = np.empty((len(fixes), 4, 4))
    for i, fix in enumerate(fixes):
        p2 = (fix.accuracy if fix.accuracy is not None else config.sigma_pos) ** 2
        _noise(r[i], fix.speed, fix.heading, p2, v2, sigma_h)
    return r


@jit
def _noise(
    r: np.ndarray, speed: float, heading: float, p2: float, v2: float, sigma_h: float
) -> None:
    """R of one fix, into r (4, 4): p2 = sigma_pos^2 on the position (the receiver's own
    accuracy if it gives one); on the velocity, v2 = sigma_v^2 (with its floor) along the
    heading and across it the heading's error s sigma_h plus the speed noise again, since
    a GNSS course over ground comes from a velocity vector whose every component carries
    it (so a slow user's heading is worth little):
    R_v = sigma_v^2 I + s^2 sigma_h^2 n n',  n = (cos h, -sin h)."""
    n_e, n_n = math.cos(heading), -math.sin(heading)
    h2 = (speed * sigma_h) ** 2
    r[:, :] = 0.0
    r[0, 0] = r[1, 1] = p2
    r[2, 2] = v2 + h2 * n_e * n_e
    r[2, 3] = r[3, 2] = h2 * n_e * n_n
    r[3, 3] = v2 + h2 * n_n * n_n


def kalman_steps(tracks: list[Track], fixes: list[Fix]) -> None:
    """`Track.update`'s Kalman step for fix i of track i, all at once (each fix admitted
    by its track with `Track.admit`, one fix per track), on stacked (B, 4) states and
    (B, 4, 4) covariances; a single track is a batch of one. The arithmetic is
    `_kalman`, compiled: numpy's calls on 4 x 4 arrays cost more than the arithmetic."""
    if not tracks:
        return
    config = tracks[0]._config
    x = np.array([tr._x for tr in tracks])
    p = np.array([tr._P for tr in tracks])
    sigma_pos = config.sigma_pos
    # per fix: t, dt, e, n, speed, heading, sigma_pos^2, when its disagreement began
    rows = np.array(
        [
            (
                f.t,
                f.t - tr.t,
                f.e,
                f.n,
                f.speed,
                f.heading,
                (f.accuracy if f.accuracy is not None else sigma_pos) ** 2,
                math.nan if tr._doubted is None else tr._doubted,
            )
            for tr, f in zip(tracks, fixes, strict=True)
        ]
    )
    _kalman(
        x,
        p,
        rows,
        config.sigma_accel**2,
        config.sigma_vel**2 + _MIN_VELOCITY_VAR,
        math.radians(config.sigma_heading),
        config.track_multipath if _weighs_multipath(config) else 0.0,
    )
    doubted = rows[:, 7].tolist()
    for i, (track, fix) in enumerate(zip(tracks, fixes, strict=True)):
        track._x = x[i]
        track._P = p[i]
        track._doubted = None if math.isnan(doubted[i]) else doubted[i]
        track._accepted(fix, float(rows[i, 1]))


@jit
def _kalman(
    x: np.ndarray,
    p: np.ndarray,
    rows: np.ndarray,
    q: float,
    v2: float,
    sigma_h: float,
    share: float,
) -> None:
    """In place on x (B, 4), P (B, 4, 4) and the rows' last column (when each track's
    disagreement began, NaN for none), for fix rows (t, dt, e, n, s, h, s_pos^2, doubted):

    predict   x = F x,  P = F P F' + Q,  F = [[I, dt I], [0, I]], and the white
              acceleration of variance q gives (filterpy's Q_discrete_white_noise(dim=2,
              block_size=2))  Q = q [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]
    measure   z = (e, n, s sin h, s cos h), R = `_noise`
    weigh     with share = pi > 0, rho (`multipath_weight`): a disagreement begins
              with a fix of rho > 1/2 and ends with one of rho < 0.1; one that lasts
              `DOUBT_SECONDS` doubts the track, P's position variance raised by s_mp^2
              and the fix taken at its own sigma; otherwise R's position variance is
              raised by rho s_mp^2
    update    H = I:  S = P + R,  K = P S^-1,  x = x + K (z - x),
              P = (I - K) P (I - K)' + K R K'  (Joseph's form, which stays symmetric and
              positive; filterpy's update)
    """
    wide = MULTIPATH_SIGMA**2
    z = np.empty(4)
    r = np.empty((4, 4))
    s = np.empty((4, 4))
    k = np.empty((4, 4))
    a = np.empty((4, 4))
    t = np.empty((4, 4))
    for i in range(x.shape[0]):
        dt = rows[i, 1]
        xi, pi = x[i], p[i]
        # predict: F x, then F P F' (rows, then columns: the velocity's added dt times
        # to the position's), then + Q
        xi[0] += dt * xi[2]
        xi[1] += dt * xi[3]
        for c in range(4):
            pi[0, c] += dt * pi[2, c]
            pi[1, c] += dt * pi[3, c]
        for c in range(4):
            pi[c, 0] += dt * pi[c, 2]
            pi[c, 1] += dt * pi[c, 3]
        q4, q3, q2 = 0.25 * q * dt**4.0, 0.5 * q * dt**3.0, q * dt**2.0
        pi[0, 0] += q4
        pi[1, 1] += q4
        pi[0, 2] += q3
        pi[1, 3] += q3
        pi[2, 0] += q3
        pi[3, 1] += q3
        pi[2, 2] += q2
        pi[3, 3] += q2
        # the fix: z and R (`_noise`)
        speed, heading = rows[i, 4], rows[i, 5]
        z[0], z[1] = rows[i, 2], rows[i, 3]
        z[2], z[3] = speed * math.sin(heading), speed * math.cos(heading)
        _noise(r, speed, heading, rows[i, 6], v2, sigma_h)
        if share > 0.0:
            y0, y1 = z[0] - xi[0], z[1] - xi[1]
            s00, s01, s11 = pi[0, 0] + r[0, 0], pi[0, 1] + r[0, 1], pi[1, 1] + r[1, 1]
            rho = multipath_weight(s00, s01, s11, y0, y1, share)
            # the doubt (module docstring): a disagreement begins with rho > 1/2 and ends
            # with rho < _AGREES; one that lasted DOUBT_SECONDS doubts the track
            doubt = False
            began = rows[i, 7]
            if rho < _AGREES or (math.isnan(began) and rho <= 0.5):
                began = math.nan
            else:
                if math.isnan(began):
                    began = rows[i, 0]
                if rows[i, 0] - began >= DOUBT_SECONDS:
                    began = math.nan
                    doubt = True
            rows[i, 7] = began
            if doubt:
                pi[0, 0] += wide
                pi[1, 1] += wide
            else:
                r[0, 0] += rho * wide
                r[1, 1] += rho * wide
        # S = P + R; K' = S^-1 P (P, S symmetric), by Gauss-Jordan elimination with
        # partial pivoting on [S | P]
        s[:, :] = pi + r
        k[:, :] = pi
        for c in range(4):
            best = c
            for row in range(c + 1, 4):
                if abs(s[row, c]) > abs(s[best, c]):
                    best = row
            if best != c:
                for col in range(4):
                    s[c, col], s[best, col] = s[best, col], s[c, col]
                    k[c, col], k[best, col] = k[best, col], k[c, col]
            for row in range(4):
                if row != c:
                    f = s[row, c] / s[c, c]
                    for col in range(4):
                        s[row, col] -= f * s[c, col]
                        k[row, col] -= f * k[c, col]
        for row in range(4):
            for col in range(4):
                k[row, col] /= s[row, row]
        kk = k.T.copy()  # K = (S^-1 P)'
        # x = x + K (z - x)
        innovation = z - xi
        for row in range(4):
            acc = 0.0
            for col in range(4):
                acc += kk[row, col] * innovation[col]
            xi[row] += acc
        # P = (I - K) P (I - K)' + K R K'
        a[:, :] = -kk
        for c in range(4):
            a[c, c] += 1.0
        # (4 x 4 products written out: numba's `@` calls BLAS, whose call costs more
        # than 64 multiplications)
        _product(a, pi, t, False)  # t = (I - K) P
        _product(t, a, s, True)  # s = t (I - K)'
        _product(kk, r, t, False)  # t = K R
        _product(t, kk, pi, True)  # P = t K'
        pi += s


@jit
def _product(a: np.ndarray, b: np.ndarray, out: np.ndarray, transposed: bool) -> None:
    """out = a b, or a b' with `transposed`, for 4 x 4 arrays (out not a or b)."""
    for i in range(4):
        for j in range(4):
            acc = 0.0
            for k in range(4):
                acc += a[i, k] * (b[j, k] if transposed else b[k, j])
            out[i, j] = acc
