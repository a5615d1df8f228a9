"""One report on one network track: the update, a track's start and its prediction.

:func:`advance_track` applies one report to its emitter's track (or starts the track) and
:func:`predicted_track` moves a track to a later time without a report; :mod:`core.tracking.network` keeps
the session state and calls these, and the association of unlabelled bearings
(:mod:`core.tracking.association`) calls them per track. The filter, its start and its statuses are
described in :mod:`core.tracking.network`; the compiled update is :mod:`core.tracking.network_kernel`. This
module imports the values of :mod:`core.tracking.network_types` only, never :mod:`core.tracking.network`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace
from typing import NamedTuple

import numpy as np
from scipy.stats import chi2

from core.errors import LocalizationError
from core.measurements import AZIMUTH, ELEVATION, RANGE, SPEED_OF_LIGHT_MPS, TOA
from core.tracking import imm
from core.tracking.motion import transitions
from core.tracking.network_kernel import STATE_SIZE, UPDATED, network_ukf_kernel, predict_kernel
from core.tracking.network_types import NetworkConfig, Report, Track
from core.tracking.range_mixture import component_ranges, moments, pruned, reweighted
from core.tracking.state import freeze, frozen_array

#: Components of a start's Gaussian sum closer than this (standard deviations of the sum) are one.
MERGE_DISTANCE = 0.5

_CHI2_OUTLIER = 0.999
_CHI2_AGREE = 0.99

class ReportRows(NamedTuple):
    """A report in the units of the measurement model (:func:`report_rows`).

    Attributes
    ----------
    values : ndarray, shape (M,)
        Radians, metres; a TOA as ``c (toa - toa_reference)`` (m, 0 for the reference itself).
    variances : ndarray, shape (M,)
    rows : ndarray of int, shape (R,)
        The measurements an update uses (every one but the TOA reference and a lone TOA).
    toa_reference : int
        Index of the reference TOA, -1 when fewer than two TOAs.
    warnings : tuple of (str, str)
    """

    values: np.ndarray
    variances: np.ndarray
    rows: np.ndarray
    toa_reference: int
    warnings: tuple


def report_rows(report: Report) -> ReportRows:
    """The report's model values, variances and update rows; its TOAs referred to one of them (the one with
    the smallest sigma), subtracted in seconds first so that epoch-sized TOAs keep their digits."""
    kinds = report.kinds
    is_toa = kinds == TOA
    if not is_toa.any():
        return ReportRows(report.values, report.sigmas * report.sigmas, _all_rows(kinds.size), -1, ())
    values = report.values.copy()
    sigmas = report.sigmas.copy()
    toa_index = np.flatnonzero(is_toa)
    warnings = ()
    reference = -1
    use = np.ones(kinds.size, dtype=bool)
    if toa_index.size == 1:
        use[toa_index] = False
        warnings = (("toa_single", f"report seq {report.seq}: one TOA (station {report.station_ids[toa_index[0]]!r}) "
                                   "carries no information without a second one to difference it with; not used"),)
    elif toa_index.size > 1:
        reference = int(toa_index[np.argmin(sigmas[toa_index])])
        values[is_toa] = (values[is_toa] - report.values[reference]) * SPEED_OF_LIGHT_MPS
        sigmas[is_toa] *= SPEED_OF_LIGHT_MPS
        use[reference] = False
    return ReportRows(values, sigmas * sigmas, np.flatnonzero(use).astype(np.int64), reference, warnings)


@functools.lru_cache(maxsize=64)
def _all_rows(count: int) -> np.ndarray:
    rows = np.arange(count, dtype=np.int64)
    rows.flags.writeable = False
    return rows


def advance_track(track: Track | None, report: Report, config: NetworkConfig) -> tuple[Track | None, tuple]:
    """Apply one report to its emitter's track (start it if there is none, or the old one has ended).

    Returns
    -------
    track : Track or None
        None when no track exists and the report cannot start one.
    warnings : tuple of (str, str)
    """
    rows = report_rows(report)
    if track is None or report.time_s - track.time_s > config.end_after_s:
        return _start(report, rows, config)
    warnings = rows.warnings
    if rows.rows.size == 0:
        return replace(track, warnings=warnings), warnings
    dt = report.time_s - track.time_s
    weights = track.weights
    means = np.array(track.means)
    covs = np.array(track.covariances)
    if track.stage == "imm":
        switching = imm.switching_matrix(weights.size, dt, config.imm_mean_sojourn_s)
        weights, means, covs = imm.mixed(weights, means, covs, switching)
        levels = config.imm_accel_sigmas_mps2
    else:
        levels = (config.accel_sigma_mps2,) * weights.size
    phi, noises = motion_model(config, dt, levels)
    new_means, new_covs, nis, log_det, status = _update(means, covs, phi, noises, dt > 0.0, report, rows,
                                                        config.linearisation_passes)
    return _updated(track, report, rows, weights, means, covs, new_means, new_covs, nis, log_det, status, config,
                    warnings)


def updated_track(track: Track, report: Report, rows: ReportRows, predicted_mean, predicted_cov, new_mean, new_cov,
                  nis: float, log_det: float, status: int, config: NetworkConfig,
                  track_id: str | None = None) -> Track:
    """The track after one report whose update the caller has already run: what :func:`advance_track` returns
    for a ``single``-stage track (no IMM) from the same kernel outputs.

    Parameters
    ----------
    track : Track
        Stage ``single``, at most ``config.end_after_s`` before the report.
    report : Report
    rows : ReportRows
        :func:`report_rows` of the report.
    predicted_mean : ndarray, shape (6,)
    predicted_cov : ndarray, shape (6, 6)
        The track predicted to the report's time (:func:`predicted_track`).
    new_mean, new_cov, nis, log_det, status
        :func:`core.tracking.network_kernel.network_ukf_kernel`'s outputs for that prediction and the report,
        with ``config.linearisation_passes`` passes.
    track_id : str, optional
        The id of the returned track (default ``report.emitter_id``).
    """
    if track.stage != "single" or config.imm_accel_sigmas_mps2:
        raise ValueError("updated_track takes a single-stage track without IMM")
    return _updated(track, report, rows, np.ones(1), np.asarray(predicted_mean)[None],
                    np.asarray(predicted_cov)[None], np.asarray(new_mean)[None], np.asarray(new_cov)[None],
                    np.array([nis]), np.array([log_det]), np.array([status]), config, rows.warnings, track_id)[0]


def _updated(track, report, rows, weights, means, covs, new_means, new_covs, nis, log_det, status, config, warnings,
             track_id=None):
    """:func:`advance_track` after its update: ``means``, ``covs`` predicted, ``new_*`` the kernel's output."""
    dof = rows.rows.size
    ok = status == UPDATED
    if not ok.any() or (track.stage != "mixture" and not ok.all()):
        warnings += (("numerical_failure", f"report seq {report.seq}: the update failed; the track was predicted"),)
        return _finish(track, report, weights, means, covs, np.nan, dof, config, warnings, track_id=track_id)
    if weights.size == 1:
        weights = np.ones(1)
    else:
        weights = reweighted(weights, np.where(ok, -0.5 * (nis + log_det), -np.inf))
        if track.stage == "imm":
            weights = imm.floored(weights)
    combined_nis = float(nis[ok][np.argmax(weights[ok])]) if track.stage == "mixture" else float(
        np.dot(weights, np.where(ok, nis, 0.0)))
    if track.stage == "mixture":
        weights, new_means, new_covs = _pruned_mixture(weights, new_means, new_covs)
    if combined_nis > chi2_point(_CHI2_OUTLIER, dof):
        warnings += (("innovation_outlier", f"report seq {report.seq}: NIS {combined_nis:.1f} on {dof} degrees "
                                            "of freedom"),)
    return _finish(track, report, weights, new_means, new_covs, combined_nis, dof, config, warnings,
                   track_id=track_id)


