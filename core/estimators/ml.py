"""Maximum likelihood by Levenberg-Marquardt over a batch of problems (section 3).

Minimises ``sum (z - h(p))^2 / sigma^2`` for any mix of azimuth, elevation,
range and TOA. Problems of different sizes are padded with zero-weight
measurements and iterated together: every step is one batched solve of
``(B, 4, 4)`` Jacobi-scaled normal equations in the common frame (metres of
order 1e5 at most, never ECEF's 6.4e6), with the Marquardt damping
``lambda diag(J^T W J)`` per problem. Problems that have converged leave the
working set, so late iterations cost only what is still moving. A known
altitude is a constraint: the position moves along the local east/north at
the current point and is put back on the altitude surface after each step.
The covariance is the inverse information at the solution (computed by the
finisher, like everything else a fix reports).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.special import chdtrc

from core.batch import TOA, ProblemBatch
from core.crlb import batch_information, normal_matrix, parameterisation
from core.errors import LocalizationError
from core.estimators.base import SolveOptions, register
from core.estimators.finish import optimal_bias_m
from core.estimators.result import Estimates, FixWarning
from core.estimators.search import candidates
from core.estimators.starting_points import initial_positions
from core.measurements import MeasurementModel
from core.problem import onto_altitude

_EYE4 = np.eye(4)
_LAMBDA_START = 1e-3
_LAMBDA_MIN = 1e-12
_LAMBDA_MAX = 1e12
#: The working set is compacted when fewer than this share of it is still active.
_COMPACT_BELOW = 0.5
#: A batch is solved in chunks of about this many measurement slots (problems x padded width),
#: and of at least ``CHUNK_MIN_PROBLEMS`` problems: the working planes then stay in cache.
CHUNK_ENTRIES = 1 << 15
CHUNK_MIN_PROBLEMS = 64


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


class _Problems:
    """What the iteration needs of B problems: their measurement model, values, weights and constraints."""

    def __init__(self, batch: ProblemBatch | None = None, **arrays):
        if batch is None:
            self.__dict__.update(arrays)
            return
        stations, rotations = batch.measurement_stations()
        self.model = MeasurementModel(stations, rotations, batch.kinds)
        self.station_positions = stations
        self.values = batch.model_values()
        self.weights = batch.weights()
        self.used = self.weights > 0
        self.is_toa = batch.kinds == TOA
        self.altitude_m = batch.altitude_m
        self.origin = batch.origin
        self.geodetic = batch.geodetic
        self.has_toa = batch.has_toa

    def take(self, rows) -> "_Problems":
        out = {name: value[rows] for name, value in self.__dict__.items() if name != "model"}
        return _Problems(model=self.model.take(rows), **out)

    def project(self, positions_enu_m):
        constrained = ~np.isnan(self.altitude_m)
        if not np.any(constrained):
            return positions_enu_m
        moved = onto_altitude(positions_enu_m, np.nan_to_num(self.altitude_m), self.origin, self.geodetic)
        return np.where(constrained[:, None], moved, positions_enu_m)

    def parameterisation(self, positions_enu_m):
        return parameterisation(positions_enu_m, self.altitude_m, self.has_toa, self.origin, self.geodetic)

    def optimal_bias(self, positions_enu_m):
        ranges = np.linalg.norm(positions_enu_m[:, None, :] - self.station_positions, axis=-1)
        return optimal_bias_m(self.weights, self.values, ranges, self.is_toa)

    def evaluate(self, positions_enu_m, bias_m):
        """Residuals ``(B, M)`` (model units, zero on padding), cost ``(B,)`` and Jacobian ``(B, 4, M)``."""
        predicted, jacobian = self.model.predict(positions_enu_m, bias_m)
        residual = self.model.residuals(self.values, predicted) * self.used
        cost = np.einsum("bm,bm->b", self.weights, residual * residual)
        return residual, cost, jacobian


def levenberg_marquardt(batch: ProblemBatch, start_enu_m, max_iterations=50, tolerance_m=1e-3) -> Solution:
    """Iterate every problem of a batch to its ML position.

    Parameters
    ----------
    batch : ProblemBatch
    start_enu_m : ndarray, shape (B, 3)
    max_iterations : int
    tolerance_m : float

    Returns
    -------
    Solution
    """
    problems = _Problems(batch)
    x_all = problems.project(np.asarray(start_enu_m, dtype=float).copy())
    bias_all = problems.optimal_bias(x_all)
    size = x_all.shape[0]
    converged_all = np.zeros(size, dtype=bool)
    iterations_all = np.zeros(size, dtype=int)
    cost_all = np.zeros(size)

    work = np.arange(size)
    sub = problems
    x, bias = x_all, bias_all
    damping = np.full(size, _LAMBDA_START)
    active = np.ones(size, dtype=bool)
    converged = np.zeros(size, dtype=bool)
    iterations = np.zeros(size, dtype=int)
    r, cost, jacobian = sub.evaluate(x, bias)

    def store():
        x_all[work], bias_all[work], cost_all[work] = x, bias, cost
        converged_all[work], iterations_all[work] = converged, iterations

    eye = _EYE4
    for _ in range(max_iterations):
        n_active = np.count_nonzero(active)
        if n_active == 0:
            break
        if n_active < _COMPACT_BELOW * work.size:
            store()
            keep = np.flatnonzero(active)
            work, sub = work[keep], sub.take(keep)
            x, bias, r, cost, jacobian = x[keep], bias[keep], r[keep], cost[keep], jacobian[keep]
            damping, converged, iterations = damping[keep], converged[keep], iterations[keep]
            active = active[keep]
        axes, free = sub.parameterisation(x)
        information, local = normal_matrix(jacobian, sub.weights, axes, free)
        gradient = np.einsum("bim,bm->bi", local * sub.weights[:, None, :], r)
        diag = np.einsum("bii->bi", information)
        scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
        scaled = information * scale[:, :, None] * scale[:, None, :] + damping[:, None, None] * eye
        scaled[~active | ~np.all(np.isfinite(scaled), axis=(-2, -1))] = eye
        step = scale * np.linalg.solve(scaled, (scale * gradient)[..., None])[..., 0]
        step = np.where(active[:, None], step * free, 0.0)
        delta = step[:, :3] if axes is None else np.einsum("bi,bij->bj", step[:, :3], axes)
        x_new = sub.project(x + delta)
        bias_new = bias + step[:, 3]
        r_new, cost_new, jacobian_new = sub.evaluate(x_new, bias_new)
        accept = active & np.isfinite(cost_new) & (cost_new <= cost * (1.0 + 1e-12) + 1e-300)
        x = np.where(accept[:, None], x_new, x)
        bias = np.where(accept, bias_new, bias)
        r = np.where(accept[:, None], r_new, r)
        cost = np.where(accept, cost_new, cost)
        jacobian = np.where(accept[:, None, None], jacobian_new, jacobian)
        iterations += active
        damping = np.where(accept, np.maximum(damping / 10.0, _LAMBDA_MIN), damping * 10.0)
        done = active & (np.sqrt(np.einsum("bi,bi->b", delta, delta)) < tolerance_m)
        stuck = active & (damping > _LAMBDA_MAX)
        converged |= done
        active &= ~(done | stuck)
    store()
    return Solution(x_all, bias_all, iterations_all, converged_all, cost_all)


def iterate(batch: ProblemBatch, starts_enu_m, options: SolveOptions) -> Solution:
    """:func:`levenberg_marquardt` in cache-sized chunks (results do not depend on the chunking)."""
    starts = np.asarray(starts_enu_m, dtype=float)
    rows = max(CHUNK_MIN_PROBLEMS, CHUNK_ENTRIES // max(batch.kinds.shape[1], 1))
    if rows >= batch.size:
        return levenberg_marquardt(batch, starts, options.max_iterations, options.tolerance_m)
    parts = [levenberg_marquardt(batch.take(np.arange(first, min(first + rows, batch.size))),
                                 starts[first:first + rows], options.max_iterations, options.tolerance_m)
             for first in range(0, batch.size, rows)]
    return Solution(*(np.concatenate([getattr(p, f) for p in parts]) for f in Solution.__dataclass_fields__))


def estimate_from(batch: ProblemBatch, starts_enu_m, options: SolveOptions, start_names, failures,
                  solution: Solution | None = None) -> Estimates:
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
    """
    starts = np.array(starts_enu_m, dtype=float)
    missing = ~np.all(np.isfinite(starts), axis=-1)
    errors = dict(failures)
    for b in np.flatnonzero(missing):
        errors.setdefault(int(b), LocalizationError("no starting point for this geometry"))
    starts[missing] = batch.stations_enu_m[missing, 0] + [0.0, 0.0, 1.0]
    solution = solution or iterate(batch, starts, options)
    return Estimates(
        position_enu_m=solution.position_enu_m,
        covariance_source="information",
        errors=errors,
        converged=solution.converged,
        iterations=solution.iterations,
        bias_m=solution.bias_m,
        details=[{"start": name} if name is not None else {} for name in start_names],
    )


