"""The default mode's arithmetic for all the users of one area in a batch, as stacked arrays.

`cooperative` prepares each user of the batch (its lane table, transition and motion fit,
the geometry of its fix); the equations of its module docstring then run here once for
the whole area instead of once per user. Users have different lane counts L_i and spans
of u-cells H_i = hi_i - lo_i, so each is padded to the largest, H and L: a padded lane has
no probability (its column of alpha and its motion fit are 0), so it never takes mass,
and a padded cell lies outside the posterior's window, so no cell of b reads it.

    prediction   a[i, h, l] = sum_k alpha[i, h, k] T[i, k, l] * F[i, l]
    evidence     like[i, h, l] = (eps + N~(d_i - u[lo_i + h] - o[i, l]))^w_i
                 c[i, h] = sum_l a[i, h, l] like[i, h, l]
    lanes        alpha'[i, h, l] = a[i, h, l] like[i, h, l] / c[i, h]

and, on the area's posterior p(b) once every user's log c is in it, the lane's
marginal and the common error given the lane (`lanes_and_conditionals`). Both read the
posterior only through u_i = n_i . b, so they are taken from its moments per u-cell
(`CommonError.u_moments`), once per distinct normal, in O(H) per user rather than over
the whole window.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from laas.engine.jit import jit

__all__ = ["evidence", "lanes_and_conditionals", "pad"]

_K = 1.0 / math.sqrt(2.0 * math.pi)
# cells x lanes up to which `evidence` is computed cell by cell: below it numpy's fixed
# cost per call (some 15 us) outweighs its vectorised exponentials (about 20 ns a cell
# against 40), measured on the development machine (`scripts/engine_bench.py` shows the
# effect one at a time and in batches)
_FEW_CELLS = 1024


def pad(blocks: Sequence[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    """Stack arrays of up to `shape` into (n, *shape), zeros where a block is smaller."""
    if all(block.shape == shape for block in blocks):  # nothing to pad (one user: always)
        return np.array(blocks)
    out = np.zeros((len(blocks), *shape))
    for i, block in enumerate(blocks):
        at: tuple[int | slice, ...] = (i, *(slice(0, k) for k in block.shape))
        out[at] = block
    return out


def evidence(
    alpha: np.ndarray,
    transition: np.ndarray,
    fit: np.ndarray,
    d: np.ndarray,
    u: np.ndarray,
    lo: np.ndarray,
    offsets: np.ndarray,
    sigma: np.ndarray,
    weight: np.ndarray,
    off_lane: float,
    share: float,
    wide: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(alpha', log c) of the module docstring for stacked users: alpha (n, H, L),
    transition (n, L, L), fit (n, L) already raised to dt / tau, each fix's offset d
    (n,), the u-grid's values u (U,) of which user i's cells are lo_i, lo_i + 1, ...
    (a cell past the grid reads its last value), the lane centres o (n, L), sigma s (n,),
    weight w (n,); the residual is r[i, h, l] = d_i - u[lo_i + h] - o[i, l]. The lateral
    likelihood N~ is the multipath mixture (1 - pi) N(r; 0, s^2) + pi N(r; 0, s^2 +
    s_mp^2), with pi = `share` and s_mp = `wide`.

    Compiled cell by cell for a few cells (one user: its few lanes over its span),
    in numpy's array calls for many; `tests/test_stacked.py` holds the two together."""
    kernel = _evidence_cells if alpha.size <= _FEW_CELLS else _evidence_arrays
    out: tuple[np.ndarray, np.ndarray] = kernel(
        alpha, transition, fit, d, u, lo, offsets, sigma, weight, off_lane, share, wide
    )
    return out


@jit
def _evidence_cells(
    alpha: np.ndarray,
    transition: np.ndarray,
    fit: np.ndarray,
    d: np.ndarray,
    u: np.ndarray,
    lo: np.ndarray,
    offsets: np.ndarray,
    sigma: np.ndarray,
    weight: np.ndarray,
    off_lane: float,
    share: float,
    wide: float,
) -> tuple[np.ndarray, np.ndarray]:
    """`evidence` cell by cell, compiled."""
    n, h, lanes = alpha.shape
    last = u.size - 1
    joint = np.empty((n, h, lanes))
    log_c = np.empty((n, h))
    a = np.empty(lanes)
    for i in range(n):
        s = sigma[i]
        s_wide = math.sqrt(s * s + wide * wide)
        narrow_k = (1.0 - share) * _K / s
        wide_k = share * _K / s_wide
        w = weight[i]
        for k in range(h):
            d_u = d[i] - u[min(lo[i] + k, last)]
            # prediction: a[l] = sum_j alpha[j] T[j, l] F[l]
            for lane in range(lanes):
                acc = 0.0
                for j in range(lanes):
                    acc += alpha[i, k, j] * transition[i, j, lane]
                a[lane] = acc * fit[i, lane]
            # like = eps + (1 - pi) K / s exp(-(r / s)^2 / 2) + pi K / s_w exp(-(r / s_w)^2 / 2);
            # joint = a like^w, c = sum_l joint, alpha' = joint / c
            c = 0.0
            for lane in range(lanes):
                r = d_u - offsets[i, lane]
                like = narrow_k * math.exp(-0.5 * (r / s) ** 2)
                like += wide_k * math.exp(-0.5 * (r / s_wide) ** 2)
                like += off_lane
                j_l = a[lane] * like**w
                joint[i, k, lane] = j_l
                c += j_l
            c = max(c, 1e-300)
            for lane in range(lanes):
                joint[i, k, lane] /= c
            log_c[i, k] = math.log(c)
    return joint, log_c


