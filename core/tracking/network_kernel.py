"""The network tracker's per-report work, compiled: predict a set of constant-velocity states and update them
with one report through :func:`core.measurements.measure_point`.

State ``[east_m, north_m, up_m, east_mps, north_mps, up_mps]`` in the session's common ENU frame. Every
measurement of a report depends on the position only, so the unscented transform runs over the position:
the six cubature points ``p +- sqrt(3) L[:, j]`` (``L L^T = P_pp``, weights 1/6; the third-degree spherical
rule, every weight positive, so the transformed covariance is positive semi-definite by construction). The
velocity's covariance with the measurement then follows exactly from its linear regression on the
position (``P_vz = P_vp P_pp^-1 P_pz``, exact for a Gaussian state because the measurement depends on the
position alone), at half the model evaluations of a transform of the whole state.

Each update iterates the posterior linearisation (Garcia-Fernandez, Svensson, Morelande and Sarkka 2015):
the statistical linear regression of the measurement on the position, ``z ~ A p + b + e`` with
``cov(e) = P_zz - A P_pp A^T``, is taken over the cubature points of the current posterior (the prior in the
first pass, which is the plain unscented update) and the prior is updated with that linear model; each pass
linearises where the posterior lies. Where the prior is wide against the measurement's curvature (a range
learnt from bearings) this is what reaches the bound; where it is narrow the passes agree with the first
(the caller, :mod:`core.tracking.network_update`, gives a report without bearings one pass). A
pass that moves the estimate by more than :data:`MAX_PASS_STEP` standard deviations of the last posterior
has jumped to another solution of the measurement and is not taken; the NIS and the likelihood are the
first pass's (the report's predictive density).

TOA rows are differences ``TOA_i - TOA_ref`` of one report's TOAs (as pseudo-ranges, metres), with the
differences' full noise covariance (``sigma_i^2`` on the diagonal plus ``sigma_ref^2`` everywhere): that is
the exact marginal over the unknown emission time under a flat prior on it, whichever TOA is the
reference. The update is in whitened form: with the innovation covariance ``S = L_S L_S^T``,
``V = L_S^-1 P_zx`` and ``t = L_S^-1 innovation``, the mean moves by ``V^T t``, the covariance loses
``V^T V`` (exactly symmetric), the NIS is ``|t|^2`` and ``log det S = 2 sum log diag L_S`` (of the last pass).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from core.angles import wrap_point
from core.linalg import cholesky_into, linear_predict_into, lower_inverse_into, whiten_into
from core.measurements import AZIMUTH, TOA, measure_point

#: Outcome of :func:`network_ukf_kernel` per state: updated; the predicted position covariance, the
#: innovation covariance or the updated covariance not positive definite; the update not finite.
UPDATED, PREDICTED_NOT_PD, INNOVATION_NOT_PD, UPDATED_NOT_PD, NOT_FINITE = range(5)

STATE_SIZE = 6
#: Largest move of a linearisation pass after the first, in standard deviations of the last posterior's
#: position (see :func:`network_ukf_kernel`).
MAX_PASS_STEP = 3.0
#: A pass that moves the estimate by less than this (same units) ends the passes.
PASS_TOLERANCE = 1e-3


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rows_at(east_m, north_m, up_m, stations_enu_m, rotations, kinds, rows, toa_reference, out):
    """The model value of each row at a position: angles (rad), ranges (m), TOA rows as the pseudo-range
    difference to the reference TOA's station (m)."""
    reference = 0.0
    if toa_reference >= 0:
        reference = measure_point(east_m, north_m, up_m, 0.0, stations_enu_m, rotations, toa_reference, TOA)[0]
    for r in range(rows.size):
        m = rows[r]
        value = measure_point(east_m, north_m, up_m, 0.0, stations_enu_m, rotations, m, kinds[m])[0]
        out[r] = value - reference if kinds[m] == TOA else value


