"""The Levenberg-Marquardt iteration of ML (:mod:`core.estimators.methods.ml`), over a batch of problems.

Minimises ``sum (z - h(p))^2 / sigma^2`` for any mix of azimuth, elevation,
range and TOA. One compiled kernel iterates each problem of a batch on its
own (:func:`levenberg_marquardt`; zero-weight padding is skipped): ``4 x 4``
Jacobi-scaled normal equations in the common frame (metres of order 1e5 at
most, never ECEF's 6.4e6), with the Marquardt damping ``lambda diag(J^T W J)``.
A known altitude is a constraint: the position moves along the local
east/north at the current point and is put back on the altitude surface
after each step.

A robust loss (``options.loss``, scipy's names: :mod:`core.estimators.loss`)
is minimised as scipy's ``least_squares`` does: the gradient weights each
measurement by ``rho'``, the normal equations by ``rho' + 2 rho'' z``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from core.angles import wrap_point
from core.estimators.base import SolveOptions
from core.estimators.loss import CURVATURE_FLOOR, loss_code, loss_point
from core.kernel_data import Fitting, Frames, Measurements
from core.measurements import AZIMUTH, ELEVATION, RANGE, TOA, measure_point, toa_offset_point
from core.problem.batch import ProblemBatch
from core.problem.frame import local_axes_point, onto_altitude_point

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

    @classmethod
    def empty(cls, size: int) -> "Solution":
        """A solution of ``size`` problems for :func:`_lm_kernel` to fill (a compiled call costs more for each
        array it returns than for each it is given)."""
        return cls(np.empty((size, 3)), np.empty(size), np.zeros(size, dtype=np.int64), np.zeros(size, dtype=np.bool_),
                   np.empty(size))

    def put(self, rows, other: "Solution", picks) -> None:
        """Rows ``rows`` of this solution become rows ``picks`` of ``other`` (in place; int or ``(K,)`` each)."""
        for name in self.__dataclass_fields__:
            getattr(self, name)[rows] = getattr(other, name)[picks]


class Linearization(NamedTuple):
    """One problem's measurements linearised at a point (:func:`_evaluate` writes them; zero where unweighted).

    Attributes
    ----------
    residual : ndarray, shape (M,)
        Model units, angles wrapped.
    jacobian : ndarray, shape (4, M)
        Of the predictions by ``(east, north, up, bias)``.
    gradient_w, curvature_w : ndarray, shape (M,)
        Each measurement's weight in the gradient (``w rho'``) and in the Gauss-Newton matrix.
    """

    residual: np.ndarray
    jacobian: np.ndarray
    gradient_w: np.ndarray
    curvature_w: np.ndarray


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _linearization(width):
    return Linearization(np.empty(width), np.empty((4, width)), np.empty(width), np.empty(width))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _evaluate(position_enu_m, bias_m, measurements, b, fitting, out):
    """Problem ``b``'s measurements linearised at a point (into ``out``, a :class:`Linearization`); returns the
    cost ``sum C^2 rho(z / C^2)`` of the squared whitened residuals ``z`` under ``fitting``'s loss."""
    stations, rotations = measurements.stations_enu_m[b], measurements.rotations[b]
    kinds, values, weights = measurements.kinds[b], measurements.model_values[b], measurements.weights[b]
    residual, jacobian, gradient_w, curvature_w = out
    loss_code, c2 = fitting.loss_code, fitting.c2
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
def _lm_kernel(measurements, frames, starts_enu_m, fitting, out):
    """Every problem's Levenberg-Marquardt iteration (:func:`levenberg_marquardt`) from ``starts_enu_m``
    ``(B, 3)``: a batch's :class:`~core.kernel_data.Measurements` and :class:`~core.kernel_data.Frames`, and
    the :class:`~core.kernel_data.Fitting` (named or plain tuples); into ``out``, the fields of a
    :class:`Solution` (:meth:`Solution.empty`)."""
    measurements, frames, fitting = Measurements(*measurements), Frames(*frames), Fitting(*fitting)
    position_out, bias_out, iterations_out, converged_out, cost_out = out
    size, count = measurements.kinds.shape
    altitude_m, geodetic, has_toa = frames.altitude_m, frames.geodetic, frames.has_toa
    origin_ecef_m, origin_rotation = frames.origin_ecef_m, frames.origin_rotation
    loss_code = fitting.loss_code
    current, trial = _linearization(count), _linearization(count)
    local = np.empty((4, count))
    axes = np.empty((3, 3))
    information, scaled, undamped, curvature = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((3, 3))
    free_right, free_step = np.empty(4), np.empty(4)
    gradient, scale, right, step, free = np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    x, x_new, delta = np.empty(3), np.empty(3), np.empty(3)
    for b in range(size):
        st, kd = measurements.stations_enu_m[b], measurements.kinds[b]
        val, wt = measurements.model_values[b], measurements.weights[b]
        constrained = not math.isnan(altitude_m[b])
        x[:] = starts_enu_m[b]
        if constrained:
            onto_altitude_point(x, altitude_m[b], geodetic[b], origin_ecef_m[b], origin_rotation[b])
        bias = toa_offset_point(x[0], x[1], x[2], st, kd, val, wt)
        free[0] = free[1] = 1.0
        free[2] = 0.0 if constrained else 1.0
        free[3] = 1.0 if has_toa[b] else 0.0
        cost = _evaluate(x, bias, measurements, b, fitting, current)
        has_distance = False
        for m in range(count):
            has_distance |= wt[m] > 0.0 and (kd[m] == RANGE or kd[m] == TOA)
        damping = LAMBDA_START
        stationary = False
        iterations = 0
        converged = False
        for _ in range(fitting.max_iterations):
            residual, jacobian, gradient_w, curvature_w = current
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
            cost_new = _evaluate(x_new, bias_new, measurements, b, fitting, trial)
            iterations += 1
            if math.isfinite(cost_new) and cost_new <= cost * (1.0 + 1e-12) + 1e-300:
                x[:] = x_new
                bias, cost = bias_new, cost_new
                current, trial = trial, current
                damping = max(damping / 10.0, LAMBDA_MIN)
            else:
                damping *= 10.0
            if math.sqrt(length2) < fitting.tolerance_m:
                converged = True
                break
            if damping > LAMBDA_MAX:
                break
        converged = converged or stationary
        position_out[b] = x
        bias_out[b], cost_out[b] = bias, cost
        iterations_out[b], converged_out[b] = iterations, converged


