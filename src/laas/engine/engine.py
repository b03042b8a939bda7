"""The positioning engine: map -> tracks (Kalman) -> segments -> lane filter -> answers.

Pure: no MQTT, no files, no clock of its own. Time comes from the measurements, so
`laas replay`, `laas evaluate` and the live worker drive the same `Engine` and get the
same answers. Work per measurement is bounded by the size of the measurement's own
segment group; no step touches users elsewhere on the map.

Per fix of user u at time t:
 1. Kalman-filter the fix into u's track (duplicates and stale fixes are refused).
 2. Default mode: subtract the common-error estimate b of u's area (paper mode: b = 0).
 3. Locate u's road element; u leaves its old group and joins the new one, keeping
    its lane belief when the lane count carries over.
 4. Run the mode's lane filter over the group, the others' tracks predicted to t.
 5. Answer with the position placed on the chosen lane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from laas.config import EngineConfig
from laas.engine.assignment import best_assignment
from laas.engine.common_error import CommonError, CommonErrorField
from laas.engine.paper import JointHypothesisFilter
from laas.engine.tracking import Fix, Track, TrackUpdate
from laas.engine.transition import direction_likelihood, lane_transition
from laas.map.hdmap import HdMap, Segment
from laas.models import CorrectedPosition, GpsMeasurement

__all__ = ["Engine", "EngineStats"]


@dataclass
class EngineStats:
    """Counters of what the engine did with the fixes it was given."""

    answered: int = 0
    started: int = 0
    restarted: int = 0
    duplicate: int = 0
    out_of_order: int = 0
    off_map: int = 0
    expired: int = 0


@dataclass
class _Place:
    """Where a user was in its segment at its own last step, and the common error then."""

    t: float
    p: np.ndarray  # (2,) filtered position, common error not removed
    v: np.ndarray  # (2,) velocity
    b: np.ndarray  # (2,) the common error removed for s and d
    s: float
    d: float
    offsets: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    lateral_var: float

    def at(self, t: float, b: np.ndarray) -> _Geometry:
        """The place predicted to time t with common error b, to first order:
        d(t) = d + (v . n)(t - t_k) - n . (b - b_k), and likewise s along the tangent."""
        dt = t - self.t
        db = b - self.b
        return _Geometry(
            p=self.p + self.v * dt - b,
            s=self.s + float(self.v @ self.tangent) * dt - float(self.tangent @ db),
            d=self.d + float(self.v @ self.normal) * dt - float(self.normal @ db),
            offsets=self.offsets,
            normal=self.normal,
            tangent=self.tangent,
            lateral_var=self.lateral_var,
        )


@dataclass
class _User:
    track: Track
    segment: Segment | None = None
    belief: np.ndarray | None = None  # default mode: (L,) lane probabilities in `segment`
    place: _Place | None = None  # set at the user's own step in `segment`


@dataclass
class _Geometry:
    """A user's place in a segment's frame at the time of the step."""

    p: np.ndarray  # (2,) filtered position minus the common error, m
    s: float  # station along the segment
    d: float  # lateral offset, + to the right
    offsets: np.ndarray  # (L,) lane centres at s
    normal: np.ndarray  # (2,) unit normal to the right
    tangent: np.ndarray  # (2,) unit reference direction
    lateral_var: float  # n' P n of the track, m^2


@dataclass
class _Group:
    """The users currently in one segment, and paper mode's joint belief over them."""

    users: set[str] = field(default_factory=set)
    joint: JointHypothesisFilter | None = None