def _update(means, covs, phi, noises, predict: bool, report: Report, rows: ReportRows, passes: int):
    """Predict and update each component (:func:`core.tracking.network_kernel.network_ukf_kernel`); ``passes``
    linearisations for a report with bearings, one for a report of ranges and TOAs alone: these bend over
    the prior far less than a bearing across an unknown range, and passes at a posterior moved by the
    report's own noise only add that noise (four TOA stations lose a few per cent of RMSE to them)."""
    kinds = report.kinds[rows.rows]
    if not ((kinds == AZIMUTH) | (kinds == ELEVATION)).any():  # (np.isin costs more than the update here)
        passes = 1
    count = means.shape[0]
    new_means, new_covs = np.empty((count, STATE_SIZE)), np.empty((count, STATE_SIZE, STATE_SIZE))
    nis, log_det, status = np.empty(count), np.empty(count), np.empty(count, dtype=np.int64)
    network_ukf_kernel(means, covs, phi, noises, predict, report.stations_enu_m, report.rotations, report.kinds,
                       rows.values, rows.variances, rows.rows, rows.toa_reference, passes, new_means, new_covs, nis,
                       log_det, status)
    return new_means, new_covs, nis, log_det, status


def _finish(track: Track | None, report: Report, weights, means, covs, nis: float, dof: int, config: NetworkConfig,
            warnings: tuple, stage: str | None = None, track_id: str | None = None) -> tuple[Track, tuple]:
    """The track after a report: stage change (a mixture collapsed to one), moments, confirmation; its id
    ``track_id``, by default the report's emitter."""
    stage = stage or track.stage
    if stage == "mixture" and weights.size == 1:
        stage = "single"
    if stage == "single" and config.imm_accel_sigmas_mps2:
        modes = imm.uniform_modes(means[0], covs[0], len(config.imm_accel_sigmas_mps2))
        stage, weights, means, covs = "imm", modes.weights, modes.means, modes.covariances
    if weights.size == 1:
        mean, cov = np.array(means[0]), np.array(covs[0])
    else:
        mean, cov = moments(np.asarray(weights), np.asarray(means), np.asarray(covs))
    agreeing = 0 if track is None else track.agreeing
    agreeing = agreeing + 1 if math.isfinite(nis) and nis <= chi2_point(_CHI2_AGREE, dof) else 0
    if track is not None and track.confirmed:
        confirmed, reference_range_m = True, track.reference_range_m
    else:
        reference_range_m = float(np.linalg.norm(report.stations_enu_m - mean[:3], axis=1).min())
        # A Gaussian sum is judged by its moments: one along a line of sight is far wider than the bound
        # below, while one over altitude (four TOA stations) may place the emitter to it and stay a sum.
        confirmed = (agreeing >= config.confirm_updates
                     and math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0))
                     <= config.confirm_relative_sigma * reference_range_m)
    updates = 1 if track is None else track.updates + 1
    out = Track(report.emitter_id if track_id is None else track_id, "confirmed" if confirmed else "tentative", report.time_s, freeze(mean),
                freeze(cov), updates, warnings, stage, freeze(np.asarray(weights, dtype=float)),
                freeze(np.asarray(means, dtype=float)), freeze(np.asarray(covs, dtype=float)), agreeing,
                bool(confirmed), reference_range_m)
    return out, warnings


