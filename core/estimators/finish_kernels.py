"""The finisher's compiled numbers and verdicts (:func:`core.estimators.finish.finish` words them).

:func:`fix_kernel` computes, each problem of a batch on its own, the
residuals, chi-square, CRLB, covariance, studentized residuals and the
line-of-sight facts of an estimate (:func:`_finish_kernel`), then the degrees
of freedom, sigma scales, worst measurement, GDOP and the verdict bits
(:func:`_verdicts_kernel`).

The chi-square and studentized residuals judge the measurements, not the
method: they are those of the residuals the ML fit of the used measurements
leaves (:func:`_ml_residuals`), whatever estimate a method returned.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from core.angles import wrap_point
from core.crlb import (OBSERVABILITY_THRESHOLD, SandwichScratch, gdop_point, invert_point, normal_point,
                       parameters_point, reference_sigma_point, sandwich_point)
from core.estimators.loss import loss_point
from core.kernel_data import Frames, Measurements
from core.measurements import AZIMUTH, ELEVATION, SPEED_OF_LIGHT_MPS, TOA, ahead_point, measure_point, toa_offset_point
from core.problem.frame import onto_altitude_point

#: Studentized residual above which a measurement is flagged as a suspected outlier.
OUTLIER_SIGMAS = 4.0
#: A detected fault is isolated (its measurement named) only with two degrees of freedom or more and where the
#: largest studentized residual exceeds every other request measurement's by more than this many standard
#: deviations of their difference (``2 (1 -+ rho)``, ``rho`` their correlation): were the other one the fault,
#: so large a lead would happen with probability below ``norm.sf`` of it (0.1 %). RAIM's isolation: with one
#: degree of freedom every studentized residual is as large, and none can be told from another.
ISOLATION_SIGMAS = 3.09
#: Lines of sight closer than this to parallel (rad) make a fix collinear.
COLLINEAR_SPREAD_RAD = np.deg2rad(2.0)
#: Minimum unit-diagonal information eigenvalue below which a fix is ill-conditioned.
ILL_CONDITIONED_EIGENVALUE = 1e-6
#: Robust-loss weight factor (``rho'``) below which a measurement is named as downweighted.
DOWNWEIGHTED_FACTOR = 0.1
#: A fix whose CRLB (root of its trace) exceeds this many times its distance from its farthest station is not
#: determined by the measurements: the fit ran off along a direction they do not see (parallel lines of sight
#: meet at infinity, where every residual vanishes and the Jacobi-scaled information still looks regular).
RUNAWAY_SIGMA_RATIO = 1e6

# Bits of the verdicts a problem's measurements raise (:func:`_verdicts_kernel`, and COARSE_TOA:
# :func:`core.estimators.finish._coarse_toas`); RUNAWAY makes the fix an error, and so does SINGULAR where the covariance is the
# inverse information.
(ILL, OUTLIER, COLLINEAR, BEHIND, ZENITH, EXCLUDED, UNUSED, DOWNWEIGHTED, RUNAWAY, COARSE_TOA, SINGULAR,
 NOT_CONVERGED, NOT_ISOLABLE) = (1 << k for k in range(13))


class Estimate(NamedTuple):
    """An estimator's estimates of a batch, as the finisher judges them (:func:`fix_kernel`).

    Attributes
    ----------
    position_enu_m : ndarray, shape (B, 3)
    bias_m : ndarray, shape (B,)
        The TOA offset (metres of pseudo-range), where ``has_bias``.
    has_bias : bool
        False: the offset is the one that fits best at each position.
    converged : ndarray of bool, shape (B,)
        The estimator's own verdict.
    sigmas : ndarray, shape (B, M)
        The sigmas judged by (problem units): the batch's, or those the estimator estimated.
    excluded : ndarray of bool, shape (B, M)
        Measurements outlier exclusion set aside (not in the batch's ``valid``).
    loss_code : int
        The robust loss's code, -1 for none.
    c2 : float
        Its scale squared (1 for none).
    """

    position_enu_m: np.ndarray
    bias_m: np.ndarray
    has_bias: bool
    converged: np.ndarray
    sigmas: np.ndarray
    excluded: np.ndarray
    loss_code: int
    c2: float


class _Linearised(NamedTuple):
    """One problem's measurements at an estimate, as :func:`_ml_residuals` takes them: model values and weights
    ``(M,)``, the whitened local Jacobian ``local`` ``(4, M)``, the inverse information ``params`` ``(4, 4)``,
    the residuals ``(M,)`` and a Gauss-Newton step ``(4,)``."""

    model_values: np.ndarray
    weights: np.ndarray
    local: np.ndarray
    params: np.ndarray
    residual: np.ndarray
    step: np.ndarray


class _Refit(NamedTuple):
    """Where :func:`_ml_residuals` refines the ML fit: the point, its Jacobian, whitened local Jacobian,
    information, inverse information (``params``), CRLB (``position``), local axes and free parameters, and
    scratch."""

    gradient: np.ndarray
    point: np.ndarray
    jacobian: np.ndarray
    local: np.ndarray
    information: np.ndarray
    params: np.ndarray
    position: np.ndarray
    axes: np.ndarray
    free: np.ndarray
    work: np.ndarray
    vectors: np.ndarray


class Finished(NamedTuple):
    """What :func:`fix_kernel` returns for a batch, in six arrays (views of them unpack the rest,
    :func:`core.estimators.finish.finish`): planes of a few arrays, since numba boxes each returned array on
    its own, a cost per array that a batch of one feels.

    Attributes
    ----------
    measured : ndarray, shape (4, B, M)
        The residuals (problem units), normalized and studentized residuals, and the loss's weight factors.
    bounds : ndarray, shape (2, B, 3, 3)
        The CRLB and the covariance (made symmetric).
    seen_lines : ndarray of bool, shape (2, B, M)
        Per line of sight, whether the fix is behind its station, and at its zenith.
    scalars : ndarray, shape (8, B)
        Chi-square, the smallest unit-diagonal information eigenvalue, the lines' smallest spread, the degrees
        of freedom as floats (NaN where there are none: the p-value's), the plain and the reported sigma scale,
        the worst measurement's studentized residual, and GDOP.
    counts : ndarray of int, shape (3, B)
        The degrees of freedom, the worst measurement and the verdict bits.
    isolated : ndarray of bool, shape (B,)
        Whether the largest studentized residual singles its measurement out (``ISOLATION_SIGMAS``).
    """

    measured: np.ndarray
    bounds: np.ndarray
    seen_lines: np.ndarray
    scalars: np.ndarray
    counts: np.ndarray
    isolated: np.ndarray


class _Numbers(NamedTuple):
    """What :func:`_finish_kernel` computes for a batch: ``measured`` ``(4, B, M)`` (residuals in problem units,
    normalized and studentized residuals, the loss's weight factors), ``bounds`` ``(2, B, 3, 3)`` (the CRLB and
    the covariance), ``seen_lines`` ``(2, B, M)`` (behind the station, at its zenith), and per problem the
    chi-square, the count of measurements in it, the smallest unit-diagonal information eigenvalue, the robust
    cost, the reference sigma, the lines' smallest spread, whether the fix ran off, and how far its largest
    studentized residual stands out (:func:`_separation`)."""

    measured: np.ndarray
    bounds: np.ndarray
    seen_lines: np.ndarray
    chi2: np.ndarray
    known_count: np.ndarray
    smallest: np.ndarray
    robust_cost: np.ndarray
    sigma_ref: np.ndarray
    spread: np.ndarray
    runaway: np.ndarray
    separation: np.ndarray


#: A fit whose residuals are judged lies farther than this (squared Mahalanobis distance, its own information)
#: from the ML fit one Gauss-Newton step points to: the step's linearisation is then refined by further steps.
REFINE_MAHALANOBIS2 = 1.0
#: ... at most this many.
REFINE_STEPS = 20


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gauss_newton_step(residual, local, params, weights, gradient, step):
    """``step`` ``(4,)`` = ``params local W residual`` (``gradient`` ``(4,)``: ``local W residual``); returns
    ``step . gradient``, the chi-square the step removes to first order (its squared Mahalanobis length)."""
    width = residual.size
    for i in range(4):
        g = 0.0
        for m in range(width):
            g += local[i, m] * weights[m] * residual[m]
        gradient[i] = g
    removed = 0.0
    for i in range(4):
        total = 0.0
        for j in range(4):
            total += params[i, j] * gradient[j]
        step[i] = total
        removed += total * gradient[i]
    return removed


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _residuals_at(x, bias, stations, rotations, kinds, model_values, weights, count, residual, jacobian):
    """Residuals ``(M,)`` (model units, angles wrapped; 0 past ``count``) and Jacobian ``(4, M)`` at ``x``;
    returns their chi-square."""
    chi2 = 0.0
    for m in range(kinds.size):
        predicted, jacobian[0, m], jacobian[1, m], jacobian[2, m], jacobian[3, m] = measure_point(
            x[0], x[1], x[2], bias, stations, rotations, m, kinds[m])
        if m >= count:
            residual[m] = 0.0
            continue
        r = model_values[m] - predicted
        if kinds[m] == AZIMUTH or kinds[m] == ELEVATION:
            r = wrap_point(r)
        residual[m] = r
        chi2 += weights[m] * r * r
    return chi2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _ml_residuals(position, bias, measurements, frames, b, at_estimate, fit):
    """The residuals the ML fit of problem ``b``'s measurements leaves, to first order from an estimate.

    On entry ``at_estimate`` (:class:`_Linearised`) holds the residuals at ``position`` and the whitened
    Jacobian and inverse information there; its ``step`` becomes the Gauss-Newton step to the ML fit, so
    that ``residual - local^T step`` are its residuals (exact for a linear model). When that step is longer than
    ``REFINE_MAHALANOBIS2`` (an inefficient closed form, an unfinished iteration), its linearisation is not
    trusted: Gauss-Newton steps are taken from ``position`` while they lower the chi-square (at most
    ``REFINE_STEPS``), and ``residual``, ``step``, and ``fit.local`` / ``fit.params`` (then returned True) are
    those at the last point (``fit``: a :class:`_Refit`).
    """
    model_values, weights, local, params, residual, step = at_estimate
    gradient, point, jacobian_fit, local_fit, information_fit, params_fit, position_fit, axes_fit, free, work, \
        vectors = fit
    stations, rotations, kinds = measurements.stations_enu_m[b], measurements.rotations[b], measurements.kinds[b]
    count = measurements.n_measurements[b]
    altitude_m, has_toa, geodetic = frames.altitude_m[b], frames.has_toa[b], frames.geodetic[b]
    origin_ecef_m, origin_rotation = frames.origin_ecef_m[b], frames.origin_rotation[b]
    removed = _gauss_newton_step(residual, local, params, weights, gradient, step)
    if not removed > REFINE_MAHALANOBIS2:
        return False
    constrained = not math.isnan(altitude_m)
    for i in range(3):
        point[i] = position[i]
    current = 0.0
    for m in range(count):
        current += weights[m] * residual[m] * residual[m]
    moved = False
    trial = np.empty(3)
    trial_residual = np.empty(residual.size)
    for _ in range(REFINE_STEPS):
        if moved:
            parameters_point(point, altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation, axes_fit, free)
        else:
            parameters_point(position, altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation, axes_fit, free)
        for j in range(3):
            if constrained:
                trial[j] = point[j] + step[0] * axes_fit[0, j] + step[1] * axes_fit[1, j]
            else:
                trial[j] = point[j] + step[j]
        if constrained:
            onto_altitude_point(trial, altitude_m, geodetic, origin_ecef_m, origin_rotation)
        trial_bias = bias + step[3]
        chi2 = _residuals_at(trial, trial_bias, stations, rotations, kinds, model_values, weights, count,
                             trial_residual, jacobian_fit)
        if not chi2 < current:
            break
        moved = True
        current, bias = chi2, trial_bias
        for j in range(3):
            point[j] = trial[j]
        for m in range(residual.size):
            residual[m] = trial_residual[m]
        parameters_point(point, altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation, axes_fit, free)
        normal_point(jacobian_fit, weights, axes_fit, constrained, free, local_fit, information_fit)
        if not invert_point(information_fit, axes_fit, constrained, free, params_fit, position_fit, work,
                            vectors) > OBSERVABILITY_THRESHOLD:
            break
        if not _gauss_newton_step(residual, local_fit, params_fit, weights, gradient, step) > 1e-12:
            break
    if not moved:
        return False
    # The step from the last point (``local_fit``/``params_fit`` there, unless its inversion failed: then none).
    if not invert_point(information_fit, axes_fit, constrained, free, params_fit, position_fit, work,
                        vectors) > OBSERVABILITY_THRESHOLD:
        for i in range(4):
            step[i] = 0.0
    else:
        _gauss_newton_step(residual, local_fit, params_fit, weights, gradient, step)
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _separation(studentized, room, weights, local, params, sigmas, measurements, b):
    """How far one problem's largest studentized residual stands out: the least, over the other request
    measurements ``j``, of ``(|t_w| - |t_j|) / sd(t_w -+ t_j)``, the sd ``sqrt(2 (1 -+ rho_wj))`` from their
    correlation ``rho_wj = -H_wj / sqrt((1 - h_w)(1 - h_j))`` (``H`` the hat matrix of ``local`` ``(4, M)`` and
    ``params`` ``(4, 4)``; ``room`` ``(M,)``: ``1 - h``) of problem ``b`` of ``measurements``
    (:class:`~core.kernel_data.Measurements`), whose sigmas the estimate took are ``sigmas`` ``(M,)``. Infinite
    where no other measurement is judged; 0 with one degree of freedom, where every ``|t|`` is the same."""
    count, valid, source_index = measurements.n_measurements[b], measurements.valid[b], measurements.source_index[b]
    worst, largest = -1, -1.0
    for m in range(count):
        if valid[m] and math.isfinite(sigmas[m]) and abs(studentized[m]) > largest:
            worst, largest = m, abs(studentized[m])
    if worst < 0:
        return np.inf
    least = np.inf
    for j in range(count):
        if j == worst or not (valid[j] and math.isfinite(sigmas[j])) or source_index[j] == source_index[worst]:
            continue
        cross = 0.0
        for i in range(4):
            for k in range(4):
                cross += local[i, worst] * params[i, k] * local[k, j]
        rho = -cross * math.sqrt(weights[worst] * weights[j]) / math.sqrt(room[worst] * room[j])
        sign = 1.0 if studentized[worst] * studentized[j] >= 0.0 else -1.0
        spread = math.sqrt(max(2.0 * (1.0 - sign * rho), 1e-12))
        least = min(least, (largest - abs(studentized[j])) / spread)
    return least


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _finish_kernel(measurements, frames, estimate):
    """The numbers of :func:`core.estimators.finish.finish`, each problem on its own: residuals (problem units), normalized and
    studentized residuals, chi-square and the count of measurements in it, the CRLB, the covariance (the
    CRLB, or with a robust loss (``estimate.loss_code`` not -1) the sandwich of its weights), the smallest
    unit-diagonal information eigenvalue, the loss's weight factors and cost, the reference sigma, and per
    line of sight whether the fix is behind its station or at its zenith, the lines' smallest spread, and whether
    the fix ran off (``RUNAWAY_SIGMA_RATIO``)."""
    kinds, n_measurements, valid, values = measurements.kinds, measurements.n_measurements, measurements.valid, \
        measurements.values
    stations_enu_m, rotations = measurements.stations_enu_m, measurements.rotations
    is_line, elevation_rad = measurements.is_line, measurements.elevation_rad
    altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation = frames
    positions_enu_m, bias_in_m, has_bias, sigmas = estimate.position_enu_m, estimate.bias_m, estimate.has_bias, \
        estimate.sigmas
    loss, c2 = estimate.loss_code, estimate.c2
    size, width = kinds.shape
    # The per-measurement numbers, the bounds and the line-of-sight facts are planes of one array each (see
    # :class:`Finished`).
    measured = np.zeros((4, size, width))
    raw, normalized, studentized, robust_factor = measured[0], measured[1], measured[2], measured[3]
    robust_factor[:] = 1.0
    chi2, known_count = np.zeros(size), np.zeros(size, dtype=np.int64)
    bounds = np.empty((2, size, 3, 3))
    crlb, covariance = bounds[0], bounds[1]
    smallest, robust_cost = np.empty(size), np.zeros(size)
    sigma_ref, spread = np.empty(size), np.full(size, np.pi / 2)
    seen_lines = np.zeros((2, size, width), dtype=np.bool_)
    behind, zenith = seen_lines[0], seen_lines[1]
    runaway = np.zeros(size, dtype=np.bool_)
    separation, room = np.full(size, np.inf), np.ones(width)
    weights, model_values = np.empty(width), np.empty(width)
    jacobian, local = np.empty((4, width)), np.empty((4, width))
    seen = np.empty((width, 3))
    axes, free = np.empty((3, 3)), np.empty(4, dtype=np.bool_)
    information, params, work, vectors = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    bread, meat = np.empty((4, 4)), np.empty((4, 4))
    sandwich = SandwichScratch(local, bread, meat, params, work, vectors)
    bread_weights, meat_weights = np.empty(width), np.empty(width)
    model_residual, whitened, gradient, step = np.empty(width), np.empty(width), np.empty(4), np.empty(4)
    fitted_residual, local_fit, params_fit = np.empty(width), np.empty((4, width)), np.empty((4, 4))
    refit = _Refit(gradient, np.empty(3), np.empty((4, width)), local_fit, np.empty((4, 4)), params_fit,
                   np.empty((3, 3)), np.empty((3, 3)), free, work, vectors)
    for b in range(size):
        p = positions_enu_m[b]
        east, north, up = p[0], p[1], p[2]
        stations_b, rotations_b = stations_enu_m[b], rotations[b]
        for m in range(width):
            unit = SPEED_OF_LIGHT_MPS if kinds[b, m] == TOA else 1.0
            sigma = sigmas[b, m]
            weights[m] = 1.0 / (sigma * unit) ** 2 if valid[b, m] and math.isfinite(sigma) else 0.0
            model_values[m] = values[b, m] * unit
        bias = bias_in_m[b] if has_bias else toa_offset_point(east, north, up, stations_enu_m[b], kinds[b],
                                                               model_values, weights)
        for m in range(width):
            model_residual[m] = 0.0
            kind = kinds[b, m]
            predicted, jacobian[0, m], jacobian[1, m], jacobian[2, m], jacobian[3, m] = measure_point(
                east, north, up, bias, stations_b, rotations_b, m, kind)
            if m >= n_measurements[b]:
                continue
            unit = SPEED_OF_LIGHT_MPS if kind == TOA else 1.0
            r = model_values[m] - predicted
            if kind == AZIMUTH or kind == ELEVATION:
                r = wrap_point(r)
            model_residual[m] = r
            raw[b, m] = r / unit
            sigma = sigmas[b, m]
            if math.isfinite(sigma):
                normalized[b, m] = raw[b, m] / sigma
                if valid[b, m]:
                    known_count[b] += 1
        constrained = parameters_point(p, altitude_m[b], has_toa[b], geodetic[b], origin_ecef_m[b],
                                       origin_rotation[b], axes, free)
        normal_point(jacobian, weights, axes, constrained, free, local, information)
        smallest[b] = invert_point(information, axes, constrained, free, params, crlb[b], work, vectors)
        # The verdicts judge the residuals the ML fit of these measurements leaves: a closed form's (or an
        # unfinished iteration's) residuals also carry its own distance from that fit, which no chi-square on
        # m - n dof allows for (:func:`_ml_residuals`). A robust loss judges its own residuals (its weights
        # are the verdict).
        hat_local, hat_params = local, params
        for m in range(width):
            fitted_residual[m] = model_residual[m]
        for i in range(4):
            step[i] = 0.0
        if loss < 0 and smallest[b] > OBSERVABILITY_THRESHOLD:
            if _ml_residuals(p, bias, measurements, frames, b,
                             _Linearised(model_values, weights, local, params, fitted_residual, step), refit):
                hat_local, hat_params = local_fit, params_fit
        chi2[b] = 0.0
        for m in range(width):
            fitted = fitted_residual[m]
            for i in range(4):
                fitted -= hat_local[i, m] * step[i]
            whitened[m] = fitted * math.sqrt(weights[m])
            chi2[b] += whitened[m] ** 2
        reach2 = 0.0
        for m in range(n_measurements[b]):
            dx, dy, dz = east - stations_b[m, 0], north - stations_b[m, 1], up - stations_b[m, 2]
            reach2 = max(reach2, dx * dx + dy * dy + dz * dz)
        runaway[b] = crlb[b, 0, 0] + crlb[b, 1, 1] + crlb[b, 2, 2] > RUNAWAY_SIGMA_RATIO ** 2 * reach2
        sigma_ref[b] = reference_sigma_point(jacobian, weights)
        for m in range(width):
            known = m < n_measurements[b] and valid[b, m] and math.isfinite(sigmas[b, m])
            if not known:
                continue
            leverage = 0.0
            for i in range(4):
                for j in range(4):
                    leverage += hat_local[i, m] * hat_params[i, j] * hat_local[j, m]
            leverage *= weights[m]
            room[m] = max(1.0 - leverage, 1e-12) if not math.isnan(leverage) else 1e-12
            studentized[b, m] = whitened[m] / math.sqrt(room[m])
            if loss >= 0:
                rho, robust_factor[b, m], _ = loss_point(normalized[b, m] ** 2, loss, c2)
                robust_cost[b] += rho
        separation[b] = _separation(studentized[b], room, weights, hat_local, hat_params, sigmas[b], measurements, b)
        if loss >= 0:
            # The sandwich of the final weights rho': the meat holds each measurement's squared score
            # rho'^2 z (z its squared whitened residual), but never less than a clean measurement of that weight
            # adds on average (rho'^2, z averaging 1): a measurement the loss has bent keeps its pull on the fix
            # (c^2 for huber, not the rho'^2 of a clean one, 1 / z of it), and a small residual is no proof of a
            # small error.
            for m in range(width):
                bread_weights[m] = weights[m] * robust_factor[b, m]
                meat_weights[m] = weights[m] * robust_factor[b, m] ** 2 * max(normalized[b, m] ** 2, 1.0)
            sandwich_point(jacobian, bread_weights, meat_weights, axes, constrained, free, sandwich, covariance[b])
        else:
            covariance[b] = crlb[b]
        lines = 0
        for m in range(n_measurements[b]):
            if not is_line[b, m]:
                continue
            lines += 1
            dx, dy, dz = east - stations_b[m, 0], north - stations_b[m, 1], up - stations_b[m, 2]
            distance = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-9)
            ahead, e, n = ahead_point(east, north, up, stations_b, rotations_b, m, values[b, m], elevation_rad[b, m])
            behind[b, m] = ahead < 0
            zenith[b, m] = math.hypot(e, n) < 1e-4 * distance
            seen[m, 0], seen[m, 1], seen[m, 2] = dx / distance, dy / distance, dz / distance
        if lines >= 2:
            cosine = 1.0
            for i in range(n_measurements[b]):
                if not is_line[b, i]:
                    continue
                for j in range(i):
                    if is_line[b, j]:
                        dot = abs(seen[i, 0] * seen[j, 0] + seen[i, 1] * seen[j, 1] + seen[i, 2] * seen[j, 2])
                        cosine = min(cosine, dot)
            spread[b] = math.acos(cosine)
    return _Numbers(measured, bounds, seen_lines, chi2, known_count, smallest, robust_cost, sigma_ref, spread, runaway,
                    separation)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _verdicts_kernel(numbers, measurements, frames, estimate):
    """Per problem, from :func:`_finish_kernel`'s numbers: the degrees of freedom, the plain and the reported
    sigma scale (NaN without dof), the measurement with the largest ``|studentized|`` (numpy's ``argmax``:
    the first NaN, else the first largest) and its value, and the verdict bits (``ILL`` ...; with the
    estimator's own ``converged``)."""
    studentized, robust_factor = numbers.measured[2], numbers.measured[3]
    behind, zenith = numbers.seen_lines[0], numbers.seen_lines[1]
    chi2, known_count, robust_cost, smallest = numbers.chi2, numbers.known_count, numbers.robust_cost, numbers.smallest
    spread, runaway, separation = numbers.spread, numbers.runaway, numbers.separation
    is_line, n_measurements, valid = measurements.is_line, measurements.n_measurements, measurements.valid
    altitude_m, has_toa = frames.altitude_m, frames.has_toa
    excluded, sigmas, converged = estimate.excluded, estimate.sigmas, estimate.converged
    robust = estimate.loss_code >= 0
    size, width = studentized.shape
    dof, worst = np.empty(size, dtype=np.int64), np.zeros(size, dtype=np.int64)
    plain_scale, sigma_scale = np.full(size, np.nan), np.full(size, np.nan)
    worst_value, flags = np.empty(size), np.zeros(size, dtype=np.int64)
    isolated = np.zeros(size, dtype=np.bool_)
    for b in range(size):
        dof[b] = known_count[b] - (3 if math.isnan(altitude_m[b]) else 2) - (1 if has_toa[b] else 0)
        if dof[b] > 0:
            plain_scale[b] = math.sqrt(chi2[b] / dof[b])
            sigma_scale[b] = math.sqrt(robust_cost[b] / dof[b]) if robust else plain_scale[b]
        largest = -1.0
        for m in range(width):
            magnitude = abs(studentized[b, m])
            if math.isnan(magnitude):
                worst[b] = m
                break
            if magnitude > largest:
                largest, worst[b] = magnitude, m
        worst_value[b] = studentized[b, worst[b]] if width else 0.0
        bits = ILL if smallest[b] < ILL_CONDITIONED_EIGENVALUE else 0
        bits |= RUNAWAY if runaway[b] else 0
        bits |= 0 if smallest[b] > OBSERVABILITY_THRESHOLD else SINGULAR
        bits |= 0 if converged[b] else NOT_CONVERGED
        isolated[b] = dof[b] >= 2 and separation[b] > ISOLATION_SIGMAS
        if dof[b] > 0 and abs(worst_value[b]) > OUTLIER_SIGMAS:
            bits |= OUTLIER if isolated[b] else NOT_ISOLABLE
        lines = 0
        for m in range(width):  # valid and excluded measurements are present ones
            lines += 1 if is_line[b, m] else 0
            bits |= BEHIND if behind[b, m] else 0
            bits |= ZENITH if zenith[b, m] else 0
            bits |= EXCLUDED if excluded[b, m] else 0
            bits |= UNUSED if m < n_measurements[b] and not valid[b, m] and not excluded[b, m] else 0
            if robust and valid[b, m] and math.isfinite(sigmas[b, m]) and robust_factor[b, m] < DOWNWEIGHTED_FACTOR:
                bits |= DOWNWEIGHTED
        if lines >= 2 and spread[b] < COLLINEAR_SPREAD_RAD:
            bits |= COLLINEAR
        flags[b] = bits
    return dof, plain_scale, sigma_scale, worst, worst_value, flags, isolated


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fix_kernel(measurements, frames, estimate):
    """:func:`_finish_kernel` then :func:`_verdicts_kernel` in one call; returns the fields of a
    :class:`Finished`.

    ``measurements``, ``frames``: the batch's (:mod:`core.kernel_data`); ``estimate``: an :class:`Estimate`
    (each a plain tuple or named).
    """
    measurements, frames, estimate = Measurements(*measurements), Frames(*frames), Estimate(*estimate)
    numbers = _finish_kernel(measurements, frames, estimate)
    dof, plain_scale, sigma_scale, worst, worst_value, flags, isolated = _verdicts_kernel(numbers, measurements,
                                                                                         frames, estimate)
    measured, bounds, seen_lines, chi2, smallest, spread = (numbers.measured, numbers.bounds, numbers.seen_lines,
                                                            numbers.chi2, numbers.smallest, numbers.spread)
    crlb, covariance, sigma_ref = bounds[0], bounds[1], numbers.sigma_ref
    size = dof.size
    scalars, counts = np.empty((8, size)), np.empty((3, size), dtype=np.int64)
    for b in range(size):
        for i in range(3):
            for j in range(i):
                covariance[b, i, j] = covariance[b, j, i] = 0.5 * (covariance[b, i, j] + covariance[b, j, i])
        scalars[0, b], scalars[1, b], scalars[2, b] = chi2[b], smallest[b], spread[b]
        scalars[3, b] = dof[b] if dof[b] > 0 else np.nan
        scalars[4, b], scalars[5, b], scalars[6, b] = plain_scale[b], sigma_scale[b], worst_value[b]
        scalars[7, b] = gdop_point(crlb[b], sigma_ref[b])
        counts[0, b], counts[1, b], counts[2, b] = dof[b], worst[b], flags[b]
    return measured, bounds, seen_lines, scalars, counts, isolated
