"""Default mode: the common GNSS error and every user's lane, estimated jointly.

Each fix is p_i = x_i + b + e_i: the true position, the error b that every receiver of
the area shares (`CommonError`, a grid posterior), and the receiver's own error. A user
on lane l of a road with unit normal n (to the right) and lane centres o_l lies at
lateral offset o_l, so its fix's offset d_i, measured with b = 0, is

    d_i = o_l + u + e,   u = n . b,   e ~ N(0, s^2),   s^2 = s_lane^2 + s_rx^2 + s_fix^2

with s_fix the fix's own 1-sigma (its stated accuracy, else `sigma_pos`) and s_rx the
receiver's own lasting error (bias, multipath; `sigma_receiver`). The evidence is the fix
itself, not the Kalman-filtered position: the filter holds the velocity to the receiver's
course, and a course need not show a lane change (a smoothed or map-matched course, a
phone's fused bearing), so the filtered position then creeps over to the new lane for
several seconds while the lanes' evidence says "old lane" at p 1.00; a fix's noise is its
own and shows the change the moment it is made. (The filtered position still places the
answer, and its velocity still announces lane changes, `transition`.) d_i is taken in the
element's frame at the fix itself, the same for every b; beyond the element's ends, where
that frame is only the straight extension of its last tangent, at the fix less the
estimate b^ of b, d_i = d(p_i - b^) + n . b^.

Which lane a user is on and what b is explain the same fixes: moving b by a lane width
and every user by one lane fits them as well. They are therefore estimated together,
as a Rao-Blackwellised point-mass filter: b on a grid, and for each user its lane
probabilities *given* b, alpha_i(u, l) = P(l_i = l | u = n . b, fixes of i), on a 1-D
grid of u. Given b the users' lanes are independent Markov chains, so one fix of user i
does, exactly:

    prediction   a(u, l) = sum_k alpha_i(u, k) T[k, l] * F[l]^(dt / tau)
                 (F[l] = D[l] S[l]: how well lane l fits the user's motion, its
                 direction D and its type's speeds S, see `transition`; counted once
                 per tau = motion_memory seconds, since motion is a lasting trait of a
                 user. T: lane changes at a base rate, announced by lateral motion
                 beyond its own noise, and never into a lane that does not fit)
    evidence     c(u)    = sum_l a(u, l) (eps + N~(d_i - u - o_l))
    common error log p(b) += log c(n . b)
    lanes        alpha_i(u, l) = a(u, l) (eps + N~(d_i - u - o_l)) / c(u)

    N~(r) = (1 - pi) N(r; 0, s^2) + pi N(r; 0, s^2 + s_mp^2): a receiver in multipath
    (a share pi of the time) is s_mp metres off, so one user's few fixes far from a lane
    centre make that lane less likely, not impossible

With `max_user_evidence` K set (off by default), the common error is not the plain sum of
every user's log c: user i's evidence so far, T_i(b) = sum_k log c_k(n_k . b), enters the
one-liar mixture log p(b) = sum_i T_i + log(1 + sum_j e^(-K - T_j)) (common_error), so a
participant that reports a false path moves b by at most sqrt(2 K) standard deviations
of what the others say.

The slide this prevents: when one user changes lanes, "b moved by a lane width" would
need every other user to have changed lanes at that moment too, which their own
alpha_j (sharp, since lanes persist) makes improbable; "one user changed lanes" costs
only that user's lane-change probability. eps keeps a fix off every lane (an outlier,
a car park) from ruling anything out.

A user's answer: its lane l* = argmax_l sum_u p(u) alpha_i(u, l), with p(u) the
posterior of u = n . b; the common error given that lane, b* = E[b | l*], removed from
its filtered position; and the lateral offset fused with the lane centre,

    d = (o_l* / s_lane^2 + d_m / s_m^2) / (1 / s_lane^2 + 1 / s_m^2),
    s_m^2 = n' (P_track + P_b*) n.

A user's table is tied to the normal it was built for. When the road turns under the
user, or it enters another road element, the table is carried over through the
posterior of b: alpha'(u', l') = E[alpha(n . b, l) M[l, l'] | n' . b = u'], with M the
lane each old lane leads to (the nearest lane at the same place).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from laas.config import EngineConfig
from laas.engine.common_error import CommonError, CommonErrorField
from laas.engine.handover import AreaState, HandoverError, LaneState
from laas.engine.jit import jit
from laas.engine.lanefilter import LaneFilter, Placement
from laas.engine.stacked import evidence, lanes_and_conditionals, pad
from laas.engine.tracking import MULTIPATH_SIGMA, Track
from laas.engine.transition import LaneTraits, prediction_of
from laas.map.hdmap import Segment

__all__ = ["CooperativeLaneFilter"]

_OFF_LANE = 1e-3  # eps, per metre: a fix that fits no lane (an outlier, a car park)
_TURN = math.radians(2.0)  # rebuild a user's table when its road has turned this much
_CARRY_MIX = 0.05  # share of a uniform lane belief mixed in when entering a new element
# A receiver spends a share of its time in multipath, its fix then metres off: in the
# development families 3-10 % of the time (up to 1/60-1/20 jumps per s, each lasting
# 1-9 s), jumps of 1-6 m; in cities it is the most common receiver fault.
_MULTIPATH_SHARE = 0.05  # the default of EngineConfig.track_multipath, which the tracks use
_HANDED_MASS = 1e-9  # a hand-over carries the lane table where p(u) > this * its peak
_HANDED_MARGIN = 10  # and this many u-cells (1 m) on either side
_FEW_FRAMES = 96  # a road element's users whose fixes take the frame one by one


@dataclass
class _Lanes:
    """One user's lane probabilities given the common error, in one road element."""

    segment: Segment
    area: CommonError
    normal: np.ndarray  # (2,) the road normal the table is conditioned on
    alpha: np.ndarray  # (U, L): P(lane | u = normal . b) on the area's u-grid


