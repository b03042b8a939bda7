"""The most probable joint lane assignment of N users, without enumerating L^N hypotheses.

Within one road element the users share one residual lateral error delta (what is
left of the common GNSS error across the road). User i, at lateral offset d_i from
the segment's reference line, assigned to lane l whose centre lies at o_il, costs

    c_il(delta) = (d_i - delta - o_il)^2 / (2 sigma_i^2) - log pi_il

and the joint cost of an assignment h with a Gaussian prior delta ~ N(mu, tau^2) is

    C(h, delta) = sum_i c_{i,h_i}(delta) + (delta - mu)^2 / (2 tau^2).

For a fixed h the best delta is a weighted mean (w_i = 1/sigma_i^2, w_0 = 1/tau^2):

    delta*(h) = (w_0 mu + sum_i w_i (d_i - o_{i,h_i})) / (w_0 + sum_i w_i).

For a fixed delta every user's best lane is independent. Each c_il - c_im is linear in
delta, so a user's best lane can change only at the N L (L-1)/2 breakpoints where two
of its lanes cost the same. Between consecutive breakpoints the best response h(delta)
is constant, and the optimum (h*, delta*) has h* = h(delta*), so evaluating delta*(h)
for the best response of every interval finds the exact minimum of C over all L^N
assignments in O(N^2 L^3) numpy work instead of O(L^N N).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

__all__ = ["Assignment", "best_assignment", "enumerate_assignments"]

_LOG_FLOOR = -700.0  # log of a probability that is as good as zero, but keeps sums finite


@dataclass(frozen=True)
class Assignment:
    """The winning joint assignment and what it implies.

    lanes: (N,) lane index per user; delta: the residual lateral error (m);
    cost: C(h*, delta*); marginals: (N, L) posterior lane probabilities per user,
    mixed over every candidate assignment the search visited (weight exp(-C));
    candidates: how many distinct assignments were scored.
    """

    lanes: np.ndarray
    delta: float
    cost: float
    marginals: np.ndarray
    candidates: int


@dataclass(frozen=True)
class _Problem:
    """The inputs as float arrays, checked: w = 1/sigma^2, lp floored, w0 = 1/tau^2."""

    d: np.ndarray
    offsets: np.ndarray
    sigma: np.ndarray
    w: np.ndarray
    lp: np.ndarray
    w0: float

    @classmethod
    def of(
        cls,
        d: np.ndarray,
        offsets: np.ndarray,
        sigma: np.ndarray,
        log_prior: np.ndarray,
        delta_sigma: float,
    ) -> _Problem:
        d = np.asarray(d, dtype=float)
        offsets = np.asarray(offsets, dtype=float)
        sigma = np.asarray(sigma, dtype=float)
        lp = np.maximum(np.asarray(log_prior, dtype=float), _LOG_FLOOR)
        n, lanes = offsets.shape
        if d.shape != (n,) or sigma.shape != (n,) or lp.shape != (n, lanes):
            raise ValueError(
                f"shapes disagree: d {d.shape}, offsets {offsets.shape}, sigma {sigma.shape}, "
                f"log_prior {lp.shape}; expected (N,), (N, L), (N,), (N, L)"
            )
        if n == 0 or lanes == 0:
            raise ValueError("an assignment needs at least one user and one lane")
        if not np.all(sigma > 0):
            raise ValueError("every sigma must be positive")
        return cls(d, offsets, sigma, 1.0 / sigma**2, lp, 1.0 / delta_sigma**2)


def _costs(
    h: np.ndarray,
    d: np.ndarray,
    offsets: np.ndarray,
    w: np.ndarray,
    lp: np.ndarray,
    mu: float,
    w0: float,
) -> tuple[np.ndarray, np.ndarray]:
    """delta*(h) and C(h, delta*(h)) for K assignments h of shape (K, N)."""
    rows = np.arange(d.shape[0])
    a = d[None, :] - offsets[rows, h]  # (K, N): d_i - o_{i,h_i}
    delta = (w0 * mu + a @ w) / (w0 + w.sum())
    r = a - delta[:, None]
    cost = 0.5 * (r * r) @ w - lp[rows, h].sum(axis=1) + 0.5 * w0 * (delta - mu) ** 2
    return delta, cost


def _mixture(
    hs: np.ndarray,
    deltas: np.ndarray,
    costs: np.ndarray,
    d: np.ndarray,
    offsets: np.ndarray,
    w: np.ndarray,
    lp: np.ndarray,
) -> np.ndarray:
    """Per-user lane marginals, sum_k p_k softmax_l(-c_il(delta_k)), p_k ~ exp(-C_k)."""
    pk = np.exp(-(costs - costs.min()))
    pk /= pk.sum()
    r = d[None, :, None] - deltas[:, None, None] - offsets[None, :, :]  # (K, N, L)
    c = 0.5 * r * r * w[None, :, None] - lp[None, :, :]
    c -= c.min(axis=2, keepdims=True)
    p = np.exp(-c)
    p /= p.sum(axis=2, keepdims=True)
    marg: np.ndarray = np.einsum("k,knl->nl", pk, p)
    return marg


def best_assignment(
    d: np.ndarray,
    offsets: np.ndarray,
    sigma: np.ndarray,
    log_prior: np.ndarray,
    delta_mean: float = 0.0,
    delta_sigma: float = 10.0,
    mixture_size: int = 16,
) -> Assignment:
    """The exact minimiser of C(h, delta) by the breakpoint sweep described above.

    d: (N,) lateral offsets; offsets: (N, L) lane centres at each user's station;
    sigma: (N,) lateral 1-sigma per user; log_prior: (N, L) log lane probabilities.
    The marginals mix the `mixture_size` best assignments the sweep visited.
    """
    pr = _Problem.of(d, offsets, sigma, log_prior, delta_sigma)
    d, offsets, sigma, w, lp, w0 = pr.d, pr.offsets, pr.sigma, pr.w, pr.lp, pr.w0
    n, lanes = offsets.shape
    a = d[:, None] - offsets  # (N, L): a_il = d_i - o_il

    # Breakpoints of user i between lanes l and m, where c_il = c_im:
    #   delta = (a_l + a_m)/2 - sigma_i^2 (lp_l - lp_m) / (a_l - a_m).
    li, mi = np.triu_indices(lanes, k=1)
    diff = a[:, li] - a[:, mi]
    with np.errstate(divide="ignore", invalid="ignore"):
        bp = 0.5 * (a[:, li] + a[:, mi]) - sigma[:, None] ** 2 * (lp[:, li] - lp[:, mi]) / diff
    # Keep those on the user's lower envelope: no third lane is cheaper there.
    r = a[:, None, :] - bp[:, :, None]  # (N, P, L)
    c = 0.5 * r * r * w[:, None, None] - lp[:, None, :]
    pair_cost = np.take_along_axis(c, li[None, :, None].repeat(n, axis=0), axis=2)[:, :, 0]
    on_envelope = (np.abs(diff) > 1e-12) & np.isfinite(bp) & (c.min(axis=2) >= pair_cost - 1e-9)
    user, pair = np.nonzero(on_envelope)
    at = bp[user, pair]
    order = np.argsort(at, kind="stable")
    user, pair, at = user[order], pair[order], at[order]
    # Crossing a breakpoint upwards, the user moves to the lane with the larger a.
    lo, hi = li[pair], mi[pair]
    to = np.where(a[user, lo] > a[user, hi], lo, hi)
    frm = np.where(to == lo, hi, lo)

    # Best response left of every breakpoint, then one event per breakpoint.
    start = at[0] - 1.0 if at.size else delta_mean
    c0 = 0.5 * (a - start) ** 2 * w[:, None] - lp
    h0 = np.argmin(c0, axis=1)
    rows = np.arange(n)
    # Running sums over users of w a, w a^2 and lp for the assignment of each interval;
    # the profile cost of an assignment (delta minimised out) is
    #   C = (sum w a^2 + w0 mu^2)/2 - (sum w a + w0 mu)^2 / (2 (W + w0)) - sum lp.
    wa = np.concatenate([[w @ a[rows, h0]], w[user] * (a[user, to] - a[user, frm])]).cumsum()
    wa2 = np.concatenate(
        [[w @ a[rows, h0] ** 2], w[user] * (a[user, to] ** 2 - a[user, frm] ** 2)]
    ).cumsum()
    slp = np.concatenate([[lp[rows, h0].sum()], lp[user, to] - lp[user, frm]]).cumsum()
    big_w = w.sum() + w0
    costs = 0.5 * (wa2 + w0 * delta_mean**2) - 0.5 * (wa + w0 * delta_mean) ** 2 / big_w - slp
    deltas = (wa + w0 * delta_mean) / big_w

    # Rebuild the assignments of the best intervals: each user takes the lane of its
    # last event at or before the interval (or its starting lane).
    keep = np.argsort(costs, kind="stable")[:mixture_size]
    hs = np.repeat(h0[None, :], keep.size, axis=0)
    for j, k in enumerate(keep):
        if k:
            hs[j, user[:k]] = to[:k]
    first = list({row.tobytes(): j for j, row in reversed(list(enumerate(hs)))}.values())
    hs, deltas, costs = hs[first], deltas[keep][first], costs[keep][first]
    best = int(np.argmin(costs))
    return Assignment(
        lanes=hs[best].copy(),
        delta=float(deltas[best]),
        cost=float(costs[best]),
        marginals=_mixture(hs, deltas, costs, d, offsets, w, lp),
        candidates=int(at.size + 1),
    )


def enumerate_assignments(
    d: np.ndarray,
    offsets: np.ndarray,
    sigma: np.ndarray,
    log_prior: np.ndarray,
    delta_mean: float = 0.0,
    delta_sigma: float = 10.0,
) -> Assignment:
    """The same minimiser by brute force over all L^N assignments (tests and benchmarks).

    Its `marginals` mix every assignment, so they are the exact plug-in posterior.
    """
    pr = _Problem.of(d, offsets, sigma, log_prior, delta_sigma)
    d, offsets, sigma, w, lp, w0 = pr.d, pr.offsets, pr.sigma, pr.w, pr.lp, pr.w0
    n, lanes = offsets.shape
    hs = np.array(list(itertools.product(range(lanes), repeat=n)), dtype=np.intp)
    deltas, costs = _costs(hs, d, offsets, w, lp, delta_mean, w0)
    k = int(np.argmin(costs))
    return Assignment(
        lanes=hs[k].copy(),
        delta=float(deltas[k]),
        cost=float(costs[k]),
        marginals=_mixture(hs, deltas, costs, d, offsets, w, lp),
        candidates=int(hs.shape[0]),
    )
