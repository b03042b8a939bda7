"""The Kalman track on known motion."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from laas.config import EngineConfig
from laas.engine.tracking import DOUBT_SECONDS, Fix, Track, TrackUpdate, kalman_steps


def _fix(t: float, e: float, n: float, speed: float = 10.0, heading_deg: float = 90.0) -> Fix:
    return Fix(t, e, n, speed, math.radians(heading_deg))


def test_constant_velocity_track_is_smoothed_below_the_noise() -> None:
    rng = np.random.default_rng(7)
    track: Track | None = None
    errors = []
    raw = []
    for k in range(120):
        t = k * 0.5  # irregular enough: every other step skips a beat
        t += 0.25 * (k % 3 == 0)
        true = np.array([500_000.0 + 10.0 * t, 5_900_000.0])
        noisy = true + rng.normal(0.0, 2.0, 2)
        fix = _fix(t, float(noisy[0]), float(noisy[1]), speed=10.0 + rng.normal(0, 0.2))
        if track is None:
            track = Track(EngineConfig(sigma_pos=2.0, sigma_vel=0.2), fix)
        else:
            assert track.update(fix) is TrackUpdate.ACCEPTED
        if k > 20:
            errors.append(np.hypot(*(track.position - true)))
            raw.append(np.hypot(*(noisy - true)))
    assert track is not None
    assert np.mean(errors) < 0.6 * np.mean(raw)
    np.testing.assert_allclose(track.velocity, [10.0, 0.0], atol=0.3)
    # Extrapolation at constant velocity.
    np.testing.assert_allclose(
        track.position_at(track.t + 2.0) - track.position, [20.0, 0.0], atol=0.6
    )


def test_duplicates_and_stale_fixes_are_refused_and_gaps_restart() -> None:
    config = EngineConfig(track_timeout=5.0)
    track = Track(config, _fix(10.0, 0.0, 0.0))
    assert track.update(_fix(11.0, 10.0, 0.0)) is TrackUpdate.ACCEPTED
    before = track.position.copy()
    assert track.update(_fix(11.0, 99.0, 99.0)) is TrackUpdate.DUPLICATE
    assert track.update(_fix(10.5, 99.0, 99.0)) is TrackUpdate.OUT_OF_ORDER
    np.testing.assert_array_equal(track.position, before)
    assert track.update(_fix(30.0, 500.0, 0.0)) is TrackUpdate.RESTARTED
    np.testing.assert_allclose(track.position, [500.0, 0.0])


def test_without_kalman_the_track_is_the_raw_fix() -> None:
    track = Track(EngineConfig(kalman=False), _fix(0.0, 0.0, 0.0))
    track.update(_fix(1.0, 13.0, 2.0))
    np.testing.assert_allclose(track.position, [13.0, 2.0])


def test_the_track_is_filterpys_kalman_filter_to_rounding() -> None:
    """The written-out predict and update against filterpy's own KalmanFilter and
    Q_discrete_white_noise on the same fixes: irregular steps, turns, stops (the plain
    filter: multipath weighting off)."""
    from filterpy.kalman import KalmanFilter

    config = EngineConfig(sigma_pos=1.5, sigma_accel=0.9, track_multipath=0.0)
    rng = np.random.default_rng(11)
    t, e, n = 0.0, 500_000.0, 5_900_000.0
    first = _fix(t, e, n, speed=8.0, heading_deg=30.0)
    track = Track(config, first)
    kf = KalmanFilter(dim_x=4, dim_z=4)
    kf.H = np.eye(4)
    kf.x = np.array([e, n, *first.velocity]).reshape(4, 1)
    kf.P = track._measurement_noise(first).copy()
    for _ in range(300):
        dt = float(rng.choice([0.1, 0.5, 1.0, 2.3]))
        t += dt
        speed = max(0.0, 8.0 + rng.normal(0, 3.0))
        fix = _fix(t, e + rng.normal(0, 30), n + rng.normal(0, 30), speed, rng.uniform(0, 360))
        assert track.update(fix) is TrackUpdate.ACCEPTED
        _filterpy_step(kf, config, dt, fix, track)
        _assert_same(track, kf)


def test_a_batch_of_tracks_steps_as_filterpy_steps_each() -> None:
    """`kalman_steps` on five tracks at once, each with its own irregular steps, speeds
    and headings (one with the receiver's own accuracy), against one filterpy
    KalmanFilter per track (the plain filter: multipath weighting off)."""
    from filterpy.kalman import KalmanFilter

    config = EngineConfig(sigma_pos=1.5, sigma_accel=0.9, track_multipath=0.0)
    rng = np.random.default_rng(5)
    times = [0.0] * 5
    tracks, filters = [], []
    for i in range(5):
        first = _fix(0.0, 500_000.0 + 100 * i, 5_900_000.0, speed=2.0 * i, heading_deg=70.0 * i)
        tracks.append(Track(config, first))
        kf = KalmanFilter(dim_x=4, dim_z=4)
        kf.H = np.eye(4)
        kf.x = np.array([first.e, first.n, *first.velocity]).reshape(4, 1)
        kf.P = tracks[-1]._measurement_noise(first).copy()
        filters.append(kf)
    for _ in range(100):
        fixes = []
        for i, track in enumerate(tracks):
            times[i] += float(rng.choice([0.1, 0.5, 1.0, 2.3]))
            e, n = track.position + rng.normal(0, 20, 2)
            speed, heading = max(0.0, 8.0 + rng.normal(0, 3.0)), rng.uniform(0, 360)
            acc = 3.0 if i == 4 else None
            fix = Fix(times[i], float(e), float(n), speed, math.radians(heading), acc)
            assert track.admit(fix) is TrackUpdate.ACCEPTED
            fixes.append(fix)
        steps = [fx.t - tr.t for tr, fx in zip(tracks, fixes, strict=True)]
        kalman_steps(tracks, fixes)
        for track, kf, fix, dt in zip(tracks, filters, fixes, steps, strict=True):
            _filterpy_step(kf, config, dt, fix, track)
            assert track.t == fix.t and track.dt == dt and track.last_fix is fix
            _assert_same(track, kf)


def _filterpy_step(kf: Any, config: EngineConfig, dt: float, fix: Fix, track: Track) -> None:
    """filterpy's own predict and update for the track's model, R from the track."""
    from filterpy.common import Q_discrete_white_noise

    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    q = Q_discrete_white_noise(
        dim=2, dt=dt, var=config.sigma_accel**2, block_size=2, order_by_dim=False
    )
    kf.predict(F=f, Q=q)
    kf.update(np.array([fix.e, fix.n, *fix.velocity]), R=track._measurement_noise(fix))


def _assert_same(track: Track, kf: Any) -> None:
    """The track's state and covariance are filterpy's, to rounding."""
    np.testing.assert_allclose(track.position, kf.x[:2, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(track.velocity, kf.x[2:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(track.position_cov, kf.P[:2, :2], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(track.velocity_cov, kf.P[2:, 2:], rtol=1e-9, atol=1e-12)


def _multipath_run(config: EngineConfig) -> tuple[float, float]:
    """A car at 10 m/s east, 10 Hz fixes of sigma 1 m, in multipath 4 m to the north from
    20 s to 24 s: the track's largest northward error during the reflection and 2 s
    after it ends."""
    rng = np.random.default_rng(3)
    track: Track | None = None
    during, after = 0.0, 0.0
    for k in range(300):
        t = k * 0.1
        true = np.array([500_000.0 + 10.0 * t, 5_900_000.0])
        off = 4.0 if 20.0 <= t < 24.0 else 0.0
        e, n = true + rng.normal(0.0, 1.0, 2) + [0.0, off]
        fix = _fix(t, float(e), float(n), speed=10.0 + rng.normal(0, 0.1))
        if track is None:
            track = Track(config, fix)
            continue
        track.update(fix)
        error = float(track.position[1] - true[1])
        if 20.0 <= t < 24.0:
            during = max(during, error)
        elif t >= 26.0:
            after = max(after, error)
    return during, after


def test_a_reflection_barely_moves_a_default_mode_track() -> None:
    """The same fixes, plain and multipath-weighted: the plain filter follows a 4 m
    reflection for metres (2.8 m when this was written) and keeps it for seconds after;
    the weighted one is pulled less than half as far (1.3 m) and keeps less (0.8 m
    against 1.6 m from 2 s after the reflection ends)."""
    plain = _multipath_run(EngineConfig(track_multipath=0.0))
    weighted = _multipath_run(EngineConfig())
    paper = _multipath_run(EngineConfig(mode="paper"))
    assert plain[0] > 2.0, plain
    assert weighted[0] < 0.5 * plain[0], (weighted, plain)
    assert weighted[1] < 0.6 * plain[1], (weighted, plain)
    assert paper == plain  # paper mode keeps the plain filter


def test_a_batch_weighs_multipath_as_one_track_at_a_time() -> None:
    """`kalman_steps` with the weighting on gives each track what `Track.update` gives."""
    config = EngineConfig(sigma_pos=1.5)
    rng = np.random.default_rng(8)
    one = [Track(config, _fix(0.0, 100.0 * i, 0.0, speed=5.0)) for i in range(4)]
    many = [Track(config, _fix(0.0, 100.0 * i, 0.0, speed=5.0)) for i in range(4)]
    for k in range(1, 60):
        fixes = [
            _fix(
                0.5 * k,
                100.0 * i + 2.5 * k + float(rng.normal(0, 1)),
                float(rng.normal(0, 1)) + 5.0 * (k % 7 == 0),
                speed=5.0,
            )
            for i in range(4)
        ]
        _step_alike(one, many, fixes, cov=True)


def _step_alike(one: list[Track], many: list[Track], fixes: list[Fix], cov: bool) -> None:
    """One step: `one` a track at a time (`Track.update`), `many` in one batch
    (`kalman_steps`); their positions (and covariances, if `cov`) must agree."""
    for track, fix in zip(one, fixes, strict=True):
        track.update(fix)
    for track, fix in zip(many, fixes, strict=True):
        track.admit(fix)
    kalman_steps(many, fixes)
    for a, b in zip(one, many, strict=True):
        np.testing.assert_allclose(b.position, a.position, rtol=0, atol=1e-9)
        if cov:
            np.testing.assert_allclose(b.position_cov, a.position_cov, rtol=0, atol=1e-12)


def test_a_track_that_its_fixes_keep_contradicting_follows_them() -> None:
    """Fixes that jump 4 m and stay there (a track started in multipath, or one that missed
    a manoeuvre, looks the same to it) are weighed as a reflection for `DOUBT_SECONDS`;
    then the track is doubted and follows them, within half a metre a second later."""
    config = EngineConfig()
    rng = np.random.default_rng(4)
    track: Track | None = None
    error = np.inf
    for k in range(300):
        t = k * 0.1
        true = np.array([500_000.0 + 10.0 * t, 5_900_000.0 + (4.0 if t >= 20.0 else 0.0)])
        e, n = true + rng.normal(0.0, 0.3, 2)
        fix = _fix(t, float(e), float(n), speed=10.0)
        if track is None:
            track = Track(config, fix)
            continue
        track.update(fix)
        if t >= 20.0 + DOUBT_SECONDS + 1.0:
            error = min(error, float(np.hypot(*(track.position - true))))
            assert np.hypot(*(track.position - true)) < 0.5, t
    assert error < 0.5


def test_a_batch_doubts_its_tracks_as_one_track_at_a_time() -> None:
    """Fixes that jump 4 m for good on two of four tracks: `kalman_steps` doubts those
    tracks when `Track.update` does, and the states stay the same."""
    config = EngineConfig(sigma_pos=0.5)
    rng = np.random.default_rng(9)
    one = [Track(config, _fix(0.0, 100.0 * i, 0.0, speed=10.0)) for i in range(4)]
    many = [Track(config, _fix(0.0, 100.0 * i, 0.0, speed=10.0)) for i in range(4)]
    for k in range(1, 80):
        t = 0.1 * k
        fixes = [
            _fix(
                t,
                100.0 * i + 10.0 * t + float(rng.normal(0, 0.3)),
                float(rng.normal(0, 0.3)) + (4.0 if i % 2 and t >= 3.0 else 0.0),
                speed=10.0,
            )
            for i in range(4)
        ]
        _step_alike(one, many, fixes, cov=False)
    for i in (1, 3):  # the jumped tracks were doubted and follow their fixes
        assert abs(one[i].position[1] - 4.0) < 0.5 and abs(many[i].position[1] - 4.0) < 0.5