def _start(report: Report, rows: ReportRows, config: NetworkConfig) -> tuple[Track | None, tuple]:
    """A new track from its first report (:mod:`core.tracking.network`: starting honestly)."""
    warnings = rows.warnings
    azimuths = np.flatnonzero(report.kinds == AZIMUTH)
    if azimuths.size:
        first = int(azimuths[0])
        station = report.station_ids[first]
        elevations = [i for i in np.flatnonzero(report.kinds == ELEVATION) if report.station_ids[i] == station]
        elevation = int(elevations[0]) if elevations else -1
        weights, means, covs = _line_of_sight_mixture(report, first, elevation, config)
        rest = np.array([r for r in rows.rows if r not in (first, elevation)], dtype=np.int64)
        nis = np.nan
        if rest.size:
            rows_rest = rows._replace(rows=rest)
            phi, noises = motion_model(config, 0.0, (config.accel_sigma_mps2,) * weights.size)
            new_means, new_covs, nis_all, log_det, status = _update(means, covs, phi, noises, False, report, rows_rest,
                                                                config.linearisation_passes)
            ok = status == UPDATED
            if ok.any():
                weights = reweighted(weights, np.where(ok, -0.5 * (nis_all + log_det), -np.inf))
                weights, means, covs = _pruned_mixture(weights, new_means, new_covs)
        return _finish(None, report, weights, means, covs, nis, max(rest.size, 1), config, warnings, "mixture")
    started = _fix_start(report, rows, config)
    if started is None:
        warnings += (("track_not_started", f"report seq {report.seq}: no bearing and no fix from its ranges and TOAs; "
                                           f"the track of {report.emitter_id!r} starts with a report that places it"),)
        return None, warnings
    weights, means, covs = started
    return _finish(None, report, weights, means, covs, np.nan, 1, config, warnings, "mixture")


