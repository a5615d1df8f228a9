"""Maximum likelihood over a batch of problems (section 3).

Minimises ``sum (z - h(p))^2 / sigma^2`` for any mix of azimuth, elevation,
range and TOA by Levenberg-Marquardt (:mod:`core.estimators.lm`), from the
closed-form start for the mix, or from the geometry's candidates where there
is none or the fit from it is implausible (:func:`ml`). The covariance is the
inverse information at the solution (computed by the finisher, like
everything else a fix reports), except where ML says more: a fix with a
plausible second solution reports the two-solution mixture's
(:func:`core.estimators.ties.second_solution`), and a fix from the search (a
mix without a closed form, or whose closed-form fit failed) the unscented
spread of the estimator, never below the bound and widened until its 99 %
region holds the curved error (:mod:`core.estimators.unscented_fix`): the
inverse information is the covariance only where the model is linear over
the fix's uncertainty.

A robust loss (``options.loss``) is minimised as scipy's ``least_squares``
does; the finisher then reports the sandwich covariance of the final weights
``rho'`` (``covariance_source`` ``"robust"``): that of a weighted least-squares
fit with those weights, which is the bound without a measurement the loss has
set aside, and never below the bound. A robust fit whose residuals fail the
chi-square test (``SUBSET_P``) may sit in the basin of a gross error that
pulled its closed-form start: it is started again from the closed form of
each subset that leaves one of its most suspect request measurements out
(:func:`subset_starts`), and the lowest robust cost is kept.

Where a second point fits as well (ties), :mod:`core.estimators.ties` finds
and judges it.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.special import chdtrc

from core.crlb import batch_information
from core.errors import LocalizationError
from core.estimators.base import SolveOptions, register
from core.estimators.lm import Solution, _fields, _lm_kernel, fitting_of, iterate, levenberg_marquardt, loss_of
from core.estimators.loss import REDESCENDING
from core.estimators.methods.orthogonal_vector import SOLVED, _orthogonal_kernel
from core.estimators.result import Estimates, FixWarning
from core.estimators.starting_points import START_PASSES, initial_positions
from core.estimators.ties import (REFINE_ITERATIONS, Fits, above_ground, fit_from, mirror_applies, mirror_points,
                                  refine, rivals, searched_starts, second_solution)
from core.estimators.unscented_fix import CURVED_VARIANCE_RATIO, curved_covariance
from core.kernel_data import Frames, Measurements
from core.measurements import AZIMUTH, ELEVATION, ahead_point, predict, residuals
from core.problem.batch import ProblemBatch

#: A robust fit whose residuals' chi-square p-value is below this is started again from subsets (:func:`subset_starts`).
SUBSET_P = 0.01
#: ... each leaving out one of at most this many request measurements, the most suspect first.
SUBSET_CANDIDATES = 8


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
        loss=None if options.loss == "linear" else loss_of(options),
        errors=errors,
        converged=solution.converged,
        iterations=solution.iterations,
        warnings=warnings,
        bias_m=solution.bias_m,
        details=[{"start": name} if name is not None else {} for name in start_names],
    )


#: A fit from the closed-form start whose chi-square has a p-value below this is retried from the search
#: (unless :func:`one_basin` says no other basin is there to find).
IMPLAUSIBLE_P = 1e-9


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _one_basin_kernel(positions_enu_m, measurements):
    """:func:`one_basin` of a batch's :class:`~core.kernel_data.Measurements` (a plain tuple or named)."""
    measurements = Measurements(*measurements)
    kinds, valid, is_line, values = measurements.kinds, measurements.valid, measurements.is_line, measurements.values
    stations_enu_m, rotations = measurements.stations_enu_m, measurements.rotations
    elevation_rad, n_measurements = measurements.elevation_rad, measurements.n_measurements
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
    return _one_basin_kernel(np.ascontiguousarray(positions_enu_m, dtype=float), tuple(batch.kernel_measurements))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _eove_fit_kernel(measurements, frames, fitting, kind_counts, initial_guess_enu_m, out):
    """Every problem's weighted-EOVE start (the orthogonal kernel as :func:`initial_positions` runs it: both
    normals, first-order weights, ``START_PASSES``) and ML's iteration from it (the LM kernel as :func:`iterate`
    runs it, into ``out``: :func:`core.estimators.lm._fields`), in one call; returns ``(starts, solved)``,
    ``solved`` False, and no fits, where some problem is not started so: it has no azimuth (``kind_counts``
    ``(B, 4)``), an initial guess (a row of ``initial_guess_enu_m`` ``(B, 3)`` not NaN), or no solution of its
    rows (the structures: plain tuples or named, :mod:`core.kernel_data`)."""
    measurements, frames = Measurements(*measurements), Frames(*frames)
    for b in range(kind_counts.shape[0]):
        if kind_counts[b, AZIMUTH] == 0 or not math.isnan(initial_guess_enu_m[b, 0]):
            return np.empty((0, 3)), False
    _, _, _, starts, status, _ = _orthogonal_kernel(measurements, frames, True, True, True, START_PASSES)
    for b in range(status.size):
        if status[b] != SOLVED:
            return starts, False
    _lm_kernel(measurements, frames, starts, fitting, out)
    return starts, True


