"""Maximum likelihood by Levenberg-Marquardt over a batch of problems (section 3).

Minimises ``sum (z - h(p))^2 / sigma^2`` for any mix of azimuth, elevation,
range and TOA. Problems of different sizes are padded with zero-weight
measurements and iterated together: every step is one batched solve of
``(B, 4, 4)`` Jacobi-scaled normal equations in the common frame (metres of
order 1e5 at most, never ECEF's 6.4e6), with the Marquardt damping
``lambda diag(J^T W J)`` per problem. A known altitude is a constraint: the
position moves along the local east/north at the current point and is put
back on the altitude surface after each step. The covariance is the inverse
information at the solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.crlb import Information, invert_information, normal_matrix
from core.errors import LocalizationError, UnobservableGeometry
from core.estimators.base import Fix, FixWarning, SolveOptions, finish_fix, register
from core.estimators.start import initial_position
from core.measurements import Kind, predict, residuals
from core.problem import Problem, local_axes, onto_altitude

_LAMBDA_START = 1e-3
_LAMBDA_MIN = 1e-12
_LAMBDA_MAX = 1e12


@dataclass(frozen=True)
class ProblemStack:
    """Problems padded to one measurement count (zero weight fills the gaps).

    Attributes
    ----------
    stations_enu_m : ndarray, shape (B, M, 3)
        Station of each measurement.
    rotations : ndarray, shape (B, M, 3, 3)
    kinds : ndarray of int, shape (B, M)
    values : ndarray, shape (B, M)
        Model units (TOA as pseudo-range metres).
    weights : ndarray, shape (B, M)
        ``1 / sigma^2`` in model units; 0 for padding.
    altitude_m : ndarray, shape (B,)
        NaN where unconstrained.
    origin : ndarray, shape (B, 3)
        Each problem's frame origin ``(lat_rad, lon_rad, alt_m)``.
    geodetic : ndarray of bool, shape (B,)
    has_toa : ndarray of bool, shape (B,)
    """

    stations_enu_m: np.ndarray
    rotations: np.ndarray
    kinds: np.ndarray
    values: np.ndarray
    weights: np.ndarray
    altitude_m: np.ndarray
    origin: np.ndarray
    geodetic: np.ndarray
    has_toa: np.ndarray

    @classmethod
    def from_problems(cls, problems: list[Problem]) -> "ProblemStack":
        batch = len(problems)
        size = max(p.n_measurements for p in problems)
        stations = np.zeros((batch, size, 3))
        stations[..., 0] = 1.0
        rotations = np.broadcast_to(np.eye(3), (batch, size, 3, 3)).copy()
        kinds = np.full((batch, size), Kind.RANGE, dtype=np.int8)
        values = np.zeros((batch, size))
        weights = np.zeros((batch, size))
        for b, p in enumerate(problems):
            m = p.n_measurements
            stations[b, :m] = p.stations_enu_m[p.station_index]
            rotations[b, :m] = p.station_rotations[p.station_index]
            kinds[b, :m] = p.kinds
            values[b, :m] = p.model_values()
            weights[b, :m] = 1.0 / p.model_sigmas() ** 2
        return cls(
            stations_enu_m=stations,
            rotations=rotations,
            kinds=kinds,
            values=values,
            weights=weights,
            altitude_m=np.array([np.nan if p.altitude_m is None else p.altitude_m for p in problems]),
            origin=np.array([p.frame.origin_array() for p in problems]),
            geodetic=np.array([p.frame.is_geodetic for p in problems]),
            has_toa=np.array([p.has_toa for p in problems]),
        )

    @property
    def constrained(self) -> np.ndarray:
        return ~np.isnan(self.altitude_m)

    def parameterisation(self, positions_enu_m):
        """Local axes ``(B, 3, 3)`` and free parameters ``(B, 4)`` at positions ``(B, 3)``."""
        batch = positions_enu_m.shape[0]
        free = np.ones((batch, 4), dtype=bool)
        free[:, 2] = ~self.constrained
        free[:, 3] = self.has_toa
        axes = np.broadcast_to(np.eye(3), (batch, 3, 3))
        if np.any(self.constrained):
            axes = np.where(self.constrained[:, None, None],
                            local_axes(positions_enu_m, self.origin, self.geodetic), axes)
        return axes, free

    def project(self, positions_enu_m):
        """Put constrained problems' positions back on their altitude surface."""
        if not np.any(self.constrained):
            return positions_enu_m
        moved = onto_altitude(positions_enu_m, np.nan_to_num(self.altitude_m), self.origin, self.geodetic)
        return np.where(self.constrained[:, None], moved, positions_enu_m)

    def evaluate(self, positions_enu_m, bias_m):
        """Residuals ``(B, M)`` (model units, zero on padding), cost ``(B,)`` and Jacobian."""
        predicted, jacobian = predict(positions_enu_m, bias_m, self.stations_enu_m, self.rotations, self.kinds)
        r = residuals(self.values, predicted, self.kinds) * (self.weights > 0)
        return r, np.einsum("bm,bm->b", self.weights, r * r), jacobian

    def optimal_bias(self, positions_enu_m):
        """Weighted-mean TOA offset ``(B,)`` given positions; 0 without TOA."""
        is_toa = (self.kinds == Kind.TOA) & (self.weights > 0)
        ranges = np.linalg.norm(positions_enu_m[:, None, :] - self.stations_enu_m, axis=-1)
        w = self.weights * is_toa
        total = w.sum(axis=-1)
        return np.where(total > 0, np.einsum("bm,bm->b", w, self.values - ranges) / np.where(total > 0, total, 1), 0.0)


