"""A covariance is a promise: its 99 % region holds the truth 99 % of the time.

A client reads a covariance as a Gaussian's: the ellipsoid
``d^T P^-1 d <= chi2_99(r)`` (``r`` its rank: 2 with the altitude known, else
3) is where the truth is, 99 times in 100. Where the fix's error is no
Gaussian, a covariance that is its honest second moment breaks that promise:

- over a curved region (a line of sight nearly along a TDOA hyperbola) the
  fix slides along the curve, its offset from the straight axis growing as the
  square of the slide; the second moment of that offset is matched, but the
  draws that slide two sigmas or more fall outside the thin ellipse (5 % of
  them at 99 %);
- with a plausible second solution of probability ``w``, the mixture's second
  moment stretches the ellipse by ``sqrt(w)`` of the distance to it, which
  leaves it outside the 99 % region whenever ``1 % < w < 11 %``.

:func:`holding` widens such a covariance, along the direction the departure
from a Gaussian lies in, by the least amount that makes its 99 % region hold
:data:`PROMISED_COVERAGE` of a stated model of the error (draws of it, with
weights): the curved fix's second-order expansion from its sigma points
(:func:`core.estimators.unscented_fix.quadratic_offsets`), or the two
solutions' mixture (:func:`core.estimators.ambiguity.mixture_region`). The
widened covariance then states more than the error's second moment (its NEES
mean falls below its dof): it is the smallest in that family whose region
keeps the promise, and a fix whose covariance is so widened says why in its
warnings.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.special import ndtri
from scipy.stats import chi2, qmc

#: The coverage a fix's stated 99 % region must give its error model.
PROMISED_COVERAGE = 0.99
#: Draws of a standard normal (a scrambled Sobol sequence, fixed seed: a fix is a function of its data).
NORMAL_DRAWS = 4096
#: A covariance is left as it is unless its region's coverage of the draws falls this far short of the promise
#: (about the draws' own error at 99 %: a Gaussian model's exact covariance is never widened).
DRAW_SLACK = 1e-3
#: The widening along the departure's direction is searched up to this many times the covariance there
#: (variance); beyond it the remaining shortfall is met by scaling the whole covariance.
MAX_WIDENING = 1e6
#: Halvings of the bracket of a draw's widening (on ``log gamma`` from ``-30`` to ``log MAX_WIDENING``: to a
#: relative 4e-8 of it).
BISECTIONS = 30


@functools.lru_cache(maxsize=8)
def normal_draws(dimensions: int) -> np.ndarray:
    """``(NORMAL_DRAWS, dimensions)`` fixed quasi-random draws of a standard normal (read-only)."""
    uniform = qmc.Sobol(dimensions, scramble=True, seed=20261205).random(NORMAL_DRAWS)
    draws = ndtri(np.clip(uniform, 0.5 / NORMAL_DRAWS, 1.0 - 0.5 / NORMAL_DRAWS))
    draws.setflags(write=False)
    return draws


def holding(covariance_enu_m2, offsets_enu_m, weights, along_enu_m2):
    """Each covariance widened by the least ``gamma`` along ``along`` (then, if that is not enough, scaled) so
    that its 99 % region holds ``PROMISED_COVERAGE`` of its error model.

    Parameters
    ----------
    covariance_enu_m2 : ndarray, shape (B, 3, 3)
        The covariances as they stand (their range is kept: a known altitude leaves them rank 2).
    offsets_enu_m : ndarray, shape (B, N, 3)
        Draws of each fix's error model (truth minus fix, or its negative: the region is symmetric), finite.
    weights : ndarray, shape (B, N)
        The draws' probabilities (each row sums to 1).
    along_enu_m2 : ndarray, shape (B, 3, 3)
        The direction(s) to widen along, as a positive semidefinite shape (say ``sum h h^T`` of the curvature
        terms, or ``d d^T`` towards a second solution).

    Returns
    -------
    covariance_enu_m2 : ndarray, shape (B, 3, 3)
        ``c (P + gamma A)`` with ``A`` restricted to ``P``'s range, ``gamma >= 0``, ``c >= 1`` (``c > 1`` only
        where widening along ``A`` alone cannot hold the draws): ``P`` itself where its region already holds.
    widened : ndarray of bool, shape (B,)
        Where it did not.
    """
    covariance = np.asarray(covariance_enu_m2, dtype=float)
    offsets = np.asarray(offsets_enu_m, dtype=float)
    weights = np.asarray(weights, dtype=float)
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.swapaxes(-1, -2)))
    keep = values > 1e-12 * np.maximum(values[:, -1:], 1e-300)
    scale = np.where(keep, np.sqrt(np.clip(values, 0.0, None)), 0.0)
    whiten = vectors * np.where(keep, 1.0 / np.where(keep, scale, 1.0), 0.0)[:, None, :]  # (B, 3, 3)
    root = vectors * scale[:, None, :]
    level = chi2.ppf(PROMISED_COVERAGE, np.maximum(np.count_nonzero(keep, axis=-1), 1))  # (B,)
    shape = np.einsum("bji,bjk,bkl->bil", whiten, np.asarray(along_enu_m2, dtype=float), whiten)
    strengths, turn = np.linalg.eigh(0.5 * (shape + shape.swapaxes(-1, -2)))
    strengths = np.clip(strengths, 0.0, None) / np.maximum(strengths[:, -1:], 1e-300)  # the largest is 1
    squared = np.matmul(offsets, whiten @ turn) ** 2  # (B, N, 3) in the shape's axes

    nees = np.sum(squared, axis=-1)  # (B, N)
    inside = nees <= level[:, None]
    short = np.sum(weights * inside, axis=-1) < PROMISED_COVERAGE - DRAW_SLACK
    gamma, factor = np.zeros(covariance.shape[0]), np.ones(covariance.shape[0])
    if np.any(short):
        gamma[short] = _least_widening(squared[short], weights[short], inside[short], strengths[short], level[short])
        nees = np.sum(squared / (1.0 + gamma[:, None, None] * strengths[:, None, :]), axis=-1)
        still = short & (np.sum(weights * (nees <= level[:, None]), axis=-1) < PROMISED_COVERAGE - DRAW_SLACK)
        for b in np.flatnonzero(still).tolist():  # the departure is not only along ``along``: scale the rest
            order = np.argsort(nees[b])
            reached = min(int(np.searchsorted(np.cumsum(weights[b, order]), PROMISED_COVERAGE)), order.size - 1)
            factor[b] = max(1.0, float(nees[b, order[reached]]) / float(level[b]))
    inner = np.einsum("bij,bj,bkj->bik", turn, 1.0 + gamma[:, None] * strengths, turn) * factor[:, None, None]
    widened = np.einsum("bij,bjk,blk->bil", root, inner, root)
    out = np.where(short[:, None, None], 0.5 * (widened + widened.swapaxes(-1, -2)), covariance)
    return out, short


def _least_widening(squared, weights, inside, strengths, level):
    """Per problem, the least ``gamma`` ``(B,)`` at which the draws inside its region weigh
    ``PROMISED_COVERAGE``; ``MAX_WIDENING`` where none does.

    A draw's NEES ``sum_j u_j^2 / (1 + gamma s_j)`` falls with ``gamma``: each draw outside at ``gamma = 0``
    enters at a ``gamma`` of its own (bisected on its log), and the least ``gamma`` is where the weight of
    those entered makes up the shortfall. Only the draws outside (a few in a hundred) are bisected.

    Parameters
    ----------
    squared : ndarray, shape (B, N, 3)
        The draws' squared whitened coordinates along the widening's axes.
    weights : ndarray, shape (B, N)
    inside : ndarray of bool, shape (B, N)
        Inside the region at ``gamma = 0``.
    strengths : ndarray, shape (B, 3)
        The widening's strength along each axis (the largest 1).
    level : ndarray, shape (B,)
    """
    rows, draws = np.nonzero(~inside)
    terms, strength = squared[rows, draws], strengths[rows]
    low, high = np.full(rows.size, -30.0), np.full(rows.size, np.log(MAX_WIDENING))
    for _ in range(BISECTIONS):
        middle = 0.5 * (low + high)
        holds = np.sum(terms / (1.0 + np.exp(middle)[:, None] * strength), axis=-1) <= level[rows]
        high, low = np.where(holds, middle, high), np.where(holds, low, middle)
    enters = np.exp(high)
    enters[np.sum(terms / (1.0 + MAX_WIDENING * strength), axis=-1) > level[rows]] = np.inf
    order = np.lexsort((enters, rows))
    rows, enters, weight = rows[order], enters[order], weights[rows[order], draws[order]]
    counts = np.bincount(rows, minlength=squared.shape[0])
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    total = np.cumsum(weight)
    entered = total - np.repeat(np.concatenate([[0.0], total])[first], counts)  # the weight entered so far, per problem
    needed = PROMISED_COVERAGE - np.sum(weights * inside, axis=-1)  # (B,)
    gamma = np.full(squared.shape[0], MAX_WIDENING)
    enough = np.flatnonzero((entered >= needed[rows] - 1e-12) & np.isfinite(enters))
    if enough.size:
        firsts = enough[np.r_[True, rows[enough][1:] != rows[enough][:-1]]]
        gamma[rows[firsts]] = enters[firsts]
    return gamma
