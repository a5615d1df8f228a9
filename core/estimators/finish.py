"""The one finisher: what every fix reports, for a whole batch at once.

Given an estimator's :class:`~core.estimators.result.Estimates`, :func:`finish`
computes at each estimate the residuals, chi-square and p-value, the CRLB,
studentized residuals (leverage-corrected, so the largest names a gross
error's culprit) and the conditioning and geometry warnings, and returns a
:class:`~core.estimators.result.FixBatch`. Every method, and a single fix
(a batch of one), goes through here.
"""

from __future__ import annotations

import numpy as np
from scipy.special import chdtrc

from core.angles import line_of_sight_enu
from core.crlb import gdop, invert_information, normal_matrix, parameterisation, reference_sigma_m, sandwich_covariance
from core.errors import LocalizationError, UnobservableGeometry
from core.estimators.loss import loss_weights
from core.estimators.result import Estimates, FixBatch, FixWarning
from core.linalg import row_sums
from core.measurements import Kind, MeasurementModel, toa_offsets
from core.problem_batch import ProblemBatch

#: Studentized residual above which a measurement is flagged as a suspected outlier.
OUTLIER_SIGMAS = 4.0
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
#: Pairwise line-of-sight cosines are formed for at most this many entries at once.
_GRAM_ENTRIES = 1 << 21


