"""Maximum likelihood by Levenberg-Marquardt over a batch of problems (section 3).

Minimises ``sum (z - h(p))^2 / sigma^2`` for any mix of azimuth, elevation,
range and TOA. One compiled kernel iterates each problem of a batch on its
own (:func:`levenberg_marquardt`; zero-weight padding is skipped): ``4 x 4``
Jacobi-scaled normal equations in the common frame (metres of order 1e5 at
most, never ECEF's 6.4e6), with the Marquardt damping ``lambda diag(J^T W J)``.
A known altitude is a constraint: the position moves along the local
east/north at the current point and is put back on the altitude surface
after each step.
The covariance is the inverse information at the solution (computed by the
finisher, like everything else a fix reports), except where ML says more: a
fix with a plausible second solution reports the two-solution mixture's, and
a fix from the search (a mix without a closed form, or whose closed-form fit
failed) the unscented spread of the estimator, never below the bound
(:mod:`core.estimators.unscented_fix`): the inverse information is the
covariance only where the model is linear over the fix's uncertainty.

A robust loss (``options.loss``, scipy's names: :mod:`core.estimators.loss`)
is minimised as scipy's ``least_squares`` does: the gradient weights each
measurement by ``rho'``, the normal equations by ``rho' + 2 rho'' z``. The
finisher then reports the sandwich covariance of the final weights ``rho'``
(``covariance_source`` ``"robust"``): that of a weighted least-squares fit
with those weights, which is the bound without a measurement the loss has
set aside, and never below the bound. A robust fit whose residuals fail the
chi-square test (``SUBSET_P``) may sit in the basin of a gross error that
pulled its closed-form start: it is started again from the closed form of
each subset that leaves one of its most suspect request measurements out
(:func:`subset_starts`), and the lowest robust cost is kept.

Ties. Where the measurements leave (almost) no degree of freedom, a second
point may fit as well: a line of sight crosses a TDOA hyperboloid twice, or
ranges, TOAs and azimuths from nearly coplanar stations fit a point and its
mirror image through their plane. ML looks for one among the search's
solutions (from the geometry's candidates and from the best fit's own
uncertainty, :func:`~core.estimators.ambiguity.axis_starts`) and from the
fix's mirror image (:func:`mirror_points`); a rival
is itself a converged fit of the data (an iterate the cap stopped on its way
is iterated further first, :func:`refine`, and is no rival unless that
converges), whose cost is within ``PLAUSIBLE_COST`` of the fix, farther than
one sigma from the fix under the fix's bound and under its own
(``DISTINCT_MAHALANOBIS2``: nearer, the covariance covers both; a refinement
that converges onto the fix is the fix) and physically possible (a geodetic
point more than 1 km below the ellipsoid is no solution; a point behind a bearing
station never ties, its azimuth residual is near pi; a TOA's emission
precedes its arrival by construction of the model). One rule judges it for
every mix (:mod:`core.estimators.ambiguity`): within ``AMBIGUITY_COST`` a tie,
a :class:`~core.errors.AmbiguousGeometry` (422 ``ambiguous_geometry``) naming
both points, unless the client's ``initial_guess`` picks the nearer one;
worse but plausible, the fix warns ``second_solution_plausible`` (the rival
and its probability) and its covariance is the two-solution mixture's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
from scipy.special import chdtrc

from core.crlb import batch_information
from core.errors import AmbiguousGeometry, LocalizationError
from core.angles import wrap_point
from core.estimators.ambiguity import (AMBIGUITY_COST, PLAUSIBLE_COST, axis_starts, mixture_covariance,
                                       rival_probability)
from core.estimators.base import SolveOptions, register
from core.estimators.loss import CURVATURE_FLOOR, REDESCENDING, loss_code, loss_point
from core.estimators.result import Estimates, FixWarning
from core.estimators.search import candidates
from core.estimators.starting_points import initial_positions
from core.estimators.unscented_fix import CURVED_VARIANCE_RATIO, never_below, unscented_covariance
from core.geodesy import enu_to_geodetic
from core.linalg import jacobi_svd
from core.measurements import (AZIMUTH, ELEVATION, RANGE, TOA, ahead_point, measure_point, predict, residuals,
                               toa_offset_point)
from core.problem import local_axes_point, onto_altitude_point
from core.problem_batch import ProblemBatch

#: Plain least squares: ``(loss name, scale in sigmas)``.
LINEAR = ("linear", 1.0)
#: Marquardt damping: the first, and the bounds (past LAMBDA_MAX the iteration gives up).
LAMBDA_START = 1e-3
LAMBDA_MIN = 1e-12
LAMBDA_MAX = 1e12
#: An iteration that reaches its cap is still converged where the undamped step would lower the cost by less
#: than this share of it: the fix is then within ``sqrt(STATIONARY_GAIN * cost)`` sigmas of the minimum (the
#: data are inconsistent, their cost large, and the steps along a poorly determined direction stay above the
#: tolerance while the fix no longer moves within its uncertainty). Noise-free data, of cost near 0, converge
#: by the step tolerance only.
STATIONARY_GAIN = 1e-9
#: A fit is converged, whatever the step's length in metres, when the undamped step's squared Mahalanobis
#: length (the cost it would remove) is below this: the fix moves by less than 1e-6 of its sigma (a direction
#: the measurements barely see, of sigma kilometres, keeps float64 steps above a millimetre).
STEP_MAHALANOBIS2 = 1e-12
#: Where the undamped Gauss-Newton step would remove less than this share of the cost, the residuals are too
#: large for Gauss-Newton's model (inconsistent data) and the ranges' and TOAs' own curvature joins the matrix
#: (:func:`_add_distance_curvature`); farther from a fit of consistent data the step removes most of the cost,
#: and Gauss-Newton's matrix, never indefinite, steers the iteration.
NEWTON_SHARE = 1e-3
#: The search's fits from every candidate run in chunks of about this many measurement slots
#: (candidates x padded width): the expanded problems then take megabytes, not gigabytes.
CHUNK_ENTRIES = 1 << 15
#: A robust fit whose residuals' chi-square p-value is below this is started again from subsets (:func:`subset_starts`).
SUBSET_P = 0.01
#: ... each leaving out one of at most this many request measurements, the most suspect first.
SUBSET_CANDIDATES = 8


@dataclass(frozen=True)
class Solution:
    """Where the iteration ended, for B problems.

    Attributes
    ----------
    position_enu_m : ndarray, shape (B, 3)
    bias_m : ndarray, shape (B,)
    iterations : ndarray of int, shape (B,)
    converged : ndarray of bool, shape (B,)
    cost : ndarray, shape (B,)
        Weighted sum of squared residuals at the end.
    """

    position_enu_m: np.ndarray
    bias_m: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    cost: np.ndarray

    def put(self, rows, other: "Solution", picks) -> None:
        """Rows ``rows`` of this solution become rows ``picks`` of ``other`` (in place; int or ``(K,)`` each)."""
        for name in self.__dataclass_fields__:
            getattr(self, name)[rows] = getattr(other, name)[picks]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _evaluate(position_enu_m, bias_m, stations, rotations, kinds, values, weights, loss_code, c2,
              residual, jacobian, gradient_w, curvature_w):
    """Residuals, Jacobian and the gradient and Gauss-Newton weights of one problem's measurements (written
    in place; zero where the weight is); returns the cost ``sum C^2 rho(z / C^2)`` of the squared whitened
    residuals ``z``."""
    cost = 0.0
    east, north, up = position_enu_m[0], position_enu_m[1], position_enu_m[2]
    for m in range(kinds.size):
        w = weights[m]
        if not w > 0.0:
            residual[m] = 0.0
            gradient_w[m] = curvature_w[m] = 0.0
            for i in range(4):
                jacobian[i, m] = 0.0
            continue
        kind = kinds[m]
        predicted, jacobian[0, m], jacobian[1, m], jacobian[2, m], jacobian[3, m] = measure_point(
            east, north, up, bias_m, stations, rotations, m, kind)
        r = values[m] - predicted
        if kind == AZIMUTH or kind == ELEVATION:
            r = wrap_point(r)
        residual[m] = r
        z = w * r * r
        rho, rho1, rho2 = loss_point(z, loss_code, c2)
        cost += rho
        gradient_w[m] = w * rho1
        curvature_w[m] = w if loss_code == 0 else w * max(rho1 + 2.0 * rho2 * z, CURVATURE_FLOOR)
    return cost


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_small(a, rhs, out):
    """``a x = rhs`` for one small matrix by Gaussian elimination with partial pivoting (``a``, ``rhs`` overwritten)."""
    size = rhs.size
    for k in range(size):
        pivot = k
        for i in range(k + 1, size):
            if abs(a[i, k]) > abs(a[pivot, k]):
                pivot = i
        if pivot != k:
            for j in range(size):
                a[k, j], a[pivot, j] = a[pivot, j], a[k, j]
            rhs[k], rhs[pivot] = rhs[pivot], rhs[k]
        for i in range(k + 1, size):
            factor = a[i, k] / a[k, k]
            for j in range(k, size):
                a[i, j] -= factor * a[k, j]
            rhs[i] -= factor * rhs[k]
    for k in range(size - 1, -1, -1):
        total = rhs[k]
        for j in range(k + 1, size):
            total -= a[k, j] * out[j]
        out[k] = total / a[k, k]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _undamped_gain(information, gradient, work, right, step):
    """The cost the undamped step ``information^-1 gradient`` would remove, ``gradient . step`` (Jacobi-scaled
    solve; ``work`` ``(4, 4)``, ``right`` and ``step`` ``(4,)``: scratch); infinite where not finite."""
    for i in range(4):
        d = information[i, i]
        right[i] = 1.0 / math.sqrt(d if d > 0.0 else 1.0)
    for i in range(4):
        for j in range(4):
            work[i, j] = information[i, j] * right[i] * right[j]
            if not math.isfinite(work[i, j]):
                return np.inf
    scale0, scale1, scale2, scale3 = right[0], right[1], right[2], right[3]
    right[0], right[1], right[2], right[3] = (scale0 * gradient[0], scale1 * gradient[1], scale2 * gradient[2],
                                              scale3 * gradient[3])
    rhs0, rhs1, rhs2, rhs3 = right[0], right[1], right[2], right[3]
    _solve_small(work, right, step)
    gain = step[0] * rhs0 + step[1] * rhs1 + step[2] * rhs2 + step[3] * rhs3
    return gain if math.isfinite(gain) else np.inf


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _add_distance_curvature(x, stations, kinds, count, gradient_w, residual, axes, constrained, free, curvature,
                            information):
    """Add the residual curvature of the ranges and TOAs, ``-sum w rho' r (I - u u^T) / |d|`` (the Hessian of a
    distance ``|d|``, ``u = d / |d|``), to the Gauss-Newton matrix ``information`` ``(4, 4)`` of the local
    parameters, where the sum keeps it positive definite (else it is left as it was).

    Gauss-Newton drops that term, which is right for residuals of the size of the noise; a gross error leaves
    residuals of tens of sigmas, and Gauss-Newton then converges only linearly (slowly, along a poorly
    determined direction); Newton's matrix converges there quadratically.
    """
    for i in range(3):
        for j in range(3):
            curvature[i, j] = 0.0
    for m in range(count):
        if not (gradient_w[m] > 0.0 and (kinds[m] == RANGE or kinds[m] == TOA)):
            continue
        dx, dy, dz = x[0] - stations[m, 0], x[1] - stations[m, 1], x[2] - stations[m, 2]
        distance = math.sqrt(dx * dx + dy * dy + dz * dz)
        if not distance > 0.0:
            continue
        u0, u1, u2 = dx / distance, dy / distance, dz / distance
        factor = -gradient_w[m] * residual[m] / distance
        curvature[0, 0] += factor * (1.0 - u0 * u0)
        curvature[1, 1] += factor * (1.0 - u1 * u1)
        curvature[2, 2] += factor * (1.0 - u2 * u2)
        curvature[0, 1] -= factor * u0 * u1
        curvature[0, 2] -= factor * u0 * u2
        curvature[1, 2] -= factor * u1 * u2
    curvature[1, 0], curvature[2, 0], curvature[2, 1] = curvature[0, 1], curvature[0, 2], curvature[1, 2]
    added = np.zeros((3, 3))  # the curvature in the local parameters, on the free ones
    for i in range(3):
        if not free[i]:
            continue
        for j in range(3):
            if not free[j]:
                continue
            term = 0.0
            if constrained:
                for k in range(3):
                    for n in range(3):
                        term += axes[i, k] * curvature[k, n] * axes[j, n]
            else:
                term = curvature[i, j]
            added[i, j] = term
    trial = information.copy()
    for i in range(3):
        for j in range(3):
            trial[i, j] += added[i, j]
    # Positive definite (Cholesky succeeds): take it.
    for k in range(4):
        pivot = trial[k, k]
        for n in range(k):
            pivot -= trial[k, n] * trial[k, n]
        if not pivot > 1e-12 * max(information[k, k], 1e-300):
            return
        pivot = math.sqrt(pivot)
        trial[k, k] = pivot
        for i in range(k + 1, 4):
            total = trial[i, k]
            for n in range(k):
                total -= trial[i, n] * trial[k, n]
            trial[i, k] = total / pivot
    for i in range(3):
        for j in range(3):
            information[i, j] += added[i, j]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lm_kernel(stations, rotations, kinds, values, weights, starts, altitude_m, geodetic, origin_ecef_m,
               origin_rotation, has_toa, loss_code, c2, max_iterations, tolerance_m):
    size, count = kinds.shape
    position_out = np.empty((size, 3))
    bias_out = np.empty(size)
    iterations_out = np.zeros(size, dtype=np.int64)
    converged_out = np.zeros(size, dtype=np.bool_)
    cost_out = np.empty(size)
    residual, gradient_w, curvature_w = np.empty(count), np.empty(count), np.empty(count)
    residual_new, gradient_w_new, curvature_w_new = np.empty(count), np.empty(count), np.empty(count)
    jacobian, jacobian_new = np.empty((4, count)), np.empty((4, count))
    local = np.empty((4, count))
    axes = np.empty((3, 3))
    information, scaled, undamped, curvature = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((3, 3))
    free_right, free_step = np.empty(4), np.empty(4)
    gradient, scale, right, step, free = np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    x, x_new, delta = np.empty(3), np.empty(3), np.empty(3)
    for b in range(size):
        st, rot, kd, val, wt = stations[b], rotations[b], kinds[b], values[b], weights[b]
        constrained = not math.isnan(altitude_m[b])
        x[:] = starts[b]
        if constrained:
            onto_altitude_point(x, altitude_m[b], geodetic[b], origin_ecef_m[b], origin_rotation[b])
        bias = toa_offset_point(x[0], x[1], x[2], st, kd, val, wt)
        free[0] = free[1] = 1.0
        free[2] = 0.0 if constrained else 1.0
        free[3] = 1.0 if has_toa[b] else 0.0
        cost = _evaluate(x, bias, st, rot, kd, val, wt, loss_code, c2, residual, jacobian, gradient_w,
                         curvature_w)
        has_distance = False
        for m in range(count):
            has_distance |= wt[m] > 0.0 and (kd[m] == RANGE or kd[m] == TOA)
        damping = LAMBDA_START
        stationary = False
        iterations = 0
        converged = False
        for _ in range(max_iterations):
            if constrained:
                local_axes_point(x, geodetic[b], origin_ecef_m[b], origin_rotation[b], axes)
            for m in range(count):
                for i in range(3):
                    if constrained:
                        local[i, m] = (axes[i, 0] * jacobian[0, m] + axes[i, 1] * jacobian[1, m]
                                       + axes[i, 2] * jacobian[2, m]) * free[i]
                    else:
                        local[i, m] = jacobian[i, m] * free[i]
                local[3, m] = jacobian[3, m] * free[3]
            finite = True
            for i in range(4):
                g = 0.0
                for m in range(count):
                    g += local[i, m] * gradient_w[m] * residual[m]
                gradient[i] = g
                for j in range(4):
                    total = 0.0
                    for m in range(count):
                        total += local[i, m] * curvature_w[m] * local[j, m]
                    information[i, j] = total + (1.0 - free[i] if i == j else 0.0)
            if has_distance and cost > 0.0 and _undamped_gain(information, gradient, undamped, free_right,
                                                              free_step) < NEWTON_SHARE * cost:
                _add_distance_curvature(x, st, kd, count, gradient_w, residual, axes, constrained, free, curvature,
                                        information)
            for i in range(4):
                d = information[i, i]
                if loss_code != 0:
                    d_gradient = 0.0
                    for m in range(count):
                        d_gradient += local[i, m] * gradient_w[m] * local[i, m]
                    d = max(d, d_gradient)
                scale[i] = 1.0 / math.sqrt(d if d > 0.0 else 1.0)
            for i in range(4):
                for j in range(4):
                    scaled[i, j] = information[i, j] * scale[i] * scale[j] + (damping if i == j else 0.0)
                    if not math.isfinite(scaled[i, j]):
                        finite = False
                right[i] = scale[i] * gradient[i]
            if not finite:
                for i in range(4):
                    for j in range(4):
                        scaled[i, j] = 1.0 if i == j else 0.0
            elif cost > 0.0:
                # Stationary (STATIONARY_GAIN), should the cap be reached.
                gain = _undamped_gain(information, gradient, undamped, free_right, free_step)
                if gain >= 0.0 and gain < STEP_MAHALANOBIS2:
                    converged = True  # the undamped step would move the fix by less than 1e-6 of its sigma
                    break
                stationary = gain >= 0.0 and gain < STATIONARY_GAIN * cost
            _solve_small(scaled, right, step)
            for i in range(4):
                step[i] *= scale[i] * free[i]
            length2 = 0.0
            for j in range(3):
                if constrained:
                    delta[j] = step[0] * axes[0, j] + step[1] * axes[1, j] + step[2] * axes[2, j]
                else:
                    delta[j] = step[j]
                x_new[j] = x[j] + delta[j]
                length2 += delta[j] * delta[j]
            if constrained:
                onto_altitude_point(x_new, altitude_m[b], geodetic[b], origin_ecef_m[b], origin_rotation[b])
            bias_new = bias + step[3]
            cost_new = _evaluate(x_new, bias_new, st, rot, kd, val, wt, loss_code, c2, residual_new,
                                 jacobian_new, gradient_w_new, curvature_w_new)
            iterations += 1
            if math.isfinite(cost_new) and cost_new <= cost * (1.0 + 1e-12) + 1e-300:
                x[:] = x_new
                bias, cost = bias_new, cost_new
                residual, residual_new = residual_new, residual
                jacobian, jacobian_new = jacobian_new, jacobian
                gradient_w, gradient_w_new = gradient_w_new, gradient_w
                curvature_w, curvature_w_new = curvature_w_new, curvature_w
                damping = max(damping / 10.0, LAMBDA_MIN)
            else:
                damping *= 10.0
            if math.sqrt(length2) < tolerance_m:
                converged = True
                break
            if damping > LAMBDA_MAX:
                break
        converged = converged or stationary
        position_out[b] = x
        bias_out[b], cost_out[b] = bias, cost
        iterations_out[b], converged_out[b] = iterations, converged
    return position_out, bias_out, iterations_out, converged_out, cost_out


def levenberg_marquardt(batch: ProblemBatch, start_enu_m, max_iterations=50, tolerance_m=1e-3,
                        loss=LINEAR) -> Solution:
    """Iterate every problem of a batch to its ML position (or, with a robust loss, its M-estimate).

    One compiled kernel runs each problem's iteration on its own (so a problem's result does not depend on
    the batch it is in): Jacobi-scaled normal equations of ``(east, north, up, b)`` with the Marquardt
    damping ``lambda diag(J^T W J)`` (with a robust loss, the larger of the Gauss-Newton and the ``rho'``
    weighted diagonal: :mod:`core.estimators.loss`), a step accepted when the cost does not rise; with a
    known altitude the step moves along the local east and north and the point is put back on the altitude surface
    (:func:`core.problem.onto_altitude`, the same geodesy). The model is
    :func:`core.measurements.measure_point`, the loss :func:`core.estimators.loss.loss_point`.

    Parameters
    ----------
    batch : ProblemBatch
    start_enu_m : ndarray, shape (B, 3)
    max_iterations : int
    tolerance_m : float
        Converged when a step moves the position less than this (or, at the cap, where the cost is stationary:
        ``STATIONARY_GAIN``).
    loss : tuple of (str, float)
        The loss's name and scale in sigmas (:mod:`core.estimators.loss`); the cost minimised is its sum.

    Returns
    -------
    Solution
    """
    stations, rotations = batch.measurement_stations()
    origin_ecef, origin_rotation = batch.frame_placements()
    out = _lm_kernel(np.ascontiguousarray(stations, dtype=float), np.ascontiguousarray(rotations, dtype=float),
                     np.ascontiguousarray(batch.kinds, dtype=np.int64), np.ascontiguousarray(batch.model_values()),
                     np.ascontiguousarray(batch.weights()),
                     np.ascontiguousarray(start_enu_m, dtype=float), np.asarray(batch.altitude_m, dtype=float),
                     np.asarray(batch.geodetic, dtype=np.bool_), origin_ecef, origin_rotation,
                     np.asarray(batch.has_toa, dtype=np.bool_), loss_code(loss[0]), float(loss[1]) ** 2,
                     int(max_iterations), float(tolerance_m))
    return Solution(*out)


def _loss(options: SolveOptions) -> tuple[str, float]:
    return options.loss, options.loss_scale


def iterate(batch: ProblemBatch, starts_enu_m, options: SolveOptions) -> Solution:
    """:func:`levenberg_marquardt` with the options' iteration limits and loss."""
    return levenberg_marquardt(batch, np.asarray(starts_enu_m, dtype=float), options.max_iterations,
                               options.tolerance_m, _loss(options))


