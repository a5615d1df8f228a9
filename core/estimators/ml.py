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
from core.errors import AmbiguousGeometry, LocalizationError
from core.estimators.base import SolveOptions, register
from core.estimators.finish import optimal_bias_m
from core.estimators.loss import loss_weights
from core.estimators.result import Estimates, FixWarning
from core.estimators.search import candidates
from core.estimators.starting_points import initial_positions
from core.geodesy import enu_to_geodetic
from core.measurements import MeasurementModel
from core.problem import onto_altitude

_EYE4 = np.eye(4)
#: Plain least squares: ``(loss name, scale in sigmas)``.
LINEAR = ("linear", 1.0)
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

    def evaluate(self, positions_enu_m, bias_m, loss=LINEAR):
        """Residuals ``(B, M)`` (model units, zero on padding), cost ``(B,)``, Jacobian ``(B, 4, M)`` and the
        gradient and Gauss-Newton weights ``(B, M)`` (``weights`` themselves for the linear loss).

        ``loss`` is ``(name, scale in sigmas)``; the cost is ``sum C^2 rho(z / C^2)`` of the squared whitened
        residuals ``z`` (:mod:`core.estimators.loss`).
        """
        predicted, jacobian = self.model.predict(positions_enu_m, bias_m)
        residual = self.model.residuals(self.values, predicted) * self.used
        squared = self.weights * residual * residual
        if loss[0] == "linear":
            return residual, squared.sum(axis=-1), jacobian, self.weights, self.weights
        rho, gradient_factor, curvature_factor = loss_weights(squared, *loss)
        return (residual, np.sum(rho * self.used, axis=-1), jacobian, self.weights * gradient_factor,
                self.weights * curvature_factor)


