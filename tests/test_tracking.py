"""The Kalman track on known motion."""

from __future__ import annotations

import math

import numpy as np

from laas.config import EngineConfig
from laas.engine.tracking import Fix, Track, TrackUpdate


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
