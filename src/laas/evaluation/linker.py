"""The attacker on the service side: join a user's old and new pseudonyms by continuity.

It sees exactly what a worker sees, per input: the pseudonym, the fix's time, position,
speed and heading. Each pseudonym ends (a *death*: its last fix) and begins (a *birth*:
its first fix); a change of pseudonym is a death followed by a birth. For every death d
and every later birth b within ``MAX_GAP`` s, a constant-velocity prediction from d's
last fix to b's first gives

    dt   = t_b - t_d
    r    = p_b - (p_d + v_d dt)                       position residual, m (east, north)
    w    = v_b - v_d                                  velocity residual, m/s
    S_p  = 2 s_fix^2 + (s_v dt)^2 + (a dt^2 / 2)^2    its variance per axis
    S_v  = 2 s_v^2 + (a dt)^2
    D^2  = |r|^2 / S_p + |w|^2 / S_v                  Mahalanobis distance, 4 dof
    L    = D^2 + 2 ln(S_p / S_p(1)) + 2 ln(S_v / S_v(1))   its negative log-likelihood,
                                                      less that of a 1 s gap

and the pair is a candidate when D^2 < ``GATE`` (the 3-sigma gate of 4 dof), among the
``CANDIDATES`` of the death's with the least L (the ln terms keep a far birth after a long
gap from beating a near one after a short gap) or the ``CANDIDATES`` with the least D^2
(so that, where silences differ in length, the death's own birth after a long one is not
crowded out by a dozen others after short ones). All deaths and births are then joined at
once by an optimal assignment: as many candidate pairs as possible (each death and each
birth used at most once), and among those the least total L; solved by
`scipy.optimize.linear_sum_assignment` on each connected group of candidates.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment  # type: ignore[import-untyped]
from scipy.sparse import coo_matrix  # type: ignore[import-untyped]
from scipy.sparse.csgraph import connected_components  # type: ignore[import-untyped]

from ldm.wire.rotation import MAX_SILENCE

__all__ = [
    "ACCEL",
    "CANDIDATES",
    "GATE",
    "MAX_GAP",
    "NO_LINK",
    "SIGMA_FIX",
    "SIGMA_SPEED",
    "Observation",
    "link",
]

MAX_GAP = MAX_SILENCE + 5.0  # s: the longest silence a policy may ask for (public) and a margin
CANDIDATES = 12  # births kept per death, the least L and the least D^2: a crowd's
#                  unlikely members never win
SIGMA_FIX = 2.0  # m: a fix's own noise per axis (the error the receiver shares with the
#                  next fix, common and bias, cancels in the residual)
SIGMA_SPEED = 1.0  # m/s: a reported velocity's noise per axis
ACCEL = 2.0  # m/s^2: the braking and turning the constant-velocity model leaves out (a
#               car's firm braking); `link` takes others, `laas privacy` tries 0.5 as well
GATE = 16.25  # chi-square of 4 dof at 99.73 % (3 sigma)
NO_LINK = 1000.0  # a death or birth left alone: above any gated L (< GATE + the ln terms,
#                   about 70 at MAX_GAP), so the assignment links all it can first


@dataclass(frozen=True, slots=True)
class Observation:
    """One input as the service sees it: pseudonym, time (s), position east/north (m)
    and the reported velocity east/north (m/s)."""

    pseudonym: str
    t: float
    e: float
    n: float
    ve: float
    vn: float


@dataclass(frozen=True, slots=True)
class _End:
    pseudonym: str
    t: float
    p: np.ndarray
    v: np.ndarray


def _ends(observations: Sequence[Observation]) -> tuple[list[_End], list[_End]]:
    """Each pseudonym's first (birth) and last (death) observation."""
    first: dict[str, Observation] = {}
    last: dict[str, Observation] = {}
    for o in observations:
        if o.pseudonym not in first or o.t < first[o.pseudonym].t:
            first[o.pseudonym] = o
        if o.pseudonym not in last or o.t >= last[o.pseudonym].t:
            last[o.pseudonym] = o

    def end(o: Observation) -> _End:
        return _End(o.pseudonym, o.t, np.array([o.e, o.n]), np.array([o.ve, o.vn]))

    return [end(o) for o in last.values()], [end(o) for o in first.values()]