def levenberg_marquardt(batch: ProblemBatch, start_enu_m, max_iterations=50, tolerance_m=1e-3,
                        loss=LINEAR) -> Solution:
    """Iterate every problem of a batch to its ML position (or, with a robust loss, its M-estimate).

    Parameters
    ----------
    batch : ProblemBatch
    start_enu_m : ndarray, shape (B, 3)
    max_iterations : int
    tolerance_m : float
    loss : tuple of (str, float)
        The loss's name and scale in sigmas (:mod:`core.estimators.loss`); the cost minimised is its sum.

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
    r, cost, jacobian, gradient_w, curvature_w = sub.evaluate(x, bias, loss)
    robust = loss[0] != "linear"

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
            gradient_w, curvature_w = (gradient_w[keep], curvature_w[keep]) if robust else (sub.weights,) * 2
            damping, converged, iterations = damping[keep], converged[keep], iterations[keep]
            active = active[keep]
        axes, free = sub.parameterisation(x)
        information, local = normal_matrix(jacobian, curvature_w, axes, free)
        gradient = np.einsum("bim,bm->bi", local * gradient_w[:, None, :], r)
        diag = np.einsum("bii->bi", information)
        scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
        scaled = information * scale[:, :, None] * scale[:, None, :] + damping[:, None, None] * eye
        scaled[~active | ~np.all(np.isfinite(scaled), axis=(-2, -1))] = eye
        step = scale * np.linalg.solve(scaled, (scale * gradient)[..., None])[..., 0]
        step = np.where(active[:, None], step * free, 0.0)
        delta = step[:, :3] if axes is None else np.einsum("bi,bij->bj", step[:, :3], axes)
        x_new = sub.project(x + delta)
        bias_new = bias + step[:, 3]
        r_new, cost_new, jacobian_new, gradient_w_new, curvature_w_new = sub.evaluate(x_new, bias_new, loss)
        accept = active & np.isfinite(cost_new) & (cost_new <= cost * (1.0 + 1e-12) + 1e-300)
        x = np.where(accept[:, None], x_new, x)
        bias = np.where(accept, bias_new, bias)
        r = np.where(accept[:, None], r_new, r)
        cost = np.where(accept, cost_new, cost)
        jacobian = np.where(accept[:, None, None], jacobian_new, jacobian)
        if robust:
            gradient_w = np.where(accept[:, None], gradient_w_new, gradient_w)
            curvature_w = np.where(accept[:, None], curvature_w_new, curvature_w)
        iterations += active
        damping = np.where(accept, np.maximum(damping / 10.0, _LAMBDA_MIN), np.where(active, damping * 10.0, damping))
        done = active & (np.sqrt(np.einsum("bi,bi->b", delta, delta)) < tolerance_m)
        stuck = active & (damping > _LAMBDA_MAX)
        converged |= done
        active &= ~(done | stuck)
    store()
    return Solution(x_all, bias_all, iterations_all, converged_all, cost_all)


def _loss(options: SolveOptions) -> tuple[str, float]:
    return options.loss, options.loss_scale


def iterate(batch: ProblemBatch, starts_enu_m, options: SolveOptions) -> Solution:
    """:func:`levenberg_marquardt` in cache-sized chunks (results do not depend on the chunking)."""
    starts = np.asarray(starts_enu_m, dtype=float)
    rows = max(CHUNK_MIN_PROBLEMS, CHUNK_ENTRIES // max(batch.kinds.shape[1], 1))
    if rows >= batch.size:
        return levenberg_marquardt(batch, starts, options.max_iterations, options.tolerance_m, _loss(options))
    parts = [levenberg_marquardt(batch.take(np.arange(first, min(first + rows, batch.size))),
                                 starts[first:first + rows], options.max_iterations, options.tolerance_m,
                                 _loss(options))
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
        loss=None if options.loss == "linear" else _loss(options),
        errors=errors,
        converged=solution.converged,
        iterations=solution.iterations,
        bias_m=solution.bias_m,
        details=[{"start": name} if name is not None else {} for name in start_names],
    )


#: A second solution whose cost is within this of the best (chi-square units) makes the fix ambiguous.
AMBIGUITY_COST = 4.0
#: ... when it is farther from the best than this squared Mahalanobis distance (the best's CRLB): within one
#: basin a point whose cost is within ``AMBIGUITY_COST`` of the minimum is within about that distance.
DISTINCT_MAHALANOBIS2 = 25.0
#: Below this height above the ellipsoid (m) a point of a geodetic scene is inside the earth: no solution.
MIN_ALTITUDE_M = -1000.0


def above_ground(batch: ProblemBatch, positions_enu_m) -> np.ndarray:
    """Which positions ``(B, 3)`` are physically possible: in a geodetic scene, not below ``MIN_ALTITUDE_M``
    (a flat local frame does not say where the ground is)."""
    if not np.any(batch.geodetic):
        return np.ones(batch.size, dtype=bool)
    origin = batch.origin
    altitude = enu_to_geodetic(np.nan_to_num(positions_enu_m), origin[:, 0], origin[:, 1], origin[:, 2])[2]
    return ~batch.geodetic | (altitude >= MIN_ALTITUDE_M)


def searched_starts(batch: ProblemBatch, options: SolveOptions, extra_enu_m=None) -> tuple[np.ndarray, np.ndarray]:
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
        The best of the other solutions that are distinct from the best (``DISTINCT_MAHALANOBIS2``) and whose
        cost is within ``AMBIGUITY_COST`` of it (the second crossing of a line of sight with a hyperboloid,
        the mirror of coplanar stations, when the measurements leave no degree of freedom to tell them
        apart); NaN rows where none.
    """
    points = candidates(batch)
    if extra_enu_m is not None:
        points = np.concatenate([np.asarray(extra_enu_m, dtype=float)[:, None, :], points], axis=1)
    size, count = points.shape[:2]
    tried = np.repeat(np.arange(size), count)
    flat = points.reshape(-1, 3)
    finite = np.all(np.isfinite(flat), axis=-1)
    out, rival = np.full((size, 3), np.nan), np.full((size, 3), np.nan)
    if not np.any(finite):
        return out, rival
    tried, flat = tried[finite], flat[finite]
    expanded = batch.take(tried)
    solution = levenberg_marquardt(expanded, flat, options.max_iterations, options.tolerance_m, _loss(options))
    position = solution.position_enu_m
    finite = np.all(np.isfinite(position), axis=-1)
    information = batch_information(expanded, np.where(finite[:, None], position, 0.0))
    regular = finite & information.observable & above_ground(expanded, position)
    cost = np.where(regular, solution.cost, np.inf)
    order = np.lexsort((cost, tried))
    first = order[np.r_[True, tried[order][1:] != tried[order][:-1]]]
    good = np.isfinite(cost[first])
    out[tried[first][good]] = position[first][good]
    best_of = first[np.searchsorted(tried[first], tried)]
    apart = np.nan_to_num(position - position[best_of])
    precision = np.linalg.pinv(information.covariance_enu_m2[best_of], rcond=1e-9, hermitian=True)
    distance2 = np.einsum("ki,kij,kj->k", apart, precision, apart)
    close = regular & (distance2 > DISTINCT_MAHALANOBIS2) & (cost <= cost[best_of] + AMBIGUITY_COST)
    second = np.where(close, cost, np.inf)
    order = np.lexsort((second, tried))
    lowest = order[np.r_[True, tried[order][1:] != tried[order][:-1]]]
    found = np.isfinite(second[lowest])
    rival[tried[lowest][found]] = position[lowest][found]
    return out, rival


