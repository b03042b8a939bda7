"""Paper mode: the discrete Bayes filter over joint lane hypotheses (section IV-D).

For one road element with L lanes and users v_1..v_N, the state is the set H of all
L^N joint assignments h = (v_1 -> l_1, ..., v_N -> l_N), held as a tensor of shape
(L,) * N whose axis k is user k's lane. The belief starts uniform. When user u reports:

  prediction   p(h) <- sum_{h'} p(h') T_u[h'_u, h_u] * D_u[h_u]
               (T_u from its heading against the lanes' direction, D_u its wrong-way
               factor; only u's axis moves, the others have not reported)
  update       p(h) <- p(h) * prod_{j != u} exp(-|r_h(u,j) - r(u,j)|^2 / (4 s^2))
               r(u,j) = p_u - p_j  the relative position of the Kalman-filtered fixes,
               r_h(u,j) = c_u[h_u] - c_j[h_j] the same with both placed on their
               assigned lanes, s^2 = 2 (sigma_lane^2 + sigma_kf^2) per pair; each pair
               is updated by both of its users, hence 4 s^2 rather than 2 s^2.

The winner is argmax_h p(h); a user's answer is its lane in the winner and the
marginal probability of that lane. A user who joins adds a uniform axis; one who
leaves is summed out, so what is known about the others is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from laas.config import EngineConfig
from laas.engine.lanefilter import LaneFilter, Placement
from laas.engine.tracking import Track
from laas.engine.transition import direction_likelihood, lane_transition
from laas.map.hdmap import Segment

__all__ = ["JointHypothesisFilter", "PaperLaneFilter"]


class JointHypothesisFilter:
    """The joint belief of one segment's users. Users past `max_hypotheses` are solo."""

    def __init__(self, lanes: int, max_hypotheses: int) -> None:
        self.lanes = lanes
        self.max_hypotheses = max_hypotheses
        self.users: list[str] = []
        self.belief = np.ones(())
        self.solo: dict[str, np.ndarray] = {}

    def __contains__(self, user: str) -> bool:
        return user in self.users or user in self.solo

    @property
    def hypotheses(self) -> int:
        """|H| = L^N for the users in the joint belief."""
        return int(self.belief.size)

    def add(self, user: str, prior: np.ndarray | None = None) -> None:
        """Give `user` an axis (uniform, or `prior`), or a solo belief past the cap."""
        p = np.full(self.lanes, 1.0 / self.lanes) if prior is None else prior / prior.sum()
        if self.belief.size * self.lanes > self.max_hypotheses:
            self.solo[user] = p
            return
        self.users.append(user)
        self.belief = np.multiply.outer(self.belief, p)

    def remove(self, user: str) -> np.ndarray:
        """Sum `user` out of the belief and return its marginal lane distribution."""
        if user in self.solo:
            return self.solo.pop(user)
        k = self.users.index(user)
        marginal = self.marginal(user)
        self.belief = self.belief.sum(axis=k)
        self.users.pop(k)
        return marginal

    def marginal(self, user: str) -> np.ndarray:
        """(L,) P(user on lane l)."""
        if user in self.solo:
            return self.solo[user]
        k = self.users.index(user)
        axes = tuple(i for i in range(self.belief.ndim) if i != k)
        m: np.ndarray = self.belief.sum(axis=axes)
        return m

    def step(
        self,
        user: str,
        transition: np.ndarray,
        direction: np.ndarray,
        placed: dict[str, np.ndarray],
        positions: dict[str, np.ndarray],
        pair_var: dict[str, float],
    ) -> tuple[int, float]:
        """Predict and update on `user`'s fix; return its lane in the winner and P(lane).

        placed[v]: (L, 2) the user's fix placed on each lane; positions[v]: (2,) the
        filtered fix; pair_var[v]: s^2 for the pair (user, v). Users of the joint belief
        missing from `placed` are not compared this step.
        """
        if user in self.solo:
            p = (self.solo[user] @ transition) * direction
            self.solo[user] = p / p.sum()
            lane = int(np.argmax(self.solo[user]))
            return lane, float(self.solo[user][lane])
        k = self.users.index(user)
        # Prediction along u's axis: p(.., l, ..) = sum_l' p(.., l', ..) T[l', l] D[l]
        b = np.moveaxis(np.tensordot(self.belief, transition, axes=([k], [0])), -1, k)
        shape = [1] * b.ndim
        shape[k] = self.lanes
        b = b * direction.reshape(shape)
        # Update with the relative positions to every other joint user.
        log_like = np.zeros(b.shape)
        for j, other in enumerate(self.users):
            if other == user or other not in placed:
                continue
            r = positions[user] - positions[other]
            r_h = placed[user][:, None, :] - placed[other][None, :, :]  # (L, L, 2)
            cost = ((r_h - r) ** 2).sum(axis=2) / (4.0 * pair_var[other])
            pair_shape = [1] * b.ndim
            pair_shape[k] = pair_shape[j] = self.lanes
            pair = cost if k < j else cost.T
            log_like = log_like - pair.reshape(pair_shape)
        b = b * np.exp(log_like - log_like.max())
        total = b.sum()
        if not np.isfinite(total) or total <= 0.0:
            b = np.exp(log_like - log_like.max())  # the evidence overrules a dead belief
            total = b.sum()
        self.belief = b / total
        winner = np.unravel_index(int(np.argmax(self.belief)), self.belief.shape)
        lane = int(winner[k])
        return lane, float(self.marginal(user)[lane])


