"""Second solutions of an ML fix: where the search looks for them, and what a fix says of one.

Where the measurements leave (almost) no degree of freedom a second point may
fit the data too: a line of sight crosses a TDOA hyperbola twice, a point and
its mirror through coplanar stations fit alike. :func:`core.estimators.ties.searched_starts`
fits from the geometry's candidates; candidates placed at fixed distances
can miss a second crossing near the first (a line of sight nearly tangent to
the hyperbola crosses it twice a kilometre apart), so the search also starts
from the best fit's own uncertainty: along each principal axis of its bound,
at :data:`AXIS_SIGMAS` sigmas either side (:func:`axis_starts`).

One rule judges a rival (a converged, regular fit distinct from the best:
:func:`core.estimators.ties.rivals`) for every measurement mix, by the cost
difference ``delta = cost_rival - cost_best`` (chi-square units: twice the
log-likelihood ratio of the two fits at the stated sigmas):

- ``delta <= AMBIGUITY_COST``: a tie. The rival's likelihood is at least
  ``exp(-AMBIGUITY_COST / 2)`` (13.5 %) of the best's: a C2 user given one of
  the two would act on a position that is as likely kilometres elsewhere, so
  the request is refused, 422 ``ambiguous_geometry`` naming both (an
  ``initial_guess`` near one picks it; the fix then warns
  ``ambiguous_solution``).
- ``AMBIGUITY_COST < delta <= PLAUSIBLE_COST``: the rival is worse but not
  rejected at :data:`RIVAL_PROBABILITY`. The best fix is answered with the
  warning ``second_solution_plausible`` naming the rival and its probability
  ``w = 1 / (1 + exp(delta / 2))`` (the two fits' likelihoods, normalised),
  and its covariance is the two-solution mixture's second moment about the
  reported fix, ``(1 - w) P_best + w (P_rival + d d^T)`` with ``d`` the rival
  minus the fix (:func:`mixture_covariance`), widened where its 99 % region
  would not hold the mixture (:func:`mixture_region`: a rival of probability
  above 1 % must lie inside it).
- ``delta > PLAUSIBLE_COST``: rejected; the fix is answered as if alone.
"""

from __future__ import annotations

import math

import numpy as np

from core.estimators.region import holding, normal_draws
from core.problem.batch import ProblemBatch

#: A rival whose cost is within this of the best's (chi-square units) ties with it: 422 ``ambiguous_geometry``.
AMBIGUITY_COST = 4.0
#: A worse rival is rejected when its probability ``1 / (1 + exp(delta / 2))`` is below this.
RIVAL_PROBABILITY = 1e-3
#: ... that is, when its cost exceeds the best's by more than this (13.8).
PLAUSIBLE_COST = 2.0 * math.log((1.0 - RIVAL_PROBABILITY) / RIVAL_PROBABILITY)
#: The search also starts this many sigmas either side of the best fit along each principal axis of its bound:
#: a second root near the first (a nearly tangent crossing) lies along the direction the data barely see.
AXIS_SIGMAS = (0.5, 1.5, 4.0, 12.0)