#: A second solution whose cost is within this of the best (chi-square units) makes the fix ambiguous.
AMBIGUITY_COST = 4.0


def searched_starts(batch: ProblemBatch, options: SolveOptions) -> tuple[np.ndarray, np.ndarray]:
    """Starts where no closed form applies: ML from every candidate of
    :func:`core.estimators.search.candidates`, the lowest final cost where the information is regular kept
    (an iterate that ran off to where the measurements say nothing may fit better, and is no fix).

    Returns
    -------
    starts : ndarray, shape (B, 3)
        NaN rows where no candidate gave a regular solution.
    rival : ndarray, shape (B, 3)
        Another regular solution, distinct from the best (farther than ten iteration tolerances), whose
        cost is within ``AMBIGUITY_COST`` of it (the second crossing of a line of sight with a hyperboloid,
        the mirror of coplanar stations, when the measurements leave no degree of freedom to tell them
        apart); NaN rows where none.
    """
    points = candidates(batch)
    size, count = points.shape[:2]
    tried = np.repeat(np.arange(size), count)
    flat = points.reshape(-1, 3)
    finite = np.all(np.isfinite(flat), axis=-1)
    out, rival = np.full((size, 3), np.nan), np.full((size, 3), np.nan)
    if not np.any(finite):
        return out, rival
    tried, flat = tried[finite], flat[finite]
    position, cost = np.empty_like(flat), np.full(tried.size, np.inf)
    step = max(1, CHUNK_ENTRIES // max(batch.kinds.shape[1], 1))  # memory: candidates x measurements
    for first in range(0, tried.size, step):
        part = slice(first, first + step)
        expanded = batch.take(tried[part])
        solution = levenberg_marquardt(expanded, flat[part], options.max_iterations, options.tolerance_m)
        position[part] = solution.position_enu_m
        finite = np.all(np.isfinite(position[part]), axis=-1)
        observable = batch_information(expanded, np.where(finite[:, None], position[part], 0.0)).observable
        cost[part] = np.where(finite & observable, solution.cost, np.inf)
    order = np.lexsort((cost, tried))
    first = order[np.r_[True, tried[order][1:] != tried[order][:-1]]]
    good = np.isfinite(cost[first])
    out[tried[first][good]] = position[first][good]
    best = out[tried]
    scale = np.linalg.norm(best - batch.stations_enu_m[tried, 0], axis=-1)
    apart = np.linalg.norm(np.nan_to_num(position) - best, axis=-1) > np.maximum(10.0 * options.tolerance_m,
                                                                                1e-7 * scale)
    close = np.isfinite(cost) & apart & (cost <= cost[first][np.searchsorted(tried[first], tried)] + AMBIGUITY_COST)
    for k in np.flatnonzero(close)[::-1]:
        rival[tried[k]] = position[k]
    return out, rival


#: A fit from the closed-form start whose chi-square has a p-value below this is retried from the search.
IMPLAUSIBLE_P = 1e-9


@register("ml", "maximum likelihood (Levenberg-Marquardt) over any mix of measurements; the reference")
def ml(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """ML from the closed-form start for the mix; where there is none, or the fit from it did not converge
    or is implausible (chi-square p below ``IMPLAUSIBLE_P``: the start sat in another basin), ML from the
    geometry's candidates too, keeping the lower cost when that fit is plausible itself."""
    starts, names, failures = initial_positions(batch)
    missing = ~np.all(np.isfinite(starts), axis=-1)
    solution = iterate(batch, np.where(missing[:, None], batch.stations_enu_m[:, 0] + [0.0, 0.0, 1.0], starts),
                       options)
    dof = np.count_nonzero(batch.valid & np.isfinite(batch.sigmas), axis=-1) - (
        np.where(batch.constrained, 2, 3) + batch.has_toa)
    implausible = chdtrc(np.maximum(dof, 1), solution.cost) < IMPLAUSIBLE_P
    retry = missing | ~solution.converged | implausible
    warnings: list[tuple] = [()] * batch.size
    if np.any(retry):
        rows = np.flatnonzero(retry)
        found, rival = searched_starts(batch.take(rows), options)
        ok = np.all(np.isfinite(found), axis=-1)
        again = iterate(batch.take(rows[ok]), found[ok], options) if np.any(ok) else None
        for j, b in enumerate(rows[ok].tolist()):
            plausible = chdtrc(max(int(dof[b]), 1), again.cost[j]) >= IMPLAUSIBLE_P
            if plausible and (missing[b] or again.cost[j] < solution.cost[b]):
                starts[b], names[b] = found[ok][j], "search"
                failures.pop(b, None)
                missing[b] = False
                for name in Solution.__dataclass_fields__:
                    getattr(solution, name)[b] = getattr(again, name)[j]
            if np.all(np.isfinite(rival[ok][j])):
                other = rival[ok][j]
                warnings[b] = (FixWarning("ambiguous_solution", "another point fits the measurements as well, at "
                                          f"({other[0]:.0f}, {other[1]:.0f}, {other[2]:.0f}) m in the common frame: "
                                          "add a measurement to tell them apart"),)
    estimates = estimate_from(batch, starts, options, names, failures, solution)
    return replace(estimates, warnings=warnings)
