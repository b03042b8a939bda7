"""The GNSS error that nearby receivers share: a grid posterior per area.

Receivers close together see almost the same satellite and atmosphere errors, so every
fix is p_i = x_i + b + e_i with one common error b per area, a slowly drifting 2-D
random walk (b_k = b_{k-1} + w, w ~ N(0, q dt I)).

A user on a road observes b only across it: its evidence is a function of u = n . b,
with n the road's unit normal at the user. Such evidence can be many-peaked (one peak
per lane the user might be on), so the posterior of b is kept on a grid (a point-mass
filter: the discrete Bayes filter of the paper, applied to the common error):

    log p(b) <- log p(b) + log c(n . b)      update: c is given on a 1-D grid of u
    p(b)     <- p(b) * blur(q dt)             prediction: the random walk

Across one straight road the posterior is a ridge along the road: nothing is corrected
along it until some user drives a road of another direction, and the covariance of b
says so (and with it every answer's along-road accuracy). `UGrid` is the 1-D grid of
u = n . b shared by every direction n, and `u_moments` gives the posterior of u
(and its moments of b) per cell of that grid.

Evidence fades (`memory` tau, `EngineConfig.evidence_memory`). A receiver's own error
is lasting: a bias of up to a metre across the road stays with it for minutes. Each of its
fixes is counted as news, so a bias that happens to match the difference of two lane
widths makes the wrong lanes ever more likely the longer the user stays: the group
lock-in (issue 22; on dev edge/20 one cyclist's receiver, 0.83 m off, matched the 1.04 m
between the shifts of the bicycle and the driving lanes, and the first 20 s placed
everyone one lane over at 0.9 and more, where the later users, who fit the true lanes,
could not undo it; `scripts/lock_in.py`). Old evidence therefore fades, before each prediction,

    log p(b) <- lam log p(b) + (1 - lam) log p0(b),   lam = e^(-dt / tau)

(p0 the prior): evidence of age a counts with weight e^(-a / tau), and a lasting error
counts about tau / evidence_interval times, not without bound. tau is 30 s: ten
evidence intervals, long enough for a user on a curve or a turn to carry the along-road
error into the next half minute, short enough that what the first users' errors said is
re-judged by those who come after.

A participant that lies (issue 11). Pooled in full, the evidence of one user who
reports a false path (or whose receiver is broken) pulls b towards its false value by
about its share of all the evidence, however far off it is. The robust posterior (on
when `cap` K is given) admits that one participant of the area may not be honest: with
prior probability pi each, user j's fixes say nothing about b, and at most one such
user at a time:

    p(fixes | b) = (1 - N pi) prod_i L_i(b) + sum_j pi L0_j prod_{i != j} L_i(b)

with L_i(b) = prod_k c_k(n_k . b) user i's own likelihood (c_k its k-th fix's evidence,
lanes summed out: `update`'s log_c). Setting pi L0_j = (1 - N pi) e^-K max_b L_j(b),
the floor K nats below the user's own best,

    log p(b) = [log p0(b) + sum_i log L_i(b)] + log(1 + S(b)),
    S(b) = sum_j exp(-K - T_j(b)),   T_j = log L_j - max_b log L_j   (max over the window)

The bracket is the pooled posterior of the model without the cap; log(1 + S) forgives.
User j's part, T_j + log(1 + R + e^(-K - T_j)) = log((1 + R) e^T_j + e^-K) with
R = sum_{i != j} e^(-K - T_i), lies in [-K, log(1 + R)]. Where the others agree with each
other (R ~ N e^-K), whatever j reports moves log p(b) by at most K (+ log(1 + R)) between
any two values of b, so the posterior's maximum moves by at most

    |b_L - b_H|_{P^-1} <= sqrt(2 (K + log(1 + R)))  ~  sqrt(2 K)

standard deviations of the others' estimate P (for it, f(b) = -d^2 / 2 + C(b), C in
[-K, 0], has f(b_max) >= f(b_H) >= -K, so d^2 / 2 <= K). An honest user near the
consensus (T_i well above -K there) counts as before; a second user far off where the
first is forgiven counts in full, so a value of b that needs two liars keeps no mass and
the window shrinks as without the cap. Each user keeps its own record T_j (the sum of its
fixes' log c, normalised), renewed at each of its fixes, so a liar's earlier fixes are
forgiven with its later ones. One fix of user j does

    T_j      <- T_j + log c_k(n_k . b) - max(.)
    S        += exp(-K - T_j,new) - exp(-K - T_j,old)          (kept as log S)
    log p(b) += log c_k(n_k . b) + log(1 + S_new) - log(1 + S_old)

and the prediction blurs log p(b) as a whole, as without the cap (the records are not
blurred: the walk is the posterior's; blurring each user's part on its own would let the
estimate follow a drifting b too slowly). A user silent for `_EVIDENCE_KEEP` s has left:
its term leaves S and the forgiveness it gave stays in log p as it stands. A participant
can be doubted only against another's evidence: the first user of an area counts in
full (S = 0) until a second joins. Each record keeps T on a frame of grid cells that
only grows; T is the user's evidence as it went into log p, so where the window never
held a cell at the user's fixes T = 0 (log p there holds none of it to forgive), and S
stays the sum over the records cell by cell.

Regional workers (`laas.engine.handover`). Each fix goes to one worker, so two workers
that serve one area see disjoint users, and the posterior one worker for all would hold
is the prior times both workers' evidence. An area that `record`s keeps its own users'
evidence E = sum_k log c_k(n_k . b) since it last gave it away (`shared`); the other
worker adds it to its own log p (`take_shared`), and what it takes it never shares on,
so no evidence echoes back and none counts twice (tests/test_handover.py holds two
sharing areas to one fed everything). With `memory`, E fades as log p does, so what a
neighbour takes is the evidence as it counts here by then.

With two users and nobody else, either may be the liar: the posterior then leans to one
of them where the Gaussian pool split the difference. The bound is per participant: a
liar with several identities (or one that is silent for `_EVIDENCE_KEEP` s and returns)
is several participants.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from laas.engine.jit import jit

__all__ = ["CommonError", "CommonErrorField", "UGrid"]

_U_STEP = 0.1  # m: cell of the 1-D grid of u = n . b, well below any lane-evidence width
# u-cells beyond the window's span that a user's fix still works on (5 m). A cell outside
# the span is read again only once the window grows over it: by one 0.3 m cell per blur of
# the walk (about every 4 s at the default drift), or as a user's road turns by up to 2
# degrees under a kept table (1.2 m at the window's widest). Kept 5 m fresh, no stale cell
# enters before the user's next fix; the recorded answers agree to 1e-12 m with it, and
# not with 2 m (tests/reference_answers).
_SPAN_MARGIN = 50
_CELL_WINDOWS = 4  # windows whose u-cells per normal are kept (`CommonError._cells`)
_CELL_NORMALS = 256  # normals kept per window
_DROP = 40.0  # cells this far below the maximum in log p hold no mass worth keeping
_BLUR_STEP = 0.05  # blur once the walk's variance since the last blur is 2 * this * res^2
_EVIDENCE_KEEP = 60.0  # s: a user silent this long has left; its evidence joins `base`
_RESUM = 256  # every this many robust updates S is summed afresh from the records
_HALF = math.log(2.0)


class UGrid:
    """A 1-D grid of u = n . b: `size` cells of width `step` from `lo` (cell centres)."""

    def __init__(self, half: float, step: float) -> None:
        self.step = step
        self.size = math.ceil(2.0 * half / step) + 1
        self.lo = -half
        self.values = self.lo + step * np.arange(self.size)


class CommonError:
    """The common error of one area: a grid posterior with mean b (2,) and covariance P.

    Only a window of the grid holds mass worth keeping (log p > -`_DROP` below the
    maximum); updates touch only that window, which shrinks as evidence comes in and
    grows by the random-walk blur, so a settled estimate costs little per fix.
    """

    def __init__(
        self,
        centre: np.ndarray,
        prior_sigma: float,
        drift: float,
        resolution: float,
        cap: float | None = None,
        memory: float | None = None,
    ) -> None:
        self.centre = centre.copy()
        self.centre_xy: tuple[float, float] = (float(centre[0]), float(centre[1]))
        half = 3.5 * prior_sigma  # wide enough that no ridge of likely values is clipped
        self._res = resolution
        self._axis = np.arange(-half, half + resolution / 2, resolution)
        n = self._axis.size
        sq = self._axis**2
        self._log = -0.5 * (sq[:, None] + sq[None, :]) / prior_sigma**2  # (n, n): [east, north]
        # a robust area keeps all its evidence: its records judge each participant on
        # all it said, and log(1 + S) holds only beside the whole of it
        self.memory = memory if cap is None else None
        self._prior_log = self._log.copy() if self.memory is not None else None
        self._win = (0, n, 0, n)
        self.u = UGrid(half * math.sqrt(2.0), _U_STEP)
        # the u-grid cells of n . b over the window, per normal n, for the last few
        # windows: a batch's blur grows the window by a cell and its update shrinks it
        # again, so a settled area goes back and forth between the same few windows
        self._cells_by_win: dict[
            tuple[int, int, int, int],
            dict[tuple[float, float], tuple[np.ndarray, tuple[int, int]]],
        ] = {}
        self._drift_var = drift**2
        self._pending_var = 0.0
        self.t: float | None = None
        self.updates = 0
        self.b = np.zeros(2)
        self.P = np.eye(2) * prior_sigma**2
        # the robust posterior (module docstring): the records of `_users`, S and
        # log(1 + S) on the grid (kept outside the window too, like the records)
        self.cap = cap
        self._users: dict[str, _UserEvidence] = {}
        self._ls = np.full_like(self._log, -np.inf) if cap is not None else self._log  # log S
        self._l = np.zeros_like(self._log) if cap is not None else self._log  # log(1 + S)
        self._robust_updates = 0
        self._quorum = False  # the records are counted in S (two users or more)
        # the own users' evidence since the last `shared`, kept once `record` is called
        self._own: np.ndarray | None = None
        self._own_any = False
        self._moments()

    def _moments(self) -> None:
        """The window's weights p(b), b = E[b] and P = Cov[b] (`_window_moments`)."""
        i0, i1, j0, j1 = self._win
        # exp in numpy's call, which vectorises it (a window holds hundreds of cells)
        self._w = np.exp(self._log[i0:i1, j0:j1])
        stats = _window_moments(self._w, self._axis[i0:i1], self._axis[j0:j1])
        me, mn, cee, cen, cnn = stats
        own = self._res**2 / 12.0
        self.b = np.array([me, mn])
        self.P = np.array([[cee + own, cen], [cen, cnn + own]])

    def _shrink(self) -> None:
        """Drop the window's edges that hold no mass; keep two cells of margin."""
        i0, i1, j0, j1 = self._win
        r0, r1, c0, c1 = _held(self._log, i0, i1, j0, j1, -_DROP)
        n = self._axis.size
        new = (max(0, i0 + r0 - 2), min(n, i0 + r1 + 3), max(0, j0 + c0 - 2), min(n, j0 + c1 + 3))
        if new != self._win:
            inside = (slice(new[0], new[1]), slice(new[2], new[3]))
            if self.cap is None:
                # Outside the window every cell already holds -2 _DROP (each change of
                # log p outside it also grows the window over it), so only the old
                # window's cells are reset, not the whole grid: a grid's worth of
                # writes a batch saved. (The robust posterior's S changes log p outside
                # the window, `_add_e`: there the grid is made afresh.)
                kept = self._log[inside].copy()
                self._log[i0:i1, j0:j1] = -2.0 * _DROP
                self._log[inside] = kept
            else:
                outside = np.full_like(self._log, -2.0 * _DROP)
                outside[inside] = self._log[inside]
                self._log = outside
            self._win = new

    def predict(self, t: float) -> None:
        """Fade old evidence (`memory`), then blur the grid by the random walk
        accumulated since the last call; the moments once, after both."""
        if self.t is not None and t > self.t:
            moved = False
            if self._prior_log is not None:
                self._fade(t - self.t)
                moved = True
            self._pending_var += self._drift_var * (t - self.t)
            a = self._pending_var / (2.0 * self._res**2)  # a walk of +-res steps, prob a each
            if a >= _BLUR_STEP:
                a = min(a, 0.25)
                self._pending_var -= 2.0 * a * self._res**2
                n = self._axis.size
                i0, i1, j0, j1 = self._win
                i0, i1, j0, j1 = max(0, i0 - 1), min(n, i1 + 1), max(0, j0 - 1), min(n, j1 + 1)
                p = _walk(np.exp(self._log[i0:i1, j0:j1]), a)
                self._log[i0:i1, j0:j1] = np.log(np.maximum(p, 1e-300))
                self._win = (i0, i1, j0, j1)
                moved = True
            if moved:
                self._moments()
        if self.t is None or t > self.t:
            self.t = t

    def _fade(self, dt: float) -> None:
        """Evidence fades with age: log p <- lam log p + (1 - lam) log p0, lam = e^(-dt / tau).
        Outside the window log p is kept only as a floor, 2 `_DROP` below the maximum; the
        floor fades like the rest, so cells the window dropped come back as the evidence
        that dropped them fades (a little sooner than their own log p would: the side of
        doubt). A floor cell ends at most -2 _DROP lam below the window's new maximum M
        (log p0 <= 0), so while M + 2 _DROP lam >= _DROP none comes back, and the window
        alone is faded (the per-batch case: lam = 0.97 at dt = 1 s); else the whole grid."""
        assert self._prior_log is not None and self.memory is not None
        lam = math.exp(-dt / self.memory)
        if self._own is not None:
            self._own *= lam  # what is shared has faded as it has here
        i0, i1, j0, j1 = self._win
        n = self._axis.size
        whole = self._win == (0, n, 0, n)
        if not _fade_window(self._log, self._prior_log, i0, i1, j0, j1, lam, _DROP, whole):
            outside = np.ones_like(self._log, dtype=bool)
            outside[i0:i1, j0:j1] = False
            self._log[outside] = -2.0 * _DROP * lam + (1.0 - lam) * self._prior_log[outside]
            self._log -= self._log.max()
            self._win = (0, n, 0, n)
        self._shrink()

    def weights_and_cells(self, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(window weights p(b), the u-grid cell of n . b for each window cell)."""
        return self._w, self._cells(normal)

    def _cells(self, normal: np.ndarray) -> np.ndarray:
        """The u-grid cell of n . b for each window cell (kept per n while the window is)."""
        return self._cells_and_span(normal)[0]

    def _cells_and_span(self, normal: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        """`_cells`, and the cells [lo, hi) they take."""
        cells_of = self._cells_by_win.get(self._win)
        if cells_of is None:
            if len(self._cells_by_win) >= _CELL_WINDOWS:
                del self._cells_by_win[next(iter(self._cells_by_win))]  # the oldest
            cells_of = self._cells_by_win[self._win] = {}
        elif len(cells_of) >= _CELL_NORMALS:  # users on curves: a normal each
            cells_of.clear()
        key = (float(normal[0]), float(normal[1]))
        found = cells_of.get(key)
        if found is None:
            i0, i1, j0, j1 = self._win
            idx, lo, hi = _u_cells(
                self._axis[i0:i1],
                self._axis[j0:j1],
                key[0],
                key[1],
                self.u.lo,
                self.u.step,
                self.u.size,
            )
            found = cells_of[key] = (idx, (lo, hi))
        return found

    def u_moments(self, normal: np.ndarray) -> np.ndarray:
        """(U, 6): for each u-cell k of n . b, the sums over the window's cells b with
        n . b in k of p(b) times 1, b_e, b_n, b_e^2, b_e b_n, b_n^2. A weight g(u) on the
        u-grid then has its moments of b in O(U):  E_g[b] = sum_k g_k M1_k / sum_k g_k M0_k,
        and the same for the second moments."""
        i0, i1, j0, j1 = self._win
        return _u_moments(
            self._w, self._axis[i0:i1], self._axis[j0:j1], self._cells(normal), self.u.size
        )

    @property
    def cell_var(self) -> float:
        """A grid cell's own variance of b per axis, res^2 / 12."""
        return self._res**2 / 12.0

    def taken(self, normal: np.ndarray) -> tuple[int, int]:
        """The u-grid cells [lo, hi) that n . b takes over the window, without `span`'s
        margin."""
        return self._cells_and_span(normal)[1]

    def span(self, normal: np.ndarray) -> tuple[int, int]:
        """The u-grid cells [lo, hi) that n . b takes over the window: the only values of
        u = n . b whose evidence `update` reads, and where `u_moments` has mass."""
        lo, hi = self._cells_and_span(normal)[1]
        return max(lo - _SPAN_MARGIN, 0), min(hi + _SPAN_MARGIN, self.u.size)

    def update(
        self, normal: np.ndarray, log_c: np.ndarray, user: str | None = None, lo: int = 0
    ) -> None:
        """Fold in evidence about u = n . b: log p(b) += log_c[cell of n . b - lo] (log_c
        given on the u-grid from cell `lo`, covering at least `span(normal)`); in a robust
        area, as `user`'s renewed part of the one-liar mixture (module docstring)."""
        self.update_many([(normal, log_c, user, lo)])

    def update_many(
        self, evidence: Sequence[tuple[np.ndarray, np.ndarray, str | None, int]]
    ) -> None:
        """`update` with the evidence of a batch of fixes, (normal, log_c, user, lo) each,
        as one measurement update: log p(b) += sum_k log_c_k[cell of n_k . b - lo_k],
        then the window shrunk and the moments taken once."""
        i0, i1, j0, j1 = self._win
        sub = self._log[i0:i1, j0:j1]
        for normal, log_c, user, lo in evidence:
            cells = self._cells(normal) - lo if lo else self._cells(normal)
            term = log_c[cells]
            self._recorded(term)
            if self.cap is not None and user is not None:
                self._robust(user, term)
                sub = self._log[i0:i1, j0:j1]
            else:
                sub += term
        self._settle(sub, len(evidence))

    def update_stacked(
        self, normals: np.ndarray, log_c: np.ndarray, lo: np.ndarray, users: Sequence[str]
    ) -> None:
        """`update_many` for stacked evidence: log_c (n, H), user k's from u-cell lo[k]."""
        if self.cap is not None:
            self.update_many([(normals[k], log_c[k], users[k], int(lo[k])) for k in range(len(lo))])
            return
        # users along one normal read the same cells (and from the same lo: the span
        # depends on the normal and the window only), so their log c add up first
        i0, i1, j0, j1 = self._win
        sub = self._log[i0:i1, j0:j1]
        groups: dict[tuple[float, float], tuple[int, np.ndarray]] = {}
        for k, normal in enumerate(normals):
            key = (float(normal[0]), float(normal[1]))
            found = groups.get(key)
            if found is None:
                groups[key] = (k, log_c[k].copy())
            else:
                found[1][:] += log_c[k]
        for k, summed in groups.values():
            term = summed[self._cells(normals[k]) - lo[k]]
            self._recorded(term)
            sub += term
        self._settle(sub, len(lo))

    def _settle(self, sub: np.ndarray, count: int) -> None:
        """After an update of the window `sub` (a view of log p): normalised, shrunk,
        its moments taken."""
        sub -= sub.max()
        self.updates += count
        self._shrink()
        self._moments()

    def _robust(self, user: str, evidence: np.ndarray) -> None:
        """One fix of `user` in the robust posterior: the pooled update, and the change of
        log(1 + S) as the user's record T is renewed."""
        assert self.cap is not None
        k = self.cap
        win = self._win
        i0, i1, j0, j1 = win
        t = self.t if self.t is not None else 0.0
        self._robust_updates += 1
        if self._robust_updates % 16 == 0:
            self._leave_silent(t)
        record = self._users.get(user)
        if record is None:
            record = self._users[user] = _UserEvidence(win, t, counted=self._quorum)
            if record.counted:  # T = 0: e = e^-K on its frame
                at = (slice(i0, i1), slice(j0, j1))
                self._add_e(at, np.ones(record.log.shape, dtype=bool), self._log_e(record))
        record.t = t
        self._cover(record, win)
        mine = record.cells(win)
        old_t = record.log[mine].astype(np.float64)
        own = old_t + evidence
        own -= own.max()
        new_t = own.astype(np.float32)
        record.log[mine] = new_t
        sub = self._log[i0:i1, j0:j1] + evidence
        if record.counted:
            # log S' = log(S - e_old + e_new) = logaddexp(log S + log(1 - r), log e_new),
            # r = e_old / S <= 1; where e_old was most of S (r > 1/2, digits would be lost)
            # log S is summed afresh from the records
            ls = self._ls[i0:i1, j0:j1]
            back = new_t.astype(np.float64)
            r = np.minimum(np.exp(-k - old_t - ls), 1.0)
            lost = (r > 0.5) & (back - old_t > _HALF)  # e_new < e_old / 2
            with np.errstate(divide="ignore"):  # r = 1: the user was all of S
                fresh = np.logaddexp(ls + np.log1p(-r), -k - back)
            if lost.any():
                fresh[lost] = self._sum(win, lost)
            ls[:] = fresh
            one = self._l[i0:i1, j0:j1]
            sub -= one
            one[:] = np.logaddexp(0.0, fresh)
            sub += one
        if not self._quorum and len(self._users) >= 2:
            self._log[i0:i1, j0:j1] = sub
            self._count()
            sub = self._log[i0:i1, j0:j1]
        if self._robust_updates % _RESUM == 0:
            self._log[i0:i1, j0:j1] = sub
            self._resum()
            sub = self._log[i0:i1, j0:j1]
        self._log[i0:i1, j0:j1] = sub - sub.max()

    def _log_e(self, record: _UserEvidence, cells: tuple[slice, slice] | None = None) -> np.ndarray:
        """log e = -K - T of a record (float64), on its frame or some of its cells."""
        assert self.cap is not None
        own = record.log if cells is None else record.log[cells]
        out: np.ndarray = -self.cap - own.astype(np.float64)
        return out

    def _sum(self, win: tuple[int, int, int, int], where: np.ndarray) -> np.ndarray:
        """log S at the cells `where` of window `win`, summed afresh from the records."""
        total = np.full(int(where.sum()), -np.inf)
        for record in self._users.values():
            if record.counted:
                self._cover(record, win)
                total = np.logaddexp(total, self._log_e(record, record.cells(win))[where])
        return total

    def _count(self) -> None:
        """Start counting the records in S. A participant's fixes can be doubted only
        against someone else's: the first user of an area counts in full (forgiving it
        would only mix the prior into its own answers) until a second one joins; from then
        on every user is counted, the area's earlier evidence standing for the others."""
        self._quorum = True
        for record in self._users.values():
            if not record.counted:
                f = record.frame
                at = (slice(f[0], f[1]), slice(f[2], f[3]))
                self._add_e(at, np.ones(record.log.shape, dtype=bool), self._log_e(record))
                record.counted = True

    def _cover(self, record: _UserEvidence, win: tuple[int, int, int, int]) -> None:
        """Grow the record's frame to hold `win`. The new cells were outside the window
        at every fix of the user, so none of its evidence is in log p there: T = 0, and
        their e joins S (so S stays the sum over the records)."""
        f = record.frame
        if f[0] <= win[0] and win[1] <= f[1] and f[2] <= win[2] and win[3] <= f[3]:
            return
        new = (min(f[0], win[0]), max(f[1], win[1]), min(f[2], win[2]), max(f[3], win[3]))
        grown = np.zeros((new[1] - new[0], new[3] - new[2]), dtype=np.float32)
        old = (slice(f[0] - new[0], f[1] - new[0]), slice(f[2] - new[2], f[3] - new[2]))
        grown[old] = record.log
        fresh = np.ones(grown.shape, dtype=bool)
        fresh[old] = False
        record.log, record.frame = grown, new
        if record.counted:
            at = (slice(new[0], new[1]), slice(new[2], new[3]))
            self._add_e(at, fresh, self._log_e(record))

    def _add_e(self, at: tuple[slice, slice], where: np.ndarray, log_e: np.ndarray) -> None:
        """S at the cells `where` of block `at` gains the e there (log e, an array over
        the block), log(1 + S) with it, and log p its change (outside the window log p
        holds no mass: it changes there only as the window's edge grows into it)."""
        ls, one, log = self._ls[at], self._l[at], self._log[at]
        ls[where] = np.logaddexp(ls[where], log_e[where])
        fresh = np.logaddexp(0.0, ls)
        i0, i1, j0, j1 = self._win
        r0, c0 = at[0].start, at[1].start
        inside = np.zeros_like(where)
        inside[max(i0 - r0, 0) : max(i1 - r0, 0), max(j0 - c0, 0) : max(j1 - c0, 0)] = True
        inside &= where
        log[inside] += fresh[inside] - one[inside]
        one[where] = fresh[where]

    def _leave_silent(self, t: float) -> None:
        """Users silent for `_EVIDENCE_KEEP` s have left: their term leaves S, and the
        forgiveness it gave stays in log p as it stands."""
        gone = [u for u, r in self._users.items() if t - r.t > _EVIDENCE_KEEP]
        for user in gone:
            record = self._users.pop(user)
            if not record.counted:
                continue
            f = record.frame
            at = (slice(f[0], f[1]), slice(f[2], f[3]))
            ls = self._ls[at]
            r = np.minimum(np.exp(self._log_e(record) - ls), 1.0)
            lost = r > 0.5
            with np.errstate(divide="ignore"):
                fresh = ls + np.log1p(-r)
            if lost.any():  # summed afresh where its term was most of S
                total = np.full(int(lost.sum()), -np.inf)
                for other in self._users.values():
                    if other.counted:
                        self._cover(other, f)
                        total = np.logaddexp(total, self._log_e(other, other.cells(f))[lost])
                fresh[lost] = total
            ls[:] = fresh
            self._l[at] = np.logaddexp(0.0, fresh)

    def _resum(self) -> None:
        """log S on the window summed afresh from the records (differences accumulate
        rounding), log p following log(1 + S)."""
        i0, i1, j0, j1 = self._win
        total = self._sum(self._win, np.ones((i1 - i0, j1 - j0), dtype=bool))
        total = total.reshape(i1 - i0, j1 - j0)
        fresh = np.logaddexp(0.0, total)
        self._log[i0:i1, j0:j1] += fresh - self._l[i0:i1, j0:j1]
        self._ls[i0:i1, j0:j1] = total
        self._l[i0:i1, j0:j1] = fresh

    def shared(self) -> tuple[tuple[int, int, int, int], np.ndarray, float | None] | None:
        """The evidence this area's own users gave since the last call, for the
        neighbouring workers that serve its place (`take_shared`): on the grid window
        that holds mass now, sum_k log c_k(n_k . b) less its maximum, faded to the time
        of the area's last prediction, and that time; None if there was none (or the
        area keeps no record, `record`)."""
        if self._own is None or not self._own_any:
            return None
        i0, i1, j0, j1 = self._win
        out = self._own[i0:i1, j0:j1] - self._own[i0:i1, j0:j1].max()
        self._own.fill(0.0)
        self._own_any = False
        return self._win, out.astype(np.float32), self.t

    def take_shared(
        self, win: tuple[int, int, int, int], evidence: np.ndarray, t: float | None = None
    ) -> None:
        """A neighbour's `shared` evidence, folded in as if its users' fixes had come
        here: log p(b) += sum_k log c_k(n_k . b) on its window. Its users are not ours
        (each fix goes to one worker), so nothing counts twice, and what we take is not
        shared on (it is not our own).

        Where its window does not reach, the neighbour had ruled b out before (by the
        evidence it shared then) and worked out nothing new; those cells count as ruled
        out by it, _DROP below its best, as do the cells it rules out by more, so that no
        cell gains by having been left out, and none that our own evidence ruled out (held
        at the floor, 2 _DROP below our best) comes back by the neighbour's word alone:

            log p(b) += max(E(b) - max E, -_DROP) + _DROP   on its window,
                        0                                   elsewhere   (then normalised)

        It comes a share interval late, so the random walk has blurred it a little less
        than ours: a second or so, far below a cell. With a memory, evidence faded to time
        `t` is faded here to ours (or ours to its, if it is newer), so that it counts as
        it would had its fixes come here."""
        n = self._axis.size
        i0, i1, j0, j1 = win
        if not (0 <= i0 < i1 <= n and 0 <= j0 < j1 <= n) or evidence.shape != (i1 - i0, j1 - j0):
            raise ValueError(f"shared evidence of window {win} does not fit a grid of {n}")
        if not np.isfinite(evidence).all():
            raise ValueError("shared evidence holds NaN or infinite values")
        if t is not None and self.memory is not None:
            if self.t is None or t > self.t:
                self.predict(t)
            elif t < self.t:
                evidence = evidence * math.exp(-(self.t - t) / self.memory)
        self._log[i0:i1, j0:j1] += np.maximum(evidence - evidence.max(), -_DROP) + _DROP
        w0, w1, v0, v1 = self._win
        self._win = (min(w0, i0), max(w1, i1), min(v0, j0), max(v1, j1))
        i0, i1, j0, j1 = self._win
        self._settle(self._log[i0:i1, j0:j1], 0)

    def record(self) -> None:
        """Keep this area's own evidence from now on, for `shared`."""
        if self._own is None:
            self._own = np.zeros_like(self._log)

    def _recorded(self, term: np.ndarray) -> None:
        """Add an update's evidence on the window to the record (if one is kept). The
        cells outside the window, which the posterior had ruled out, take the window's
        worst term: had they been worked out, they would have fared no better. Without
        that a cell the window left out kept a record of no evidence against it, and a
        cell the window takes back later, when the evidence fades, read in the record as
        the best of all (a neighbour's posterior went there after a hand-over). Adding
        the worst term to every cell and the rest to the window's is, up to a constant
        that `shared` takes away (it subtracts the maximum) and that fading only scales,
        adding term - min(term) to the window's alone."""
        if self._own is None:
            return
        i0, i1, j0, j1 = self._win
        self._own[i0:i1, j0:j1] += term - term.min()
        self._own_any = True

    def user_evidence(self, user: str) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
        """(window, T) of `user`'s own normalised log-likelihood of b, if it is kept: the
        grid cells [i0:i1, j0:j1] of the area's axes (east, north); for diagnostics."""
        record = self._users.get(user)
        return None if record is None else (record.frame, record.log)

    def cell(self, b: np.ndarray) -> tuple[int, int]:
        """The grid cell (east, north index) nearest a common error b (clipped to the grid)."""
        n = self._axis.size
        k = np.clip(np.rint((b - self._axis[0]) / self._res).astype(int), 0, n - 1)
        return int(k[0]), int(k[1])


class _UserEvidence:
    """One user's record in a robust area: T(b), the sum of its fixes' log c normalised to
    max 0 (when last updated), on the cells `frame` of the
    area's grid (a frame only grows, so S stays the sum of the records' e = exp(-K - T));
    `counted`: its e is in S; `t`: its last fix."""

    __slots__ = ("counted", "frame", "log", "t")

    def __init__(self, frame: tuple[int, int, int, int], t: float, counted: bool) -> None:
        self.frame = frame
        self.log = np.zeros((frame[1] - frame[0], frame[3] - frame[2]), dtype=np.float32)
        self.counted = counted  # (in S from its first fix on, once the area has two users)
        self.t = t

    def cells(self, win: tuple[int, int, int, int]) -> tuple[slice, slice]:
        """The window's cells in the record's frame (which holds the window)."""
        f = self.frame
        return slice(win[0] - f[0], win[1] - f[0]), slice(win[2] - f[2], win[3] - f[2])


def _walk(p: np.ndarray, a: float) -> np.ndarray:
    """One step of the walk on a grid of probabilities: each cell gives a to each
    neighbour along each axis, p <- (1 - 2a) p + a (p[-1] + p[+1]); what would leave the
    array is lost (nothing wraps around from the other side)."""
    for axis in (0, 1):
        q = (1 - 2 * a) * p
        if axis == 0:
            q[1:] += a * p[:-1]
            q[:-1] += a * p[1:]
        else:
            q[:, 1:] += a * p[:, :-1]
            q[:, :-1] += a * p[:, 1:]
        p = q
    return p


class CommonErrorField:
    """One `CommonError` per area: a fix joins the nearest area centre within
    `size / 2`, else founds a new area there (no grid seams on a compact map). Areas are
    indexed by a coarse grid of cell `size`, so finding one looks at nine cells at most."""

    def __init__(
        self,
        size: float,
        prior_sigma: float,
        drift: float,
        resolution: float,
        cap: float | None = None,
        memory: float | None = None,
    ) -> None:
        self.size = size
        self._prior = prior_sigma
        self._drift = drift
        self._resolution = resolution
        self._cap = cap
        self._memory = memory
        self.recording = False  # new areas keep their own evidence (`CommonError.record`)
        self.areas: list[CommonError] = []
        self._cells: dict[tuple[int, int], list[CommonError]] = {}
        # the areas of the places asked about since `forget_places`: a batch asks each
        # fix's place twice, for its correction and for its step (areas are never removed,
        # so an answer stays true; the memo only bounds how much is kept)
        self._memo: dict[tuple[float, float], CommonError] = {}

    def _cell(self, xy: np.ndarray) -> tuple[int, int]:
        return math.floor(float(xy[0]) / self.size), math.floor(float(xy[1]) / self.size)

    def at(self, xy: np.ndarray) -> CommonError:
        """The area whose centre is nearest `xy`, created if none is within size / 2."""
        key = (float(xy[0]), float(xy[1]))
        area = self._memo.get(key)
        if area is None:
            area = self._memo[key] = self._nearest(xy)
        return area

    def forget_places(self) -> None:
        """Empty the memo of `at` (a batch starts)."""
        self._memo.clear()

    def _nearest(self, xy: np.ndarray) -> CommonError:
        best: CommonError | None = None
        best_d = self.size / 2.0
        ci, cj = self._cell(xy)
        x, y = float(xy[0]), float(xy[1])
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                for area in self._cells.get((ci + di, cj + dj), ()):
                    cx, cy = area.centre_xy
                    dist = float(np.hypot(cx - x, cy - y))
                    if dist <= best_d:
                        best, best_d = area, dist
        if best is None:
            best = CommonError(
                xy, self._prior, self._drift, self._resolution, self._cap, self._memory
            )
            if self.recording:
                best.record()
            self.areas.append(best)
            self._cells.setdefault((ci, cj), []).append(best)
        return best


# -- the window's arithmetic, compiled (`laas.engine.jit`) ----------------------------------


@jit
def _window_moments(
    w: np.ndarray, ae: np.ndarray, an: np.ndarray
) -> tuple[float, float, float, float, float]:
    """The window's weights p(b) = w / sum w, normalised in place (w: exp(log p) on its
    cells, [east, north]; ae, an: their axes), and the moments of b under them without
    the cells' own spread: (E b_e, E b_n, Var b_e, Cov(b_e, b_n), Var b_n)."""
    ni, nj = w.shape
    total = 0.0
    for i in range(ni):
        for j in range(nj):
            total += w[i, j]
    we = np.zeros(ni)
    wn = np.zeros(nj)
    for i in range(ni):
        for j in range(nj):
            v = w[i, j] / total
            w[i, j] = v
            we[i] += v
            wn[j] += v
    me = 0.0
    for i in range(ni):
        me += we[i] * ae[i]
    mn = 0.0
    for j in range(nj):
        mn += wn[j] * an[j]
    cee = 0.0
    for i in range(ni):
        cee += we[i] * (ae[i] - me) ** 2
    cnn = 0.0
    for j in range(nj):
        cnn += wn[j] * (an[j] - mn) ** 2
    cen = 0.0
    for i in range(ni):
        row = 0.0
        for j in range(nj):
            row += w[i, j] * (an[j] - mn)
        cen += (ae[i] - me) * row
    return me, mn, cee, cen, cnn


@jit
def _fade_window(
    log: np.ndarray,
    prior: np.ndarray,
    i0: int,
    i1: int,
    j0: int,
    j1: int,
    lam: float,
    drop: float,
    whole: bool,
) -> bool:
    """`CommonError._fade` on the window [i0, i1) x [j0, j1) of log p, in place:
    log p <- lam log p + (1 - lam) log p0, then less its new maximum M if the window is
    the whole grid or no floor cell comes back (M + 2 drop lam >= drop); whether it was
    (if not, the caller fades the floor outside the window)."""
    top = -math.inf
    for i in range(i0, i1):
        for j in range(j0, j1):
            v = log[i, j] * lam + (1.0 - lam) * prior[i, j]
            log[i, j] = v
            top = max(top, v)
    if not (whole or top + 2.0 * drop * lam >= drop):
        return False
    for i in range(i0, i1):
        for j in range(j0, j1):
            log[i, j] -= top
    return True


@jit
def _held(
    log: np.ndarray, i0: int, i1: int, j0: int, j1: int, floor: float
) -> tuple[int, int, int, int]:
    """The first and last row, and first and last column, of the window [i0, i1) x
    [j0, j1) of `log` that hold a cell above `floor` (the maximum, 0, always is),
    counted from the window's corner. (The whole grid and its bounds, not a view: one
    compiled version serves every window.)"""
    ni, nj = i1 - i0, j1 - j0
    r0, r1, c0, c1 = ni, -1, nj, -1
    for i in range(ni):
        for j in range(nj):
            if log[i0 + i, j0 + j] > floor:
                r0, r1 = min(r0, i), max(r1, i)
                c0, c1 = min(c0, j), max(c1, j)
    return r0, r1, c0, c1


@jit
def _u_cells(
    ae: np.ndarray, an: np.ndarray, n_e: float, n_n: float, lo: float, step: float, size: int
) -> tuple[np.ndarray, int, int]:
    """The u-grid cell of n . b for each window cell, k = (u - lo) / step + 1/2 rounded
    toward zero and clipped to the grid's `size` cells, and the first and one past the
    last cell they take."""
    idx = np.empty((ae.size, an.size), dtype=np.intp)
    first, last = size, 0
    for i in range(ae.size):
        for j in range(an.size):
            k = int((ae[i] * n_e + an[j] * n_n - lo) / step + 0.5)
            k = min(max(k, 0), size - 1)
            idx[i, j] = k
            first, last = min(first, k), max(last, k)
    return idx, first, last + 1


@jit
def _u_moments(
    w: np.ndarray, ae: np.ndarray, an: np.ndarray, idx: np.ndarray, size: int
) -> np.ndarray:
    """`CommonError.u_moments`: per u-cell the sums of p(b) times 1, b_e, b_n, b_e^2,
    b_e b_n, b_n^2 over the window's cells in it."""
    out = np.zeros((size, 6))
    for i in range(ae.size):
        e = ae[i]
        for j in range(an.size):
            k = idx[i, j]
            p = w[i, j]
            pe, pn = p * e, p * an[j]
            out[k, 0] += p
            out[k, 1] += pe
            out[k, 2] += pn
            out[k, 3] += pe * e
            out[k, 4] += pe * an[j]
            out[k, 5] += pn * an[j]
    return out
