"""The joint UKF started over a range interval: a range-parameterised Gaussian sum (Peach 1995).

A fixed observer's angles say where the emitter is seen, not how far; the range is learnt from the TOA
differences (the radial acceleration ``r Bdot^2`` of a constant-velocity emitter) through a strongly
nonlinear map. One Gaussian over ``[range_min_m, range_max_m]`` would be far too wide for the unscented
transform (and a prior in the middle converges slowly and overconfidently when the emitter is much
nearer). Instead the interval is split geometrically into ``M`` sub-intervals of ratio at most
:data:`RANGE_RATIO`; each carries a joint UKF started at its middle range with a standard deviation that
covers it (relative width :func:`relative_sigma`). All run on the same epochs with the same pulse count;
each weight is multiplied by its update's innovation density. Components whose weight falls below
:data:`MIN_WEIGHT` are dropped; when one is left the session continues as the single joint UKF
(stage ``"tracking"``). Until then the state reports the sum's mean and covariance.

Components are never merged. Replacing two neighbours by their moments (Runnalls' cost below 0.2, as
this module first did) gives one component as wide as both: the very Gaussian the sum is there to
avoid. Against the PCRB on paper 001 with truths from the model (q = 0.5 m/s^2, last 50 s, 400 runs:
seeds 30000 + 100 b + i, b < 8, i < 50) that cost 1.27x / 1.27x (known / unknown period) against
1.06x / 1.06x without merging, with sub-intervals of ratio 2 (ratio 1.5: 1.04x / 1.10x; 1.25:
1.19x / 1.23x); at q = 0.05 m/s^2 it is 1.03x either way. The sum then lives longer: at q = 0.5, 80
(known) and 110 (unknown period) epochs on average instead of 57 and 72, and 3 % and 13 % of the
sessions still hold two or three components at 200 s (30 runs).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from core.tracking.config import SPEED_OF_LIGHT_MPS as C
from core.tracking.config import TrackerConfig
from core.tracking.state import Components, frozen_array

#: Largest ratio of the far to the near end of one component's range interval.
RANGE_RATIO = 2.0
#: Components below this weight are dropped (after renormalising).
MIN_WEIGHT = 1e-3


def component_ranges(config: TrackerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Middle ranges ``(M,)`` and standard deviations ``(M,)`` (m) of the components.

    The sub-interval ``[a, a rho]`` is uniform in range around its geometric middle ``a sqrt(rho)``; its
    standard deviation ``a (rho - 1) / sqrt(12)``, i.e. ``(sqrt(rho) - 1 / sqrt(rho)) / sqrt(12)`` of the
    middle, is each component's.
    """
    span = config.range_max_m / config.range_min_m
    count = max(1, math.ceil(math.log(span) / math.log(RANGE_RATIO) - 1e-9))
    ratio = span ** (1.0 / count)
    middles = config.range_min_m * ratio ** (np.arange(count) + 0.5)
    return middles, middles * relative_sigma(ratio)


def relative_sigma(ratio: float) -> float:
    """Standard deviation over the middle range of a uniform range interval of ``ratio``."""
    return (math.sqrt(ratio) - 1.0 / math.sqrt(ratio)) / math.sqrt(12.0)


def moments(weights: np.ndarray, means: np.ndarray, covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(..., F)`` and covariance ``(..., F, F)`` of Gaussian sums over the axis before the components'
    (``weights`` ``(..., M)`` summing to one along the last axis; leading axes broadcast).

    The covariance ``sum_m w_m (P_m + (x_m - x)(x_m - x)^T)`` is exactly symmetric (only the lower
    triangles of the ``P_m`` are read). Compiled
    (:func:`_moments_kernel`): a handful of numpy calls on these small arrays cost ten times the arithmetic.
    """
    m, f = means.shape[-2:]
    lead = weights.shape[:-1]
    if means.shape[:-2] != lead or covariances.shape[:-3] != lead:
        lead = np.broadcast_shapes(lead, means.shape[:-2], covariances.shape[:-3])
        weights, means = np.broadcast_to(weights, (*lead, m)), np.broadcast_to(means, (*lead, m, f))
        covariances = np.broadcast_to(covariances, (*lead, m, f, f))
    batch = math.prod(lead)
    mean, cov = np.empty((*lead, f)), np.empty((*lead, f, f))
    # Fresh C-ordered copies: one argument type for the kernel whatever the callers' arrays (frozen, broadcast).
    _moments_kernel(np.array(weights, dtype=float, order="C").reshape(batch, m),
                    np.array(means, dtype=float, order="C").reshape(batch, m, f),
                    np.array(covariances, dtype=float, order="C").reshape(batch, m, f, f), mean.reshape(batch, f),
                    cov.reshape(batch, f, f))
    return mean, cov


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _moments_kernel(weights, means, covariances, mean, cov):
    """:func:`moments` of ``B`` sums ``(B, M)``, ``(B, M, F)``, ``(B, M, F, F)`` into ``mean`` ``(B, F)`` and
    ``cov`` ``(B, F, F)`` (lower triangle summed in component order, then mirrored)."""
    batch, m, f = means.shape
    for b in range(batch):
        for i in range(f):
            total = 0.0
            for k in range(m):
                total += weights[b, k] * means[b, k, i]
            mean[b, i] = total
        for i in range(f):
            for j in range(i + 1):
                total = 0.0
                for k in range(m):
                    total += weights[b, k] * (covariances[b, k, i, j] + (means[b, k, i] - mean[b, i])
                                              * (means[b, k, j] - mean[b, j]))
                cov[b, i, j] = total
                cov[b, j, i] = total


def components_of(weights, means, covariances) -> Components:
    """Frozen :class:`Components` from lists or arrays."""
    return Components(frozen_array(weights), frozen_array(means), frozen_array(covariances))


def reweighted(weights: np.ndarray, log_likelihoods: np.ndarray) -> np.ndarray:
    """Posterior weights ``(M,)`` from log-likelihoods that are finite or ``-inf`` (a failed update: weight
    zero), or None when every update failed."""
    log_w = np.log(weights) + log_likelihoods
    top = log_w.max()
    if top == -np.inf:
        return None
    w = np.exp(log_w - top)
    return w / w.sum()


def pruned(weights: np.ndarray) -> np.ndarray:
    """Indices of the components kept (weight at least :data:`MIN_WEIGHT`)."""
    return (weights >= MIN_WEIGHT).nonzero()[0]


def fold_period(mean, period_s: float, period_known: bool):
    """``(mean, period_s)`` with an unknown period's error folded into ``period_s``."""
    mean = list(mean)
    if not period_known:
        period_s = period_s + mean[6] / C
        mean[6] = 0.0
    return mean, period_s