@dataclass(frozen=True)
class BatchSolution:
    """Raw ML output for a batch (arrays with leading axis B)."""

    positions_enu_m: np.ndarray
    bias_m: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    information: Information


def levenberg_marquardt(stack: ProblemStack, start_enu_m, max_iterations=50, tolerance_m=1e-3) -> BatchSolution:
    """Iterate every problem of a stack to its ML position.

    Parameters
    ----------
    stack : ProblemStack
    start_enu_m : ndarray, shape (B, 3)
    max_iterations : int
    tolerance_m : float

    Returns
    -------
    BatchSolution
    """
    x = stack.project(np.asarray(start_enu_m, dtype=float).copy())
    bias = stack.optimal_bias(x)
    batch = x.shape[0]
    damping = np.full(batch, _LAMBDA_START)
    active = np.ones(batch, dtype=bool)
    converged = np.zeros(batch, dtype=bool)
    iterations = np.zeros(batch, dtype=int)
    r, cost, jacobian = stack.evaluate(x, bias)
    for _ in range(max_iterations):
        if not np.any(active):
            break
        axes, free = stack.parameterisation(x)
        information, local_jacobian = normal_matrix(jacobian, stack.weights, axes, free)
        gradient = np.einsum("bmi,bm,bm->bi", local_jacobian, stack.weights, r)
        diag = np.einsum("bii->bi", information)
        scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
        scaled = information * scale[:, :, None] * scale[:, None, :] + damping[:, None, None] * np.eye(4)
        scaled = np.where(active[:, None, None], scaled, np.eye(4))
        step = scale * np.linalg.solve(scaled, (scale * gradient)[..., None])[..., 0]
        step = np.where(active[:, None], step * free, 0.0)
        delta = np.einsum("bi,bij->bj", step[:, :3], axes)
        x_new = stack.project(x + delta)
        bias_new = bias + step[:, 3]
        r_new, cost_new, jacobian_new = stack.evaluate(x_new, bias_new)
        accept = active & np.isfinite(cost_new) & (cost_new <= cost * (1.0 + 1e-12) + 1e-300)
        x = np.where(accept[:, None], x_new, x)
        bias = np.where(accept, bias_new, bias)
        r = np.where(accept[:, None], r_new, r)
        cost = np.where(accept, cost_new, cost)
        jacobian = np.where(accept[:, None, None], jacobian_new, jacobian)
        iterations += active
        damping = np.where(accept, np.maximum(damping / 10.0, _LAMBDA_MIN), damping * 10.0)
        done = active & (np.linalg.norm(delta, axis=-1) < tolerance_m)
        stuck = active & (damping > _LAMBDA_MAX)
        converged |= done
        active &= ~(done | stuck)
    axes, free = stack.parameterisation(x)
    information, _ = normal_matrix(jacobian, stack.weights, axes, free)
    return BatchSolution(x, bias, iterations, converged, invert_information(information, axes, free))


def solve_ml_batch(problems: list[Problem], options: SolveOptions, method: str = "ml") -> list[Fix | LocalizationError]:
    """ML fixes for many problems in one batched iteration.

    Returns
    -------
    list of Fix or LocalizationError
        In input order; a problem that cannot be solved gets its error.
    """
    results: list[Fix | LocalizationError | None] = [None] * len(problems)
    starts, start_names, solvable = [], [], []
    for i, problem in enumerate(problems):
        try:
            start, name = initial_position(problem)
        except LocalizationError as error:
            results[i] = error
            continue
        starts.append(start)
        start_names.append(name)
        solvable.append(i)
    if solvable:
        subset = [problems[i] for i in solvable]
        solution = levenberg_marquardt(ProblemStack.from_problems(subset), np.array(starts),
                                       options.max_iterations, options.tolerance_m)
        for j, i in enumerate(solvable):
            results[i] = _finish(problems[i], solution, j, start_names[j], method)
    return results


def _finish(problem: Problem, solution: BatchSolution, j: int, start: str, method: str) -> Fix | LocalizationError:
    info = solution.information
    if not info.observable[j]:
        return UnobservableGeometry(
            "the measurements do not determine the position: the information matrix is singular "
            f"(min scaled eigenvalue {info.min_eigenvalue[j]:.1e}); add stations, elevations or an altitude constraint")
    single = Information(info.covariance_enu_m2[j:j + 1], info.covariance_params[j:j + 1],
                         info.observable[j:j + 1], info.min_eigenvalue[j:j + 1])
    warnings = []
    if not solution.converged[j]:
        warnings.append(FixWarning("not_converged",
                                   f"no convergence in {int(solution.iterations[j])} iterations; last accepted iterate returned"))
    try:
        return finish_fix(problem, method, solution.positions_enu_m[j], single.covariance_enu_m2[0],
                          covariance_source="information", converged=bool(solution.converged[j]),
                          iterations=int(solution.iterations[j]), warnings=warnings,
                          bias_m=float(solution.bias_m[j]), crlb=single, details={"start": start})
    except LocalizationError as error:
        return error


@register("ml", "maximum likelihood (Levenberg-Marquardt) over any mix of measurements; the reference")
def ml(problem: Problem, options: SolveOptions) -> Fix:
    (result,) = solve_ml_batch([problem], options)
    if isinstance(result, LocalizationError):
        raise result
    return result
