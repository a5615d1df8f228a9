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
from typing import NamedTuple

import numba
import numpy as np

from core.angles import wrap_point
from core.linalg import (
    cholesky_into,
    linear_predict_into,
    lower_inverse_into,
    whiten_into,
    whitened_update_into,
)
from core.measurements import AZIMUTH, TOA, measure_point
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

STATE_SIZE = 6
#: Largest move of a linearisation pass after the first, in standard deviations of the last posterior's
#: position (see :func:`update_states`).
MAX_PASS_STEP = 3.0
#: A pass that moves the estimate by less than this (same units) ends the passes.
PASS_TOLERANCE = 1e-3


class ReportModel(NamedTuple):
    """One report in the measurement model's units, as the update uses it.

    Attributes
    ----------
    stations_enu_m : ndarray, shape (M, 3)
    rotations : ndarray, shape (M, 3, 3)
        Each measurement's station and its rotation (station ENU <- common ENU) at the report's time.
    kinds : ndarray of int, shape (M,)
    values : ndarray, shape (M,)
        Radians, metres; a TOA as ``c (toa - toa_of_reference)`` (m).
    variances : ndarray, shape (M,)
        Model units squared.
    rows : ndarray of int, shape (R,)
        The measurements used, in row order; a TOA row is differenced with ``toa_reference`` (not a row).
    toa_reference : int
        Index of the reference TOA, -1 without TOA rows.
    """

    stations_enu_m: np.ndarray
    rotations: np.ndarray
    kinds: np.ndarray
    values: np.ndarray
    variances: np.ndarray
    rows: np.ndarray
    toa_reference: int


class Regression(NamedTuple):
    """The statistical linear regression ``z ~ slope p + offset + e`` of ``R`` rows on the position over the
    six cubature points of ``N(p_around, P_pp)``.

    Attributes
    ----------
    chol, inverse : ndarray, shape (3, 3)
        ``L`` (``L L^T = P_pp``) and ``L^-1``.
    centre : ndarray, shape (R,)
        The rows at ``p_around``.
    deviation : ndarray, shape (R, 6)
        The rows at each cubature point less ``centre`` (azimuths wrapped).
    mean_deviation : ndarray, shape (R,)
    whitened : ndarray, shape (3, R)
        ``L^-1 P_pz``.
    slope : ndarray, shape (R, 3)
        ``P_zp P_pp^-1``.
    """

    chol: np.ndarray
    inverse: np.ndarray
    centre: np.ndarray
    deviation: np.ndarray
    mean_deviation: np.ndarray
    whitened: np.ndarray
    slope: np.ndarray


