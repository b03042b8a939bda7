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

Each lane type also bounds how fast its users move (`speed_likelihood`): nobody walks
a sidewalk at 10 m/s and no car parks at 15 m/s. With v the fix's speed and v_max,
v_width and floor the type's limits below,

    S_type(v) = floor + (1 - floor) / (1 + exp((v - v_max) / v_width))

so a lane is judged only by speeds its own users do not reach. The limits are facts
about road users, not fitted constants: walking and jogging stay under about 3 m/s and
cyclists who ride a sidewalk under about 5 m/s; a parking lane is a manoeuvre or, when
free, a cyclist's lane (under about 7 m/s); cycling, e-bikes included, stays under
about 12 m/s; a driving lane takes every speed (cars stop, and slow users share it).
What the limits rule out is a car at speed on a sidewalk, a parking or a bicycle lane.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from laas.engine.jit import jit
from laas.map.hdmap import Lane

__all__ = [
    "SPEED_LIMITS",
    "LaneTraits",
    "direction_likelihood",
    "lane_transition",
    "motion_fit",
    "prediction_of",
    "speed_likelihood",
]

_MOVING = 1.5  # m/s: below this a heading says little about the direction of travel

SPEED_LIMITS: dict[str, tuple[float, float, float]] = {
    # lane type: (v_max m/s, v_width m/s, floor)
    "sidewalk": (5.0, 0.8, 0.05),
    "parking": (7.0, 1.0, 0.02),
    "bicycle": (12.0, 1.5, 0.02),
}
"""How fast a lane type's own users move; types not listed take every speed."""


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


def speed_likelihood(types: tuple[str, ...], speed: float) -> np.ndarray:
    """(L,) factor per lane: how plausible a fix at `speed` (m/s) is on each lane type.

    >>> speed_likelihood(("driving", "sidewalk"), 12.0).round(3).tolist()
    [1.0, 0.05]
    """
    out = np.ones(len(types))
    for i, kind in enumerate(types):
        limit = SPEED_LIMITS.get(kind)
        if limit is not None:
            v_max, width, floor = limit
            z = min((speed - v_max) / width, 50.0)
            out[i] = floor + (1.0 - floor) / (1.0 + np.exp(z))
    return out


def motion_fit(lanes: Sequence[Lane], along_speed: float, speed: float) -> np.ndarray:
    """(L,) F_l = D_l S_l: how well each lane fits a user's motion, its direction against
    the velocity along the element (`direction_likelihood`) and its type's speeds
    (`speed_likelihood`)."""
    directions = tuple(lane.direction for lane in lanes)
    types = tuple(lane.type for lane in lanes)
    fit: np.ndarray = direction_likelihood(directions, along_speed) * speed_likelihood(types, speed)
    return fit


# -- many users of one road element at once (the default mode's batches) -------------------

_DIRECTION_CODE = {"forward": 1.0, "backward": -1.0}


class LaneTraits:
    """The lanes of one road element as arrays, for `prediction_of`: each lane's
    direction (+1 forward, -1 backward, 0 both) and its type's speed limits (v_max,
    v_width, floor; a type without limits takes v_max = inf, so S = 1)."""

    __slots__ = ("direction", "floor", "v_max", "v_width")

    def __init__(self, lanes: Sequence[Lane]) -> None:
        self.direction = np.array([_DIRECTION_CODE.get(lane.direction, 0.0) for lane in lanes])
        limits = [SPEED_LIMITS.get(lane.type, (math.inf, 1.0, 1.0)) for lane in lanes]
        self.v_max, self.v_width, self.floor = (np.array(col) for col in zip(*limits, strict=True))


def prediction_of(
    traits: LaneTraits,
    along: np.ndarray,
    speed: np.ndarray,
    lateral: np.ndarray,
    dt: np.ndarray,
    memory: np.ndarray,
    offsets: np.ndarray,
    rate: float,
    p_max: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The prediction's motion fit and transition for n users of one element, from
    each one's velocity along the element, speed, lateral speed beyond its noise, time
    step and the share of tau = motion_memory it is (dt / tau, at most 1), and the lane
    centres o (n, L) at its station:

        F[l]      = D[l] S[l]   (`motion_fit`: `wrong_way` against the lane's direction
                                 when moving, the type's speeds)
        T[l, l']  = P(l -> l') F[l'] / max F  off the diagonal (`lane_transition`: never
                                 into a lane that does not fit), T[l, l] the rest

    as (F^(dt / tau) (n, L), T (n, L, L))."""
    out: tuple[np.ndarray, np.ndarray] = _prediction(
        traits.direction,
        traits.v_max,
        traits.v_width,
        traits.floor,
        along,
        speed,
        lateral,
        dt,
        memory,
        offsets,
        rate,
        p_max,
        0.05,
    )
    return out


@jit
def _prediction(
    direction: np.ndarray,
    v_max: np.ndarray,
    v_width: np.ndarray,
    floor: np.ndarray,
    along: np.ndarray,
    speed: np.ndarray,
    lateral: np.ndarray,
    dt: np.ndarray,
    memory: np.ndarray,
    offsets: np.ndarray,
    rate: float,
    p_max: float,
    wrong_way: float,
) -> tuple[np.ndarray, np.ndarray]:
    """`prediction_of`, compiled."""
    n, lanes = offsets.shape
    fit = np.empty((n, lanes))
    transition = np.zeros((n, lanes, lanes))
    scale = np.empty(lanes)
    for i in range(n):
        moving = abs(along[i]) >= _MOVING
        # against: the lane's direction opposes the motion along the element
        against = -1.0 if along[i] > 0.0 else 1.0
        top = -math.inf
        for lane in range(lanes):
            z = min((speed[i] - v_max[lane]) / v_width[lane], 50.0)
            f = floor[lane] + (1.0 - floor[lane]) / (1.0 + math.exp(z))
            if moving and direction[lane] == against:
                f = wrong_way * f
            scale[lane] = f
            top = max(top, f)
        for lane in range(lanes):
            fit[i, lane] = scale[lane] ** memory[i]
            scale[lane] = scale[lane] / top
        drift = lateral[i] * max(dt[i], 0.0)
        base = rate * dt[i]
        t = transition[i]
        for j in range(lanes - 1):
            gap = max(offsets[i, j + 1] - offsets[i, j], 0.1)
            t[j, j + 1] = min(p_max, base + max(0.0, drift) / gap) * scale[j + 1]
            t[j + 1, j] = min(p_max, base + max(0.0, -drift) / gap) * scale[j]
        for lane in range(lanes):
            rest = 0.0
            for j in range(lanes):
                rest += t[lane, j]
            t[lane, lane] = 1.0 - rest
    return fit, transition