def levenberg_marquardt(batch: ProblemBatch, start_enu_m, max_iterations=50, tolerance_m=1e-3,
                        loss=LINEAR) -> Solution:
    """Iterate every problem of a batch to its ML position (or, with a robust loss, its M-estimate).

    One compiled kernel runs each problem's iteration on its own (so a problem's result does not depend on
    the batch it is in): Jacobi-scaled normal equations of ``(east, north, up, b)`` with the Marquardt
    damping ``lambda diag(J^T W J)`` (with a robust loss, the larger of the Gauss-Newton and the ``rho'``
    weighted diagonal: :mod:`core.estimators.loss`), a step accepted when the cost does not rise; with a
    known altitude the step moves along the local east and north and the point is put back on the altitude surface
    (:func:`core.problem.frame.onto_altitude`, the same geodesy). The model is
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
    solution = Solution.empty(batch.size)
    _lm_kernel(tuple(batch.kernel_measurements), tuple(batch.kernel_frames), np.ascontiguousarray(start_enu_m, dtype=float),
               tuple(fitting_of(loss, max_iterations, tolerance_m)), _fields(solution))
    return solution


def _fields(solution: Solution) -> tuple:
    """A solution's arrays in :func:`_lm_kernel`'s order, for it to fill."""
    return solution.position_enu_m, solution.bias_m, solution.iterations, solution.converged, solution.cost


def fitting_of(loss, max_iterations, tolerance_m) -> Fitting:
    """The :class:`~core.kernel_data.Fitting` of a loss ``(name, scale in sigmas)`` and the iteration's limits."""
    return Fitting(loss_code(loss[0]), float(loss[1]) ** 2, int(max_iterations), float(tolerance_m))


def loss_of(options: SolveOptions) -> tuple[str, float]:
    """The options' loss as :func:`levenberg_marquardt` takes it: ``(name, scale in sigmas)``."""
    return options.loss, options.loss_scale


def iterate(batch: ProblemBatch, starts_enu_m, options: SolveOptions) -> Solution:
    """:func:`levenberg_marquardt` with the options' iteration limits and loss."""
    return levenberg_marquardt(batch, np.asarray(starts_enu_m, dtype=float), options.max_iterations,
                               options.tolerance_m, loss_of(options))

