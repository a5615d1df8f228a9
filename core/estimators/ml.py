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

A robust loss (``options.loss``, scipy's names: :mod:`core.estimators.loss`)
is minimised as scipy's ``least_squares`` does: the gradient weights each
measurement by ``rho'``, the normal equations by ``rho' + 2 rho'' z``. The
finisher then reports the sandwich covariance of the final weights ``rho'``
(``covariance_source`` ``"robust"``): that of a weighted least-squares fit
with those weights, which is the bound without a measurement the loss has
set aside, and never below the bound.

Ties. Where the measurements leave (almost) no degree of freedom, a second
point may fit as well: a line of sight crosses a TDOA hyperboloid twice, or
ranges, TOAs and azimuths from nearly coplanar stations fit a point and its
mirror image through their plane. ML looks for one among the search's
solutions and from the fix's mirror image (:func:`mirror_points`); a rival
is a solution whose cost is within ``AMBIGUITY_COST`` of the fix, farther
than one sigma of the fix's bound (``DISTINCT_MAHALANOBIS2``: nearer, the
covariance covers both) and physically possible (a geodetic point more
than 1 km below the ellipsoid is no solution; a point behind a bearing
station never ties, its azimuth residual is near pi; a TOA's emission
precedes its arrival by construction of the model). A tie is a
:class:`~core.errors.AmbiguousGeometry` (422 ``ambiguous_geometry``) naming
both points, unless the client's ``initial_guess`` picks the nearer one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.special import chdtrc

from core.problem_batch import ELEVATION, TOA, ProblemBatch
from core.crlb import batch_information, normal_matrix, parameterisation
from core.errors import AmbiguousGeometry, LocalizationError
from core.estimators.base import SolveOptions, register
from core.estimators.finish import optimal_bias_m
from core.estimators.loss import loss_weights
from core.estimators.result import Estimates, FixWarning
from core.estimators.search import candidates
from core.estimators.starting_points import initial_positions
from core.geodesy import enu_to_geodetic
from core.linalg import jacobi_svd
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
#: ... when it is a converged solution farther from the best than this squared Mahalanobis distance (the
#: best's CRLB): nearer, no measurement at the stated noise tells them apart and the covariance covers both.
DISTINCT_MAHALANOBIS2 = 1.0
#: An iterate that stopped before converging is a rival only farther than this (it may be still sliding
#: down the best's own valley).
DISTINCT_UNCONVERGED_MAHALANOBIS2 = 25.0
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


def _rivals(best_covariance_enu_m2, best_enu_m, best_cost, position_enu_m, cost, converged, eligible):
    """Which solutions ``(K,)`` are rivals of their best: eligible (regular, possible), distinct
    (``DISTINCT_MAHALANOBIS2``, or ``DISTINCT_UNCONVERGED_MAHALANOBIS2`` if not converged) and as good
    (``AMBIGUITY_COST``)."""
    apart = np.nan_to_num(position_enu_m - best_enu_m)
    precision = np.linalg.pinv(best_covariance_enu_m2, rcond=1e-9, hermitian=True)
    distance2 = np.einsum("ki,kij,kj->k", apart, precision, apart)
    distinct = distance2 > np.where(converged, DISTINCT_MAHALANOBIS2, DISTINCT_UNCONVERGED_MAHALANOBIS2)
    return eligible & distinct & (cost <= best_cost + AMBIGUITY_COST)


def mirror_points(batch: ProblemBatch, positions_enu_m) -> np.ndarray:
    """Each position reflected through its stations' plane ``(B, 3)``, where that mirror image may fit as
    well: unconstrained problems without an elevation (ranges, TOAs and azimuths cannot tell a point from its
    mirror through the plane of nearly coplanar stations); NaN rows elsewhere.

    The plane is the stations' least-squares plane; with fewer than three stations, or collinear ones, the
    most horizontal plane through them.
    """
    size = batch.size
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
    mirrored = positions_enu_m - 2.0 * height[:, None] * normal
    elevation = np.any(batch.valid & (batch.kinds == ELEVATION), axis=-1)
    applies = ~batch.constrained & ~elevation & (size > 0)
    return np.where(applies[:, None], mirrored, np.nan)


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
    position, cost = np.empty_like(flat), np.full(tried.size, np.inf)
    converged, regular = np.zeros(tried.size, dtype=bool), np.zeros(tried.size, dtype=bool)
    covariance = np.empty((tried.size, 3, 3))
    loss = _loss(options)
    step = max(1, CHUNK_ENTRIES // max(batch.kinds.shape[1], 1))  # memory: candidates x measurements
    for start in range(0, tried.size, step):
        part = slice(start, start + step)
        expanded = batch.take(tried[part])
        solution = levenberg_marquardt(expanded, flat[part], options.max_iterations, options.tolerance_m, loss)
        here = solution.position_enu_m
        position[part], converged[part] = here, solution.converged
        finite = np.all(np.isfinite(here), axis=-1)
        information = batch_information(expanded, np.where(finite[:, None], here, 0.0))
        regular[part] = finite & information.observable & above_ground(expanded, here)
        covariance[part] = information.covariance_enu_m2
        cost[part] = np.where(regular[part], solution.cost, np.inf)
    order = np.lexsort((cost, tried))
    first = order[np.r_[True, tried[order][1:] != tried[order][:-1]]]
    good = np.isfinite(cost[first])
    out[tried[first][good]] = position[first][good]
    best_of = first[np.searchsorted(tried[first], tried)]
    close = _rivals(covariance[best_of], position[best_of], cost[best_of], position, cost, converged, regular)
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
    # A closed form's (or the search's) fix may have a mirror image that fits as well: try it.
    plausible = chdtrc(np.maximum(dof, 1), solution.cost) >= IMPLAUSIBLE_P
    mirrored = mirror_points(batch, solution.position_enu_m)
    check = np.flatnonzero(~missing & plausible & np.all(np.isfinite(mirrored), axis=-1)
                           & np.array([not w for w in warnings]))
    check = np.array([b for b in check.tolist() if b not in failures], dtype=np.intp)
    if check.size:
        part = batch.take(check)
        image = iterate(part, mirrored[check], options)
        position = image.position_enu_m
        finite = np.all(np.isfinite(position), axis=-1)
        information = batch_information(part, np.where(finite[:, None], position, 0.0))
        at_fix = batch_information(part, solution.position_enu_m[check])
        eligible = finite & information.observable & above_ground(part, position)
        rival = _rivals(at_fix.covariance_enu_m2, solution.position_enu_m[check], solution.cost[check], position,
                        image.cost, image.converged, eligible)
        possible = above_ground(part, solution.position_enu_m[check])
        for j in np.flatnonzero(rival).tolist():
            b = int(check[j])
            if possible[j]:
                warnings[b] = _ambiguous(batch, b, position[j], starts, names, failures, solution, options)
                continue
            starts[b], names[b] = mirrored[b], "mirror"
            for name in Solution.__dataclass_fields__:
                getattr(solution, name)[b] = getattr(image, name)[j]
    estimates = estimate_from(batch, starts, options, names, failures, solution)
    return replace(estimates, warnings=warnings)