def _evidence_arrays(
    alpha: np.ndarray,
    transition: np.ndarray,
    fit: np.ndarray,
    d: np.ndarray,
    u: np.ndarray,
    lo: np.ndarray,
    offsets: np.ndarray,
    sigma: np.ndarray,
    weight: np.ndarray,
    off_lane: float,
    share: float,
    wide: float,
) -> tuple[np.ndarray, np.ndarray]:
    """`evidence` in numpy's array calls: cheaper for many cells (its exponentials
    vectorised), dearer for few (a fixed cost per call)."""
    # each user's u-cells lo..lo + H (a cell past the grid reads its last value)
    cell = np.minimum(lo[:, None] + np.arange(alpha.shape[1]), u.size - 1)
    residual = (d[:, None] - u[cell])[:, :, None] - offsets[:, None, :]
    a = np.matmul(alpha, transition) * fit[:, None, :]
    s = sigma[:, None, None]
    s_wide = np.sqrt(s * s + wide * wide)
    # like = eps + (1 - pi) K / s exp(-(r / s)^2 / 2) + pi K / s_w exp(-(r / s_w)^2 / 2),
    # worked in place on two (n, H, L) arrays (the same values as written out)
    like = residual / s
    like *= like
    like *= -0.5
    np.exp(like, out=like)
    like *= (1.0 - share) * _K / s
    broad = residual / s_wide
    broad *= broad
    broad *= -0.5
    np.exp(broad, out=broad)
    broad *= share * _K / s_wide
    like += broad
    like += off_lane
    # joint = a like^w, c = sum_l joint, alpha' = joint / c; like^w as exp(w log like)
    # (like >= eps > 0): numpy vectorises exp and log, not power
    joint = np.log(like, out=like)
    joint *= weight[:, None, None]
    np.exp(joint, out=joint)
    joint *= a
    c = np.maximum(joint.sum(axis=2), 1e-300)
    joint /= c[:, :, None]
    return joint, np.log(c)


@jit
def lanes_and_conditionals(
    moments: np.ndarray, group: np.ndarray, lo: np.ndarray, alpha: np.ndarray, cell_var: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(P(l) (n, L), l* (n,), E[b | l*] (n, 2), its covariance (n, 2, 2), held (n,)) from
    the posterior's u-moments along each distinct normal (`CommonError.u_moments`,
    stacked (G, U, 6)), user i's normal's row group_i and its span's first cell lo_i (a
    cell past the grid reads its last value, M[h] below being M[lo_i + h]), and each
    user's lane table alpha (n, H, L):

        P(l)      = sum_h M0[h] alpha[h, l]                          (normalised)
        E[b | l*] = sum_h g[h] M1[h] / sum_h g[h] M0[h],   g = alpha[:, l*]
        Cov       = sum_h g[h] M2[h] / sum_h g[h] M0[h] - E E' + res^2 / 12

    held is False where the lane keeps no mass of the posterior; there the caller takes
    the area's own b and P."""
    n, h, lanes = alpha.shape
    last = moments.shape[1] - 1
    marginal = np.zeros((n, lanes))
    lane = np.empty(n, dtype=np.intp)
    mean = np.empty((n, 2))
    cov = np.empty((n, 2, 2))
    held = np.empty(n, dtype=np.bool_)
    sums = np.empty(6)
    for i in range(n):
        m = moments[group[i]]
        for k in range(h):
            m0 = m[min(lo[i] + k, last), 0]
            for j in range(lanes):
                marginal[i, j] += m0 * alpha[i, k, j]
        total = 0.0
        for j in range(lanes):
            total += marginal[i, j]
        best = 0
        for j in range(lanes):
            marginal[i, j] /= total
            if marginal[i, j] > marginal[i, best]:
                best = j
        lane[i] = best
        sums[:] = 0.0
        for k in range(h):
            g = alpha[i, k, best]
            row = min(lo[i] + k, last)
            for c in range(6):
                sums[c] += g * m[row, c]
        mass = sums[0]
        held[i] = mass > 0.0
        if held[i]:
            for c in range(6):
                sums[c] /= mass
        e, nn = sums[1], sums[2]
        # E[b b'] - E[b] E[b]' (+ res^2 / 12 on the diagonal), from (ee, en, nn)
        mean[i, 0], mean[i, 1] = e, nn
        cov[i, 0, 0] = sums[3] - e * e + cell_var
        cov[i, 0, 1] = cov[i, 1, 0] = sums[4] - e * nn
        cov[i, 1, 1] = sums[5] - nn * nn + cell_var
    return marginal, lane, mean, cov, held