def motion_model(config: NetworkConfig, dt_s: float, accel_sigmas_mps2: tuple[float, ...]):
    """Transition ``(6, 6)`` and process noises ``(C, 6, 6)`` over ``dt_s`` of the constant-velocity model at
    each horizontal intensity (:func:`core.tracking.motion.transitions`), the vertical axis at
    ``vertical_accel_sigma_mps2 / accel_sigma_mps2`` of it when that is set."""
    phi, noises = transitions(STATE_SIZE, (3,), True, dt_s, tuple(q * q for q in accel_sigmas_mps2))
    if config.vertical_accel_sigma_mps2 is not None:
        scale = np.ones(STATE_SIZE)
        scale[[2, 5]] = config.vertical_accel_sigma_mps2 / config.accel_sigma_mps2
        noises = noises * np.outer(scale, scale)
    return phi, noises


def velocity_prior(config: NetworkConfig) -> np.ndarray:
    """Covariance ``(3, 3)`` of the velocity at a track's start."""
    vertical = config.velocity_prior_sigma_mps if config.vertical_velocity_prior_sigma_mps is None else \
        config.vertical_velocity_prior_sigma_mps
    return np.diag([config.velocity_prior_sigma_mps ** 2] * 2 + [vertical ** 2])


def _pruned_mixture(weights, means, covs):
    """The Gaussian sum without components below :data:`core.tracking.range_mixture.MIN_WEIGHT`, and collapsed
    to its moments once every component's mean lies within :data:`MERGE_DISTANCE` of its own standard
    deviations from the sum's mean (Mahalanobis, under the component's covariance: the sum is then one
    Gaussian to within a fraction of each component's width): neighbouring components that the data have
    pulled onto the same point stay apart in weight forever and would keep the track a mixture."""
    keep = pruned(weights)
    weights, means, covs = weights[keep] / weights[keep].sum(), means[keep], covs[keep]
    if weights.size > 1:
        mean, cov = moments(weights, means, covs)
        offsets = means - mean
        distances = np.einsum("ci,ci->c", offsets, np.linalg.solve(covs, offsets[..., None])[..., 0])
        if distances.max() < MERGE_DISTANCE ** 2:
            return np.ones(1), mean[None], cov[None]
    return weights, means, covs


