"""ML's ties: a second point that fits the measurements as well as the fix.

Where the measurements leave (almost) no degree of freedom, a second point
may fit as well: a line of sight crosses a TDOA hyperboloid twice, or
ranges, TOAs and azimuths from nearly coplanar stations fit a point and its
mirror image through their plane. ML (:mod:`core.estimators.methods.ml`) looks for
one among the search's solutions (:func:`searched_starts`: from the geometry's
candidates and from the best fit's own uncertainty,
:func:`~core.estimators.ambiguity.axis_starts`) and from the fix's
mirror image (:func:`mirror_points`); a rival is itself a converged fit of the
data (an iterate the cap stopped on its way is iterated further first,
:func:`refine`, and is no rival unless that converges), whose cost is within
``PLAUSIBLE_COST`` of the fix, farther than one sigma from the fix under the
fix's bound and under its own (``DISTINCT_MAHALANOBIS2``: nearer, the
covariance covers both; a refinement that converges onto the fix is the fix)
and physically possible (a geodetic point more than 1 km below the ellipsoid
is no solution; a point behind a bearing station never ties, its azimuth
residual is near pi; a TOA's emission precedes its arrival by construction of
the model). One rule judges it for every mix (:mod:`core.estimators.ambiguity`,
:func:`second_solution`): within ``AMBIGUITY_COST`` a tie, a
:class:`~core.errors.AmbiguousGeometry` (422 ``ambiguous_geometry``) naming
both points, unless the client's ``initial_guess`` picks the nearer one
(:func:`ambiguous`); worse but plausible, the fix warns
``second_solution_plausible`` (the rival and its probability) and its
covariance is the two-solution mixture's, its 99 % region holding both.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from core.crlb import batch_information
from core.errors import AmbiguousGeometry
from core.estimators.ambiguity import AMBIGUITY_COST, PLAUSIBLE_COST, axis_starts, mixture_region, rival_probability
from core.estimators.base import SolveOptions
from core.estimators.lm import Solution, iterate, levenberg_marquardt, loss_of
from core.estimators.result import FixWarning
from core.estimators.search import candidates
from core.geodesy import enu_to_geodetic
from core.linalg import jacobi_svd
from core.measurements import ELEVATION
from core.problem.batch import ProblemBatch

#: (candidates x padded width): the expanded problems then take megabytes, not gigabytes.
CHUNK_ENTRIES = 1 << 15

#: A second solution is a rival (:func:`rivals`; judged by :mod:`core.estimators.ambiguity`: a tie within
#: ``AMBIGUITY_COST``, a plausible worse solution within ``PLAUSIBLE_COST``) when it is a converged solution
#: farther from the best than this squared Mahalanobis distance, under the best's CRLB and under its own: nearer,
#: no measurement at the stated noise tells them apart and the covariance covers both.
DISTINCT_MAHALANOBIS2 = 1.0
#: Where the best is itself unconverged (the answer is flagged so), an unconverged iterate is a rival farther
#: than this from it: neither is a solution, and the two may still be sliding down one valley.
DISTINCT_UNCONVERGED_MAHALANOBIS2 = 25.0
#: An unconverged candidate that might be a rival (cost within ``PLAUSIBLE_COST`` of the best) goes on for this
#: many
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
        solution = levenberg_marquardt(expanded, starts[part], max_iterations, options.tolerance_m, loss_of(options))
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


def rivals(best: Fits, fits: Fits) -> np.ndarray:
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
        The lowest-cost rival of the best (:func:`rivals`, after :func:`refine`): the second crossing of a
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
    close = rivals(Fits(*(field[best_of] for field in fits)), fits)
    second = np.where(close, cost, np.inf)
    order = np.lexsort((second, tried))
    lowest = order[np.r_[True, tried[order][1:] != tried[order][:-1]]]
    found = np.isfinite(second[lowest])
    rival[tried[lowest][found]] = position[lowest][found]
    rival_cost[tried[lowest][found]] = cost[lowest][found]
    return out, rival, rival_cost


#: A fit from the closed-form start whose chi-square has a p-value below this is retried from the search

def second_solution(batch: ProblemBatch, b: int, other_enu_m, other_cost: float, starts, names, failures,
                    solution: Solution, options: SolveOptions, covariance) -> tuple:
    """Problem ``b``'s rival at ``other_enu_m`` of cost ``other_cost``, judged by the one rule
    (:mod:`core.estimators.ambiguity`): a tie is :func:`ambiguous`; a worse but plausible rival (plain least
    squares) makes the fix warn ``second_solution_plausible`` and writes the two-solution mixture's covariance
    into ``covariance[b]``."""
    delta = float(other_cost) - float(solution.cost[b])
    if delta <= AMBIGUITY_COST:
        return ambiguous(batch, b, other_enu_m, starts, names, failures, solution, options)
    if options.loss != "linear" or delta > PLAUSIBLE_COST:  # a robust cost is no chi-square: only its ties count
        return ()
    fix = solution.position_enu_m[b]
    bounds = batch_information(batch.take([b, b]), np.stack([fix, other_enu_m])).covariance_enu_m2
    probability = float(rival_probability(delta))
    covariance[b] = mixture_region(fix, bounds[0], other_enu_m, bounds[1], probability)
    return (FixWarning("second_solution_plausible",
                       f"a second solution at {_point(batch, b, other_enu_m)} fits the measurements worse "
                       f"(chi2 {delta:.1f} above this fix) but is not ruled out: probability {probability:.1%}; "
                       "the covariance covers both (their mixture about this fix, its 99 % region holding both)"),)


def ambiguous(batch: ProblemBatch, b: int, other_enu_m, starts, names, failures, solution: Solution,
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