@dataclass(slots=True)
class _User:
    """One user's fix in a batch, prepared for its area's stacked step: its lane table
    (the kept one itself, updated in place on u-cells [lo, hi)), its fix's lateral
    offset d and the lane centres there, the prediction's transition and motion fit
    (raised to dt / tau), and its evidence's width s and weight w."""

    user: str
    track: Track
    segment: Segment
    area: CommonError
    normal: np.ndarray
    alpha: np.ndarray
    lo: int
    hi: int
    d: float
    offsets: np.ndarray
    transition: np.ndarray
    fit: np.ndarray
    sigma: float
    weight: float


class CooperativeLaneFilter(LaneFilter):
    """The default mode's lane filter (see the module docstring)."""

    def __init__(self, config: EngineConfig) -> None:
        super().__init__(config)
        self._errors = CommonErrorField(
            config.bias_area,
            config.bias_prior,
            config.bias_drift,
            config.bias_resolution,
            config.max_user_evidence,
            config.evidence_memory,
        )
        self._lanes: dict[str, _Lanes] = {}
        self._traits: dict[str, LaneTraits] = {}  # per road element

    def common_errors(self) -> list[CommonError]:
        return list(self._errors.areas)

    def correction(self, position: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        return self.corrections(position[None, :], t)[0]

    def leave(self, user: str) -> None:
        self._lanes.pop(user, None)

    def segment_groups(self) -> int:
        return len({lanes.segment.id for lanes in list(self._lanes.values())})

    def export_lanes(self, user: str) -> LaneState | None:
        kept = self._lanes.get(user)
        if kept is None:
            return None
        # only the u-cells where the posterior of u = n . b holds mass, and a few more
        # (the next worker's posterior, which pools the same evidence, holds about the
        # same): a few dozen rows, not the hundreds the window's margin keeps fresh
        mass = kept.area.u_moments(kept.normal)[:, 0]
        held = np.flatnonzero(mass > _HANDED_MASS * mass.max())
        lo = max(int(held[0]) - _HANDED_MARGIN, 0)
        hi = min(int(held[-1]) + 1 + _HANDED_MARGIN, kept.area.u.size)
        return LaneState(
            kept.segment.id, kept.normal.copy(), kept.area.u.size, lo, kept.alpha[lo:hi].copy()
        )

    def import_lanes(self, user: str, state: LaneState, segment: Segment, at: np.ndarray) -> None:
        """The table's u-cells as given; the others (which the old area's posterior held
        no mass at) the given cells' marginal lane probabilities."""
        area = self._errors.at(at)
        lanes = len(segment.lanes)
        if state.cells != area.u.size or state.alpha.shape[1] != lanes or not len(state.alpha):
            self._lanes.pop(user, None)  # another grid or another map: start afresh
            return
        given = np.maximum(state.alpha, 0.0)
        marginal = given.sum(axis=0)
        marginal = marginal / marginal.sum() if marginal.sum() > 0 else np.full(lanes, 1 / lanes)
        alpha = np.tile(marginal, (area.u.size, 1))
        alpha[state.lo : state.lo + len(given)] = given
        self._lanes[user] = _Lanes(segment, area, state.normal.copy(), alpha)

    def record_areas(self) -> None:
        self._errors.recording = True
        for area in self._errors.areas:
            area.record()

    def export_areas(self, box: tuple[float, float, float, float]) -> list[AreaState]:
        x0, y0, x1, y1 = box
        out = []
        for area in self._errors.areas:
            e, n = float(area.centre[0]), float(area.centre[1])
            if x0 <= e <= x1 and y0 <= n <= y1:
                found = area.shared()
                if found is not None:
                    out.append(AreaState((e, n), area.u.size, *found))
        return out

    def import_areas(
        self,
        source: str,
        states: list[AreaState],
        box: tuple[float, float, float, float] | None = None,
    ) -> int:
        taken = 0
        for state in states:
            e, n = state.centre
            if box is not None and not (box[0] <= e <= box[2] and box[1] <= n <= box[3]):
                continue
            area = self._errors.at(np.array(state.centre))
            if state.cells != area.u.size:
                continue  # another prior: not the same grid
            try:
                area.take_shared(state.window, state.log, state.t)
            except ValueError as exc:
                raise HandoverError(f"hand-over from {source}: {exc}") from None
            taken += 1
        self._errors.forget_places()
        return taken

    def corrections(self, positions: np.ndarray, t: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each area of the batch brought to the batch's time t once, then read."""
        self._errors.forget_places()
        areas = [self._errors.at(p) for p in positions]
        for area in {id(a): a for a in areas}.values():
            area.predict(t)
        return [(area.b, area.P) for area in areas]

    def step(self, user: str, track: Track, segment: Segment, t: float) -> Placement:
        return self.step_many([(user, track, segment, t)])[0]

    def step_many(self, work: Sequence[tuple[str, Track, Segment, float]]) -> list[Placement]:
        """One batch: every user's fix weighed against its area's common error as it
        stood before the batch, the evidence of the whole batch folded into each area in
        one measurement update, then every user placed on the posterior that all of it
        gives. Given b the users' lanes are independent, so the posterior of b is the same
        as fix by fix; what changes is that a user's answer also sees the evidence of the
        fixes that came with it. The users of a road element are prepared together
        (`_prepare`), those of an area stepped together (`_area_step`, `stacked`)."""
        by_segment: dict[str, list[int]] = {}
        for k, (_, _, segment, _) in enumerate(work):
            by_segment.setdefault(segment.id, []).append(k)
        users: list[_User] = [cast(_User, None)] * len(work)
        for ks in by_segment.values():
            for k, u in zip(ks, self._prepare([work[k] for k in ks]), strict=True):
                users[k] = u
        by_area: dict[int, list[int]] = {}
        for k, u in enumerate(users):
            by_area.setdefault(id(u.area), []).append(k)
        out: list[Placement] = [cast(Placement, None)] * len(work)
        for ks in by_area.values():
            for k, placement in zip(ks, self._area_step([users[k] for k in ks]), strict=True):
                out[k] = placement
        return out

    def _prepare(self, work: Sequence[tuple[str, Track, Segment, float]]) -> list[_User]:
        """What the users of one road element bring to the batch: their tables, the
        prediction's transition and motion fit, their fixes' offsets and evidence
        widths (module docstring). A road element's users in a batch are few (one, one
        at a time), so what is a number per user is worked out in plain floats, user by
        user; only what is an array over the lanes is stacked."""
        c = self.config
        segment = work[0][2]
        length = segment.length
        n = len(work)
        lasting = c.sigma_lane**2 + c.sigma_receiver**2 + _MULTIPATH_SHARE * MULTIPATH_SIGMA**2
        spread = c.sigma_lane**2 + c.sigma_receiver**2
        # The road's frame at the fix p (the fix itself, not the filtered position:
        # module docstring): there the offset measured with b = 0 is
        # d = d(p), for every b alike, so a curve, whose normal turns under the user,
        # makes the common error along the road observable. A fix is up to 15 m off,
        # though, and beyond the element's ends its frame is only the straight extension
        # of its last tangent: a user turning there would seem to sweep across the lanes.
        # There the frame is taken where the user is, at its fix less the area's current
        # estimate of the common error, q = p - b^, and linear about q, d = d(q) + n . b^.
        fixed = [(track.last_fix.e, track.last_fix.n) for _, track, _, _ in work]
        frames = (
            [segment.frame(e, n_) for e, n_ in fixed]
            if n <= _FEW_FRAMES
            else segment.frame_many(np.array(fixed)).tolist()
        )
        areas: list[CommonError] = []
        positions: list[np.ndarray] = []
        normals: list[np.ndarray] = []
        stations, ds, alongs, speeds, laterals, dts, memories, sigmas, weights = (
            [0.0] * n for _ in range(9)
        )
        for i, (_, track, _, _) in enumerate(work):
            position = track.position
            area = self._errors.at(position)
            s, d = frames[i]
            fix = track.last_fix
            beyond = s < 0.0 or s > length
            if beyond:
                b_e, b_n = area.b.tolist()
                s, d = segment.frame(fix.e - b_e, fix.n - b_n)
            t_e, t_n = segment.tangent_at(s)
            n_e, n_n = t_n, -t_e
            if beyond:
                d = d + (n_e * b_e + n_n * b_n)
            x, p = track.moments()
            v_e, v_n = x[2], x[3]
            # Lane changes: announced by lateral motion beyond its own noise (2 sigma),
            # n' Cov(v) n the velocity's variance across the road
            v_lat = v_e * n_e + v_n * n_n
            var = n_e * n_e * p[2][2] + 2.0 * n_e * n_n * p[2][3] + n_n * n_n * p[3][3]
            noise = 2.0 * math.sqrt(max(var, 0.0))
            dt = track.dt
            # Prediction: a(u, l) = sum_k alpha(u, k) T[k, l] F[l]^(dt / tau). Motion is
            # a lasting trait of the user, not news at every fix: it counts once per
            # tau = motion_memory seconds.
            memories[i] = min(1.0, dt / c.motion_memory)
            # Evidence of the fix: eps + N~(d - u - o_l) on the u-grid, with
            # s^2 = s_lane^2 + s_rx^2 + s_fix^2 (s_rx: the receiver's own lasting error).
            s_fix = c.sigma_pos if fix.accuracy is None else fix.accuracy
            sigmas[i] = math.sqrt(spread + s_fix**2)
            # A fix's error is partly its own (s_fix, independent from fix to fix) and
            # partly lasting: the user's place in its lane, the receiver's bias and its
            # multipath, s_last^2 = s_lane^2 + s_rx^2 + pi s_mp^2, which persist for about
            # evidence_interval seconds. Of n = evidence_interval / dt fixes that share a
            # lasting error, the mean has variance s_last^2 + s_fix^2 / n: they are worth
            # n_eff = n (s_last^2 + s_fix^2) / (n s_last^2 + s_fix^2) independent fixes,
            # so each counts as like^w with
            #     w = n_eff / n = (s_last^2 + s_fix^2) / (n s_last^2 + s_fix^2)  (at most 1):
            # a noisy receiver's fixes count nearly in full, a precise one's once per
            # interval.
            if dt <= 0.0:
                weights[i] = 1.0
            else:
                shared = c.evidence_interval / max(dt, 1e-9)
                weights[i] = min(1.0, (lasting + s_fix**2) / (shared * lasting + s_fix**2))
            areas.append(area)
            positions.append(position)
            normals.append(np.array((n_e, n_n)))
            stations[i], ds[i], dts[i] = s, d, dt
            alongs[i] = v_e * t_e + v_n * t_n
            speeds[i] = fix.speed
            laterals[i] = math.copysign(max(0.0, abs(v_lat) - noise), v_lat)
        traits = self._traits.get(segment.id)
        if traits is None:
            traits = self._traits[segment.id] = LaneTraits(segment.lanes)
        offsets = segment.lane_offsets_many(np.array(stations))
        # How well each lane fits the user's motion, F[l] = D[l] S[l] (its direction and
        # its type's speeds), and the lane changes, never into a lane that does not fit
        # the motion (its share stays in the lane): T[l, l'] = P(l -> l') F[l'] / max F
        # off the diagonal, the rest stays.
        fit_all, transition_all = prediction_of(
            traits,
            np.array(alongs),
            np.array(speeds),
            np.array(laterals),
            np.array(dts),
            np.array(memories),
            offsets,
            c.lane_change_rate,
            c.max_lane_change,
        )
        out = []
        for i, (user, track, _, _) in enumerate(work):
            area, normal = areas[i], normals[i]
            alpha = self._table(user, segment, area, normal, positions[i])
            self._lanes[user] = _Lanes(segment, area, normal, alpha)
            # Only the values of u = n . b that the posterior of b still holds, [lo, hi),
            # are worked on (`CommonError.span`, with a margin): the update of b and the
            # answer read nothing else, and the margin keeps fresh the cells the posterior
            # could grow into before this user's next fix. The rest of the table stays.
            lo, hi = area.span(normal)
            out.append(
                _User(
                    user,
                    track,
                    segment,
                    area,
                    normal,
                    alpha,
                    lo,
                    hi,
                    ds[i],
                    offsets[i],
                    transition_all[i],
                    fit_all[i],
                    sigmas[i],
                    weights[i],
                )
            )
        return out

    def _area_step(self, users: list[_User]) -> list[Placement]:
        """The module docstring's prediction, evidence, update of b and answers for the
        users of one area, stacked (`stacked`)."""
        area = users[0].area
        h = max(u.hi - u.lo for u in users)
        lanes = max(len(u.offsets) for u in users)
        lo = np.array([u.lo for u in users])
        alpha, log_c = evidence(
            pad([u.alpha[u.lo : u.hi] for u in users], (h, lanes)),
            pad([u.transition for u in users], (lanes, lanes)),
            pad([u.fit for u in users], (lanes,)),
            np.array([u.d for u in users]),
            area.u.values,
            lo,
            pad([u.offsets for u in users], (lanes,)),
            np.array([u.sigma for u in users]),
            np.array([u.weight for u in users]),
            _OFF_LANE,
            _MULTIPATH_SHARE,
            MULTIPATH_SIGMA,
        )
        for k, u in enumerate(users):
            u.alpha[u.lo : u.hi] = alpha[k, : u.hi - u.lo, : len(u.offsets)]
        normals = np.array([u.normal for u in users])
        # The common error: log p(b) += log c(n . b); with K = max_user_evidence, the
        # user's whole part of the one-liar mixture renewed instead (common_error).
        area.update_stacked(normals, log_c, lo, [u.user for u in users])

        # The lane: the marginal over u; the common error given that lane, from the
        # posterior's u-moments along each user's normal (once per distinct normal).
        groups: dict[tuple[float, float], tuple[int, np.ndarray]] = {}
        group = np.empty(len(users), dtype=np.intp)
        for k, u in enumerate(users):
            key = (float(u.normal[0]), float(u.normal[1]))
            group[k] = groups.setdefault(key, (len(groups), u.normal))[0]
        moments = np.array([area.u_moments(normal) for _, normal in groups.values()])
        marginal, lane, b, cov, held = lanes_and_conditionals(
            moments, group, lo, alpha, area.cell_var
        )
        if not held.all():
            b[~held], cov[~held] = area.b, area.P
        by_segment: dict[str, list[int]] = {}
        for k, u in enumerate(users):
            by_segment.setdefault(u.segment.id, []).append(k)
        out: list[Placement] = [cast(Placement, None)] * len(users)
        for ks in by_segment.values():
            rows = np.array(ks)
            width = len(users[ks[0]].offsets)
            placed = self._place(
                [users[k] for k in ks], marginal[rows, :width], lane[rows], b[rows], cov[rows]
            )
            for k, placement in zip(ks, placed, strict=True):
                out[k] = placement
        return out

    def _place(
        self,
        users: list[_User],
        marginal: np.ndarray,
        lane: np.ndarray,
        b: np.ndarray,
        cov: np.ndarray,
    ) -> list[Placement]:
        """Place users of one road element on their lanes: each filtered position, b
        removed, fused with the lane centre,
            d = (o_l* / s_lane^2 + d_m / s_m^2) / (1 / s_lane^2 + 1 / s_m^2),
            s_m^2 = n' (P_track + P_b*) n."""
        c = self.config
        segment = users[0].segment
        w_lane = 1.0 / c.sigma_lane**2
        covs = cov.tolist()
        stations, d_now, w_ms = [], [], []
        tangent_list: list[tuple[float, float]] = []
        for k, u in enumerate(users):
            x, p = u.track.moments()
            pe, pn = x[0], x[1]
            be, bn = b[k].tolist()
            s_now, d = segment.frame(pe - be, pn - bn)
            t_e, t_n = segment.tangent_at(s_now)
            n_e, n_n = t_n, -t_e
            (c00, c01), (_, c11) = covs[k]
            # s_m^2 = n' (P_track + P_b*) n
            var_m = (
                n_e * n_e * (p[0][0] + c00)
                + 2.0 * n_e * n_n * (p[0][1] + c01)
                + n_n * n_n * (p[1][1] + c11)
            )
            stations.append(s_now)
            d_now.append(d)
            w_ms.append(1.0 / max(var_m, 1e-6))
            tangent_list.append((t_e, t_n))
        offsets = segment.lane_offsets_many(np.array(stations))
        rows = np.arange(len(users))
        o = offsets[rows, lane]
        # Across the road the position is the posterior mean over lanes: on lane l the
        # user lies at its centre fused with the measurement as on l*, fused_l = fused +
        # o_l - o_l*, so  d = fused + sum_l P(l) (o_l - o_l*).  Sure of its lane, that is
        # the lane's own point; unsure, it stays between the lanes it cannot tell apart
        # rather than snap onto the wrong one. Its 1-sigma is the mixture's about it,
        # s_x^2 = 1 / (w_lane + w_m) + sum_l P(l) (o_l - o_bar)^2.
        shift = offsets - o[:, None]
        mean_shift = (marginal * shift).sum(axis=1)
        spread = (marginal * (shift - mean_shift[:, None]) ** 2).sum(axis=1)
        lanes = lane.tolist()
        points, crosses = [], []
        for k, (o_k, m_k, v_k) in enumerate(
            zip(o.tolist(), mean_shift.tolist(), spread.tolist(), strict=True)
        ):
            w_m = w_ms[k]
            fused = (w_lane * o_k + w_m * d_now[k]) / (w_lane + w_m)
            points.append(segment.point(stations[k], fused + m_k))
            crosses.append(math.sqrt(1.0 / (w_lane + w_m) + v_k))
        point, tangent = np.array(points), np.array(tangent_list)
        p_lane = marginal[rows, lane].tolist()
        return [
            Placement(lanes[k], p_lane[k], point[k], cov[k], crosses[k], tangent[k], stations[k])
            for k in range(len(users))
        ]

    def _table(
        self,
        user: str,
        segment: Segment,
        area: CommonError,
        normal: np.ndarray,
        position: np.ndarray,
    ) -> np.ndarray:
        """The user's alpha for `segment` and `normal`: kept, carried over, or new."""
        lanes = len(segment.lanes)
        old = self._lanes.get(user)
        if old is None or old.area is not area:
            return np.full((area.u.size, lanes), 1.0 / lanes)
        alpha = old.alpha
        if old.segment is not segment:
            alpha = alpha @ _lane_map(old.segment, segment, position - area.b)
            alpha = (1.0 - _CARRY_MIX) * alpha + _CARRY_MIX / lanes
        elif float(old.normal @ normal) > math.cos(_TURN):
            return alpha
        return _reproject(area, alpha, old.normal, normal)


def _lane_map(old: Segment, new: Segment, q: np.ndarray) -> np.ndarray:
    """M[l, l'] = 1 where old lane l, at the station of point q, lies nearest new lane l'."""
    s_old, _ = old.frame(float(q[0]), float(q[1]))
    s_old = min(max(s_old, 0.0), old.length)
    m = np.zeros((len(old.lanes), len(new.lanes)))
    for lane, o in enumerate(old.lane_offsets(s_old)):
        x, y = old.point(s_old, float(o))
        s_new, d_new = new.frame(x, y)
        m[lane, int(np.argmin(np.abs(new.lane_offsets(s_new) - d_new)))] = 1.0
    return m


def _reproject(
    area: CommonError, alpha: np.ndarray, n_old: np.ndarray, n_new: np.ndarray
) -> np.ndarray:
    """alpha'(u', l) = E[alpha(n_old . b, l) | n_new . b = u'] under the posterior of b;
    where no mass lies, the user's marginal lane probabilities."""
    w, idx_old = area.weights_and_cells(n_old)
    _, idx_new = area.weights_and_cells(n_new)
    # only the u'-cells [lo, hi) that n_new . b takes over the window get any mass
    lo, hi = area.taken(n_new)
    num, den = _carry(alpha, w, idx_old, idx_new, lo, hi)
    marginal = num.sum(axis=0)
    marginal = marginal / marginal.sum()
    out = np.tile(marginal, (area.u.size, 1))
    held = den > 1e-12
    out[lo:hi][held] = num[held] / den[held, None]
    return out


@jit
def _carry(
    alpha: np.ndarray,
    w: np.ndarray,
    idx_old: np.ndarray,
    idx_new: np.ndarray,
    lo: int,
    hi: int,
) -> tuple[np.ndarray, np.ndarray]:
    """`_reproject`'s sums over the window's cells b, by the u'-cell k = n_new . b
    (from `lo`): num[k, l] = sum p(b) alpha(n_old . b, l), den[k] = sum p(b)."""
    lanes = alpha.shape[1]
    num = np.zeros((hi - lo, lanes))
    den = np.zeros(hi - lo)
    ni, nj = w.shape
    for i in range(ni):
        for j in range(nj):
            p = w[i, j]
            k = idx_new[i, j] - lo
            row = idx_old[i, j]
            den[k] += p
            for lane in range(lanes):
                num[k, lane] += p * alpha[row, lane]
    return num, den


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a . b of (g, 2) arrays."""
    out: np.ndarray = a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]
    return out


def _quad(n: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Row-wise n' C n of (g, 2) vectors and (g, 2, 2) covariances."""
    out: np.ndarray = (
        n[:, 0] * n[:, 0] * cov[:, 0, 0]
        + 2.0 * n[:, 0] * n[:, 1] * cov[:, 0, 1]
        + n[:, 1] * n[:, 1] * cov[:, 1, 1]
    )
    return out