def _line_of_sight_mixture(report: Report, azimuth: int, elevation: int, config: NetworkConfig):
    """Gaussian sum ``(C,)``, ``(C, 6)``, ``(C, 6, 6)`` along the line of sight of one bearing: each component
    centred at its middle range on the measured direction, covering its sub-interval along the line of sight
    and the bearing's noise across it, velocity zero +- ``velocity_prior_sigma_mps``."""
    az = float(report.values[azimuth])
    sigma_az = float(report.sigmas[azimuth])
    if elevation >= 0:
        el, sigma_el = float(report.values[elevation]), float(report.sigmas[elevation])
    else:
        el, sigma_el = 0.0, config.azimuth_only_elevation_sigma_rad
    along = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    across_az = np.array([math.cos(az), -math.sin(az), 0.0])
    across_el = np.array([-math.sin(el) * math.sin(az), -math.sin(el) * math.cos(az), math.cos(el)])
    to_common = report.rotations[azimuth].T
    station = report.stations_enu_m[azimuth]
    middles, sigmas = component_ranges(config)
    count = middles.size
    means = np.zeros((count, STATE_SIZE))
    covs = np.zeros((count, STATE_SIZE, STATE_SIZE))
    for c, (r, sigma_r) in enumerate(zip(middles.tolist(), sigmas.tolist())):
        local = (sigma_r ** 2 * np.outer(along, along) + (r * sigma_az * math.cos(el)) ** 2 * np.outer(across_az, across_az)
                 + (r * sigma_el) ** 2 * np.outer(across_el, across_el))
        means[c, :3] = station + to_common @ (r * along)
        covs[c, :3, :3] = to_common @ local @ to_common.T
        covs[c, 3:, 3:] = velocity_prior(config)
    return np.full(count, 1.0 / count), means, 0.5 * (covs + np.swapaxes(covs, 1, 2))


def _fix_start(report: Report, rows: ReportRows, config: NetworkConfig):
    """A Gaussian, or a Gaussian sum over altitude, from the static fixes of a report without bearings.

    The free fix (:func:`core.estimators.solve`) with its CRLB when that places the emitter within
    :attr:`NetworkConfig.start_altitude_step_m` vertically. Otherwise (four TOAs from stations on the
    ground fix a point exactly, twice, and their hyperboloids meet at a shallow angle in height) the fixes at
    known altitudes over ``start_altitudes_m`` (step ``start_altitude_step_m``): each a component with its
    horizontal CRLB and half a step of height, weighted by the Laplace approximation of its likelihood
    (``exp(-chi2 / 2)`` times the square root of its CRLB's determinant). None when nothing fits.
    """
    from core.estimators import solve, solve_batch
    from core.problem.build import Range, TimeOfArrival, build_problem
    from core.problem.frame import LocalPoint

    used = [int(i) for i in rows.rows] + ([rows.toa_reference] if rows.toa_reference >= 0 else [])
    if not used:
        return None
    stations = [(f"s{i}", LocalPoint(*report.stations_enu_m[i].tolist())) for i in used]
    measurements = []
    for i in used:
        if report.kinds[i] == RANGE:
            measurements.append(Range(f"s{i}", float(report.values[i]), float(report.sigmas[i])))
        else:
            measurements.append(TimeOfArrival(f"s{i}", float(report.values[i] - report.values[rows.toa_reference]),
                                              float(report.sigmas[i])))
    step = config.start_altitude_step_m
    try:
        fix = solve(build_problem(stations, measurements))
        if np.all(np.isfinite(fix.crlb_enu_m2)) and math.sqrt(fix.crlb_enu_m2[2, 2]) <= step:
            means = np.zeros((1, STATE_SIZE))
            covs = np.zeros((1, STATE_SIZE, STATE_SIZE))
            means[0, :3] = fix.position_enu_m
            covs[0, :3, :3] = fix.crlb_enu_m2
            covs[0, 3:, 3:] = velocity_prior(config)
            return np.ones(1), means, covs
    except LocalizationError:
        pass
    low, high = config.start_altitudes_m
    altitudes = np.arange(low, high + 0.5 * step, step)
    fixes = solve_batch([build_problem(stations, measurements, altitude_m=float(h)) for h in altitudes])
    kept = [(h, f) for h, f in zip(altitudes.tolist(), fixes)
            if not isinstance(f, LocalizationError) and np.all(np.isfinite(f.crlb_enu_m2[:2, :2]))
            and np.linalg.det(f.crlb_enu_m2[:2, :2]) > 0.0]
    if not kept:
        return None
    log_w = np.array([-0.5 * f.chi2 + 0.5 * math.log(np.linalg.det(f.crlb_enu_m2[:2, :2])) for _, f in kept])
    weights = np.exp(log_w - log_w.max())
    weights /= weights.sum()
    means = np.zeros((len(kept), STATE_SIZE))
    covs = np.zeros((len(kept), STATE_SIZE, STATE_SIZE))
    for c, (h, f) in enumerate(kept):
        means[c, :3] = f.position_enu_m[0], f.position_enu_m[1], h
        covs[c, :2, :2] = f.crlb_enu_m2[:2, :2]
        covs[c, 2, 2] = (0.5 * step) ** 2
        covs[c, 3:, 3:] = velocity_prior(config)
    keep = pruned(weights)
    return weights[keep] / weights[keep].sum(), means[keep], covs[keep]


