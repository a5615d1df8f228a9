"""Interacting multiple model (Blom and Bar-Shalom 1988) over process-noise levels of the joint UKF.

Modes differ only in the acceleration noise of the constant-velocity prediction, so they share one state
layout and mixing is exact moment matching. Per epoch: the Markov switching matrix over the interval
mixes the mode-conditioned states (:func:`mixed`); each mode is predicted and updated by
:func:`core.tracking.joint_ukf.joint_epoch`; the mode probabilities are the mixed prior weights times
each update's innovation density; the reported state is the moments of the modes.
"""

from __future__ import annotations

import math

import numpy as np

from core.tracking.range_mixture import components_of, moments
from core.tracking.state import Components

#: Smallest mode probability kept (a mode must be able to come back).
MIN_PROBABILITY = 1e-9


def switching_matrix(modes: int, dt_s: float, mean_sojourn_s: float) -> np.ndarray:
    """``(M, M)`` row-stochastic: stay with ``exp(-dt / sojourn)``, the rest spread evenly."""
    stay = math.exp(-dt_s / mean_sojourn_s)
    out = np.full((modes, modes), (1.0 - stay) / (modes - 1))
    np.fill_diagonal(out, stay)
    return out


def mixed(weights: np.ndarray, means: np.ndarray, covariances: np.ndarray, switching: np.ndarray):
    """The IMM mixing step, for one set of modes or a batch of them (leading axes).

    Parameters
    ----------
    weights : ndarray, shape (..., M)
        Mode probabilities after the last epoch (summing to one, or to the batch member's total weight).
    means : ndarray, shape (..., M, F)
    covariances : ndarray, shape (..., M, F, F)
    switching : ndarray, shape (M, M)
        ``switching[i, j]``: probability of going from mode ``i`` to ``j`` over the interval.

    Returns
    -------
    prior : ndarray, shape (..., M)
        Predicted mode probabilities ``c_j = sum_i switching[i, j] weights[i]``.
    means, covariances : ndarray, shape (..., M, F) and (..., M, F, F)
        Each mode's start: the moments of the modes weighted by ``switching[i, j] weights[i] / c_j``.
    """
    joint = weights[..., :, None] * switching
    prior = joint.sum(axis=-2)
    mixing = np.swapaxes(joint / prior[..., None, :], -1, -2)
    mean, cov = moments(mixing, means[..., None, :, :], covariances[..., None, :, :, :])
    return prior, mean, cov


def uniform_modes(mean: np.ndarray, cov: np.ndarray, modes: int) -> Components:
    """``modes`` copies of one state with equal probabilities: the IMM's start."""
    return components_of(np.full(modes, 1.0 / modes), np.tile(mean, (modes, 1)), np.tile(cov, (modes, 1, 1)))


def floored(weights: np.ndarray) -> np.ndarray:
    """Probabilities floored at :data:`MIN_PROBABILITY` and renormalised."""
    out = np.maximum(weights, MIN_PROBABILITY)
    return out / out.sum()