class Workspace(NamedTuple):
    """Scratch of one report's update (``R`` rows), allocated once per call."""

    regression: Regression
    innovation: np.ndarray
    innovation_cov: np.ndarray
    innovation_chol: np.ndarray
    cross: np.ndarray
    whitened_innovation: np.ndarray
    around: np.ndarray
    around_cov: np.ndarray
    full_chol: np.ndarray
    point: np.ndarray
    work: np.ndarray


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _cubature_rows(around, chol, report, centre, deviation):
    """The model value of each of ``report``'s rows at ``around`` into ``centre`` ``(R,)``, and its deviation
    from that at the six cubature points ``around +- sqrt(3) L[:, c]`` (``L`` is ``chol``) into ``deviation``
    ``(R, 6)`` (azimuths wrapped). Angles in radians, ranges in metres, TOA rows as the pseudo-range difference
    to the reference TOA's station (m)."""
    stations_enu_m, rotations, kinds, rows = report.stations_enu_m, report.rotations, report.kinds, report.rows
    toa_reference = report.toa_reference
    spread = math.sqrt(3.0)
    x0, y0, z0 = around[0], around[1], around[2]
    for j in range(-1, 6):
        east_m, north_m, up_m = x0, y0, z0
        if j >= 0:
            c = j % 3
            sign = 1.0 if j < 3 else -1.0
            east_m, north_m, up_m = (x0 + sign * (spread * chol[0, c]), y0 + sign * (spread * chol[1, c]),
                                     z0 + sign * (spread * chol[2, c]))
        reference = 0.0
        if toa_reference >= 0:
            reference = measure_point(east_m, north_m, up_m, 0.0, stations_enu_m, rotations, toa_reference, TOA)[0]
        for r in range(rows.size):
            m = rows[r]
            kind = kinds[m]
            value = measure_point(east_m, north_m, up_m, 0.0, stations_enu_m, rotations, m, kind)[0]
            if kind == TOA:
                value = value - reference
            if j < 0:
                centre[r] = value
            else:
                change = value - centre[r]
                deviation[r, j] = wrap_point(change) if kind == AZIMUTH else change


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _regress(around, around_cov, report, regression):
    """Statistical linear regression of the report's rows on the position over ``N(around, around_cov)``
    (:class:`Regression`), from the six cubature points; False when the position covariance is not positive
    definite."""
    chol, inverse, centre = regression.chol, regression.inverse, regression.centre
    deviation, mean_deviation = regression.deviation, regression.mean_deviation
    whitened, slope = regression.whitened, regression.slope
    if not cholesky_into(around_cov[:3, :3], chol):
        return False
    lower_inverse_into(chol, inverse)
    spread = math.sqrt(3.0)
    weight = 1.0 / 6.0
    size = centre.size
    _cubature_rows(around, chol, report, centre, deviation)
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
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _innovation_into(report, prior_mean, around, regression, innovation):
    """The innovation ``(R,)`` against the regression taken at ``around``, evaluated at the prior:
    ``z - (slope p_prior + offset)`` (azimuths wrapped, TOA rows less the reference TOA's value)."""
    kinds, rows, values = report.kinds, report.rows, report.values
    centre, mean_deviation, slope = regression.centre, regression.mean_deviation, regression.slope
    reference_value = values[report.toa_reference] if report.toa_reference >= 0 else 0.0
    for r in range(rows.size):
        m = rows[r]
        raw = values[m] - centre[r]
        if kinds[m] == AZIMUTH:
            raw = wrap_point(raw)
        elif kinds[m] == TOA:
            raw -= reference_value
        raw -= mean_deviation[r]
        for k in range(3):
            raw -= slope[r, k] * (prior_mean[k] - around[k])
        innovation[r] = raw


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _innovation_cov_into(report, regression, prior_cov, out):
    """``S = slope P_pp slope^T + (P_zz - (L^-1 P_pz)^T L^-1 P_pz) + R`` ``(R, R)`` over the prior's ``P_pp``;
    TOA rows share the reference TOA's variance."""
    deviation, mean_deviation = regression.deviation, regression.mean_deviation
    whitened, slope = regression.whitened, regression.slope
    kinds, rows, variances = report.kinds, report.rows, report.variances
    reference_variance = variances[report.toa_reference] if report.toa_reference >= 0 else 0.0
    weight = 1.0 / 6.0
    for r in range(rows.size):
        for q in range(r + 1):
            total = 0.0
            for j in range(6):
                total += (deviation[r, j] - mean_deviation[r]) * (deviation[q, j] - mean_deviation[q])
            total *= weight
            for a in range(3):
                total -= whitened[a, r] * whitened[a, q]
            for k in range(3):
                for l in range(3):
                    total += slope[r, k] * prior_cov[k, l] * slope[q, l]
            if kinds[rows[r]] == TOA and kinds[rows[q]] == TOA:
                total += reference_variance
            out[r, q] = total
            out[q, r] = total
        out[r, r] += variances[rows[r]]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _cross_into(prior_cov, slope, cross):
    """The state-measurement cross-covariance of the linear model, transposed: ``cross = slope P[:3, :]``
    ``(R, 6)`` (the velocity's through its regression on the position)."""
    for r in range(slope.shape[0]):
        for i in range(STATE_SIZE):
            total = 0.0
            for k in range(3):
                total += prior_cov[i, k] * slope[r, k]
            cross[r, i] = total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pass_step2(inverse, new_mean, around):
    """Squared move of a pass, ``|L^-1 (p_new - p_around)|^2``, in standard deviations of the last posterior."""
    step = 0.0
    for a in range(3):
        total = 0.0
        for k in range(a + 1):
            total += inverse[a, k] * (new_mean[k] - around[k])
        step += total * total
    return step


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _copy_state(mean, cov, to_mean, to_cov):
    """``to_mean, to_cov = mean, cov`` (element by element)."""
    for i in range(mean.shape[0]):
        to_mean[i] = mean[i]
        for j in range(mean.shape[0]):
            to_cov[i, j] = cov[i, j]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _update_state(mean, cov, report, passes, work, new_mean, new_cov):
    """One state's posterior-linearised update with one report (module docstring) into ``new_mean``,
    ``new_cov``; returns ``(outcome, nis, log_det)``, the NIS and ``log det S`` of the first pass (NaN when it
    failed before them)."""
    around, around_cov, regression = work.around, work.around_cov, work.regression
    innovation, innovation_cov, innovation_chol = work.innovation, work.innovation_cov, work.innovation_chol
    cross, whitened = work.cross, work.whitened_innovation
    _copy_state(mean, cov, around, around_cov)
    nis = log_det = math.nan
    for iteration in range(passes):
        if not _regress(around, around_cov, report, regression):
            return PREDICTED_NOT_PD, nis, log_det
        _innovation_into(report, mean, around, regression, innovation)
        _innovation_cov_into(report, regression, cov, innovation_cov)
        _cross_into(cov, regression.slope, cross)
        if not cholesky_into(innovation_cov, innovation_chol):
            return INNOVATION_NOT_PD, nis, log_det
        chi2, half_log_det = whiten_into(innovation_chol, innovation, cross, innovation.size, whitened)
        if iteration == 0:
            # The predictive density of the report (NIS, likelihood): the prior's own regression.
            nis, log_det = chi2, 2.0 * half_log_det
        if not whitened_update_into(mean, cov, cross, whitened, new_mean, new_cov):
            return NOT_FINITE, nis, log_det
        if not cholesky_into(new_cov, work.full_chol):
            return UPDATED_NOT_PD, nis, log_det
        if iteration > 0:
            # A pass refines the linearisation where the last posterior lies; one that leaves it by more than
            # MAX_PASS_STEP of its standard deviations has jumped to another branch of the measurement (two
            # points fit four TOAs): keep the last posterior.
            step = _pass_step2(regression.inverse, new_mean, around)
            if step > MAX_PASS_STEP * MAX_PASS_STEP:
                _copy_state(around, around_cov, new_mean, new_cov)
                break
            if step < PASS_TOLERANCE * PASS_TOLERANCE:
                break  # the linearisation has settled
        _copy_state(new_mean, new_cov, around, around_cov)
    return UPDATED, nis, log_det


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _workspace(size):
    f = STATE_SIZE
    regression = Regression(np.empty((3, 3)), np.empty((3, 3)), np.empty(size), np.empty((size, 6)), np.empty(size),
                            np.empty((3, size)), np.empty((size, 3)))
    return Workspace(regression, np.empty(size), np.empty((size, size)), np.empty((size, size)),
                     np.empty((size, f)), np.empty(size), np.empty(f), np.empty((f, f)), np.empty((f, f)),
                     np.empty(f), np.empty((f, f)))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def update_states(prior, motion, report, passes, posterior):
    """Predict ``C`` states over one interval and update each with one report (module docstring).

    Parameters
    ----------
    prior : GaussianStates
        With ``motion.predict``, overwritten with the prediction.
    motion : Motion
    report : ReportModel
    passes : int
        Posterior linearisation passes (1: the unscented update).
    posterior : Posterior
        Written.
    """
    work = _workspace(report.rows.size)
    for b in range(prior.means.shape[0]):
        mean, cov = prior.means[b], prior.covs[b]
        if motion.predict:
            linear_predict_into(mean, cov, motion.transition, motion.noises[b], work.point, work.work)
        posterior.status[b], posterior.nis[b], posterior.log_det[b] = _update_state(
            mean, cov, report, passes, work, posterior.means[b], posterior.covs[b])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def network_ukf_kernel(means, covs, transition, noises, predict, stations_enu_m, rotations, kinds, values, variances,
                       rows, toa_reference, passes, new_means, new_covs, nis, log_det, status):
    """:func:`update_states` called from Python: the arrays of :class:`GaussianStates`, :class:`Motion`,
    :class:`ReportModel`, ``passes`` and :class:`Posterior` in their field order, named here. Flat at this
    boundary because numba types a named-tuple argument in Python, which costs more than the update itself.
    """
    update_states(GaussianStates(means, covs), Motion(transition, noises, predict),
                  ReportModel(stations_enu_m, rotations, kinds, values, variances, rows, toa_reference), passes,
                  Posterior(new_means, new_covs, nis, log_det, status))


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
    """:func:`update_states` without prediction for ``K`` pairs of a state and a report, the reports sharing
    their stations and kinds (one station's bearings of one time), without TOA rows: pair ``k`` updates
    ``means[states[k]]`` with ``values[k]`` (exactly as its own call would). Flat from Python, as
    :func:`network_ukf_kernel`.

    Parameters
    ----------
    means : ndarray, shape (C, 6)
    covs : ndarray, shape (C, 6, 6)
        At the reports' time.
    states : ndarray of int, shape (K,)
    stations_enu_m, rotations, kinds, rows, passes
        As :class:`ReportModel`'s and :func:`update_states`', shared by the reports.
    values, variances : ndarray, shape (K, M)
        Each pair's report.
    new_means, new_covs, nis, log_det, status
        :class:`Posterior`'s fields with ``K`` rows, written per pair.
    """
    work = _workspace(rows.size)
    for k in range(states.size):
        i = states[k]
        report = ReportModel(stations_enu_m, rotations, kinds, values[k], variances[k], rows, -1)
        status[k], nis[k], log_det[k] = _update_state(means[i], covs[i], report, passes, work, new_means[k],
                                                      new_covs[k])