def predicted_track(track: Track, time_s: float, config: NetworkConfig) -> Track:
    """The track's filter predicted to ``time_s`` (no report): each component with its own process noise,
    the IMM mixed first."""
    dt = time_s - track.time_s
    weights, means, covs = track.weights, np.array(track.means), np.array(track.covariances)
    if track.stage == "imm":
        weights, means, covs = imm.mixed(weights, means, covs,
                                         imm.switching_matrix(weights.size, dt, config.imm_mean_sojourn_s))
        levels = config.imm_accel_sigmas_mps2
    else:
        levels = (config.accel_sigma_mps2,) * weights.size
    phi, noises = motion_model(config, dt, levels)
    means, covs = np.ascontiguousarray(means), np.ascontiguousarray(covs)
    predict_kernel(means, covs, phi, noises)
    mean, cov = (means[0], covs[0]) if weights.size == 1 else moments(weights, means, covs)
    return replace(track, time_s=float(time_s), mean_enu=frozen_array(mean), covariance_enu=frozen_array(cov),
                   weights=frozen_array(weights), means=frozen_array(means), covariances=frozen_array(covs),
                   warnings=())


def predicted_moments(tracks, time_s: float, config: NetworkConfig) -> tuple[np.ndarray, np.ndarray]:
    """The means ``(T, 6)`` and covariances ``(T, 6, 6)`` of tracks predicted to ``time_s``: each
    :func:`predicted_track`'s ``mean_enu`` and ``covariance_enu`` (a track not older than ``time_s`` as it is),
    the single-Gaussian tracks that share an interval predicted in one kernel call."""
    count = len(tracks)
    means, covs = np.empty((count, STATE_SIZE)), np.empty((count, STATE_SIZE, STATE_SIZE))
    groups: dict[float, list[int]] = {}
    for k, track in enumerate(tracks):
        if not time_s > track.time_s:
            means[k], covs[k] = track.mean_enu, track.covariance_enu
        elif track.stage == "single" and track.weights.size == 1:
            groups.setdefault(time_s - track.time_s, []).append(k)
        else:
            predicted = predicted_track(track, time_s, config)
            means[k], covs[k] = predicted.mean_enu, predicted.covariance_enu
    for dt, members in groups.items():
        phi, noise = motion_model(config, dt, (config.accel_sigma_mps2,))
        group_means = np.array([tracks[k].means[0] for k in members])
        group_covs = np.array([tracks[k].covariances[0] for k in members])
        predict_kernel(group_means, group_covs, phi, np.repeat(noise, len(members), axis=0))
        means[members], covs[members] = group_means, group_covs
    return means, covs


@functools.lru_cache(maxsize=64)
def chi2_point(probability: float, dof: int) -> float:
    """The chi-square quantile at ``probability`` on ``dof`` degrees of freedom, cached: the one gate and
    agreement threshold of the network tracker and of the association (:mod:`core.tracking.association`)."""
    return float(chi2.ppf(probability, dof))


__all__ = ["MERGE_DISTANCE", "ReportRows", "advance_track", "chi2_point", "motion_model", "predicted_moments", "predicted_track",
           "report_rows", "updated_track", "velocity_prior"]
