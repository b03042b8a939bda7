"""The prediction step of the lane filters: where a user can be one step later.

The paper compares a user's heading with the direction of the lane it is assigned to:
aligned means it stays, a heading across the lane means a lane change towards that
side. With v the user's velocity, n the road's unit normal (to the right) and dt the
time since its last fix, the lateral drift toward the right is  u = (v . n) dt  and

    P(l -> l+1) = min(p_max, rate dt + max(0,  u) / g_right)
    P(l -> l-1) = min(p_max, rate dt + max(0, -u) / g_left)
    P(l -> l)   = 1 - P(l -> l+1) - P(l -> l-1)

where g is the distance between the two lane centres. A lane whose permitted direction
opposes the user's motion gets the likelihood `wrong_way` (a user moving at walking
speed or less is not judged).
"""

from __future__ import annotations

import numpy as np

__all__ = ["direction_likelihood", "lane_transition"]

_MOVING = 1.5  # m/s: below this a heading says little about the direction of travel


def lane_transition(
    offsets: np.ndarray, lateral_speed: float, dt: float, rate: float, p_max: float
) -> np.ndarray:
    """T[from, to] for lanes with centres at `offsets` (m, increasing to the right).

    >>> lane_transition(np.array([0.0, 3.0]), 1.5, 1.0, 0.0, 0.45).round(2).tolist()
    [[0.55, 0.45], [0.0, 1.0]]
    """
    lanes = offsets.shape[0]
    t = np.zeros((lanes, lanes))
    drift = lateral_speed * max(dt, 0.0)
    gaps = np.maximum(np.diff(offsets), 0.1)
    for lane in range(lanes):
        right = left = 0.0
        if lane + 1 < lanes:
            right = min(p_max, rate * dt + max(0.0, drift) / gaps[lane])
            t[lane, lane + 1] = right
        if lane > 0:
            left = min(p_max, rate * dt + max(0.0, -drift) / gaps[lane - 1])
            t[lane, lane - 1] = left
        t[lane, lane] = 1.0 - right - left
    return t


def direction_likelihood(
    directions: tuple[str, ...], along_speed: float, wrong_way: float = 0.05
) -> np.ndarray:
    """(L,) factor per lane: 1, or `wrong_way` if its direction opposes the motion.

    `along_speed` is the velocity along the segment's reference direction (m/s).
    """
    out = np.ones(len(directions))
    if abs(along_speed) < _MOVING:
        return out
    against = "backward" if along_speed > 0 else "forward"
    for i, direction in enumerate(directions):
        if direction == against:
            out[i] = wrong_way
    return out