def estimate_from(batch: ProblemBatch, starts_enu_m, options: SolveOptions, start_names, failures,
                  solution: Solution | None = None, warnings: list | None = None,
                  covariance_enu_m2=None) -> Estimates:
    """ML estimates of a batch from given starts.

    Parameters
    ----------
    batch : ProblemBatch
    starts_enu_m : ndarray, shape (B, 3)
        NaN rows for problems without a start (they must be in ``failures``).
    options : SolveOptions
    start_names : list of str or None, length B
        Reported as ``details["start"]``.
    failures : dict of int to LocalizationError
        Problems with no start.
    solution : Solution, optional
        The iteration from these starts, when already run.
    warnings : list of tuple of FixWarning, length B, optional
        The estimator's own warnings.
    covariance_enu_m2 : ndarray, shape (B, 3, 3), optional
        Covariances that replace the inverse information (a two-solution mixture); NaN rows keep it.
    """
    starts = np.array(starts_enu_m, dtype=float)
    missing = ~np.isfinite(starts).all(axis=-1)
    errors = dict(failures)
    for b in missing.nonzero()[0].tolist():
        errors.setdefault(b, LocalizationError("no starting point for this geometry"))
    if solution is None:
        starts[missing] = batch.stations_enu_m[missing, 0] + [0.0, 0.0, 1.0]
        solution = iterate(batch, starts, options)
    return Estimates(
        position_enu_m=solution.position_enu_m,
        covariance_source="information",
        covariance_enu_m2=covariance_enu_m2,
        loss=None if options.loss == "linear" else _loss(options),
        errors=errors,
        converged=solution.converged,
        iterations=solution.iterations,
        warnings=warnings,
        bias_m=solution.bias_m,
        details=[{"start": name} if name is not None else {} for name in start_names],
    )


