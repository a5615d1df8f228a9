"""The one finisher: what every fix reports, for a whole batch at once.

Given an estimator's :class:`~core.estimators.result.Estimates`, :func:`finish`
computes at each estimate the residuals, chi-square and p-value, the CRLB,
studentized residuals (leverage-corrected, so the largest names a gross
error's culprit) and the conditioning and geometry warnings, and returns a
:class:`~core.estimators.result.FixBatch`. Every method, and a single fix
(a batch of one), goes through here.

The chi-square, p-value and studentized residuals judge the measurements, not
the method: they are those of the residuals the ML fit of the used
measurements leaves (:func:`_ml_residuals`), whatever estimate a method
returned. A closed form's own residuals also carry its distance from that fit,
which a chi-square on ``m - n`` dof and the ML leverage do not allow for. The
reported residuals stay those at the method's estimate.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
from scipy.special import chdtrc

from core.angles import wrap_point
from core.crlb import (OBSERVABILITY_THRESHOLD, gdop_point, invert_point, normal_point, parameters_point,
                       reference_sigma_point, sandwich_point)
from core.errors import LocalizationError, UnobservableGeometry
from core.estimators.loss import loss_code, loss_point
from core.estimators.result import Estimates, FixBatch, FixWarning
from core.measurements import (AZIMUTH, ELEVATION, KIND_NAMES, RANGE, SPEED_OF_LIGHT_MPS, TOA, ahead_point,
                               measure_point, toa_offset_point, toa_spacing_s)
from core.problem import onto_altitude_point
from core.problem_batch import ProblemBatch

#: Studentized residual above which a measurement is flagged as a suspected outlier.
OUTLIER_SIGMAS = 4.0
#: A detected fault is isolated (its measurement named) only with two degrees of freedom or more and where the
#: largest studentized residual exceeds every other request measurement's by more than this many standard
#: deviations of their difference (``2 (1 -+ rho)``, ``rho`` their correlation): were the other one the fault,
#: so large a lead would happen with probability below ``norm.sf`` of it (0.1 %). RAIM's isolation: with one
#: degree of freedom every studentized residual is as large, and none can be told from another.
ISOLATION_SIGMAS = 3.09
#: Chi-square p-value below which the stated sigmas are reported as too small.
SIGMA_MISMATCH_P = 1e-3
#: Lines of sight closer than this to parallel (rad) make a fix collinear.
COLLINEAR_SPREAD_RAD = np.deg2rad(2.0)
#: Ratio of a closed form's covariance trace to the CRLB's above which the method is flagged as inefficient.
INEFFICIENCY_RATIO = 10.0
#: Minimum unit-diagonal information eigenvalue below which a fix is ill-conditioned.
ILL_CONDITIONED_EIGENVALUE = 1e-6
#: Robust-loss weight factor (``rho'``) below which a measurement is named as downweighted.
DOWNWEIGHTED_FACTOR = 0.1
#: A fix whose CRLB (root of its trace) exceeds this many times its distance from its farthest station is not
#: determined by the measurements: the fit ran off along a direction they do not see (parallel lines of sight
#: meet at infinity, where every residual vanishes and the Jacobi-scaled information still looks regular).
RUNAWAY_SIGMA_RATIO = 1e6

# Bits of the verdicts a problem's measurements raise (:func:`_verdicts_kernel`, and COARSE_TOA:
# :func:`_coarse_toas`); RUNAWAY makes the fix an error, and so does SINGULAR where the covariance is the
# inverse information.
(ILL, OUTLIER, COLLINEAR, BEHIND, ZENITH, EXCLUDED, UNUSED, DOWNWEIGHTED, RUNAWAY, COARSE_TOA, SINGULAR,
 NOT_CONVERGED, NOT_ISOLABLE) = (1 << k for k in range(13))


def finish(batch: ProblemBatch, method: str, estimates: Estimates, excluded=None) -> FixBatch:
    """Everything a fix reports, for every problem of a batch.

    Parameters
    ----------
    batch : ProblemBatch
    method : str
        The API name of the method that ran.
    estimates : Estimates
    excluded : ndarray of bool, shape (B, M), optional
        Measurements outlier exclusion set aside (not in ``batch.valid``); each is named in a warning.

    Returns
    -------
    FixBatch
    """
    size = batch.size
    errors = dict(estimates.errors)
    position = np.array(estimates.position_enu_m, dtype=float).reshape(size, 3)
    failed = np.zeros(size, dtype=bool)
    if errors:
        failed[list(errors)] = True
    if np.count_nonzero(np.isfinite(position)) < position.size:
        finite = np.isfinite(position).all(axis=-1)
        for b in np.flatnonzero(~failed & ~finite).tolist():
            errors[b] = LocalizationError(f"{method} produced no finite position for this geometry")
        failed |= ~finite
    if errors:  # exactly the failed rows
        position[failed] = batch.stations_enu_m[failed, 0] + [0.0, 0.0, 1.0]

    stations, rotations = batch.measurement_stations()
    sigmas = batch.sigmas if estimates.sigmas is None else np.where(batch.present, estimates.sigmas, np.nan)
    bias = estimates.bias_m
    is_line, elevation, _ = batch.lines_of_sight()
    origin_ecef, origin_rotation = batch.frame_placements()
    loss = estimates.loss
    present, valid = batch.present, batch.valid
    excluded = np.zeros(present.shape, dtype=bool) if excluded is None else excluded & present
    converged = np.ones(size, dtype=bool) if estimates.converged is None else np.asarray(estimates.converged)
    (raw, normalized, studentized, chi2, crlb, covariance, min_eigenvalue, robust_factor, behind, zenith, spread, dof,
     p_dof, plain_scale, sigma_scale, worst, worst_value, gdop, flags, isolated) = _fix_kernel(
        position, np.zeros(size) if bias is None else np.asarray(bias, dtype=float),
        bias is not None, np.ascontiguousarray(stations, dtype=float), np.ascontiguousarray(rotations, dtype=float),
        np.ascontiguousarray(batch.kinds, dtype=np.int64), np.ascontiguousarray(batch.values, dtype=float),
        np.ascontiguousarray(sigmas, dtype=float), np.asarray(batch.n_measurements, dtype=np.int64),
        np.ascontiguousarray(valid), np.ascontiguousarray(excluded), np.asarray(batch.altitude_m, dtype=float),
        np.asarray(batch.has_toa, dtype=np.bool_), np.asarray(batch.geodetic, dtype=np.bool_), origin_ecef,
        origin_rotation, -1 if loss is None else loss_code(loss[0]), 1.0 if loss is None else float(loss[1]) ** 2,
        is_line, elevation, np.ascontiguousarray(converged, dtype=np.bool_),
        np.ascontiguousarray(batch.source_index, dtype=np.int64))
    p_value = chdtrc(p_dof, chi2)
    if loss is None:
        robust_factor = None

    source = estimates.covariance_source
    fatal = RUNAWAY | SINGULAR if source == "information" else RUNAWAY
    if np.count_nonzero(flags & fatal):
        ran_off = (flags & RUNAWAY) != 0
        for b in np.flatnonzero((flags & fatal != 0) & ~failed).tolist():
            errors[b] = UnobservableGeometry(_singular_reason(batch, b, position[b], min_eigenvalue[b], ran_off[b]))
    if robust_factor is not None:
        source = "robust"
    elif estimates.covariance_enu_m2 is None:
        source = "information" if source == "information" else "crlb"
    else:
        own = np.asarray(estimates.covariance_enu_m2, dtype=float).reshape(size, 3, 3)
        own = 0.5 * (own + own.swapaxes(-1, -2))
        # ML's own rows (a two-solution mixture) replace the inverse information; its NaN rows keep it.
        covariance = np.where(np.isfinite(own).all(axis=(-1, -2))[:, None, None], own, covariance) \
            if source == "information" else own

    mismatch = p_value < SIGMA_MISMATCH_P
    iterations = np.zeros(size, dtype=int) if estimates.iterations is None else np.asarray(estimates.iterations)
    coarse_toas = _coarse_toas(batch) if np.count_nonzero(batch.has_toa) else None
    if coarse_toas is not None:
        flags = flags | np.where(coarse_toas.any(axis=-1), COARSE_TOA, 0)
    flagged = (flags & ~SINGULAR != 0) | mismatch
    if source == "propagated":
        bound_trace = np.trace(crlb, axis1=-2, axis2=-1)
        own_trace = np.trace(covariance, axis1=-2, axis2=-1)
        inefficient = (bound_trace > 0) & (own_trace > INEFFICIENCY_RATIO * bound_trace)
        flagged |= inefficient
    else:
        inefficient = np.zeros(size, dtype=bool)
    own = estimates.warnings or [()] * size
    warnings: list[tuple[FixWarning, ...]] = [tuple(w) for w in own]
    rows = np.flatnonzero(flagged & ~failed)
    if rows.size:
        if (flags & UNUSED).any():
            unused = present & ~valid & ~excluded
            unused_kinds = np.bitwise_or.reduce(np.where(unused, 1 << batch.kinds.astype(np.int64), 0), axis=-1)
            unused_counts = np.count_nonzero(unused, axis=-1)
        # The flagged rows' figures as Python numbers: numpy scalars cost twice as much to index and to format.
        (iterations_of, bits_of, inefficient_of, mismatch_of, worst_of, worst_value_of, chi2_of, dof_of, p_value_of,
         plain_scale_of) = (np.take(a, rows).tolist() for a in (
            iterations, flags, inefficient, mismatch, worst, worst_value, chi2, dof, p_value, plain_scale))
    for j, b in enumerate(rows.tolist()):
        found = list(own[b])
        bits = bits_of[j]
        if bits & NOT_CONVERGED and not any(w.code == "not_converged" for w in found):
            found.append(FixWarning("not_converged", f"{method} did not converge in {iterations_of[j]} iterations; "
                                                     "the last accepted iterate is returned"))
        if bits & ILL:
            found.append(FixWarning("ill_conditioned", "information matrix nearly singular "
                                                       f"(min scaled eigenvalue {min_eigenvalue[b]:.1e})"))
        if inefficient_of[j]:
            found.append(FixWarning(
                "inefficient_method",
                f"{method}'s covariance is {own_trace[b] / bound_trace[b]:.0f} x the CRLB in this geometry "
                "(its equations are nearly degenerate here); ml or weighted_eove reach the bound"))
        if bits & BEHIND:
            found.append(FixWarning("behind_station",
                                    f"the fix is behind the line of sight of {_station_list(batch, b, behind[b])}"))
        if bits & COLLINEAR:
            found.append(FixWarning(
                "collinear_geometry",
                f"lines of sight to the fix span only {np.rad2deg(spread[b]):.2f} deg: range is poorly determined"))
        if bits & ZENITH:
            found.append(FixWarning("azimuth_undefined",
                                    f"the fix is at the zenith of {_station_list(batch, b, zenith[b])}"))
        if bits & OUTLIER:
            found.append(outlier_warning(batch, b, worst_of[j], worst_value_of[j]))
        if bits & NOT_ISOLABLE:
            found.append(not_isolable_warning(chi2_of[j], dof_of[j], worst_value_of[j]))
        if mismatch_of[j]:
            found.append(FixWarning(
                "sigma_mismatch",
                f"chi2 = {chi2_of[j]:.1f} on {dof_of[j]} dof (p = {p_value_of[j]:.1e}): residuals are "
                f"{plain_scale_of[j]:.2f} x what the stated sigmas allow"))
        if bits & EXCLUDED:
            for source in sorted(set(batch.source_index[b, excluded[b]].tolist())):
                found.append(FixWarning("measurement_excluded",
                                        f"measurement {source} failed the consistency test and was excluded"))
        if bits & DOWNWEIGHTED:
            known = valid[b] & np.isfinite(sigmas[b])
            for m in np.flatnonzero(known & (robust_factor[b] < DOWNWEIGHTED_FACTOR)).tolist():
                station = batch.station_ids[b][batch.station_index[b, m]]
                found.append(FixWarning(
                    "measurement_downweighted",
                    f"measurement {int(batch.source_index[b, m])} ({KIND_NAMES[batch.kinds[b, m]]} at {station}) "
                    f"keeps {100.0 * robust_factor[b, m]:.1f} % of its weight under the {estimates.loss[0]} loss "
                    f"(scale {estimates.loss[1]:g} sigma)"))
        if bits & UNUSED:
            found.append(_unused_warning(method, int(unused_kinds[b]), int(unused_counts[b])))
        if bits & COARSE_TOA:
            found.append(_toa_resolution_warning(batch, b, coarse_toas[b]))
        warnings[b] = tuple(found)

    coarse = estimates.coarse_position_enu_m
    return FixBatch(
        method=method,
        problems=batch,
        errors=errors,
        position_enu_m=position,
        covariance_enu_m2=covariance,
        covariance_source=source,
        crlb_enu_m2=crlb,
        residuals=raw,
        normalized_residuals=normalized,
        studentized_residuals=studentized,
        chi2=chi2,
        dof=dof,
        p_value=p_value,
        sigma_scale=sigma_scale,
        converged=converged,
        iterations=iterations,
        warnings=warnings,
        coarse_position_enu_m=np.full((size, 3), np.nan) if coarse is None else np.asarray(coarse, dtype=float),
        estimated_bearing_errors_rad=estimates.estimated_bearing_errors_rad or [None] * size,
        details=estimates.details or [{} for _ in range(size)],
        used=valid,
        excluded=excluded,
        gdop=gdop,
        isolated=isolated,
    )


def outlier_warning(batch: ProblemBatch, b: int, m: int, studentized: float) -> FixWarning:
    """The ``outlier_suspected`` warning naming measurement ``m`` of problem ``b``."""
    station = batch.station_ids[b][batch.station_index[b, m]]
    return FixWarning("outlier_suspected", f"measurement {batch.source_index[b, m]} ({KIND_NAMES[batch.kinds[b, m]]} "
                                           f"at {station}) has a studentized residual of {studentized:.1f}")


def not_isolable_warning(chi2: float, dof: int, largest: float) -> FixWarning:
    """The ``fault_detected_not_isolable`` warning: the measurements hold a fault, and no single one can be
    named as it (the studentized residuals, largest ``largest``, do not single one out on ``dof`` dof)."""
    return FixWarning(
        "fault_detected_not_isolable",
        f"the measurements are inconsistent (chi2 = {chi2:.1f} on {dof} dof, largest studentized residual "
        f"{abs(largest):.1f}) but no single measurement can be blamed: leaving out one or another explains them "
        "about as well" + (" (one degree of freedom cannot isolate a fault)" if dof < 2 else "")
        + "; add measurements, or check each")


@functools.lru_cache(maxsize=1024)
def _unused_warning(method: str, kind_bits: int, count: int) -> FixWarning:
    """The ``measurements_unused`` warning of ``count`` measurements of the kinds set in ``kind_bits``
    (bit ``k``: kind code ``k``); one object for every fix that says the same."""
    kinds = ", ".join(sorted(name for code, name in enumerate(KIND_NAMES) if kind_bits >> code & 1))
    return FixWarning("measurements_unused", f"{method} does not use the {kinds} measurements ({count} left out of "
                                             "the fit and its verdicts); ml uses every kind")


def _coarse_toas(batch: ProblemBatch) -> np.ndarray:
    """``(B, M)``: the used TOAs whose value as sent (seconds since the client's epoch) float64 carries more
    coarsely than their sigma: its spacing there exceeds the sigma (at 1.7e9 s, 2.4e-7 s or 71 m)."""
    return batch.valid & (batch.kinds == TOA) & (toa_spacing_s(batch.values + batch.toa_reference_s[:, None])
                                                  > batch.sigmas)


def _toa_resolution_warning(batch: ProblemBatch, b: int, coarse) -> FixWarning:
    """The ``toa_resolution`` warning of problem ``b``, whose TOAs ``coarse`` ``(M,)`` (:func:`_coarse_toas`) are."""
    sent_s = np.abs(batch.values[b, coarse] + batch.toa_reference_s[b])
    spacing_s = float(toa_spacing_s(sent_s).max())
    return FixWarning(
        "toa_resolution",
        f"{int(coarse.sum())} TOA(s) sent as about {float(sent_s.max()):.3g} s since an epoch: float64 carries them to "
        f"{spacing_s:.1e} s ({spacing_s * SPEED_OF_LIGHT_MPS:.2g} m), coarser than their sigma "
        f"{float(batch.sigmas[b, coarse].min()):.1e} s, so the fix and its covariance are no better than that; send "
        "TOAs relative to a recent reference (say, seconds after the first arrival)")


def _station_list(batch: ProblemBatch, b: int, rows) -> str:
    ids = batch.station_ids[b]
    return ", ".join(sorted({ids[i] for i in batch.station_index[b, rows]}))


def _singular_reason(batch: ProblemBatch, b: int, position_enu_m, min_eigenvalue: float, ran_off: bool) -> str:
    """Why the information is singular at an estimate (or, ``ran_off``, too small for its distance:
    ``RUNAWAY_SIGMA_RATIO``), as specifically as can be told."""
    n = int(batch.n_stations[b])
    local = np.einsum("nij,nj->ni", batch.station_rotations[b, :n], position_enu_m - batch.stations_enu_m[b, :n])
    horizontal = np.hypot(local[:, 0], local[:, 1])
    at_zenith = horizontal < 1e-6 * np.maximum(np.linalg.norm(local, axis=-1), 1.0)
    if np.any(at_zenith):
        ids = ", ".join(batch.station_ids[b][i] for i in np.flatnonzero(at_zenith))
        return ("the bearings contradict each other: the iteration ran onto the vertical of station "
                f"{ids}, where azimuth is undefined (typically the lines of sight meet only behind a station); "
                "check the bearings, or use eove to see where the lines meet")
    stations = batch.stations_enu_m[b, :n]
    spread_m = float(np.max(np.linalg.norm(stations - stations.mean(axis=0), axis=-1))) + 1e3
    measured_distance = batch.kind_counts[b, RANGE] + batch.kind_counts[b, TOA] > 0
    if not measured_distance and np.linalg.norm(position_enu_m - stations.mean(axis=0)) > 1e4 * spread_m:
        return ("the bearings have no common point in front of the stations: the fit runs off to infinity "
                "(lines of sight are parallel, diverge, or meet only behind a station, as one gross bearing can make "
                "them); check the bearings, send options.outliers \"exclude\" to leave each out in turn, or use eove "
                "to see where the lines meet")
    if ran_off:
        return ("the lines of sight are parallel, or in line with the stations, at the fit: the measurements do not "
                "fix the position along them (its CRLB exceeds a million times its distance from the stations); add "
                "a station off their line, a range or a TOA")
    return ("the measurements do not determine the position: the information matrix is singular "
            f"(min scaled eigenvalue {min_eigenvalue:.1e}); add stations, elevations or an altitude constraint")




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
def _ml_residuals(position, bias, stations, rotations, kinds, model_values, weights, count, altitude_m, has_toa,
                  geodetic, origin_ecef_m, origin_rotation, local, params, residual, step, gradient, point,
                  jacobian_fit, local_fit, information_fit, params_fit, position_fit, axes_fit, free, work, vectors):
    """The residuals the ML fit of a problem's measurements leaves, to first order from an estimate.

    On entry ``residual`` ``(M,)`` holds the residuals at ``position`` and ``local`` / ``params`` the whitened
    Jacobian and inverse information there. ``step`` ``(4,)`` becomes the Gauss-Newton step to the ML fit, so
    that ``residual - local^T step`` are its residuals (exact for a linear model). When that step is longer than
    ``REFINE_MAHALANOBIS2`` (an inefficient closed form, an unfinished iteration), its linearisation is not
    trusted: Gauss-Newton steps are taken from ``position`` while they lower the chi-square (at most
    ``REFINE_STEPS``), and ``residual``, ``step``, and ``local_fit`` / ``params_fit`` (then returned True) are
    those at the last point. The rest: scratch.
    """
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
def _separation(studentized, room, weights, local, params, source_index, count, valid, sigmas):
    """How far one problem's largest studentized residual stands out: the least, over the other request
    measurements ``j``, of ``(|t_w| - |t_j|) / sd(t_w -+ t_j)``, the sd ``sqrt(2 (1 -+ rho_wj))`` from their
    correlation ``rho_wj = -H_wj / sqrt((1 - h_w)(1 - h_j))`` (``H`` the hat matrix of ``local`` ``(4, M)`` and
    ``params`` ``(4, 4)``; ``room`` ``(M,)``: ``1 - h``). Infinite where no other measurement is judged; 0 with
    one degree of freedom, where every ``|t|`` is the same."""
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
def _finish_kernel(positions_enu_m, bias_in_m, has_bias, stations_enu_m, rotations, kinds, values, sigmas,
                   n_measurements, valid, altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation, loss, c2,
                   is_line, elevation_rad, source_index):
    """The numbers of :func:`finish`, each problem on its own: residuals (problem units), normalized and
    studentized residuals, chi-square and the count of measurements in it, the CRLB, the covariance (the
    CRLB, or with a robust ``loss`` (code, ``-1`` for none) the sandwich of its weights), the smallest
    unit-diagonal information eigenvalue, the loss's weight factors and cost, the reference sigma, and per
    line of sight whether the fix is behind its station or at its zenith, the lines' smallest spread, and whether
    the fix ran off (``RUNAWAY_SIGMA_RATIO``)."""
    size, width = kinds.shape
    raw, normalized, studentized = np.zeros((size, width)), np.zeros((size, width)), np.zeros((size, width))
    chi2, known_count = np.zeros(size), np.zeros(size, dtype=np.int64)
    crlb, covariance = np.empty((size, 3, 3)), np.empty((size, 3, 3))
    smallest, robust_factor, robust_cost = np.empty(size), np.ones((size, width)), np.zeros(size)
    sigma_ref, spread = np.empty(size), np.full(size, np.pi / 2)
    behind, zenith = np.zeros((size, width), dtype=np.bool_), np.zeros((size, width), dtype=np.bool_)
    runaway = np.zeros(size, dtype=np.bool_)
    separation, room = np.full(size, np.inf), np.ones(width)
    weights, model_values = np.empty(width), np.empty(width)
    jacobian, local = np.empty((4, width)), np.empty((4, width))
    seen = np.empty((width, 3))
    axes, free = np.empty((3, 3)), np.empty(4, dtype=np.bool_)
    information, params, work, vectors = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    bread, meat = np.empty((4, 4)), np.empty((4, 4))
    bread_weights, meat_weights = np.empty(width), np.empty(width)
    model_residual, whitened, gradient, step = np.empty(width), np.empty(width), np.empty(4), np.empty(4)
    fitted_residual, point, jacobian_fit, local_fit = np.empty(width), np.empty(3), np.empty((4, width)), np.empty((4, width))
    information_fit, params_fit, position_fit, axes_fit = np.empty((4, 4)), np.empty((4, 4)), np.empty((3, 3)), np.empty((3, 3))
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
            if _ml_residuals(p, bias, stations_b, rotations_b, kinds[b], model_values, weights, n_measurements[b],
                             altitude_m[b], has_toa[b], geodetic[b], origin_ecef_m[b], origin_rotation[b],
                             local, params, fitted_residual, step, gradient, point, jacobian_fit, local_fit,
                             information_fit, params_fit, position_fit, axes_fit, free, work, vectors):
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
        separation[b] = _separation(studentized[b], room, weights, hat_local, hat_params, source_index[b],
                                    n_measurements[b], valid[b], sigmas[b])
        if loss >= 0:
            # The sandwich of the final weights rho': the meat holds each measurement's squared score
            # rho'^2 z (z its squared whitened residual), but never less than a clean measurement of that weight
            # adds on average (rho'^2, z averaging 1): a measurement the loss has bent keeps its pull on the fix
            # (c^2 for huber, not the rho'^2 of a clean one, 1 / z of it), and a small residual is no proof of a
            # small error.
            for m in range(width):
                bread_weights[m] = weights[m] * robust_factor[b, m]
                meat_weights[m] = weights[m] * robust_factor[b, m] ** 2 * max(normalized[b, m] ** 2, 1.0)
            sandwich_point(jacobian, bread_weights, meat_weights, axes, constrained, free, local, bread, meat,
                           params, work, vectors, covariance[b])
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
    return (raw, normalized, studentized, chi2, known_count, crlb, covariance, smallest, robust_factor, robust_cost,
            sigma_ref, behind, zenith, spread, runaway, separation)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _verdicts_kernel(studentized, chi2, known_count, robust_cost, robust_factor, smallest, spread, behind, zenith,
                     runaway, is_line, n_measurements, valid, excluded, sigmas, altitude_m, has_toa, robust, converged,
                     separation):
    """Per problem, from :func:`_finish_kernel`'s numbers: the degrees of freedom, the plain and the reported
    sigma scale (NaN without dof), the measurement with the largest ``|studentized|`` (numpy's ``argmax``:
    the first NaN, else the first largest) and its value, and the verdict bits (``ILL`` ...; ``converged``
    ``(B,)``: the estimator's)."""
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
def _fix_kernel(positions_enu_m, bias_in_m, has_bias, stations_enu_m, rotations, kinds, values, sigmas,
                n_measurements, valid, excluded, altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation, loss,
                c2, is_line, elevation_rad, converged, source_index):
    """:func:`_finish_kernel` then :func:`_verdicts_kernel` in one call: the residuals, chi-square, CRLB,
    covariance (made symmetric), smallest eigenvalue, loss factors and line-of-sight facts,
    then the degrees of freedom (also as floats, NaN where there are none: the p-value's), sigma scales, worst
    measurement, GDOP and verdict bits (``excluded`` ``(B, M)``: measurements outlier exclusion set aside;
    ``converged`` ``(B,)``: the estimator's)."""
    (raw, normalized, studentized, chi2, known_count, crlb, covariance, smallest, robust_factor, robust_cost,
     sigma_ref, behind, zenith, spread, runaway, separation) = _finish_kernel(
        positions_enu_m, bias_in_m, has_bias, stations_enu_m, rotations, kinds, values, sigmas, n_measurements, valid,
        altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation, loss, c2, is_line, elevation_rad, source_index)
    dof, plain_scale, sigma_scale, worst, worst_value, flags, isolated = _verdicts_kernel(
        studentized, chi2, known_count, robust_cost, robust_factor, smallest, spread, behind, zenith, runaway,
        is_line, n_measurements, valid, excluded, sigmas, altitude_m, has_toa, loss >= 0, converged, separation)
    size = dof.size
    p_dof, gdop = np.empty(size), np.empty(size)
    for b in range(size):
        p_dof[b] = dof[b] if dof[b] > 0 else np.nan
        gdop[b] = gdop_point(crlb[b], sigma_ref[b])
        for i in range(3):
            for j in range(i):
                covariance[b, i, j] = covariance[b, j, i] = 0.5 * (covariance[b, i, j] + covariance[b, j, i])
    return (raw, normalized, studentized, chi2, crlb, covariance, smallest, robust_factor, behind, zenith, spread, dof,
            p_dof, plain_scale, sigma_scale, worst, worst_value, gdop, flags, isolated)