def _prediction(
    segment: Segment,
    offsets: np.ndarray,
    normal: np.ndarray,
    track: Track,
    rate: float,
    p_max: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Section IV-D's prediction for a user's own step in `segment`, where the road has
    lane centres `offsets` and unit normal n: (T[from, to], wrong-way factor per lane)
    from its velocity across (v . n) and along (v . t) the road since its last fix."""
    v = track.velocity
    tangent = np.array([-normal[1], normal[0]])
    transition = lane_transition(offsets, float(v @ normal), track.dt, rate, p_max)
    directions = tuple(lane.direction for lane in segment.lanes)
    return transition, direction_likelihood(directions, float(v @ tangent))


@dataclass
class _Place:
    """Where a user was in its segment at its own last step."""

    t: float
    p: np.ndarray  # (2,) filtered position
    v: np.ndarray  # (2,) velocity
    s: float
    d: float
    offsets: np.ndarray
    normal: np.ndarray
    lateral_var: float

    def at(self, t: float) -> tuple[np.ndarray, float]:
        """(position, lateral offset) predicted to time t at constant velocity:
        p(t) = p + v (t - t_k),  d(t) = d + (v . n)(t - t_k)."""
        dt = t - self.t
        return self.p + self.v * dt, self.d + float(self.v @ self.normal) * dt


@dataclass
class _Group:
    """The users currently in one segment and their joint belief."""

    joint: JointHypothesisFilter
    users: set[str] = field(default_factory=set)


class PaperLaneFilter(LaneFilter):
    """Section IV-D: one joint-hypothesis filter per road element. The common error is
    never estimated: b = 0 with the prior's covariance."""

    def __init__(self, config: EngineConfig) -> None:
        super().__init__(config)
        self._groups: dict[str, _Group] = {}
        self._segment: dict[str, str] = {}  # user -> segment id of its group
        self._places: dict[str, _Place] = {}
        self._seen: dict[str, float] = {}  # user -> time of its last step
        self._prior = np.eye(2) * config.bias_prior**2

    def correction(self, position: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(2), self._prior

    def segment_groups(self) -> int:
        return len(self._groups)

    def leave(self, user: str) -> None:
        self._take_out(user)

    def _take_out(self, user: str) -> np.ndarray | None:
        """Take `user` out of its group; return its lane belief there."""
        seg_id = self._segment.pop(user, None)
        self._places.pop(user, None)
        self._seen.pop(user, None)
        if seg_id is None:
            return None
        group = self._groups[seg_id]
        group.users.discard(user)
        belief = group.joint.remove(user) if user in group.joint else None
        if not group.users:
            del self._groups[seg_id]
        return belief

    def _join(self, user: str, segment: Segment) -> _Group:
        carried = self._take_out(user)
        if carried is not None and carried.shape[0] != len(segment.lanes):
            carried = None
        group = self._groups.get(segment.id)
        if group is None:
            joint = JointHypothesisFilter(len(segment.lanes), self.config.max_hypotheses)
            group = self._groups[segment.id] = _Group(joint)
        group.users.add(user)
        group.joint.add(user, carried)
        self._segment[user] = segment.id
        return group

    def step(self, user: str, track: Track, segment: Segment, t: float) -> Placement:
        """Predict and update the joint hypotheses of u's segment; place u on its lane."""
        c = self.config
        if self._segment.get(user) != segment.id:
            group = self._join(user, segment)
        else:
            group = self._groups[segment.id]
        # The group's users heard from within group_timeout; the stale ones leave it.
        for v in [v for v in group.users if v != user]:
            if t - self._seen[v] > c.group_timeout:
                self._take_out(v)
        p = track.position
        s, d = segment.frame(float(p[0]), float(p[1]))
        tangent = segment.tangent(s)
        normal = np.array([tangent[1], -tangent[0]])
        offsets = segment.lane_offsets(s)
        lateral_var = float(normal @ track.position_cov @ normal)
        self._places[user] = _Place(t, p, track.velocity, s, d, offsets, normal, lateral_var)
        self._seen[user] = track.t
        transition, direction = _prediction(
            segment, offsets, normal, track, c.paper_lane_change_rate, c.max_lane_change
        )
        # c_v[l] = p_v + (o_l - d_v) n_v: each user's filtered fix moved across onto lane l.
        placed: dict[str, np.ndarray] = {}
        positions: dict[str, np.ndarray] = {}
        pair_var: dict[str, float] = {}
        base = 2.0 * c.sigma_lane**2 + lateral_var
        for v in [user, *sorted(v for v in group.users if v != user)]:
            place = self._places.get(v)
            if place is None:
                continue
            pos, dv = place.at(t)
            placed[v] = pos + np.outer(place.offsets - dv, place.normal)
            positions[v] = pos
            pair_var[v] = base + place.lateral_var
        lane, probability = group.joint.step(
            user, transition, direction, placed, positions, pair_var
        )
        return Placement(lane, probability, placed[user][lane], self._prior, c.sigma_lane)
