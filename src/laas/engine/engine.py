"""The positioning engine: map -> tracks (Kalman) -> road elements -> lane filter -> answers.

Pure: no MQTT, no files, no clock of its own. Time comes from the measurements, so
`laas replay`, `laas evaluate` and the live worker drive the same `Engine` and get the
same answers.

Per fix of user u at time t:
 1. Kalman-filter the fix into u's track (duplicates and stale fixes are refused).
 2. Ask the mode's lane filter for the common error b at u's place (paper mode: b = 0).
 3. Locate u's road element with b removed (default mode, while b is uncertain: a nearby
    element whose lanes fit u's motion much better, `_plausible`); off every element,
    answer the corrected fix.
 4. Let the lane filter place u on a lane of that element (`LaneFilter.step`).
 5. Answer with the placed position and its honest 1-sigma across and along the road,
    its lane probability calibrated (default mode: `calibration`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from laas.config import EngineConfig
from laas.engine.calibration import calibrate
from laas.engine.common_error import CommonError
from laas.engine.cooperative import CooperativeLaneFilter
from laas.engine.elements import element_share
from laas.engine.handover import AreaState, UserState
from laas.engine.lanefilter import LaneFilter, Placement
from laas.engine.paper import PaperLaneFilter
from laas.engine.tracking import Fix, Track, TrackUpdate, kalman_steps
from laas.engine.transition import motion_fit
from laas.map.hdmap import HdMap, Segment
from laas.models import CorrectedPosition, GpsMeasurement, LaneType

__all__ = ["Engine", "EngineStats", "make_lane_filter"]


def make_lane_filter(config: EngineConfig) -> LaneFilter:
    """The lane filter of `config.mode`."""
    if config.mode == "paper":
        return PaperLaneFilter(config)
    return CooperativeLaneFilter(config)


_HANDOVER_REACH = 10_000.0  # m: a handed-over track this far off the map is not ours
_FEW = 4  # fixes projected one by one (`laas.map.geo`: the same values as its array call)


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


class Engine:
    """Lane-level positions for many road users on one HD map."""

    def __init__(self, hdmap: HdMap, config: EngineConfig | None = None) -> None:
        self.map = hdmap
        self.config = config or EngineConfig()
        self.stats = EngineStats()
        self._tracks: dict[str, Track] = {}
        self._lanes = make_lane_filter(self.config)
        # GNSS headings are true bearings; the map's frame is the UTM grid. Over one map
        # the meridian convergence (grid = true - convergence) is as good as constant.
        x0, y0, x1, y1 = hdmap.bounds
        lon, lat = hdmap.projection.to_wgs84((x0 + x1) / 2.0, (y0 + y1) / 2.0)
        self._convergence = math.radians(hdmap.projection.convergence(lon, lat))

    @property
    def users(self) -> int:
        """How many users have a live track."""
        return len(self._tracks)

    def common_errors(self) -> list[CommonError]:
        """The common-error estimates per area (empty in paper mode)."""
        return self._lanes.common_errors()

    def segment_groups(self) -> int:
        """Road elements that hold users in the lane filter now."""
        return self._lanes.segment_groups()

    def process(self, user: str, measurement: GpsMeasurement) -> CorrectedPosition | None:
        """Correct one fix of `user`; None if it was a duplicate or older than the last."""
        return self.process_many([(user, measurement)])[0]

    def process_many(
        self, fixes: Sequence[tuple[str, GpsMeasurement]]
    ) -> list[CorrectedPosition | None]:
        """Correct a batch of fixes (fixes that waited together), one answer each, in order.

        A batch is one step of the whole crowd: the projections to and from the map's
        frame, the Kalman step of every track (`kalman_steps`), the road elements
        (`HdMap.locate_many`) and the lane filter (`LaneFilter.step_many`: in default
        mode, one measurement update of each area's common error at the batch's time)
        are each done once for all its fixes. A user with two fixes in the batch splits
        it: a run of the batch takes at most one fix per user, the runs in order. A batch
        of one is the fix alone (`process`).
        """
        if not fixes:
            return []
        projection = self.map.projection
        en: list[tuple[float, float]]
        if len(fixes) <= _FEW:  # pyproj's call per point costs less than its array call
            en = [projection.to_utm(m.longitude, m.latitude) for _, m in fixes]
        else:
            lon = np.array([m.longitude for _, m in fixes])
            lat = np.array([m.latitude for _, m in fixes])
            en = projection.to_utm_array(lon, lat).tolist()
        placed: list[_Answer | None] = []
        start = 0
        while start < len(fixes):  # runs in which each user has at most one fix
            seen: set[str] = set()
            end = start
            while end < len(fixes) and fixes[end][0] not in seen:
                seen.add(fixes[end][0])
                end += 1
            run = range(start, end)
            pending: list[tuple[Track, Fix]] = []
            tracks = [self._admit(fixes[i][0], self._fix(fixes[i][1], en[i]), pending) for i in run]
            kalman_steps([t for t, _ in pending], [f for _, f in pending])
            placed.extend(self._place_run(fixes[start:end], tracks))
            start = end
        return self._answers(placed)

    def _fix(self, m: GpsMeasurement, en: tuple[float, float]) -> Fix:
        """A measurement in the map's frame: heading from true north to grid north, the
        receiver's own accuracy (a horizontal 1-sigma radius) to a 1-sigma per axis."""
        return Fix(
            t=m.timestamp / 1000.0,
            e=en[0],
            n=en[1],
            speed=m.speed,
            heading=math.radians(m.heading) - self._convergence,
            accuracy=None if m.accuracy is None else m.accuracy / math.sqrt(2),
        )

    def _admit(self, user: str, fix: Fix, pending: list[tuple[Track, Fix]]) -> Track | None:
        """The user's track with the fix admitted (`Track.admit`), its Kalman step added
        to `pending`; None for a duplicate or a fix older than the track's last."""
        track = self._tracks.get(user)
        if track is None:
            track = self._tracks[user] = Track(self.config, fix)
            self.stats.started += 1
            return track
        outcome = track.admit(fix)
        if outcome is TrackUpdate.DUPLICATE:
            self.stats.duplicate += 1
            return None
        if outcome is TrackUpdate.OUT_OF_ORDER:
            self.stats.out_of_order += 1
            return None
        if outcome is TrackUpdate.RESTARTED:
            self.stats.restarted += 1
            self._lanes.leave(user)
        elif self.config.kalman:
            pending.append((track, fix))
        return track

    def _place_run(
        self, fixes: Sequence[tuple[str, GpsMeasurement]], tracks: Sequence[Track | None]
    ) -> list[_Answer | None]:
        """Steps 2-5 of the module docstring for a run of fixes already in their tracks
        (None: refused), every user at most once."""
        c = self.config
        live = [k for k, track in enumerate(tracks) if track is not None]
        out: list[_Answer | None] = [None] * len(tracks)
        if not live:
            return out
        ts = [fixes[k][1].timestamp / 1000.0 for k in live]
        positions = np.array([cast(Track, tracks[k]).position for k in live])
        corrections = self._lanes.corrections(positions, max(ts))
        q = positions - np.array([b for b, _ in corrections])
        segments = self.map.locate_many(q, c.max_map_distance)
        work: list[tuple[str, Track, Segment, float]] = []
        at: list[tuple[int, int]] = []  # (the fix, its row of q) of each entry of work
        for j, k in enumerate(live):
            user, measurement = fixes[k]
            track = cast(Track, tracks[k])
            segment = segments[j]
            self.stats.answered += 1
            if segment is not None and c.mode == "default":
                segment = self._plausible(segment, q[j], corrections[j][1], track)
            if segment is None:
                self._lanes.leave(user)
                self.stats.off_map += 1
                out[k] = self._off_map(measurement, q[j], track.position_cov + corrections[j][1])
                continue
            work.append((user, track, segment, ts[j]))
            at.append((k, j))
        for (k, j), (_, track, segment, _), placement in zip(
            at, work, self._lanes.step_many(work), strict=True
        ):
            out[k] = self._answer(fixes[k][1], segment, placement, track, q[j])
        return out

    def _plausible(
        self, segment: Segment, q: np.ndarray, b_cov: np.ndarray, track: Track
    ) -> Segment:
        """The road element for a fix while the common error is uncertain.

        `locate` takes the element under q = x - b, b the common error's mean; while b is
        uncertain (sigma_b its largest standard deviation) any element within 2 sigma_b of
        q may be the right one. Each is judged by how well its best lane fits the user's
        motion, fit(e) = max_l D_l S_l (direction and speed of the lane's type, as the lane
        filter judges lanes), and the located element stays unless another fits more than
        twice as well; then the nearest such element is taken. So a car moving at 12 m/s
        is not placed on a footway beside its road (whose evidence would pull b to the
        footway), where the lane filter could only compare the footway's own lanes.
        """
        v, speed = track.velocity, track.last_fix.speed

        def fit(e: Segment) -> float:
            s_q, _ = e.frame(float(q[0]), float(q[1]))
            along = float(v @ e.tangent(min(max(s_q, 0.0), e.length)))
            return float(np.max(motion_fit(e.lanes, along, speed)))

        # sigma_b^2, the largest eigenvalue of the 2x2 covariance: (a + c)/2 + |((a - c)/2, b)|
        a, b, c = float(b_cov[0, 0]), float(b_cov[0, 1]), float(b_cov[1, 1])
        largest = (a + c) / 2.0 + math.hypot((a - c) / 2.0, b)
        radius = min(2.0 * math.sqrt(max(largest, 0.0)), self.config.max_map_distance)
        if radius < 1.0:
            return segment
        here = fit(segment)
        if here >= 0.5:  # no element fits more than twice as well (fit <= 1): the usual case
            return segment
        near = self.map.segments_near(float(q[0]), float(q[1]), radius)
        fits = {e.id: fit(e) for e in near}
        best = max(fits.values(), default=here)
        if here >= 0.5 * best:
            return segment
        return next(e for e in near if fits[e.id] >= 0.5 * best)

    def expire(self, now_ms: int) -> list[str]:
        """Forget users whose last fix is older than `track_timeout`; return them."""
        now = now_ms / 1000.0
        gone = [u for u, tr in self._tracks.items() if now - tr.t > self.config.track_timeout]
        for user in gone:
            self.forget(user, expired=True)
        return gone

    def forget(self, user: str, *, expired: bool = False) -> None:
        """Drop a user's track and its lane state (a rotated pseudonym, say);
        `expired` counts it as an expiry (the live worker expires by its own clock)."""
        if self._tracks.pop(user, None) is not None:
            self._lanes.leave(user)
            self.stats.expired += expired

    # -- hand-over between workers (laas.engine.handover) ---------------------------------

    def export_user(self, user: str) -> UserState | None:
        """`user`'s track and lane table, for the worker of the region it goes to; None
        if it has no track."""
        track = self._tracks.get(user)
        if track is None:
            return None
        x, p = track.state()
        f = track.last_fix
        heading = f.heading + self._convergence  # back to a true bearing
        return UserState(
            x,
            p,
            (f.t, f.e, f.n, f.speed, heading, f.accuracy),
            track.dt,
            self._lanes.export_lanes(user),
        )

    def import_user(self, user: str, state: UserState) -> bool:
        """Go on with `user` from a hand-over: its track and lane table as the old worker
        left them. Not taken (False) if `user` already has a track as new, or if the
        state's position lies more than `_HANDOVER_REACH` outside the map's bounds (a
        state from another map). A state older than `track_timeout` is taken, and its
        track restarts at the next fix, as any track's would."""
        t, e, n, speed, heading, accuracy = state.fix
        known = self._tracks.get(user)
        if known is not None and known.t >= t:
            return False
        x0, y0, x1, y1 = self.map.bounds
        reach = _HANDOVER_REACH
        if not (x0 - reach <= e <= x1 + reach and y0 - reach <= n <= y1 + reach):
            return False
        fix = Fix(t, e, n, speed, heading - self._convergence, accuracy)
        track = Track.restore(self.config, state.x, state.p, fix, state.dt)
        self._lanes.leave(user)
        self._tracks[user] = track
        lanes = state.lanes
        segment = None if lanes is None else self.map.segments.get(lanes.segment)
        if lanes is not None and segment is not None:
            self._lanes.import_lanes(user, lanes, segment, track.position)
        return True

    def record_areas(self) -> None:
        """Keep each area's own evidence from now on, for `export_areas` (a regional
        worker, which shares it with its neighbours)."""
        self._lanes.record_areas()

    def export_areas(self, box: tuple[float, float, float, float]) -> list[AreaState]:
        """The evidence about the common error that this engine's own users gave since
        the last export, for the areas whose centre lies in `box` (x0, y0, x1, y1 in the
        map's frame; default mode, once `record_areas` was called)."""
        return self._lanes.export_areas(box)

    def import_areas(
        self,
        source: str,
        states: list[AreaState],
        box: tuple[float, float, float, float] | None = None,
    ) -> int:
        """A neighbour's `export_areas`, those whose centre lies in `box` (None: all),
        folded into the areas here at their centres (`CommonError.take_shared`); how
        many were taken."""
        return self._lanes.import_areas(source, states, box)

    # -- answers ---------------------------------------------------------------------------

    def _answer(
        self,
        measurement: GpsMeasurement,
        segment: Segment,
        placed: Placement,
        track: Track,
        q: np.ndarray,
    ) -> _Answer:
        """The placed position with its 1-sigma across (from the lane filter) and along
        the road: along = sqrt(t' (P_track + P_b) t + s_rx^2). `q` is the corrected
        position the element was located under."""
        point = placed.point
        tangent = placed.tangent
        if tangent is None:
            s, _ = segment.frame(float(point[0]), float(point[1]))
            tangent = segment.tangent(s)
        # default mode: the receiver's own lasting error s_rx, which the track does not
        # see, lies along the road as much as across it
        lasting = self.config.sigma_receiver**2 if self.config.mode == "default" else 0.0
        # t' C t, C = P_track + P_b, in plain floats (numpy's calls on 2 x 2 arrays cost
        # more than the arithmetic)
        t_e, t_n = tangent.tolist()
        p = track.moments()[1]
        (b00, b01), (b10, b11) = placed.common_cov.tolist()
        c00, c01, c10, c11 = p[0][0] + b00, p[0][1] + b01, p[1][0] + b10, p[1][1] + b11
        along = math.sqrt((t_e * c00 + t_n * c10) * t_e + (t_e * c01 + t_n * c11) * t_n + lasting)
        lane = placed.lane
        probability = placed.probability
        if self.config.mode == "default":
            station = placed.station
            if station is None:
                station, _ = segment.frame(float(point[0]), float(point[1]))
            probability *= self._on_element(segment, station, along)
            # n' C n + s_rx^2 across the road, n = (t_n, -t_e)
            n_e, n_n = t_n, -t_e
            var_cross = (n_e * c00 + n_n * c10) * n_e + (n_e * c01 + n_n * c11) * n_n + lasting
            probability *= element_share(
                self.map,
                segment,
                q,
                var_cross,
                track.velocity,
                track.last_fix.speed,
                self.config.sigma_vel**2,
            )
            if self.config.calibrated:
                probability = calibrate(probability)
        return _Answer(
            measurement.timestamp,
            point,
            segment.id,
            lane,
            segment.lanes[lane].type,
            probability,
            placed.cross,
            along,
        )

    def _on_element(self, segment: Segment, s: float, along: float) -> float:
        """P(the user is on `segment` and not on an element that joins it), its station
        along the road ~ N(s, along^2) on an element of length L:

            P = 1 - [joined before] Phi(-s / along) - [joined after] Phi((s - L) / along)

        An answer names a road element as well as a lane: near where two elements meet,
        within the error along the road, it may be the neighbour's, and its probability
        says so. Where no element joins (a road's end), the user is on this one."""
        sigma = max(along, 1e-6)
        out = 1.0
        if self.map.predecessors(segment.id):
            out -= _phi(-s / sigma)
        if segment.successors:
            out -= _phi((s - segment.length) / sigma)
        return max(out, 0.0)

    def _off_map(self, measurement: GpsMeasurement, point: np.ndarray, cov: np.ndarray) -> _Answer:
        """Off every road element: the corrected fix, 1-sigma the largest axis of `cov`."""
        sigma = math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))
        return _Answer(measurement.timestamp, point, None, None, None, 0.0, sigma, sigma)

    def _answers(self, placed: list[_Answer | None]) -> list[CorrectedPosition | None]:
        """The answers in WGS 84, their points projected back all at once."""
        found = [a for a in placed if a is not None]
        if not found:
            return [None] * len(placed)
        projection = self.map.projection
        lonlat: list[tuple[float, float]]
        if len(found) <= _FEW:
            lonlat = [projection.to_wgs84(*a.point.tolist()) for a in found]
        else:
            xy = np.array([a.point for a in found], dtype=float)
            lonlat = projection.to_wgs84_array(xy[:, 0], xy[:, 1]).tolist()
        out: list[CorrectedPosition | None] = []
        k = 0
        for a in placed:
            if a is None:
                out.append(None)
                continue
            lon, lat = lonlat[k]
            k += 1
            out.append(
                CorrectedPosition(
                    timestamp=a.timestamp,
                    latitude=min(max(lat, -90.0), 90.0),
                    longitude=min(max(lon, -180.0), 180.0),
                    segment=a.segment,
                    lane=a.lane,
                    lane_type=a.lane_type,
                    probability=min(max(a.probability, 0.0), 1.0),
                    accuracy=math.hypot(a.cross, a.along),
                    accuracy_cross=a.cross,
                    accuracy_along=a.along,
                )
            )
        return out


@dataclass(frozen=True, slots=True)
class _Answer:
    """An answer in the map's frame, before its point goes back to WGS 84."""

    timestamp: int
    point: np.ndarray
    segment: str | None
    lane: int | None
    lane_type: LaneType | None
    probability: float
    cross: float
    along: float


def _phi(z: float) -> float:
    """The standard normal's distribution function."""
    return 0.5 * math.erfc(-z / math.sqrt(2.0))