def _eove_started_fits(batch: ProblemBatch, options: SolveOptions):
    """``(starts, solution)``: :func:`initial_positions` then :func:`iterate` in one compiled call, for a batch
    whose every problem its first stage starts (weighted EOVE: an azimuth, no initial guess) and does start;
    None otherwise (the stages in turn then find each start, or say why there is none). The same kernels on
    the same arrays: the same numbers, without the stages' per-call work between them."""
    solution = Solution.empty(batch.size)
    starts, solved = _eove_fit_kernel(
        tuple(batch.kernel_measurements), tuple(batch.kernel_frames),
        tuple(fitting_of(loss_of(options), options.max_iterations, options.tolerance_m)), batch.kind_counts,
        batch.initial_guess_enu_m, _fields(solution))
    return (starts, solution) if solved else None


def normalized_residuals(batch: ProblemBatch, solution: Solution) -> np.ndarray:
    """``(B, M)``: each measurement's residual over its sigma at the iteration's end (0 where unweighted)."""
    stations, rotations = batch.measurement_stations()
    predicted, _ = predict(solution.position_enu_m, solution.bias_m, stations, rotations, batch.kinds)
    return residuals(batch.model_values(), predicted, batch.kinds) * np.sqrt(batch.weights())


def subset_starts(batch: ProblemBatch, rows, suspicion):
    """Closed-form starts of the subsets of problems ``rows`` that leave one request measurement out, for their
    :data:`SUBSET_CANDIDATES` most suspect (:meth:`~core.problem.batch.ProblemBatch.leave_one_out`; by
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
    started = _eove_started_fits(batch, options)
    if started is not None:
        (starts, solution), names, failures = started, ["weighted_eove"] * batch.size, {}
        missing = np.zeros(batch.size, dtype=bool)
    else:
        starts, names, failures = initial_positions(batch)
        missing = ~np.isfinite(starts).all(axis=-1)
        solution = iterate(batch, np.where(missing[:, None], batch.stations_enu_m[:, 0] + [0.0, 0.0, 1.0], starts)
                           if np.count_nonzero(missing) else starts, options)
    dof = batch.dof
    p_value = chdtrc(np.maximum(dof, 1), solution.cost)
    implausible = p_value < IMPLAUSIBLE_P
    retry = missing | ~solution.converged
    if np.count_nonzero(implausible):
        if options.loss not in REDESCENDING:
            implausible &= ~one_basin(batch, solution.position_enu_m)
        retry |= implausible
    warnings: list[tuple] = [()] * batch.size
    if options.loss == "linear" and not np.count_nonzero(
            retry | mirror_applies(batch) & ~missing & (p_value >= IMPLAUSIBLE_P)):
        # Every fit is settled from its start: no search, subset or mirror image to try (the usual batch).
        return estimate_from(batch, starts, options, names, failures, solution, warnings)
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
                warnings[b] = second_solution(batch, b, rival[ok][j], rival_cost[ok][j], starts, names, failures,
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
        rival = rivals(fix, images)
        possible = above_ground(batch.take(check), solution.position_enu_m[check])
        for j in np.flatnonzero(rival).tolist():
            b = int(check[j])
            if possible[j]:
                warnings[b] = second_solution(batch, b, images.position_enu_m[j], images.cost[j], starts, names,
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


def _spread(batch: ProblemBatch, rows, solution: Solution, options: SolveOptions, covariance, warnings) -> None:
    """The searched fixes ``rows`` ``(K,)`` (mixes without a closed form, or whose closed-form fit failed: the
    geometries where the model can be far from linear over the fix's uncertainty) get the unscented covariance
    of the estimator, never below the bound, widened until its 99 % region holds the curved error
    (:func:`core.estimators.unscented_fix.curved_covariance`), in ``covariance``; where it exceeds the bound by
    more than ``CURVED_VARIANCE_RATIO``, the warning ``curved_uncertainty``."""
    part = batch.take(rows)
    fixes = solution.position_enu_m[rows]

    def refit(moved, starts):  # to 1e-6 of a sigma (STEP_MAHALANOBIS2), not a step in metres: a thin axis is mm
        return levenberg_marquardt(moved, starts, REFINE_ITERATIONS, 0.0, loss_of(options)).position_enu_m

    held, ratio, widened = curved_covariance(part, fixes, solution.bias_m[rows], refit)
    covariance[rows] = held
    for j in np.flatnonzero(ratio > CURVED_VARIANCE_RATIO).tolist():
        b = int(rows[j])
        warnings[b] = warnings[b] + (FixWarning(
            "curved_uncertainty",
            f"the measurement model is far from linear over this fix's uncertainty: fixes of the measurements moved "
            f"by their sigmas spread up to {np.sqrt(ratio[j]):.1f} x the bound's sigma; the covariance is that spread "
            "(unscented), not the inverse information"
            + (", widened until its 99 % region holds the curved error" if widened[j] else "")),)