@numba.njit(cache=True, nogil=True, error_model="numpy")
def network_ukf_kernel(means, covs, transition, noises, predict, stations_enu_m, rotations, kinds, values, variances,
                       rows, toa_reference, passes, new_means, new_covs, nis, log_det, status):
    """Predict ``C`` states over one interval and update each with one report (module docstring).

    Parameters
    ----------
    means : ndarray, shape (C, 6)
    covs : ndarray, shape (C, 6, 6)
        With ``predict``, overwritten with the prediction.
    transition : ndarray, shape (6, 6)
    noises : ndarray, shape (C, 6, 6)
        Each state's process noise over the interval (:func:`core.tracking.motion.transitions`).
    predict : bool
        False: ``means`` and ``covs`` are already at the report's time.
    stations_enu_m : ndarray, shape (M, 3)
    rotations : ndarray, shape (M, 3, 3)
        Each measurement's station and its rotation (station ENU <- common ENU) at the report's time.
    kinds : ndarray of int, shape (M,)
    values : ndarray, shape (M,)
        Model units: radians, metres, TOAs as ``c (toa - toa_of_reference)`` (m).
    variances : ndarray, shape (M,)
        Model units squared.
    rows : ndarray of int, shape (R,)
        The measurements used, in row order; a TOA row is differenced with ``toa_reference`` (not a row).
    toa_reference : int
        Index of the reference TOA, -1 without TOA rows.
    passes : int
        Posterior linearisation passes (1: the unscented update).
    new_means : ndarray, shape (C, 6)
    new_covs : ndarray, shape (C, 6, 6)
    nis, log_det : ndarray, shape (C,)
    status : ndarray of int, shape (C,)
        Written: the updated states, the NIS (chi-square with ``R`` degrees of freedom when the model holds),
        ``log det S`` and the outcome (:data:`UPDATED` ... :data:`NOT_FINITE`).
    """
    count = means.shape[0]
    f = STATE_SIZE
    size = rows.size
    spread = math.sqrt(3.0)
    weight = 1.0 / 6.0
    work = np.empty((f, f))
    point = np.empty(f)
    chol = np.empty((3, 3))
    inverse = np.empty((3, 3))
    full_chol = np.empty((f, f))
    centre = np.empty(size)
    z = np.empty(size)
    deviation = np.empty((size, 6))
    mean_deviation = np.empty(size)
    whitened = np.empty((3, size))
    slope = np.empty((size, 3))
    innovation = np.empty(size)
    innovation_cov = np.empty((size, size))
    innovation_chol = np.empty((size, size))
    v = np.empty((size, f))
    t = np.empty(size)
    around = np.empty(f)
    around_cov = np.empty((f, f))
    reference_variance = variances[toa_reference] if toa_reference >= 0 else 0.0
    reference_value = values[toa_reference] if toa_reference >= 0 else 0.0
    for b in range(count):
        mean, cov, new_mean, new_cov = means[b], covs[b], new_means[b], new_covs[b]
        if predict:
            linear_predict_into(mean, cov, transition, noises[b], point, work)
        for i in range(f):
            around[i] = mean[i]
            for j in range(f):
                around_cov[i, j] = cov[i, j]
        outcome = UPDATED
        for iteration in range(passes):
            # Statistical linear regression of the rows on the position over N(around, around_cov):
            # z ~ slope p + offset + e, cov(e) = P_zz - slope P_pp slope^T.
            if not cholesky_into(around_cov[:3, :3], chol):
                outcome = PREDICTED_NOT_PD
                break
            lower_inverse_into(chol, inverse)
            x0, y0, z0 = around[0], around[1], around[2]
            _rows_at(x0, y0, z0, stations_enu_m, rotations, kinds, rows, toa_reference, centre)
            for j in range(6):
                c = j % 3
                sign = 1.0 if j < 3 else -1.0
                _rows_at(x0 + sign * (spread * chol[0, c]), y0 + sign * (spread * chol[1, c]),
                         z0 + sign * (spread * chol[2, c]), stations_enu_m, rotations, kinds, rows, toa_reference, z)
                for r in range(size):
                    change = z[r] - centre[r]
                    deviation[r, j] = wrap_point(change) if kinds[rows[r]] == AZIMUTH else change
            for r in range(size):
                total = 0.0
                for j in range(6):
                    total += deviation[r, j]
                mean_deviation[r] = total * weight
                # L^-1 P_pz, column r: the points' symmetric differences along each whitened direction.
                for a in range(3):
                    whitened[a, r] = (spread * weight) * (deviation[r, a] - deviation[r, a + 3])
                for k in range(3):
                    total = 0.0
                    for a in range(k, 3):
                        total += whitened[a, r] * inverse[a, k]
                    slope[r, k] = total
            # Innovation against the regression at the prior: z - (slope p_prior + offset).
            for r in range(size):
                m = rows[r]
                raw = values[m] - centre[r]
                if kinds[m] == AZIMUTH:
                    raw = wrap_point(raw)
                elif kinds[m] == TOA:
                    raw -= reference_value
                raw -= mean_deviation[r]
                for k in range(3):
                    raw -= slope[r, k] * (mean[k] - around[k])
                innovation[r] = raw
            # S = slope P_pp slope^T + (P_zz - L^-1 P_pz squared) + R, over the prior's P_pp.
            for r in range(size):
                for q in range(r + 1):
                    total = 0.0
                    for j in range(6):
                        total += (deviation[r, j] - mean_deviation[r]) * (deviation[q, j] - mean_deviation[q])
                    total *= weight
                    for a in range(3):
                        total -= whitened[a, r] * whitened[a, q]
                    for k in range(3):
                        for l in range(3):
                            total += slope[r, k] * cov[k, l] * slope[q, l]
                    if kinds[rows[r]] == TOA and kinds[rows[q]] == TOA:
                        total += reference_variance
                    innovation_cov[r, q] = total
                    innovation_cov[q, r] = total
                innovation_cov[r, r] += variances[rows[r]]
            for r in range(size):
                for i in range(f):
                    total = 0.0
                    for k in range(3):
                        total += cov[i, k] * slope[r, k]
                    v[r, i] = total
            if not cholesky_into(innovation_cov, innovation_chol):
                outcome = INNOVATION_NOT_PD
                break
            chi2, half_log_det = whiten_into(innovation_chol, innovation, v, size, t)
            if iteration == 0:
                # The predictive density of the report (NIS, likelihood): the prior's own regression.
                nis[b] = chi2
                log_det[b] = 2.0 * half_log_det
            finite = True
            for i in range(f):
                total = mean[i]
                for r in range(size):
                    total += v[r, i] * t[r]
                new_mean[i] = total
                finite = finite and math.isfinite(total)
                for j in range(i + 1):
                    total = cov[i, j]
                    for r in range(size):
                        total -= v[r, i] * v[r, j]
                    new_cov[i, j] = total
                    new_cov[j, i] = total
                    finite = finite and math.isfinite(total)
            if not finite:
                outcome = NOT_FINITE
                break
            if not cholesky_into(new_cov, full_chol):
                outcome = UPDATED_NOT_PD
                break
            if iteration > 0:
                # A pass refines the linearisation where the last posterior lies; one that leaves it by more
                # than MAX_PASS_STEP of its standard deviations has jumped to another branch of the
                # measurement (two points fit four TOAs): keep the last posterior.
                step = 0.0
                for a in range(3):
                    total = 0.0
                    for k in range(a + 1):
                        total += inverse[a, k] * (new_mean[k] - around[k])
                    step += total * total
                if step > MAX_PASS_STEP * MAX_PASS_STEP:
                    for i in range(f):
                        new_mean[i] = around[i]
                        for j in range(f):
                            new_cov[i, j] = around_cov[i, j]
                    break
                if step < PASS_TOLERANCE * PASS_TOLERANCE:
                    break  # the linearisation has settled
            for i in range(f):
                around[i] = new_mean[i]
                for j in range(f):
                    around_cov[i, j] = new_cov[i, j]
        status[b] = outcome