#: A fit from the closed-form start whose chi-square has a p-value below this is retried from the search.
IMPLAUSIBLE_P = 1e-9


def _ambiguous(batch: ProblemBatch, b: int, other_enu_m, starts, names, failures, solution: Solution,
               options: SolveOptions) -> tuple:
    """Problem ``b`` fits ``other_enu_m`` as well as its fix: the client's initial guess picks the nearer
    (the fix then warns ``ambiguous_solution``, naming the other); without one, ``AmbiguousGeometry``."""
    fix = solution.position_enu_m[b].copy()
    guess = batch.initial_guess_enu_m[b]
    if not np.all(np.isfinite(guess)):
        failures[b] = AmbiguousGeometry(
            f"two points fit the measurements equally well: {_point(batch, b, fix)} and "
            f"{_point(batch, b, other_enu_m)}; send options.initial_guess near the right one, or add a "
            "measurement that tells them apart")
        return ()
    if np.linalg.norm(other_enu_m - guess) < np.linalg.norm(fix - guess):
        picked = iterate(batch.take([b]), other_enu_m[None], options)
        for name in Solution.__dataclass_fields__:
            getattr(solution, name)[b] = getattr(picked, name)[0]
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


@register("ml", "maximum likelihood (Levenberg-Marquardt) over any mix of measurements; the reference", robust=True)
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
        earlier = np.where(missing[rows, None], np.nan, solution.position_enu_m[rows])
        found, rival = searched_starts(batch.take(rows), options, earlier)
        ok = np.all(np.isfinite(found), axis=-1)
        again = iterate(batch.take(rows[ok]), found[ok], options) if np.any(ok) else None
        for j, b in enumerate(rows[ok].tolist()):
            if chdtrc(max(int(dof[b]), 1), again.cost[j]) < IMPLAUSIBLE_P:
                continue
            if missing[b] or again.cost[j] < solution.cost[b]:
                starts[b], names[b] = found[ok][j], "search"
                failures.pop(b, None)
                missing[b] = False
                for name in Solution.__dataclass_fields__:
                    getattr(solution, name)[b] = getattr(again, name)[j]
            if np.all(np.isfinite(rival[ok][j])):
                warnings[b] = _ambiguous(batch, b, rival[ok][j], starts, names, failures, solution, options)
    estimates = estimate_from(batch, starts, options, names, failures, solution)
    return replace(estimates, warnings=warnings)