class Engine:
    """Lane-level positions for many road users on one HD map."""

    def __init__(self, hdmap: HdMap, config: EngineConfig | None = None) -> None:
        self.map = hdmap
        self.config = config or EngineConfig()
        self.stats = EngineStats()
        self._users: dict[str, _User] = {}
        self._groups: dict[str, _Group] = {}
        self._errors = CommonErrorField(
            self.config.bias_area,
            self.config.bias_prior,
            self.config.bias_drift,
            self.config.bias_resolution,
        )
        # GNSS headings are true bearings; the map's frame is the UTM grid. Over one map
        # the meridian convergence (grid = true - convergence) is as good as constant.
        x0, y0, x1, y1 = hdmap.bounds
        lon, lat = hdmap.projection.to_wgs84((x0 + x1) / 2.0, (y0 + y1) / 2.0)
        self._convergence = math.radians(hdmap.projection.convergence(lon, lat))

    # -- public ----------------------------------------------------------------------------

    @property
    def users(self) -> int:
        """How many users have a live track."""
        return len(self._users)

    def common_errors(self) -> list[CommonError]:
        """The common-error estimates per area (empty in paper mode)."""
        return list(self._errors.areas)

    def process(self, user: str, measurement: GpsMeasurement) -> CorrectedPosition | None:
        """Correct one fix of `user`; None if it was a duplicate or older than the last."""
        c = self.config
        e, n = self.map.projection.to_utm(measurement.longitude, measurement.latitude)
        fix = Fix(
            t=measurement.timestamp / 1000.0,
            e=e,
            n=n,
            speed=measurement.speed,
            heading=math.radians(measurement.heading) - self._convergence,
        )
        state = self._users.get(user)
        if state is None:
            state = self._users[user] = _User(Track(c, fix))
            self.stats.started += 1
        else:
            outcome = state.track.update(fix)
            if outcome is TrackUpdate.DUPLICATE:
                self.stats.duplicate += 1
                return None
            if outcome is TrackUpdate.OUT_OF_ORDER:
                self.stats.out_of_order += 1
                return None
            if outcome is TrackUpdate.RESTARTED:
                self.stats.restarted += 1
                self._leave(user, state)
                state.belief = None
        t = fix.t
        area: CommonError | None = None
        b = np.zeros(2)
        if c.mode == "default":
            area = self._errors.at(state.track.position)
            area.predict(t)
            b = area.b
        q = state.track.position - b
        segment = self.map.locate(float(q[0]), float(q[1]), c.max_map_distance)
        if segment is None:
            self._leave(user, state)
            self.stats.off_map += 1
            self.stats.answered += 1
            return self._answer(measurement, q, None, None, 0.0, state, area)
        if state.segment is None or state.segment.id != segment.id:
            self._join(user, state, segment)
        group = self._groups[segment.id]
        state.place = self._place(state, segment, b)
        places = {user: state.place}
        for v in self._members(group, user, t)[1:]:
            place = self._users[v].place
            if place is not None:
                places[v] = place
        if area is None:  # paper mode
            geometry = {v: place.at(t, b) for v, place in places.items()}
            lane, probability, point = self._paper_step(user, segment, group, geometry)
        else:
            lane, probability, point = self._default_step(user, segment, places, t, area)
        self.stats.answered += 1
        return self._answer(measurement, point, segment, lane, probability, state, area)

    def expire(self, now_ms: int) -> list[str]:
        """Forget users whose last fix is older than `track_timeout`; return them."""
        now = now_ms / 1000.0
        gone = [u for u, s in self._users.items() if now - s.track.t > self.config.track_timeout]
        for user in gone:
            self.forget(user, expired=True)
        return gone

    def forget(self, user: str, *, expired: bool = False) -> None:
        """Drop a user's track and its place in any group (a rotated pseudonym, say);
        `expired` counts it as an expiry (the live worker expires by its own clock)."""
        state = self._users.pop(user, None)
        if state is not None:
            self._leave(user, state)
            self.stats.expired += expired

    # -- groups ----------------------------------------------------------------------------

    def _join(self, user: str, state: _User, segment: Segment) -> None:
        carried = self._leave(user, state)
        if carried is not None and carried.shape[0] != len(segment.lanes):
            carried = None
        group = self._groups.setdefault(segment.id, _Group())
        group.users.add(user)
        state.segment = segment
        if self.config.mode == "paper":
            if group.joint is None:
                group.joint = JointHypothesisFilter(len(segment.lanes), self.config.max_hypotheses)
            group.joint.add(user, carried)
        else:
            state.belief = carried

    def _leave(self, user: str, state: _User) -> np.ndarray | None:
        """Take `user` out of its group; return its lane belief there."""
        segment = state.segment
        if segment is None:
            return None
        state.segment = None
        group = self._groups.get(segment.id)
        belief = state.belief
        if group is not None:
            group.users.discard(user)
            if group.joint is not None and user in group.joint:
                belief = group.joint.remove(user)
            if not group.users:
                del self._groups[segment.id]
        state.belief = None
        state.place = None
        return belief

    def _members(self, group: _Group, user: str, t: float) -> list[str]:
        """The group's users heard from within `group_timeout`, `user` first."""
        stale = [
            v
            for v in group.users
            if v != user and t - self._users[v].track.t > self.config.group_timeout
        ]
        for v in stale:
            self._leave(v, self._users[v])
        return [user, *sorted(v for v in group.users if v != user)]

    def _place(self, state: _User, segment: Segment, b: np.ndarray) -> _Place:
        """A user's place in `segment` now, with the common error b removed."""
        p = state.track.position
        s, d = segment.frame(float(p[0] - b[0]), float(p[1] - b[1]))
        tangent = segment.tangent(s)
        normal = np.array([tangent[1], -tangent[0]])
        return _Place(
            t=state.track.t,
            p=p,
            v=state.track.velocity,
            b=b.copy(),
            s=s,
            d=d,
            offsets=segment.lane_offsets(s),
            normal=normal,
            tangent=tangent,
            lateral_var=float(normal @ state.track.position_cov @ normal),
        )

    def _prediction(
        self, state: _User, segment: Segment, g: _Geometry
    ) -> tuple[np.ndarray, np.ndarray]:
        """The transition matrix and wrong-way factors of a user's own step."""
        c = self.config
        v = state.track.velocity
        transition = lane_transition(
            g.offsets, float(v @ g.normal), state.track.dt, c.lane_change_rate, c.max_lane_change
        )
        directions = tuple(lane.direction for lane in segment.lanes)
        return transition, direction_likelihood(directions, float(v @ g.tangent))

    # -- the two modes ---------------------------------------------------------------------

    def _paper_step(
        self, user: str, segment: Segment, group: _Group, geometry: dict[str, _Geometry]
    ) -> tuple[int, float, np.ndarray]:
        """Section IV-D: predict and update the joint hypotheses; place u on its lane."""
        joint = group.joint
        if joint is None:
            raise RuntimeError(f"segment {segment.id}: paper mode group without its joint filter")
        g_u = geometry[user]
        transition, direction = self._prediction(self._users[user], segment, g_u)
        # c_v[l] = p_v + (o_l - d_v) n_v: the filtered fix moved across onto lane l.
        placed = {v: g.p + np.outer(g.offsets - g.d, g.normal) for v, g in geometry.items()}
        positions = {v: g.p for v, g in geometry.items()}
        base = 2.0 * self.config.sigma_lane**2 + g_u.lateral_var
        pair_var = {v: base + g.lateral_var for v, g in geometry.items()}
        lane, probability = joint.step(user, transition, direction, placed, positions, pair_var)
        return lane, probability, placed[user][lane]

    def _default_step(
        self,
        user: str,
        segment: Segment,
        places: dict[str, _Place],
        t: float,
        area: CommonError,
    ) -> tuple[int, float, np.ndarray]:
        """Joint assignment with a shared residual offset, then the common-error update."""
        c = self.config
        state = self._users[user]
        g_u = places[user].at(t, area.b)
        lanes = len(segment.lanes)
        transition, direction = self._prediction(state, segment, g_u)
        prior = state.belief if state.belief is not None else np.full(lanes, 1.0 / lanes)
        prior = (prior @ transition) * direction
        prior /= prior.sum()
        # The joint search only matters while the common error is uncertain across the
        # road; then it takes u's nearest neighbours along the segment, at most max_group.
        tau = max(area.sigma_along(g_u.normal), 1e-3)
        gaps = np.diff(g_u.offsets)
        users = list(places)
        if lanes > 1 and tau < 0.1 * float(gaps.min()):
            users = [user]
        # The members' places predicted to t, all at once (see _Place.at).
        pl = [places[v] for v in users]
        dt = t - np.array([p.t for p in pl])
        db = area.b - np.array([p.b for p in pl])
        normals = np.array([p.normal for p in pl])
        tangents = np.array([p.tangent for p in pl])
        velocity = np.array([p.v for p in pl])
        d = np.array([p.d for p in pl]) + ((velocity * dt[:, None] - db) * normals).sum(axis=1)
        if len(users) > c.max_group:
            s = np.array([p.s for p in pl]) + ((velocity * dt[:, None] - db) * tangents).sum(1)
            keep = np.argsort(np.abs(s - s[0]), kind="stable")[: c.max_group]  # u is first
            users, d = [users[k] for k in keep], d[keep]
            pl = [pl[k] for k in keep]
        beliefs = [prior] + [
            b if (b := self._users[v].belief) is not None else np.full(lanes, 1.0 / lanes)
            for v in users[1:]
        ]
        # Successive filtered fixes share their errors, so each is weaker evidence of the
        # lane than its own covariance says: s_i^2 = s_lane^2 + k n'P_i n (raw fixes: k = 1).
        k = c.filtered_inflation if c.kalman else 1.0
        sigma = np.sqrt([c.sigma_lane**2 + k * p.lateral_var for p in pl])
        with np.errstate(divide="ignore"):
            log_prior = np.log(np.array(beliefs))
        result = best_assignment(d, np.array([p.offsets for p in pl]), sigma, log_prior, 0.0, tau)
        lane = int(result.lanes[0])
        posterior = result.marginals[0]
        state.belief = posterior
        # The common error, observed across u's lane by the raw fix (raw fixes have
        # independent noise; the filtered ones do not, and would count one error many
        # times), against every lane u may be on (its predicted lane probabilities).
        fix = state.track.last_fix
        s_raw, d_raw = segment.frame(fix.e, fix.n)
        area.update(
            g_u.normal,
            d_raw,
            segment.lane_offsets(s_raw),
            prior,
            math.sqrt(c.sigma_lane**2 + c.sigma_pos**2),
        )
        # Place u: its re-corrected lateral offset fused with the lane centre,
        #   d = (o / s_lane^2 + d_m / s_m^2) / (1 / s_lane^2 + 1 / s_m^2).
        p = state.track.position - area.b
        s, d = segment.frame(float(p[0]), float(p[1]))
        o = float(segment.lane_offsets(s)[lane])
        var_m = g_u.lateral_var + float(g_u.normal @ area.P @ g_u.normal)
        w_lane, w_m = 1.0 / c.sigma_lane**2, 1.0 / max(var_m, 1e-6)
        fused = (w_lane * o + w_m * d) / (w_lane + w_m)
        return lane, float(posterior[lane]), np.array(segment.point(s, fused))

    # -- answers ---------------------------------------------------------------------------

    def _answer(
        self,
        measurement: GpsMeasurement,
        point: np.ndarray,
        segment: Segment | None,
        lane: int | None,
        probability: float,
        state: _User,
        area: CommonError | None,
    ) -> CorrectedPosition:
        c = self.config
        cov = state.track.position_cov + (area.P if area is not None else np.zeros((2, 2)))
        if area is None:  # paper mode: the common error is never estimated
            cov = cov + np.eye(2) * c.bias_prior**2
        if segment is not None and lane is not None:
            s, _ = segment.frame(float(point[0]), float(point[1]))
            tangent = segment.tangent(s)
            normal = np.array([tangent[1], -tangent[0]])
            along = math.sqrt(float(tangent @ cov @ tangent))
            if area is not None:
                var_m = float(normal @ cov @ normal)
                cross = math.sqrt(1.0 / (1.0 / c.sigma_lane**2 + 1.0 / max(var_m, 1e-6)))
            else:
                cross = c.sigma_lane
        else:
            eig = np.linalg.eigvalsh(cov)
            along = cross = math.sqrt(max(float(eig[-1]), 0.0))
        lon, lat = self.map.projection.to_wgs84(float(point[0]), float(point[1]))
        return CorrectedPosition(
            timestamp=measurement.timestamp,
            latitude=min(max(lat, -90.0), 90.0),
            longitude=min(max(lon, -180.0), 180.0),
            segment=segment.id if segment is not None else None,
            lane=lane,
            lane_type=segment.lanes[lane].type
            if segment is not None and lane is not None
            else None,
            probability=min(max(probability, 0.0), 1.0),
            accuracy=math.hypot(cross, along),
            accuracy_cross=cross,
            accuracy_along=along,
        )
