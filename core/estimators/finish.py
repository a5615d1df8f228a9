"""The one finisher: what every fix reports, for a whole batch at once.

Given an estimator's :class:`~core.estimators.result.Estimates`, :func:`finish`
computes at each estimate the residuals, chi-square and p-value, the CRLB,
studentized residuals (leverage-corrected, so the largest names a gross
error's culprit) and the conditioning and geometry warnings, and returns a
:class:`~core.estimators.result.FixBatch`. Every method, and a single fix
(a batch of one), goes through here.

The chi-square, p-value and studentized residuals judge the measurements, not
the method: they are those of the residuals the ML fit of the used
measurements leaves (:func:`core.estimators.finish_kernels._ml_residuals`), whatever estimate a method
returned. A closed form's own residuals also carry its distance from that fit,
which a chi-square on ``m - n`` dof and the ML leverage do not allow for. The
reported residuals stay those at the method's estimate.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.special import chdtrc

from core.errors import LocalizationError, UnobservableGeometry
from core.estimators.finish_kernels import (BEHIND, COARSE_TOA, COLLINEAR, DOWNWEIGHTED, DOWNWEIGHTED_FACTOR, EXCLUDED,
                                            ILL, NOT_CONVERGED, NOT_ISOLABLE, OUTLIER, OUTLIER_SIGMAS, RUNAWAY, SINGULAR,
                                            UNUSED, ZENITH, Estimate, Finished, fix_kernel)
from core.estimators.loss import loss_code
from core.estimators.result import Estimates, FixBatch, FixWarning
from core.measurements import KIND_NAMES, RANGE, SPEED_OF_LIGHT_MPS, TOA, toa_spacing_s
from core.problem.batch import ProblemBatch

#: Chi-square p-value below which the stated sigmas are reported as too small.
SIGMA_MISMATCH_P = 1e-3
#: Ratio of a closed form's covariance trace to the CRLB's above which the method is flagged as inefficient.
INEFFICIENCY_RATIO = 10.0

__all__ = ["INEFFICIENCY_RATIO", "OUTLIER_SIGMAS", "SIGMA_MISMATCH_P", "finish", "not_isolable_warning",
           "outlier_warning"]


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

    sigmas = batch.sigmas if estimates.sigmas is None else np.where(batch.present, estimates.sigmas, np.nan)
    bias = estimates.bias_m
    loss = estimates.loss
    present, valid = batch.present, batch.valid
    excluded = np.zeros(present.shape, dtype=bool) if excluded is None else excluded & present
    converged = np.ones(size, dtype=bool) if estimates.converged is None else np.asarray(estimates.converged)
    measurements = batch.kernel_measurements
    estimate = Estimate(
        position_enu_m=position, bias_m=np.zeros(size) if bias is None else np.asarray(bias, dtype=float),
        has_bias=bias is not None, converged=np.ascontiguousarray(converged, dtype=np.bool_),
        sigmas=measurements.sigmas if estimates.sigmas is None else np.ascontiguousarray(sigmas, dtype=float),
        excluded=np.ascontiguousarray(excluded), loss_code=-1 if loss is None else loss_code(loss[0]),
        c2=1.0 if loss is None else float(loss[1]) ** 2)
    finished = Finished(*fix_kernel(tuple(measurements), tuple(batch.kernel_frames), tuple(estimate)))
    raw, normalized, studentized, robust_factor = finished.measured
    crlb, covariance = finished.bounds
    behind, zenith = finished.seen_lines
    chi2, min_eigenvalue, spread, p_dof, plain_scale, sigma_scale, worst_value, gdop = finished.scalars
    dof, worst, flags = finished.counts
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
    rows = (flagged & ~failed).nonzero()[0]
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
    return FixBatch.of(
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
        isolated=finished.isolated,
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