def finish(batch: ProblemBatch, method: str, estimates: Estimates, model: MeasurementModel | None = None,
           excluded=None) -> FixBatch:
    """Everything a fix reports, for every problem of a batch.

    Parameters
    ----------
    batch : ProblemBatch
    method : str
        The API name of the method that ran.
    estimates : Estimates
    model : MeasurementModel, optional
        The batch's measurement model, when the estimator already built it.
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
    failed[list(errors)] = True
    for b in np.flatnonzero(~failed & ~np.all(np.isfinite(position), axis=-1)):
        errors[int(b)] = LocalizationError(f"{method} produced no finite position for this geometry")
        failed[b] = True
    position[failed] = batch.stations_enu_m[failed, 0] + [0.0, 0.0, 1.0]

    stations, rotations = batch.measurement_stations()
    if model is None:
        model = MeasurementModel(stations, rotations, batch.kinds)
    present, valid = batch.present, batch.valid
    sigmas = batch.sigmas if estimates.sigmas is None else np.where(present, estimates.sigmas, np.nan)
    weights = batch.weights(sigmas)
    values = batch.model_values()
    bias = estimates.bias_m
    if bias is None:
        bias = toa_offsets(position, stations, batch.kinds, values, weights)
    predicted, jacobian = model.predict(position, bias)
    unit = batch.unit_scale()
    raw = np.where(present, model.residuals(values, predicted) / unit, 0.0)
    stated = present & np.isfinite(sigmas)
    normalized = np.where(stated, raw / np.where(stated, sigmas, 1.0), 0.0)
    known = valid & stated
    chi2 = row_sums(np.where(known, normalized, 0.0) ** 2)
    n_parameters = np.where(batch.constrained, 2, 3) + batch.has_toa
    dof = np.count_nonzero(known, axis=-1) - n_parameters
    positive = dof > 0
    p_value = np.where(positive, chdtrc(np.maximum(dof, 1), chi2), np.nan)
    plain_scale = np.where(positive, np.sqrt(chi2 / np.maximum(dof, 1)), np.nan)
    sigma_scale = plain_scale
    robust_factor = None
    if estimates.loss is not None:
        rho, robust_factor, _ = loss_weights(np.where(known, normalized, 0.0) ** 2, *estimates.loss)
        robust_cost = row_sums(np.where(known, rho, 0.0))
        sigma_scale = np.where(positive, np.sqrt(robust_cost / np.maximum(dof, 1)), np.nan)

    axes, free = parameterisation(position, batch.altitude_m, batch.has_toa, batch.origin, batch.geodetic)
    information, local = normal_matrix(jacobian, weights, axes, free)
    info = invert_information(information, axes, free)
    crlb = info.covariance_enu_m2
    source = estimates.covariance_source
    if source == "information":
        for b in np.flatnonzero(~failed & ~info.observable):
            errors[int(b)] = UnobservableGeometry(_singular_reason(batch, int(b), position[b], info.min_eigenvalue[b]))
    if robust_factor is not None:
        covariance = sandwich_covariance(jacobian, weights * robust_factor, weights * robust_factor**2, axes, free)
        source = "robust"
    elif estimates.covariance_enu_m2 is None:
        covariance = crlb
        source = "information" if source == "information" else "crlb"
    else:
        covariance = np.asarray(estimates.covariance_enu_m2, dtype=float).reshape(size, 3, 3)
    covariance = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))

    leverage = weights * np.einsum("bim,bij,bjm->bm", local, info.covariance_params, local)
    studentized = np.where(known, normalized, 0.0) / np.sqrt(np.clip(1.0 - leverage, 1e-12, None))
    worst = np.argmax(np.abs(studentized), axis=-1)
    worst_value = studentized[np.arange(size), worst]
    outlier = positive & (np.abs(worst_value) > OUTLIER_SIGMAS)
    mismatch = positive & (p_value < SIGMA_MISMATCH_P)
    ill = info.min_eigenvalue < ILL_CONDITIONED_EIGENVALUE
    converged = np.ones(size, dtype=bool) if estimates.converged is None else np.asarray(estimates.converged)
    iterations = np.zeros(size, dtype=int) if estimates.iterations is None else np.asarray(estimates.iterations)
    inefficient = np.zeros(size, dtype=bool)
    if source == "propagated":
        bound_trace = np.trace(crlb, axis1=-2, axis2=-1)
        own_trace = np.trace(covariance, axis1=-2, axis2=-1)
        inefficient = (bound_trace > 0) & (own_trace > INEFFICIENCY_RATIO * bound_trace)
    behind, zenith, spread, collinear = _geometry(batch, position, stations, rotations)

    excluded = np.zeros_like(present) if excluded is None else excluded & present
    unused = present & ~valid & ~excluded
    own = estimates.warnings or [()] * size
    any_behind, any_zenith = np.any(behind, axis=-1), np.any(zenith, axis=-1)
    any_excluded, any_unused = np.any(excluded, axis=-1), np.any(unused, axis=-1)
    downweighted = np.zeros_like(known) if robust_factor is None else known & (robust_factor < DOWNWEIGHTED_FACTOR)
    any_downweighted = np.any(downweighted, axis=-1)
    flagged = ~converged | ill | inefficient | outlier | mismatch | collinear | any_behind | any_zenith
    flagged |= any_unused | any_excluded | any_downweighted
    warnings: list[tuple[FixWarning, ...]] = [tuple(w) for w in own]
    for b in np.flatnonzero(flagged & ~failed):
        found = list(own[b])
        if not converged[b] and not any(w.code == "not_converged" for w in found):
            found.append(FixWarning("not_converged", f"{method} did not converge in {int(iterations[b])} iterations; "
                                                     "the last accepted iterate is returned"))
        if ill[b]:
            found.append(FixWarning("ill_conditioned", "information matrix nearly singular "
                                                       f"(min scaled eigenvalue {info.min_eigenvalue[b]:.1e})"))
        if inefficient[b]:
            ratio = np.trace(covariance[b]) / np.trace(crlb[b])
            found.append(FixWarning(
                "inefficient_method",
                f"{method}'s covariance is {ratio:.0f} x the CRLB in this geometry "
                "(its equations are nearly degenerate here); ml or weighted_eove reach the bound"))
        if any_behind[b]:
            found.append(FixWarning("behind_station",
                                    f"the fix is behind the line of sight of {_station_list(batch, b, behind[b])}"))
        if collinear[b]:
            found.append(FixWarning(
                "collinear_geometry",
                f"lines of sight to the fix span only {np.rad2deg(spread[b]):.2f} deg: range is poorly determined"))
        if any_zenith[b]:
            found.append(FixWarning("azimuth_undefined",
                                    f"the fix is at the zenith of {_station_list(batch, b, zenith[b])}"))
        if outlier[b]:
            w = worst[b]
            station = batch.station_ids[b][batch.station_index[b, w]]
            found.append(FixWarning(
                "outlier_suspected",
                f"measurement {int(batch.source_index[b, w])} ({Kind(batch.kinds[b, w]).name.lower()} at "
                f"{station}) has a studentized residual of {worst_value[b]:.1f}"))
        if mismatch[b]:
            found.append(FixWarning(
                "sigma_mismatch",
                f"chi2 = {chi2[b]:.1f} on {dof[b]} dof (p = {p_value[b]:.1e}): residuals are "
                f"{plain_scale[b]:.2f} x what the stated sigmas allow"))
        if any_excluded[b]:
            for source in sorted(set(batch.source_index[b, excluded[b]].tolist())):
                found.append(FixWarning("measurement_excluded",
                                        f"measurement {source} failed the consistency test and was excluded"))
        if any_downweighted[b]:
            for m in np.flatnonzero(downweighted[b]).tolist():
                station = batch.station_ids[b][batch.station_index[b, m]]
                found.append(FixWarning(
                    "measurement_downweighted",
                    f"measurement {int(batch.source_index[b, m])} ({Kind(batch.kinds[b, m]).name.lower()} at {station}) "
                    f"keeps {100.0 * robust_factor[b, m]:.1f} % of its weight under the {estimates.loss[0]} loss "
                    f"(scale {estimates.loss[1]:g} sigma)"))
        if any_unused[b]:
            kinds = sorted({Kind(k).name.lower() for k in batch.kinds[b, unused[b]].tolist()})
            found.append(FixWarning(
                "measurements_unused",
                f"{method} does not use the {', '.join(kinds)} measurements "
                f"({np.count_nonzero(unused[b])} left out of the fit and its verdicts); ml uses every kind"))
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
        gdop=gdop(crlb, reference_sigma_m(jacobian, weights)),
    )


def _geometry(batch: ProblemBatch, position, stations, rotations):
    """Per line of sight: behind the station, at its zenith; per problem: spread and collinearity."""
    size = batch.size
    is_line, elevation, _ = batch.lines_of_sight()
    has_el = ~np.isnan(elevation)
    to_target = position[:, None, :] - stations
    distance = np.linalg.norm(to_target, axis=-1)
    local_target = np.einsum("bmij,bmj->bmi", rotations, to_target)
    measured = line_of_sight_enu(batch.values, np.where(has_el, elevation, 0.0))
    in_plane = np.where(has_el[..., None], local_target, local_target * [1.0, 1.0, 0.0])
    behind = is_line & (np.einsum("bmi,bmi->bm", measured, in_plane) < 0)
    n_lines = np.count_nonzero(is_line, axis=-1)
    spread = np.full(size, np.pi / 2)
    several = n_lines >= 2
    if np.any(several):
        seen = to_target / np.maximum(distance, 1e-9)[..., None]
        spread[several] = _collinear_spread(seen[several], is_line[several])
    collinear = several & (spread < COLLINEAR_SPREAD_RAD)
    zenith = is_line & (np.hypot(local_target[..., 0], local_target[..., 1]) < 1e-4 * np.maximum(distance, 1e-9))
    return behind, zenith, spread, collinear


def _station_list(batch: ProblemBatch, b: int, rows) -> str:
    ids = batch.station_ids[b]
    return ", ".join(sorted({ids[i] for i in batch.station_index[b, rows]}))


def _collinear_spread(seen, is_line):
    """Smallest pairwise angle spread ``(B,)`` of unit vectors ``(B, M, 3)`` on line rows (rad)."""
    size, width = is_line.shape
    smallest = np.ones(size)
    chunk = max(1, _GRAM_ENTRIES // max(width * width, 1))
    for start in range(0, size, chunk):
        part = slice(start, start + chunk)
        cosines = np.clip(np.abs(seen[part] @ np.swapaxes(seen[part], -1, -2)), 0.0, 1.0)
        pair = is_line[part, :, None] & is_line[part, None, :]
        smallest[part] = np.where(pair, cosines, 1.0).min(axis=(-2, -1))
    return np.arccos(smallest)


def _singular_reason(batch: ProblemBatch, b: int, position_enu_m, min_eigenvalue: float) -> str:
    """Why the information is singular at an estimate, as specifically as can be told."""
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
    if np.linalg.norm(position_enu_m - stations.mean(axis=0)) > 1e4 * spread_m:
        return ("the bearings have no common point in front of the stations: the fit runs off to infinity "
                "(lines of sight diverge, or meet only behind a station); check the bearings, or use eove "
                "to see where the lines meet")
    return ("the measurements do not determine the position: the information matrix is singular "
            f"(min scaled eigenvalue {min_eigenvalue:.1e}); add stations, elevations or an altitude constraint")