def _cost(d: _End, b: _End, accel: float) -> tuple[float, float]:
    """(D^2, L) of death d continued into birth b (module docstring), L inf outside the
    gate."""
    dt = b.t - d.t
    if not 0.0 < dt <= MAX_GAP:
        return math.inf, math.inf
    r = b.p - (d.p + d.v * dt)
    w = b.v - d.v
    s_p, s_v = _variances(dt, accel)
    d2 = float(r @ r / s_p + w @ w / s_v)
    if d2 >= GATE:
        return d2, math.inf
    p1, v1 = _variances(1.0, accel)
    return d2, d2 + 2 * math.log(s_p / p1) + 2 * math.log(s_v / v1)


def _variances(dt: float, accel: float) -> tuple[float, float]:
    """S_p and S_v after a gap of dt s (module docstring)."""
    s_p = 2 * SIGMA_FIX**2 + (SIGMA_SPEED * dt) ** 2 + (accel * dt * dt / 2) ** 2
    return s_p, 2 * SIGMA_SPEED**2 + (accel * dt) ** 2


def link(observations: Sequence[Observation], accel: float = ACCEL) -> dict[str, str]:
    """The attacker's joins: new pseudonym -> the old pseudonym it continues (`accel`:
    the acceleration, m/s^2, its prediction allows for)."""
    deaths, births = _ends(observations)
    if not deaths or not births:
        return {}
    order = sorted(range(len(births)), key=lambda k: births[k].t)
    birth_t = np.array([births[k].t for k in order])
    rows: list[int] = []
    cols: list[int] = []
    costs: list[float] = []
    for i, d in enumerate(deaths):
        lo = int(np.searchsorted(birth_t, d.t, side="right"))
        hi = int(np.searchsorted(birth_t, d.t + MAX_GAP, side="right"))
        near: list[tuple[float, float, int]] = []
        for k in order[lo:hi]:
            b = births[k]
            if b.pseudonym == d.pseudonym:
                continue
            d2, c = _cost(d, b, accel)
            if c < math.inf:
                near.append((c, d2, k))
        kept = {k: c for c, _, k in sorted(near)[:CANDIDATES]}
        kept.update({k: c for c, _, k in sorted(near, key=lambda x: x[1])[:CANDIDATES]})
        for k, c in kept.items():
            rows.append(i)
            cols.append(k)
            costs.append(c)
    if not rows:
        return {}
    nd, nb = len(deaths), len(births)
    graph = coo_matrix((np.ones(len(rows)), (rows, [nd + c for c in cols])), shape=(nd + nb,) * 2)
    _, label = connected_components(graph, directed=False)
    pairs: dict[int, list[tuple[int, int, float]]] = {}
    for r_, c_, cost in zip(rows, cols, costs, strict=True):
        pairs.setdefault(int(label[r_]), []).append((r_, c_, cost))
    joins: dict[str, str] = {}
    for edges in pairs.values():
        ds = sorted({r_ for r_, _, _ in edges})
        bs = sorted({c_ for _, c_, _ in edges})
        di = {x: j for j, x in enumerate(ds)}
        bi = {x: j for j, x in enumerate(bs)}
        m, n = len(ds), len(bs)
        # [[C, no-link of each death], [no-link of each birth, 0]]: (m + n) x (n + m);
        # leaving a pair unlinked costs 2 NO_LINK, more than any candidate pair's L
        big = NO_LINK * 4 * (m + n + 1)  # dearer than leaving everything unlinked
        table = np.full((m + n, n + m), big)
        for r_, c_, c in edges:
            table[di[r_], bi[c_]] = c
        table[np.arange(m), n + np.arange(m)] = NO_LINK
        table[m + np.arange(n), np.arange(n)] = NO_LINK
        table[m:, n:] = 0.0
        ri, ci = linear_sum_assignment(table)
        for a, b in zip(ri, ci, strict=True):
            if a < m and b < n and table[a, b] < NO_LINK:
                joins[births[bs[b]].pseudonym] = deaths[ds[a]].pseudonym
    return joins
