"""The named structures the tracking filters' compiled updates share: the Gaussian states, their linear
motion over an interval and the update's outputs (:mod:`core.tracking.joint_kernel`,
:mod:`core.tracking.network_kernel`). Numba takes these named tuples inside a kernel at no cost; from Python a
kernel is called with their arrays (typing a named tuple there costs more than a filter update).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: An update's outcome per state: updated; the predicted covariance, the innovation covariance or the updated
#: covariance not positive definite; the update not finite.
UPDATED, PREDICTED_NOT_PD, INNOVATION_NOT_PD, UPDATED_NOT_PD, NOT_FINITE = range(5)


class GaussianStates(NamedTuple):
    """``C`` Gaussian states of one filter (its layout: :mod:`core.tracking.state` for the joint UKF,
    :mod:`core.tracking.network_kernel` for the network tracker).

    Attributes
    ----------
    means : ndarray, shape (C, F)
    covs : ndarray, shape (C, F, F)
    """

    means: np.ndarray
    covs: np.ndarray


class Motion(NamedTuple):
    """The linear motion over one interval (:func:`core.tracking.motion.transitions`).

    Attributes
    ----------
    transition : ndarray, shape (F, F)
    noises : ndarray, shape (C, F, F)
        Each state's process noise over the interval.
    predict : bool
        False: the states are already predicted (``transition`` and ``noises`` unused).
    """

    transition: np.ndarray
    noises: np.ndarray
    predict: bool


class Posterior(NamedTuple):
    """An update's outputs, one per state.

    Attributes
    ----------
    means : ndarray, shape (C, F)
    covs : ndarray, shape (C, F, F)
    nis : ndarray, shape (C,)
        Chi-square with as many degrees of freedom as measurement rows when the model holds.
    log_det : ndarray, shape (C,)
        ``log det S``.
    status : ndarray of int, shape (C,)
        :data:`UPDATED` ... :data:`NOT_FINITE`; a state's other outputs are meaningful from
        :data:`UPDATED_NOT_PD` on.
    """

    means: np.ndarray
    covs: np.ndarray
    nis: np.ndarray
    log_det: np.ndarray
    status: np.ndarray