#: A second solution is a rival (:func:`_rivals`; judged by :mod:`core.estimators.ambiguity`: a tie within
#: ``AMBIGUITY_COST``, a plausible worse solution within ``PLAUSIBLE_COST``) when it is a converged solution
#: farther from the best than this squared Mahalanobis distance, under the best's CRLB and under its own: nearer,
#: no measurement at the stated noise tells them apart and the covariance covers both.
DISTINCT_MAHALANOBIS2 = 1.0
#: Where the best is itself unconverged (the answer is flagged so), an unconverged iterate is a rival farther
#: than this from it: neither is a solution, and the two may still be sliding down one valley.
DISTINCT_UNCONVERGED_MAHALANOBIS2 = 25.0
#: An unconverged candidate that might be a rival (cost within ``PLAUSIBLE_COST`` of the best) goes on for this many
#: more iterations before it is judged (:func:`refine`): an iterate the cap stopped in a crawling valley (a line
#: of sight nearly tangent to a hyperbola) is no solution until it converges, and often converges onto the best.
REFINE_ITERATIONS = 500
#: Below this height above the ellipsoid (m) a point of a geodetic scene is inside the earth: no solution.
MIN_ALTITUDE_M = -1000.0


def above_ground(batch: ProblemBatch, positions_enu_m) -> np.ndarray:
    """Which positions ``(B, 3)`` are physically possible: not more than ``-MIN_ALTITUDE_M`` underground.

    Underground is below the ellipsoid in a geodetic scene; in a local frame, below both the frame's
    ``up = 0`` and the lowest station (a local frame's datum is the user's, the stations stand on the ground).
    """
    positions = np.nan_to_num(np.asarray(positions_enu_m, dtype=float))
    present = np.arange(batch.stations_enu_m.shape[1])[None, :] < batch.n_stations[:, None]
    lowest_m = np.min(np.where(present, batch.stations_enu_m[..., 2], np.inf), axis=-1)
    possible = positions[:, 2] >= np.minimum(MIN_ALTITUDE_M, lowest_m + MIN_ALTITUDE_M)
    if np.any(batch.geodetic):
        origin = batch.origin
        altitude = enu_to_geodetic(positions, origin[:, 0], origin[:, 1], origin[:, 2])[2]
        possible = np.where(batch.geodetic, altitude >= MIN_ALTITUDE_M, possible)
    return possible