@numba.njit(cache=True, nogil=True, error_model="numpy")
def predict_kernel(means, covs, transition, noises):
    """``mean <- F mean``, ``cov <- F cov F^T + Q`` of ``C`` states in place (exactly symmetric)."""
    point = np.empty(STATE_SIZE)
    work = np.empty((STATE_SIZE, STATE_SIZE))
    for b in range(means.shape[0]):
        linear_predict_into(means[b], covs[b], transition, noises[b], point, work)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def network_ukf_pairs(means, covs, states, stations_enu_m, rotations, kinds, values, variances, rows, passes,
                      new_means, new_covs, nis, log_det, status):
    """:func:`network_ukf_kernel` without prediction for ``K`` pairs of a state and a report, the reports
    sharing their stations and kinds (one station's bearings of one time), without TOA rows: pair ``k`` updates
    ``means[states[k]]`` with ``values[k]`` (exactly as its own call would).

    Parameters
    ----------
    means : ndarray, shape (C, 6)
    covs : ndarray, shape (C, 6, 6)
        At the reports' time.
    states : ndarray of int, shape (K,)
    stations_enu_m, rotations, kinds, rows, passes
        As :func:`network_ukf_kernel`'s, shared by the reports.
    values, variances : ndarray, shape (K, M)
        Each pair's report.
    new_means : ndarray, shape (K, 6)
    new_covs : ndarray, shape (K, 6, 6)
    nis, log_det : ndarray, shape (K,)
    status : ndarray of int, shape (K,)
        Written, per pair.
    """
    transition = np.eye(STATE_SIZE)
    noises = np.zeros((1, STATE_SIZE, STATE_SIZE))
    for k in range(states.size):
        i = states[k]
        network_ukf_kernel(means[i:i + 1], covs[i:i + 1], transition, noises, False, stations_enu_m, rotations, kinds,
                           values[k], variances[k], rows, -1, passes, new_means[k:k + 1], new_covs[k:k + 1],
                           nis[k:k + 1], log_det[k:k + 1], status[k:k + 1])
