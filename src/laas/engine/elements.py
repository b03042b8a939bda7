"""Which road element, where elements lie side by side or overlap.

The lanelets of a junction overlap, and a footway or a cycle track may run a metre beside
its road as an element of its own. An answer names an element e* (the one located under
the corrected position q = x - b) and a lane of it; the lane filter weighs only e*'s lanes,
so near such a neighbour its P(lane) says nothing of whether the user is on e* at all.
Every lane of the elements beside q competes for the user, each with the same prior:

    P(e* | q) = sum_{l in e*} L_l / sum_{e near q} sum_{l in e} L_l
    L_l = H_e(v) F_l(v) N(d_l; 0, s^2 + w_l^2 / 12)

with d_l the offset of q from lane l's centre line across its element (at q's station,
which must lie on the element), w_l the lane's width (a user anywhere on the lane:
uniform, variance w^2/12), F_l how well the lane fits the user's motion (`motion_fit`:
its direction against the velocity along the element, and its type's speeds), and s^2
the variance of q across the road (the track's and the common error's, and the
receiver's own lasting error s_rx^2, which the track does not see). H_e weighs the
velocity across the element, v_perp = v x t_e: a user on e moves along it, across it only
to change lanes, H_e = N(v_perp; 0, s_v^2 + LANE_CHANGE_SPEED^2) with s_v the velocity
noise; so a road that crosses e* at a junction does not compete with it for a user who
drives along e*.

Elements joined to e* at a seam (its successors and predecessors) are the business of
`Engine._on_element`, which weighs the station along the road; they are left out here.
An element with no other element within `SIDE_MARGIN` costs nothing (the usual case on
a road of one carriageway: `HdMap.beside`), and one whose neighbours lie further than
`REACH` sigma from q costs one array query (`HdMap.beside_near`).
"""

from __future__ import annotations

import math

import numpy as np

from laas.engine.transition import motion_fit
from laas.map.hdmap import HdMap, Segment

__all__ = ["LANE_CHANGE_SPEED", "REACH", "element_share"]

REACH = 4.0
"""Sigmas across the road beyond which an element beside takes no share: its lanes'
likelihood there is below exp(-8) = 0.03 % of a lane's own."""

LANE_CHANGE_SPEED = 1.2
"""m/s, the spread of a user's velocity across its own element: a lane change moves
3.5 m across in about 3 s."""


def element_share(
    hdmap: HdMap,
    segment: Segment,
    q: np.ndarray,
    var_cross: float,
    velocity: np.ndarray,
    speed: float,
    var_velocity: float,
) -> float:
    """P(the user is on `segment` rather than on an element beside it), see the module
    docstring; 1.0 where no element lies beside it."""
    x, y = float(q[0]), float(q[1])
    # an element whose surface is further than REACH sigma from q adds less than
    # exp(-REACH^2 / 2) of a lane's own likelihood: left out
    others = hdmap.beside_near(segment.id, x, y, REACH * math.sqrt(max(var_cross, 0.0)))
    if not others:
        return 1.0
    var_perp = var_velocity + LANE_CHANGE_SPEED**2
    own = _lanes_likelihood(segment, x, y, var_cross, velocity, speed, var_perp, inside=False)
    rest = 0.0
    for other in others:
        rest += _lanes_likelihood(other, x, y, var_cross, velocity, speed, var_perp, inside=True)
    total = own + rest
    if total <= 0.0 or not math.isfinite(total):
        return 1.0
    return own / total


def _lanes_likelihood(
    segment: Segment,
    x: float,
    y: float,
    var_cross: float,
    velocity: np.ndarray,
    speed: float,
    var_perp: float,
    inside: bool,
) -> float:
    """H_e sum_l F_l N(d_l; 0, s^2 + w_l^2/12) of `segment`'s lanes at (x, y); 0 when
    `inside` and the point's station is off the element (it does not lie alongside)."""
    s, d = segment.frame(x, y)
    if inside and not 0.0 <= s <= segment.length:
        return 0.0
    s = min(max(s, 0.0), segment.length)
    offsets = segment.lane_offsets(s)
    widths = np.array([lane.width for lane in segment.lanes])
    var = var_cross + widths**2 / 12.0
    density = np.exp(-0.5 * (d - offsets) ** 2 / var) / np.sqrt(2.0 * math.pi * var)
    t = segment.tangent(s)
    along = float(velocity @ t)
    perp = float(velocity[0] * t[1] - velocity[1] * t[0])
    across = math.exp(-0.5 * perp * perp / var_perp)  # H_e, its constant shared by all
    fit = motion_fit(segment.lanes, along, speed)
    return across * float(np.sum(fit * density))