class Fits(NamedTuple):
    """ML fits of K problems with what the rival rule needs of each.

    Attributes
    ----------
    position_enu_m : ndarray, shape (K, 3)
    cost : ndarray, shape (K,)
        ``inf`` where not ``regular``.
    converged : ndarray of bool, shape (K,)
    regular : ndarray of bool, shape (K,)
        Finite, observable there and physically possible (:func:`above_ground`).
    covariance_enu_m2 : ndarray, shape (K, 3, 3)
        The CRLB at the fit.
    """

    position_enu_m: np.ndarray
    cost: np.ndarray
    converged: np.ndarray
    regular: np.ndarray
    covariance_enu_m2: np.ndarray


def fit_from(batch: ProblemBatch, owners, starts_enu_m, options: SolveOptions, max_iterations: int) -> Fits:
    """ML of problems ``owners`` ``(K,)`` of ``batch`` from starts ``(K, 3)``, with the rival rule's view of each
    fit (:class:`Fits`); in chunks of about ``CHUNK_ENTRIES`` measurement slots (the expanded problems then take
    megabytes, not gigabytes)."""
    starts = np.asarray(starts_enu_m, dtype=float)
    size = starts.shape[0]
    position, cost = np.empty((size, 3)), np.full(size, np.inf)
    converged, regular = np.zeros(size, dtype=bool), np.zeros(size, dtype=bool)
    covariance = np.empty((size, 3, 3))
    step = max(1, CHUNK_ENTRIES // max(batch.kinds.shape[1], 1))
    for start in range(0, size, step):
        part = slice(start, start + step)
        expanded = batch.take(owners[part])
        solution = levenberg_marquardt(expanded, starts[part], max_iterations, options.tolerance_m, _loss(options))
        here = solution.position_enu_m
        position[part], converged[part] = here, solution.converged
        finite = np.all(np.isfinite(here), axis=-1)
        information = batch_information(expanded, np.where(finite[:, None], here, 0.0))
        regular[part] = finite & information.observable & above_ground(expanded, here)
        covariance[part] = information.covariance_enu_m2
        cost[part] = np.where(regular[part], solution.cost, np.inf)
    return Fits(position, cost, converged, regular, covariance)


def refine(batch: ProblemBatch, owners, fits: Fits, best_cost, options: SolveOptions) -> Fits:
    """``fits`` (of problems ``owners`` ``(K,)`` of ``batch``) with every regular unconverged fit whose cost is
    within ``PLAUSIBLE_COST`` of ``best_cost`` ``(K,)`` iterated ``REFINE_ITERATIONS`` more: whether a candidate
    is a solution of the data is known only where its iteration ends. A refinement replaces its fit only where
    it converged to a regular point; the others stay as they were (an unconverged fit, judged as before)."""
    again = np.flatnonzero(fits.regular & ~fits.converged & (fits.cost <= best_cost + PLAUSIBLE_COST))
    if not again.size:
        return fits
    more = fit_from(batch, owners[again], fits.position_enu_m[again], options, REFINE_ITERATIONS)
    solved = more.converged & more.regular
    out = Fits(*(np.array(field) for field in fits))
    for name, field in zip(Fits._fields, more):
        getattr(out, name)[again[solved]] = field[solved]
    return out


def _rivals(best: Fits, fits: Fits) -> np.ndarray:
    """Which fits ``(K,)`` are rivals of their best (row for row): the one rule for every measurement mix.

    A rival is itself a converged fit of the data (:func:`refine` has taken an unconverged candidate as far
    as it goes), regular and physically possible, distinct from the best under the best's CRLB and under its
    own (``DISTINCT_MAHALANOBIS2``: a candidate that converged onto the best is no rival) and not rejected by its
    cost (within ``PLAUSIBLE_COST`` of the best; :mod:`core.estimators.ambiguity` judges a tie from a plausible
    worse solution). Where the best is itself unconverged (its answer is flagged so), an unconverged
    iterate farther than ``DISTINCT_UNCONVERGED_MAHALANOBIS2`` from it counts too: neither is known to be the
    solution.
    """
    apart = np.nan_to_num(fits.position_enu_m - best.position_enu_m)
    distance2 = []
    for covariance in (best.covariance_enu_m2, fits.covariance_enu_m2):
        precision = np.linalg.pinv(covariance, rcond=1e-9, hermitian=True)
        distance2.append(np.einsum("ki,kij,kj->k", apart, precision, apart))
    distinct = fits.converged & (np.minimum(*distance2) > DISTINCT_MAHALANOBIS2)
    distinct |= ~best.converged & ~fits.converged & (distance2[0] > DISTINCT_UNCONVERGED_MAHALANOBIS2)
    return fits.regular & distinct & (fits.cost <= best.cost + PLAUSIBLE_COST)


def mirror_applies(batch: ProblemBatch) -> np.ndarray:
    """``(B,)``: where a fix's mirror image through its stations' plane may fit as well (:func:`mirror_points`):
    unconstrained problems without an elevation (ranges, TOAs and azimuths cannot tell a point from its mirror
    through the plane of nearly coplanar stations)."""
    return ~batch.constrained & (batch.kind_counts[:, ELEVATION] == 0)


def mirror_points(batch: ProblemBatch, positions_enu_m) -> np.ndarray:
    """Each position reflected through its stations' plane ``(B, 3)`` (where that may fit as well:
    :func:`mirror_applies`).

    The plane is the stations' least-squares plane; with fewer than three stations, or collinear ones, the
    most horizontal plane through them.
    """
    present = np.arange(batch.stations_enu_m.shape[1])[None, :] < batch.n_stations[:, None]
    centroid = np.sum(np.where(present[..., None], batch.stations_enu_m, 0.0), axis=1) / batch.n_stations[:, None]
    spread, axes, _ = jacobi_svd(np.where(present[..., None], batch.stations_enu_m - centroid[:, None, :], 0.0))
    normal = np.take_along_axis(axes, np.argmin(spread, axis=-1)[:, None, None], axis=-1)[..., 0]
    largest = np.take_along_axis(axes, np.argmax(spread, axis=-1)[:, None, None], axis=-1)[..., 0]
    flat = np.sort(spread, axis=-1)[:, 1] <= 1e-9 * np.maximum(spread.max(axis=-1), 1.0)
    up = np.array([0.0, 0.0, 1.0])
    line = np.where((spread.max(axis=-1) > 0)[:, None], largest, 0.0)
    horizontal = up - np.sum(line * up, axis=-1)[:, None] * line
    normal = np.where(flat[:, None], horizontal / np.linalg.norm(horizontal, axis=-1, keepdims=True), normal)
    height = np.einsum("bi,bi->b", positions_enu_m - centroid, normal)
    return positions_enu_m - 2.0 * height[:, None] * normal


def _best_of(owners, cost):
    """Per problem, its lowest-cost row among rows owned by ``owners`` ``(K,)`` (sorted or not).

    Returns
    -------
    first : ndarray of int, shape (P,)
        The lowest-cost row of each problem present.
    best_cost : ndarray, shape (K,)
        Each row's problem's lowest cost.
    best_of : ndarray of int, shape (K,)
        Each row's problem's lowest-cost row.
    """
    order = np.lexsort((cost, owners))
    first = order[np.r_[True, owners[order][1:] != owners[order][:-1]]]
    best_of = first[np.searchsorted(owners[first], owners)]
    return first, cost[best_of], best_of


def searched_starts(batch: ProblemBatch, options: SolveOptions, extra_enu_m=None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Starts where no closed form applies: ML from every candidate of
    :func:`core.estimators.search.candidates` (and from ``extra_enu_m``, e.g. a fit already made), the
    lowest final cost kept among the solutions that are regular (an iterate that ran off to where the
    measurements say nothing may fit better, and is no fix) and physically possible (:func:`above_ground`).

    Parameters
    ----------
    batch : ProblemBatch
    options : SolveOptions
    extra_enu_m : ndarray, shape (B, 3), optional
        One more start per problem (NaN rows: none).

    Returns
    -------
    starts : ndarray, shape (B, 3)
        NaN rows where no candidate gave a regular solution.
    rival : ndarray, shape (B, 3)
        The lowest-cost rival of the best (:func:`_rivals`, after :func:`refine`): the second crossing of a
        line of sight with a hyperboloid, the mirror of coplanar stations, when the measurements leave no
        degree of freedom to tell them apart; NaN rows where none. The search's candidates are followed by
        starts along the best fit's principal axes (:func:`~core.estimators.ambiguity.axis_starts`), where a
        second root near the first lies.
    rival_cost : ndarray, shape (B,)
        Its cost (``inf`` where none).
    """
    points = candidates(batch)
    if extra_enu_m is not None:
        points = np.concatenate([np.asarray(extra_enu_m, dtype=float)[:, None, :], points], axis=1)
    size, count = points.shape[:2]
    tried = np.repeat(np.arange(size), count)
    flat = points.reshape(-1, 3)
    finite = np.all(np.isfinite(flat), axis=-1)
    out, rival, rival_cost = np.full((size, 3), np.nan), np.full((size, 3), np.nan), np.full(size, np.inf)
    if not np.any(finite):
        return out, rival, rival_cost
    tried, flat = tried[finite], flat[finite]
    fits = fit_from(batch, tried, flat, options, options.max_iterations)
    fits = refine(batch, tried, fits, _best_of(tried, fits.cost)[1], options)
    first = _best_of(tried, fits.cost)[0]
    first = first[np.isfinite(fits.cost[first])]
    owners, more = axis_starts(batch, tried[first], fits.position_enu_m[first], fits.covariance_enu_m2[first])
    if owners.size:
        best_cost = np.full(size, np.inf)
        best_cost[tried[first]] = fits.cost[first]
        extra = fit_from(batch, owners, more, options, options.max_iterations)
        extra = refine(batch, owners, extra, best_cost[owners], options)
        tried = np.concatenate([tried, owners])
        fits = Fits(*(np.concatenate([a, b]) for a, b in zip(fits, extra)))
    position, cost = fits.position_enu_m, fits.cost
    first, _, best_of = _best_of(tried, cost)
    good = np.isfinite(cost[first])
    out[tried[first][good]] = position[first][good]
    close = _rivals(Fits(*(field[best_of] for field in fits)), fits)
    second = np.where(close, cost, np.inf)
    order = np.lexsort((second, tried))
    lowest = order[np.r_[True, tried[order][1:] != tried[order][:-1]]]
    found = np.isfinite(second[lowest])
    rival[tried[lowest][found]] = position[lowest][found]
    rival_cost[tried[lowest][found]] = cost[lowest][found]
    return out, rival, rival_cost


#: A fit from the closed-form start whose chi-square has a p-value below this is retried from the search
#: (unless :func:`one_basin` says no other basin is there to find).
IMPLAUSIBLE_P = 1e-9


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _one_basin_kernel(positions_enu_m, stations_enu_m, rotations, kinds, valid, is_line, values, elevation_rad,
                      n_measurements):
    """:func:`one_basin` of ``(B, M)`` arrays (the lines of sight on their azimuth rows)."""
    size = kinds.shape[0]
    out = np.zeros(size, dtype=np.bool_)
    for b in range(size):
        east, north, up = positions_enu_m[b, 0], positions_enu_m[b, 1], positions_enu_m[b, 2]
        if not (math.isfinite(east) and math.isfinite(north) and math.isfinite(up)):
            continue
        alone = True
        for m in range(n_measurements[b]):
            if valid[b, m] and kinds[b, m] != AZIMUTH and kinds[b, m] != ELEVATION:
                alone = False
                break
            if is_line[b, m] and ahead_point(east, north, up, stations_enu_m[b], rotations[b], m, values[b, m],
                                             elevation_rad[b, m])[0] < 0:
                alone = False
                break
        out[b] = alone
    return out


def one_basin(batch: ProblemBatch, positions_enu_m) -> np.ndarray:
    """``(B,)``: whether a fit's basin is the only one the start search could find, under a loss that is not
    :data:`~core.estimators.loss.REDESCENDING` (those have a minimum per subset of measurements set aside):
    the problem measures angles only (no range or TOA) and the fit lies ahead of every line of sight.

    Ranges and TOAs make several crossings (a line of sight meets a sphere or hyperboloid twice), and a fit
    behind a station sits where its bearing points away; lines of sight that meet ahead of their stations
    have one basin there, which the weighted-EOVE start (the small-noise BLUE) is already in. A fit there
    whose chi-square is implausible has misstated sigmas or an outlier, which no other start mends: 10,000
    four-bearing problems with sigmas stated 5x too small took 7.6 s of ML (53 LM runs a problem, every
    search fit implausible too) against 0.14 s with true ones.
    """
    stations, rotations = batch.measurement_stations()
    is_line, elevation, _ = batch.lines_of_sight()
    return _one_basin_kernel(np.ascontiguousarray(positions_enu_m, dtype=float),
                             np.ascontiguousarray(stations, dtype=float), np.ascontiguousarray(rotations, dtype=float),
                             np.ascontiguousarray(batch.kinds, dtype=np.int64), np.ascontiguousarray(batch.valid),
                             is_line, np.ascontiguousarray(batch.values, dtype=float), elevation,
                             np.asarray(batch.n_measurements, dtype=np.int64))


def _spread(batch: ProblemBatch, rows, solution: Solution, options: SolveOptions, covariance, warnings) -> None:
    """The searched fixes ``rows`` ``(K,)`` (mixes without a closed form, or whose closed-form fit failed: the
    geometries where the model can be far from linear over the fix's uncertainty) get the unscented covariance
    of the estimator, never below the bound (:mod:`core.estimators.unscented_fix`), in ``covariance``; where it
    exceeds the bound by more than ``CURVED_VARIANCE_RATIO``, the warning ``curved_uncertainty``."""
    part = batch.take(rows)
    fixes = solution.position_enu_m[rows]

    def refit(moved, starts):  # to 1e-6 of a sigma (STEP_MAHALANOBIS2), not a step in metres: a thin axis is mm
        return levenberg_marquardt(moved, starts, REFINE_ITERATIONS, 0.0, _loss(options)).position_enu_m

    spread = unscented_covariance(part, fixes, solution.bias_m[rows], refit)
    raised, ratio = never_below(spread, batch_information(part, fixes).covariance_enu_m2)
    covariance[rows] = raised
    for j in np.flatnonzero(ratio > CURVED_VARIANCE_RATIO).tolist():
        b = int(rows[j])
        warnings[b] = warnings[b] + (FixWarning(
            "curved_uncertainty",
            f"the measurement model is far from linear over this fix's uncertainty: fixes of the measurements moved "
            f"by their sigmas spread {np.sqrt(ratio[j]):.1f} x the bound's sigma along its worst axis; the "
            "covariance is that spread (unscented), not the inverse information"),)


def _second_solution(batch: ProblemBatch, b: int, other_enu_m, other_cost: float, starts, names, failures,
                     solution: Solution, options: SolveOptions, covariance) -> tuple:
    """Problem ``b``'s rival at ``other_enu_m`` of cost ``other_cost``, judged by the one rule
    (:mod:`core.estimators.ambiguity`): a tie is :func:`_ambiguous`; a worse but plausible rival (plain least
    squares) makes the fix warn ``second_solution_plausible`` and writes the two-solution mixture's covariance
    into ``covariance[b]``."""
    delta = float(other_cost) - float(solution.cost[b])
    if delta <= AMBIGUITY_COST:
        return _ambiguous(batch, b, other_enu_m, starts, names, failures, solution, options)
    if options.loss != "linear" or delta > PLAUSIBLE_COST:  # a robust cost is no chi-square: only its ties count
        return ()
    fix = solution.position_enu_m[b]
    bounds = batch_information(batch.take([b, b]), np.stack([fix, other_enu_m])).covariance_enu_m2
    probability = float(rival_probability(delta))
    covariance[b] = mixture_covariance(fix, bounds[0], other_enu_m, bounds[1], probability)
    return (FixWarning("second_solution_plausible",
                       f"a second solution at {_point(batch, b, other_enu_m)} fits the measurements worse "
                       f"(chi2 {delta:.1f} above this fix) but is not ruled out: probability {probability:.1%}; "
                       "the covariance covers both (their mixture about this fix)"),)


def _ambiguous(batch: ProblemBatch, b: int, other_enu_m, starts, names, failures, solution: Solution,
               options: SolveOptions) -> tuple:
    """Problem ``b`` fits ``other_enu_m`` as well as its fix: the client's initial guess picks the nearer
    (the fix then warns ``ambiguous_solution``, naming the other); without one, ``AmbiguousGeometry`` (with
    a robust loss, the warning)."""
    fix = solution.position_enu_m[b].copy()
    guess = batch.initial_guess_enu_m[b]
    if not np.all(np.isfinite(guess)) and options.loss != "linear":
        # A redescending loss has minima of its own (one per subset it sets aside): named, not refused.
        return (FixWarning("ambiguous_solution", f"another point fits the measurements as well under the "
                                                 f"{options.loss} loss, at {_point(batch, b, other_enu_m)}"),)
    if not np.all(np.isfinite(guess)):
        failures[b] = AmbiguousGeometry(
            f"two points fit the measurements equally well: {_point(batch, b, fix)} and "
            f"{_point(batch, b, other_enu_m)}; send options.initial_guess near the right one, or add a "
            "measurement that tells them apart")
        return ()
    if np.linalg.norm(other_enu_m - guess) < np.linalg.norm(fix - guess):
        solution.put(b, iterate(batch.take([b]), other_enu_m[None], options), 0)
        starts[b], names[b], other_enu_m = other_enu_m, "initial_guess", fix
    return (FixWarning("ambiguous_solution", f"another point fits the measurements as well, at "
                                             f"{_point(batch, b, other_enu_m)}; the initial guess picked this one"),)


def _point(batch: ProblemBatch, b: int, position_enu_m) -> str:
    """A position as a message names it: common-frame ENU, and geodetic in a geodetic scene."""
    east, north, up = position_enu_m
    text = f"({east:.0f}, {north:.0f}, {up:.0f}) m in the common frame"
    if batch.geodetic[b]:
        lat, lon, alt = enu_to_geodetic(position_enu_m, *batch.origin[b])
        text += f" (lat {np.rad2deg(lat):.6f} deg, lon {np.rad2deg(lon):.6f} deg, alt {alt:.0f} m)"
    return text


def normalized_residuals(batch: ProblemBatch, solution: Solution) -> np.ndarray:
    """``(B, M)``: each measurement's residual over its sigma at the iteration's end (0 where unweighted)."""
    stations, rotations = batch.measurement_stations()
    predicted, _ = predict(solution.position_enu_m, solution.bias_m, stations, rotations, batch.kinds)
    return residuals(batch.model_values(), predicted, batch.kinds) * np.sqrt(batch.weights())


def subset_starts(batch: ProblemBatch, rows, suspicion):
    """Closed-form starts of the subsets of problems ``rows`` that leave one request measurement out, for their
    :data:`SUBSET_CANDIDATES` most suspect (:meth:`~core.problem_batch.ProblemBatch.leave_one_out`; by
    ``suspicion`` ``(B, M)``, say ``|residual| / sigma``).

    Returns
    -------
    owners : ndarray of int, shape (C,)
        The problem of each start (rows of ``batch``, in the order of ``rows``).
    starts_enu_m : ndarray, shape (C, 3)
        NaN where a subset has no closed form.
    """
    owners, dropped = batch.leave_one_out(rows, batch.valid, suspicion, SUBSET_CANDIDATES)
    subsets = batch.take(owners)
    subsets = subsets.with_used((batch.valid[owners] & ~dropped)[:, :subsets.kinds.shape[1]])
    return owners, initial_positions(subsets)[0]


@register("ml", "maximum likelihood (Levenberg-Marquardt) over any mix of measurements; the reference", robust=True)
def ml(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """ML from the closed-form start for the mix; where there is none, or the fit from it did not converge
    or is implausible (chi-square p below ``IMPLAUSIBLE_P``: the start sat in another basin) where other
    basins can be (:func:`one_basin`), ML from the geometry's candidates too, keeping the lower cost when that
    fit is plausible itself."""
    starts, names, failures = initial_positions(batch)
    missing = ~np.isfinite(starts).all(axis=-1)
    solution = iterate(batch, np.where(missing[:, None], batch.stations_enu_m[:, 0] + [0.0, 0.0, 1.0], starts),
                       options)
    dof = batch.dof
    p_value = chdtrc(np.maximum(dof, 1), solution.cost)
    implausible = p_value < IMPLAUSIBLE_P
    retry = missing | ~solution.converged
    if np.count_nonzero(implausible):
        if options.loss not in REDESCENDING:
            implausible &= ~one_basin(batch, solution.position_enu_m)
        retry |= implausible
    warnings: list[tuple] = [()] * batch.size
    covariance = np.full((batch.size, 3, 3), np.nan)  # a two-solution mixture's, where a rival is plausible
    if np.count_nonzero(retry):
        rows = np.flatnonzero(retry)
        earlier = np.where(missing[rows, None], np.nan, solution.position_enu_m[rows])
        found, rival, rival_cost = searched_starts(batch.take(rows), options, earlier)
        ok = np.all(np.isfinite(found), axis=-1)
        again = iterate(batch.take(rows[ok]), found[ok], options) if np.any(ok) else None
        for j, b in enumerate(rows[ok].tolist()):
            if chdtrc(max(int(dof[b]), 1), again.cost[j]) < IMPLAUSIBLE_P:
                continue
            if missing[b] or again.cost[j] < solution.cost[b]:
                starts[b], names[b] = found[ok][j], "search"
                failures.pop(b, None)
                missing[b] = False
                solution.put(b, again, j)
            if np.all(np.isfinite(rival[ok][j])):
                warnings[b] = _second_solution(batch, b, rival[ok][j], rival_cost[ok][j], starts, names, failures,
                                               solution, options, covariance)
        p_value[rows] = chdtrc(np.maximum(dof[rows], 1), solution.cost[rows])
    searched = np.flatnonzero(retry)
    if options.loss != "linear":
        normalized = normalized_residuals(batch, solution)
        failing = chdtrc(np.maximum(dof, 1), np.sum(normalized**2, axis=-1)) < SUBSET_P
        rows = np.array([b for b in np.flatnonzero(failing & ~missing).tolist()
                         if not warnings[b] and b not in failures], dtype=np.intp)
        owners, found = subset_starts(batch, rows, np.abs(normalized)) if rows.size else (rows, np.empty((0, 3)))
        ok = np.all(np.isfinite(found), axis=-1)
        owners, found = owners[ok], found[ok]
        if owners.size:
            again = iterate(batch.take(owners), found, options)
            cost = np.where(again.converged, again.cost, np.inf)
            order = np.lexsort((cost, owners))  # per problem, its lowest converged cost first
            lowest = order[np.flatnonzero(np.diff(owners[order], prepend=-1))]
            better = lowest[cost[lowest] < solution.cost[owners[lowest]] * (1.0 - 1e-9)]
            starts[owners[better]] = found[better]
            for b in owners[better].tolist():
                names[b] = "subset"
            solution.put(owners[better], again, better)
            p_value[rows] = chdtrc(np.maximum(dof[rows], 1), solution.cost[rows])
    # A closed form's (or the search's) fix may have a mirror image that fits as well: try it.
    check = (mirror_applies(batch) & ~missing & (p_value >= IMPLAUSIBLE_P)).nonzero()[0]
    check = np.array([b for b in check.tolist() if not warnings[b] and b not in failures], dtype=np.intp)
    if check.size:
        mirrored = mirror_points(batch, solution.position_enu_m)[check]
        finite = np.all(np.isfinite(mirrored), axis=-1)
        check, mirrored = check[finite], mirrored[finite]
    if check.size:
        images = fit_from(batch, check, mirrored, options, options.max_iterations)
        images = refine(batch, check, images, solution.cost[check], options)
        at_fix = batch_information(batch.take(check), solution.position_enu_m[check])
        fix = Fits(solution.position_enu_m[check], solution.cost[check], solution.converged[check],
                   np.ones(check.size, dtype=bool), at_fix.covariance_enu_m2)
        rival = _rivals(fix, images)
        possible = above_ground(batch.take(check), solution.position_enu_m[check])
        for j in np.flatnonzero(rival).tolist():
            b = int(check[j])
            if possible[j]:
                warnings[b] = _second_solution(batch, b, images.position_enu_m[j], images.cost[j], starts, names,
                                               failures, solution, options, covariance)
                continue
            # The fix is underground and its image a converged fit: the image is the fix.
            starts[b], names[b] = mirrored[j], "mirror"
            solution.put(b, iterate(batch.take([b]), images.position_enu_m[j][None], options), 0)
    alone = np.array([b for b in searched.tolist() if not missing[b] and b not in failures and not warnings[b]],
                     dtype=np.intp)
    if alone.size and options.loss == "linear":
        _spread(batch, alone, solution, options, covariance, warnings)
    return estimate_from(batch, starts, options, names, failures, solution, warnings,
                         covariance if np.isfinite(covariance).any() else None)