def axis_starts(batch: ProblemBatch, owners, positions_enu_m, covariances_enu_m2):
    """Starts at ``AXIS_SIGMAS`` sigmas either side of each position along each principal axis of its
    covariance (onto the known altitude where there is one).

    Parameters
    ----------
    batch : ProblemBatch
    owners : ndarray of int, shape (K,)
        The problem of each position (rows of ``batch``).
    positions_enu_m : ndarray, shape (K, 3)
    covariances_enu_m2 : ndarray, shape (K, 3, 3)

    Returns
    -------
    owners : ndarray of int, shape (S,)
    starts_enu_m : ndarray, shape (S, 3)
        Only finite starts, along axes of positive finite variance.
    """
    owners = np.asarray(owners, dtype=np.intp)
    positions = np.asarray(positions_enu_m, dtype=float)
    covariances = np.nan_to_num(np.asarray(covariances_enu_m2, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
    variances, axes = np.linalg.eigh(0.5 * (covariances + covariances.swapaxes(-1, -2)))
    sigmas = np.sqrt(np.clip(variances, 0.0, None))  # (K, 3)
    steps = np.concatenate([np.asarray(AXIS_SIGMAS), -np.asarray(AXIS_SIGMAS)])  # (S,)
    # (K, 3 axes, S steps, 3): position + step * sigma_axis * axis
    offsets = axes.swapaxes(-1, -2)[:, :, None, :] * (sigmas[:, :, None] * steps[None, None, :])[..., None]
    starts = positions[:, None, None, :] + offsets
    keep = np.broadcast_to((sigmas > 0.0)[:, :, None], starts.shape[:3]) & np.all(np.isfinite(starts), axis=-1)
    keep &= np.all(np.isfinite(positions), axis=-1)[:, None, None]
    rows = np.broadcast_to(owners[:, None, None], starts.shape[:3])[keep]
    return rows, batch.onto_altitude(starts[keep], rows)


def rival_probability(delta_cost) -> np.ndarray:
    """The rival's share of the two fits' likelihoods, ``1 / (1 + exp(delta / 2))``, for cost differences
    ``delta`` (rival minus best, chi-square units)."""
    return 1.0 / (1.0 + np.exp(0.5 * np.asarray(delta_cost, dtype=float)))


def mixture_covariance(fix_enu_m, covariance_enu_m2, rival_enu_m, rival_covariance_enu_m2, probability):
    """The second moment about the fix of a two-solution mixture ``(3, 3)``: ``(1 - w) P + w (P_r + d d^T)``.

    Parameters
    ----------
    fix_enu_m, rival_enu_m : ndarray, shape (3,)
    covariance_enu_m2, rival_covariance_enu_m2 : ndarray, shape (3, 3)
        Each fit's own bound.
    probability : float
        The rival's weight ``w`` (:func:`rival_probability`).
    """
    apart = np.asarray(rival_enu_m, dtype=float) - np.asarray(fix_enu_m, dtype=float)
    mixed = (1.0 - probability) * np.asarray(covariance_enu_m2, dtype=float) \
        + probability * (np.asarray(rival_covariance_enu_m2, dtype=float) + np.outer(apart, apart))
    return 0.5 * (mixed + mixed.T)


def mixture_region(fix_enu_m, covariance_enu_m2, rival_enu_m, rival_covariance_enu_m2, probability):
    """The two-solution mixture's covariance ``(3, 3)`` (:func:`mixture_covariance`, same parameters), widened
    towards the rival by the least amount that makes its 99 % region hold 99 % of the mixture
    (:func:`core.estimators.region.holding`): the second moment alone reaches ``sqrt(w)`` of the way to a
    rival of weight ``w``, and leaves out one whose probability ``w`` exceeds 1 %."""
    fix, rival = np.asarray(fix_enu_m, dtype=float), np.asarray(rival_enu_m, dtype=float)
    draws = normal_draws(3)
    parts = []
    for covariance in (covariance_enu_m2, rival_covariance_enu_m2):
        values, vectors = np.linalg.eigh(0.5 * (covariance + np.swapaxes(covariance, -1, -2)))
        parts.append(draws @ (vectors * np.sqrt(np.clip(values, 0.0, None))).T)  # (N, 3) of N(0, covariance)
    offsets = np.concatenate([parts[0], rival - fix + parts[1]])
    weights = np.repeat([(1.0 - probability) / draws.shape[0], probability / draws.shape[0]], draws.shape[0])
    mixed = mixture_covariance(fix, covariance_enu_m2, rival, rival_covariance_enu_m2, probability)
    held, _ = holding(mixed[None], offsets[None], weights[None], np.outer(rival - fix, rival - fix)[None])
    return held[0]
