"""The joint UKF's predict and update, compiled (:func:`joint_update`; the filter around it is
:mod:`core.tracking.joint_ukf`, the unscented transform's weights in :mod:`core.tracking.unscented`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from core.angles import wrap_point
from core.linalg import (
    cholesky_into,
    linear_predict_into,
    whiten_into,
    whitened_update_into,
)
from core.measurements import (
    AZIMUTH,
    ELEVATION,
    RANGE,
    azimuth_rate_point,
    measure_point,
)
from core.tracking.kernel_types import (
    INNOVATION_NOT_PD,
    NOT_FINITE,
    PREDICTED_NOT_PD,
    UPDATED,
    UPDATED_NOT_PD,
    GaussianStates,
    Motion,
    Posterior,
)
from core.tracking.unscented import OBSERVER_AXES, OBSERVER_ENU_M


class JointEpoch(NamedTuple):
    """One epoch's measurement as the joint UKF uses it.

    Attributes
    ----------
    n_pulses : int
    interval_s : float
        ``n_pulses`` times the period the TOA difference is referred to.
    use_toa : bool
        Whether the TOA row is used (3 measurement rows without).
    measured : ndarray, shape (4,)
        Azimuth (rad), elevation (rad), TOA difference less ``interval_s`` (m), azimuth rate (rad/s).
    variances : ndarray, shape (4,)
        Their noise variances (the TOA's is that of one TOA).
    """

    n_pulses: int
    interval_s: float
    use_toa: bool
    measured: np.ndarray
    variances: np.ndarray


class JointWork(NamedTuple):
    """Scratch of :func:`joint_update` for ``F`` state components and ``R`` rows, allocated once per call.
    ``measured_rows`` and ``noise_rows`` ``(R,)`` are the epoch's used rows and their variances."""

    measured_rows: np.ndarray
    noise_rows: np.ndarray
    chol: np.ndarray
    point: np.ndarray
    work: np.ndarray
    z: np.ndarray
    centre: np.ndarray
    deviation: np.ndarray
    mean_deviation: np.ndarray
    innovation: np.ndarray
    innovation_cov: np.ndarray
    innovation_chol: np.ndarray
    cross: np.ndarray
    whitened: np.ndarray


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _joint_measurement(state, n_pulses, interval_s, use_toa, out):
    """``(B, E, c dS, Bdot)`` (without ``c dS`` unless ``use_toa``) of one joint state into ``out``
    (:class:`JointEpoch`'s scalars).

    ``c dS = |p| - |p - v T| + n period_error_m - toa_noise_m`` with ``T = interval_s`` (the previous range
    from the current state; ``period_error_m`` only in an 8-component state).
    """
    x, y, z, vx, vy, vz = state[0], state[1], state[2], state[3], state[4], state[5]
    out[0] = measure_point(x, y, z, 0.0, OBSERVER_ENU_M, OBSERVER_AXES, 0, AZIMUTH)[0]
    out[1] = measure_point(x, y, z, 0.0, OBSERVER_ENU_M, OBSERVER_AXES, 0, ELEVATION)[0]
    rate = azimuth_rate_point(x, y, vx, vy)[0]
    if use_toa:
        qx, qy, qz = x - interval_s * vx, y - interval_s * vy, z - interval_s * vz
        change = measure_point(x, y, z, 0.0, OBSERVER_ENU_M, OBSERVER_AXES, 0, RANGE)[0] \
            - math.sqrt(qx * qx + qy * qy + qz * qz) - state[state.shape[0] - 1]
        if state.shape[0] == 8:
            change += n_pulses * state[6]
        out[2] = change
        out[3] = rate
    else:
        out[2] = rate


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _joint_work(f, epoch):
    rows = 4 if epoch.use_toa else 3
    work = JointWork(np.empty(rows), np.empty(rows), np.empty((f, f)), np.empty(f), np.empty((f, f)), np.empty(rows),
                     np.empty(rows), np.empty((rows, 2 * f)), np.empty(rows), np.empty(rows), np.empty((rows, rows)),
                     np.empty((rows, rows)), np.empty((rows, f)), np.empty(rows))
    for r in range(rows):
        source = r if epoch.use_toa or r < 2 else 3
        work.measured_rows[r] = epoch.measured[source]
        work.noise_rows[r] = epoch.variances[source]
    return work


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sigma_deviations(mean, epoch, work):
    """The measurement at ``mean`` (``work.centre``) and its deviations at the ``2 F`` sigma points
    ``mean +- sqrt(F) L[:, j]`` (``work.deviation`` ``(R, 2F)``, azimuths wrapped); ``work.chol`` holds ``L``."""
    f = mean.shape[0]
    spread = math.sqrt(f)
    chol, point, deviation, z, centre = work.chol, work.point, work.deviation, work.z, work.centre
    n_pulses, interval_s, use_toa = epoch.n_pulses, epoch.interval_s, epoch.use_toa
    _joint_measurement(mean, n_pulses, interval_s, use_toa, centre)
    for j in range(2 * f):
        for i in range(f):
            offset = spread * chol[i, j % f]
            point[i] = mean[i] + offset if j < f else mean[i] - offset
        _joint_measurement(point, n_pulses, interval_s, use_toa, z)
        for r in range(deviation.shape[0]):
            deviation[r, j] = z[r] - centre[r]
        deviation[0, j] = wrap_point(deviation[0, j])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _joint_moments(epoch, work):
    """From the sigma points' deviations: the innovation ``(R,)``, its covariance ``S`` ``(R, R)`` with the
    measurement noise, and the state-measurement cross-covariance transposed ``(R, F)`` (the symmetric
    points' differences along ``L``; the last component, the TOA noise, enters the TOA row additively)."""
    rows, columns = work.deviation.shape
    f = columns // 2
    spread = math.sqrt(f)
    weight = 1.0 / (2 * f)
    deviation, mean_deviation, innovation = work.deviation, work.mean_deviation, work.innovation
    innovation_cov, cross, chol = work.innovation_cov, work.cross, work.chol
    measured_rows, noise_rows, centre = work.measured_rows, work.noise_rows, work.centre
    var_toa = epoch.variances[2]
    for r in range(rows):
        total = 0.0
        for j in range(2 * f):
            total += deviation[r, j]
        mean_deviation[r] = total * weight
        innovation[r] = measured_rows[r] - centre[r]
    innovation[0] = wrap_point(innovation[0])
    for r in range(rows):
        innovation[r] -= mean_deviation[r]
        for q in range(r + 1):
            total = 0.0
            for j in range(2 * f):
                total += (deviation[r, j] - mean_deviation[r]) * (deviation[q, j] - mean_deviation[q])
            innovation_cov[r, q] = total * weight
            innovation_cov[q, r] = total * weight
        innovation_cov[r, r] += noise_rows[r]
        for i in range(f - 1):
            total = 0.0
            for j in range(i + 1):
                total += chol[i, j] * (deviation[r, j] - deviation[r, j + f])
            cross[r, i] = total * (spread * weight)
        cross[r, f - 1] = var_toa if epoch.use_toa and r == 2 else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fresh_toa_prior(mean, cov, var_toa, new_mean, new_cov):
    """``mean``, ``cov`` with the last component (the reference TOA's noise) replaced by the new TOA's, prior
    ``N(0, var_toa)`` and independent (lower triangle of ``new_cov``)."""
    f = mean.shape[0]
    for i in range(f - 1):
        new_mean[i] = mean[i]
        for j in range(i + 1):
            new_cov[i, j] = cov[i, j]
    new_mean[f - 1] = 0.0
    for j in range(f - 1):
        new_cov[f - 1, j] = 0.0
    new_cov[f - 1, f - 1] = var_toa


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _joint_update_state(mean, cov, epoch, work, new_mean, new_cov):
    """One predicted state's update (:func:`joint_update`) into ``new_mean``, ``new_cov``; returns
    ``(outcome, nis, log_det)`` (NaN before the innovation is whitened)."""
    if not cholesky_into(cov, work.chol):
        return PREDICTED_NOT_PD, math.nan, math.nan
    _sigma_deviations(mean, epoch, work)
    _joint_moments(epoch, work)
    if not cholesky_into(work.innovation_cov, work.innovation_chol):
        return INNOVATION_NOT_PD, math.nan, math.nan
    chi2, half_log_det = whiten_into(work.innovation_chol, work.innovation, work.cross, work.innovation.size,
                                     work.whitened)
    _fresh_toa_prior(mean, cov, epoch.variances[2], new_mean, new_cov)
    if not whitened_update_into(new_mean, new_cov, work.cross, work.whitened, new_mean, new_cov):
        return NOT_FINITE, chi2, 2.0 * half_log_det
    if not cholesky_into(new_cov, work.chol):
        return UPDATED_NOT_PD, chi2, 2.0 * half_log_det
    return UPDATED, chi2, 2.0 * half_log_det


@numba.njit(cache=True, nogil=True, error_model="numpy")
def joint_update(prior, motion, epoch, posterior):
    """Predict and update ``C`` joint UKF states (layout in :mod:`core.tracking.state`) with one epoch.

    Prediction ``mean <- F mean``, ``cov <- F cov F^T + Q`` (in place, exactly
    symmetric). Update: the ``2 F`` sigma points ``mean +- sqrt(F) L[:, j]``
    (``L L^T = cov``, weights ``1 / (2 F)``, see the module docstring), the
    measurement ``(B, E, [c dS,] Bdot)`` (:func:`_joint_measurement`; azimuth
    deviations wrapped), the innovation covariance ``S = L_S L_S^T`` with
    the measurement noise, and the whitened update: with ``v = cov_xz L_S^-T``
    and ``t = L_S^-1 innovation``, the mean moves by ``v t``, the covariance
    loses ``v v^T`` (exactly symmetric), the NIS is ``|t|^2`` and ``log det S
    = 2 sum log diag L_S``.

    The last component (the reference TOA's noise) becomes the new TOA's
    noise, prior ``N(0, var_toa)``: with a usable TOA it enters the TOA row
    additively (its covariance with the TOA row is ``var_toa``), so its
    posterior is correlated with the rest; without, it is a fresh,
    independent noise.

    Parameters
    ----------
    prior : GaussianStates
        With ``motion.predict``, overwritten with the prediction.
    motion : Motion
    epoch : JointEpoch
    posterior : Posterior
        Written (NIS with 4, or 3, degrees of freedom).
    """
    work = _joint_work(prior.means.shape[1], epoch)
    for b in range(prior.means.shape[0]):
        mean, cov = prior.means[b], prior.covs[b]
        if motion.predict:
            linear_predict_into(mean, cov, motion.transition, motion.noises[b], work.point, work.work)
        posterior.status[b], posterior.nis[b], posterior.log_det[b] = _joint_update_state(
            mean, cov, epoch, work, posterior.means[b], posterior.covs[b])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def joint_ukf_kernel(means, covs, transition, noises, predict, n_pulses, interval_s, use_toa, measured, variances,
                     new_means, new_covs, nis, log_det, status):
    """:func:`joint_update` called from Python: the arrays of :class:`GaussianStates`, :class:`Motion`,
    :class:`JointEpoch` and :class:`Posterior` in their field order, named here. Flat at this boundary because
    numba types a named-tuple argument in Python, which costs more than the update itself."""
    joint_update(GaussianStates(means, covs), Motion(transition, noises, predict),
                 JointEpoch(n_pulses, interval_s, use_toa, measured, variances),
                 Posterior(new_means, new_covs, nis, log_det, status))
