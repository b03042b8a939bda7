"""The default mode's arithmetic for all the users of one area in a batch, as stacked arrays.

`cooperative` prepares each user of the batch (its lane table, transition and motion fit,
the geometry of its fix); the equations of its module docstring then run here once for
the whole area instead of once per user. Users have different lane counts L_i and spans
of u-cells H_i = hi_i - lo_i, so each is padded to the largest, H and L: a padded lane has
no probability (its row of alpha and its motion fit are 0), so it never takes any mass,
and a padded cell lies outside the posterior's window, so no cell of b reads it.

    prediction   a[i, h, l] = sum_k alpha[i, h, k] T[i, k, l] * F[i, l]
    evidence     like[i, h, l] = (eps + N~(d_i - u[lo_i + h] - o[i, l]))^w_i
                 c[i, h] = sum_l a[i, h, l] like[i, h, l]
    lanes        alpha'[i, h, l] = a[i, h, l] like[i, h, l] / c[i, h]

and, on the area's posterior p(b) once every user's log c is in it,

    p_u[i, h]  = sum of p(b) over the cells b with n_i . b in u-cell lo_i + h
    P(l)_i     = sum_h p_u[i, h] alpha'[i, h, l]   (normalised)
    E[b | l*]  = sum_b p(b) alpha'[i, cell(n_i . b) - lo_i, l*_i] b   (normalised), and its
                 covariance, each cell's own spread res^2 / 12 added as `CommonError` does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["conditional_moments", "evidence", "lane_marginals", "pad"]

_K = 1.0 / math.sqrt(2.0 * math.pi)


def pad(blocks: Sequence[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    """Stack arrays of up to `shape` into (n, *shape), zeros where a block is smaller."""
    out = np.zeros((len(blocks), *shape))
    for i, block in enumerate(blocks):
        at: tuple[int | slice, ...] = (i, *(slice(0, k) for k in block.shape))
        out[at] = block
    return out


def evidence(
    alpha: np.ndarray,
    transition: np.ndarray,
    fit: np.ndarray,
    residual: np.ndarray,
    sigma: np.ndarray,
    weight: np.ndarray,
    off_lane: float,
    share: float,
    wide: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(alpha', log c) of the module docstring for stacked users: alpha (n, H, L),
    transition (n, L, L), fit (n, L) already raised to dt / tau, residual
    r = d - u - o (n, H, L), sigma s (n,), weight w (n,). The lateral likelihood N~ is
    the multipath mixture (1 - pi) N(r; 0, s^2) + pi N(r; 0, s^2 + s_mp^2), with
    pi = `share` and s_mp = `wide`."""
    a = np.matmul(alpha, transition) * fit[:, None, :]
    s = sigma[:, None, None]
    s_wide = np.sqrt(s * s + wide * wide)
    like = off_lane + (
        (1.0 - share) * _K / s * np.exp(-0.5 * (residual / s) ** 2)
        + share * _K / s_wide * np.exp(-0.5 * (residual / s_wide) ** 2)
    )
    joint = a * like ** weight[:, None, None]
    c = np.maximum(joint.sum(axis=2), 1e-300)
    return joint / c[:, :, None], np.log(c)


def lane_marginals(
    weights: np.ndarray, cells: np.ndarray, alpha: np.ndarray, lo: np.ndarray
) -> np.ndarray:
    """P(l)_i (n, L): the posterior of u_i = n_i . b (window weights p(b), u-cells
    `cells` (n, window) of each user, its span from `lo`) against its lane table."""
    n, h, _ = alpha.shape
    rows = (cells - lo[:, None, None]) + (np.arange(n) * h)[:, None, None]
    p_u = np.bincount(
        rows.ravel(), weights=np.broadcast_to(weights, cells.shape).ravel(), minlength=n * h
    ).reshape(n, h)
    marginal = np.einsum("nh,nhl->nl", p_u, alpha)
    out: np.ndarray = marginal / marginal.sum(axis=1, keepdims=True)
    return out


def conditional_moments(
    weights: np.ndarray,
    cells: np.ndarray,
    alpha: np.ndarray,
    lo: np.ndarray,
    lane: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray],
    cell_var: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E[b | l*_i] (n, 2), its covariance (n, 2, 2), held (n,)): held is False where
    the lane keeps no mass of the window, and there the caller takes the area's own."""
    n = alpha.shape[0]
    users = np.arange(n)[:, None, None]
    w = weights[None] * alpha[users, cells - lo[:, None, None], lane[:, None, None]]
    total = w.sum(axis=(1, 2))
    held = total > 0.0
    w = w / np.where(held, total, 1.0)[:, None, None]
    ae, an = axes
    we, wn = w.sum(axis=2), w.sum(axis=1)
    me, mn = we @ ae, wn @ an
    de, dn = ae[None, :] - me[:, None], an[None, :] - mn[:, None]
    cee = np.einsum("ne,ne->n", we, de * de)
    cnn = np.einsum("nk,nk->n", wn, dn * dn)
    cen = np.einsum("ne,nek,nk->n", de, w, dn)
    cov = np.empty((n, 2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = cee + cell_var, cnn + cell_var
    cov[:, 0, 1] = cov[:, 1, 0] = cen
    return np.stack([me, mn], axis=1), cov, held
