"""One UKF on the full state with the raw measurements: paper 001's baseline, and the sessions' default.

State ``[x, y, z (m), vx, vy, vz (m/s), period_error_m, toa_noise_m]``
(``period_error_m``, ``c`` times the period error, only when the period is
unknown; ``toa_noise_m``, ``c`` times the reference TOA's noise, so the shared
TOA of successive differences is modelled exactly, as in step 1 of the
velocity method). Measurements per epoch, with ``T = n Tr_hat``:

- ``B = atan2(x, y)``, ``E = atan2(z, rho)``,
- ``c (dTOA - n Tr_hat) = |p| - |p - v T| + n period_error_m + a_k - toa_noise_m``
  (the previous range from the current state, exact for constant velocity),
- ``Bdot = (y vx - x vy) / rho^2``.

Initialisation (``TrackerConfig.joint_initial_range``): the filter needs a
first range, which the raw measurements give only slowly and through a
strongly nonlinear map.

- ``"prior"`` (the paper's baseline, which has nothing else): at the first
  epoch, the measured angles and a wide range prior (:func:`range_prior_state`);
  the filter then learns the range from the azimuth rate and the TOA
  differences through its velocity.
- ``"kinematic"``: bootstrapped like the velocity method (steps 1-2
  until the first usable pseudo-range), so both models start from the same
  estimate at the same epoch and the comparison is of the filters after it.
  The joint UKF then borrows the velocity method's range to start with.
- ``"range_mixture"`` (the default): at the first epoch, one such UKF per
  range sub-interval of ``range_min_m`` .. ``range_max_m``, a Gaussian sum
  reweighted by each update's innovation density and pruned
  (:mod:`core.tracking.range_mixture`; stage ``"mixture"``) until one is left.

From then on one UKF runs (:func:`joint_epoch`), or, with
``TrackerConfig.imm_accel_sigmas_mps2``, an IMM of them over those
process-noise levels (:mod:`core.tracking.imm`; stage ``"imm"``; during the
range mixture each range component carries the modes).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from core.tracking.config import SPEED_OF_LIGHT_MPS as C
from core.tracking import imm, range_mixture
from core.tracking.config import TrackerConfig
from core.tracking.kinematic import (MAX_INTERVAL_MISMATCH, MAX_PULSE_COUNT_FRACTION, RangePseudoMeasurement,
                                     ToaEpoch, count_pulses, fresh_toa_reference, initial_position_state,
                                     line_of_sight_derivatives, range_pseudo_measurement, velocity_update)
from core.tracking.state import TrackState, freeze, symmetric
from core.linalg import cholesky_repaired, symmetrized
from core.tracking.motion import constant_velocity_predict, transitions
from core.tracking.joint_kernel import joint_ukf_kernel
from core.tracking.kernel_types import INNOVATION_NOT_PD, NOT_FINITE, PREDICTED_NOT_PD, UPDATED, UPDATED_NOT_PD
from core.tracking.unscented import NIS_LIMIT


def advance(state: TrackState, values, config: TrackerConfig) -> TrackState:
    """Apply one validated epoch ``(time_s, azimuth_rad, elevation_rad, azimuth_rate_rad_s, toa_s)``."""
    time_s, azimuth, elevation, rate, toa_s = values
    if state.time_s is None:
        if config.joint_initial_range == "prior" and state.stage == "velocity":
            mean, cov = range_prior_state(state.mean.tolist(), state.covariance, azimuth, elevation, config)
            return TrackState(config.model, "tracking", state.updates + 1, time_s, toa_s, state.pulse_period_s,
                              freeze(np.array(mean)), symmetric(cov))
        if config.joint_initial_range == "range_mixture" and state.stage == "velocity":
            return _mixture_start(state, values, config)
        return TrackState(config.model, state.stage, state.updates + 1, time_s, toa_s, state.pulse_period_s,
                          state.mean, state.covariance)
    dt_s = time_s - state.time_s
    dtoa_s = toa_s - state.toa_s
    q = config.accel_sigma_mps2**2
    warnings: list = []
    if abs(rate) < config.min_azimuth_rate_snr * config.sigma_azimuth_rate_rad_s:
        warnings.append(("range_unobservable",
                         f"|azimuth rate| {abs(rate):.3g} rad/s is below {config.min_azimuth_rate_snr:g} sigma "
                         f"({config.sigma_azimuth_rate_rad_s:.3g} rad/s): near-radial motion"))
    if state.stage == "mixture":
        return _mixture_epoch(state, values, config, tuple(warnings))
    if config.imm_accel_sigmas_mps2 is not None and state.stage in ("tracking", "imm"):
        return _imm_epoch(state, values, config, tuple(warnings))

    if state.stage == "velocity":
        mean, cov = constant_velocity_predict(state.mean.tolist(), state.covariance, dt_s, q, (0,), False)
        mean, cov, period_s, cross, step1_warnings = velocity_update(
            mean, cov, 0, state.pulse_period_s, ToaEpoch(dt_s, dtoa_s, azimuth, elevation), config)
        warnings += step1_warnings
        pseudo = range_pseudo_measurement(mean, cov, 0, cross, azimuth, elevation, rate, config)
        stage = "velocity"
        if isinstance(pseudo, RangePseudoMeasurement):
            if pseudo.relative_sigma <= config.max_initial_range_fraction:
                new_mean, new_cov = initial_position_state(pseudo, mean, cov, cross, azimuth, elevation, config,
                                                           False)
                _, new_cov, repaired = cholesky_repaired(new_cov)
                if repaired:
                    warnings.append(("covariance_repaired", "initial covariance was not positive definite"))
                if math.isfinite(sum(new_mean) + float(new_cov.sum())):
                    mean, cov, stage = new_mean, new_cov, "tracking"
        return TrackState(config.model, stage, state.updates + 1, time_s, toa_s, period_s, freeze(np.array(mean)),
                          symmetric(cov), None, tuple(warnings))

    result = joint_epoch(state.mean.tolist(), state.covariance, state.pulse_period_s, dt_s, dtoa_s, azimuth,
                         elevation, rate, config)
    return TrackState(config.model, "tracking", state.updates + 1, time_s, toa_s, result.period_s,
                      freeze(np.array(result.mean)), symmetric(result.cov), None, tuple(warnings) + result.warnings)


def _levels(config: TrackerConfig) -> tuple[float, ...]:
    """The acceleration-noise level of each mode: the IMM's, or the one level."""
    return config.imm_accel_sigmas_mps2 or (config.accel_sigma_mps2,)


def _mixture_start(state: TrackState, values, config: TrackerConfig) -> TrackState:
    """The first epoch of ``joint_initial_range="range_mixture"``: one joint state per range sub-interval
    (and per IMM mode, when there are modes); components are stored range-major."""
    time_s, azimuth, elevation, _, toa_s = values
    step1_mean, step1_cov = state.mean.tolist(), state.covariance
    middles, sigmas = range_mixture.component_ranges(config)
    modes = len(_levels(config))
    starts = [range_prior_state(step1_mean, step1_cov, azimuth, elevation, config, float(r), float(s))
              for r, s in zip(middles, sigmas) for _ in range(modes)]
    weights = np.full(len(starts), 1.0 / len(starts))
    means = np.array([m for m, _ in starts])
    covariances = np.array([c for _, c in starts])
    mean, cov = range_mixture.moments(weights, means, covariances)
    return TrackState(config.model, "mixture", state.updates + 1, time_s, toa_s, state.pulse_period_s,
                      freeze(mean), freeze(cov), None, (),
                      range_mixture.components_of(weights, means, covariances))


def _mixture_epoch(state: TrackState, values, config: TrackerConfig, warnings: tuple) -> TrackState:
    """One epoch of the Gaussian sum: (with IMM modes, the modes of each range component mixed first) every
    component updated with the same pulse count, reweighted by its innovation density, range components
    pruned; a single survivor continues as the joint UKF or the IMM (see :mod:`range_mixture`)."""
    time_s, azimuth, elevation, rate, toa_s = values
    dt_s, dtoa_s = time_s - state.time_s, toa_s - state.toa_s
    period_s = state.pulse_period_s
    levels = _levels(config)
    modes = len(levels)
    count = predicted_pulse_count(state.mean.tolist(), period_s, dt_s, dtoa_s)
    parts = state.components
    size = parts.means.shape[1]
    weights = parts.weights.reshape(-1, modes)
    means = parts.means.reshape(-1, modes, size)
    covariances = parts.covariances.reshape(-1, modes, size, size)
    if modes > 1:
        prior, means, covariances = imm.mixed(weights, means, covariances,
                                              imm.switching_matrix(modes, dt_s, config.imm_mean_sojourn_s))
        prior_weights = prior.ravel()
    else:
        prior_weights = weights[:, 0]
    batch = joint_epochs(means.reshape(-1, size), covariances.reshape(-1, size, size), levels * weights.shape[0],
                         period_s, dt_s, dtoa_s, azimuth, elevation, rate, config, count)
    posterior = range_mixture.reweighted(prior_weights, batch.log_likelihoods)
    if posterior is None:
        posterior = prior_weights
    warnings = warnings + batch.warnings[int(np.argmax(posterior))]
    weights = posterior.reshape(-1, modes)
    kept = range_mixture.pruned(weights.sum(axis=1))
    weights = np.array([imm.floored(w) * w.sum() for w in weights[kept]]) if modes > 1 else weights[kept]
    weights = weights / weights.sum()
    means = batch.means.reshape(-1, modes, size)[kept]
    covariances = batch.covariances.reshape(-1, modes, size, size)[kept]
    if weights.shape[0] == 1 and modes > 1:
        weights = imm.floored(weights[0] / weights[0].sum())
        means, covariances = means[0], covariances[0]
        if not config.period_known:
            shared = float(weights @ means[:, 6])
            period_s += shared / C
            means[:, 6] -= shared
        mean, cov = range_mixture.moments(weights, means, covariances)
        return TrackState(config.model, "imm", state.updates + 1, time_s, toa_s, period_s, freeze(mean),
                          freeze(cov), None, warnings, range_mixture.components_of(weights, means, covariances))
    weights, means = weights.reshape(-1), means.reshape(-1, size)
    covariances = covariances.reshape(-1, size, size)
    mean, cov = range_mixture.moments(weights, means, covariances)
    if weights.size == 1:
        mean, period_s = range_mixture.fold_period(mean.tolist(), period_s, config.period_known)
        return TrackState(config.model, "tracking", state.updates + 1, time_s, toa_s, period_s,
                          freeze(np.array(mean)), symmetric(cov), None, warnings)
    return TrackState(config.model, "mixture", state.updates + 1, time_s, toa_s, period_s, freeze(mean),
                      freeze(cov), None, warnings, range_mixture.components_of(weights, means, covariances))


def _imm_epoch(state: TrackState, values, config: TrackerConfig, warnings: tuple) -> TrackState:
    """One cycle of the interacting multiple model over ``config.imm_accel_sigmas_mps2``: mix, predict and
    update each mode with the same pulse count, update the mode probabilities, combine."""
    time_s, azimuth, elevation, rate, toa_s = values
    dt_s, dtoa_s = time_s - state.time_s, toa_s - state.toa_s
    period_s = state.pulse_period_s
    levels = config.imm_accel_sigmas_mps2
    if state.stage == "tracking":
        parts = imm.uniform_modes(state.mean, state.covariance, len(levels))
    else:
        parts = state.components
    prior, start_means, start_covs = imm.mixed(parts.weights, parts.means, parts.covariances,
                                               imm.switching_matrix(len(levels), dt_s, config.imm_mean_sojourn_s))
    count = predicted_pulse_count(state.mean.tolist(), period_s, dt_s, dtoa_s)
    batch = joint_epochs(start_means, start_covs, levels, period_s, dt_s, dtoa_s, azimuth, elevation, rate,
                         config, count)
    weights = range_mixture.reweighted(prior, batch.log_likelihoods)
    if weights is None:
        weights = prior
    weights = imm.floored(weights)
    warnings = warnings + batch.warnings[int(np.argmax(weights))]
    means, covariances = batch.means, batch.covariances
    if not config.period_known:
        shared = float(weights @ means[:, 6])
        period_s += shared / C
        means[:, 6] -= shared
    mean, cov = range_mixture.moments(weights, means, covariances)
    return TrackState(config.model, "imm", state.updates + 1, time_s, toa_s, period_s, freeze(mean), freeze(cov),
                      None, warnings, range_mixture.components_of(weights, means, covariances))


class JointEpoch(NamedTuple):
    """One epoch of the joint UKF on a tracking-stage state.

    Attributes
    ----------
    mean : list of F floats
    cov : ndarray, shape (F, F)
        Exactly symmetric.
    period_s : float
        Period estimate, the period error folded in (unless ``fold_period`` was False).
    log_likelihood : float
        ``-(nis + log det S) / 2`` of the update (the innovation density up to a constant that depends only
        on the number of measurements), ``-inf`` when the update failed.
    warnings : tuple of (str, str)
    """

    mean: list
    cov: np.ndarray
    period_s: float
    log_likelihood: float
    warnings: tuple


class JointEpochs(NamedTuple):
    """One epoch of ``M`` joint states (:func:`joint_epochs`), the period error not folded.

    Attributes
    ----------
    means : ndarray, shape (M, F)
    covariances : ndarray, shape (M, F, F)
        Exactly symmetric.
    log_likelihoods : ndarray, shape (M,)
        As :attr:`JointEpoch.log_likelihood`.
    warnings : list of M tuples of (str, str)
    """

    means: np.ndarray
    covariances: np.ndarray
    log_likelihoods: np.ndarray
    warnings: list


def pulse_count(mean, period_s: float, dt_s: float, dtoa_s: float):
    """Pulses between the reference TOA and this one from the predicted joint state ``mean``, whether the TOA
    is usable, and the warnings that raises."""
    x, y, z, vx, vy, vz = mean[:6]
    r = math.sqrt(x * x + y * y + z * z)
    n_pulses, fraction = count_pulses(dtoa_s, period_s, dt_s * (x * vx + y * vy + z * vz) / r)
    use_toa = n_pulses >= 1 and abs(fraction) <= MAX_PULSE_COUNT_FRACTION
    if not use_toa:
        return n_pulses, False, (("pulse_count_ambiguous",
                                  f"TOA difference {dtoa_s:.9g} s is {n_pulses + fraction:.3f} periods; TOA not used"),)
    if abs(n_pulses * period_s - dt_s) > MAX_INTERVAL_MISMATCH * dt_s:
        return n_pulses, True, (("pulse_count_mismatch", f"{n_pulses} pulses of {period_s:.9g} s between TOAs, "
                                                         f"but time_s advanced {dt_s:.6g} s"),)
    return n_pulses, True, ()


def joint_epoch(mean, cov, period_s: float, dt_s: float, dtoa_s: float, azimuth: float, elevation: float,
                rate: float, config: TrackerConfig, count=None, fold_period: bool = True,
                accel_sigma_mps2: float | None = None) -> JointEpoch:
    """Predict and update a joint state (layout in :mod:`core.tracking.state`) with one epoch.

    Parameters
    ----------
    mean : list of F floats
    cov : ndarray, shape (F, F)
    period_s : float
        Period the TOA difference is referred to; with an unknown period the state's ``period_error_m`` is
        relative to it.
    dt_s, dtoa_s : float
        ``time_s`` and TOA intervals since the reference epoch.
    azimuth, elevation, rate : float
        This epoch's measurements (rad, rad/s).
    config : TrackerConfig
    count : tuple (n_pulses, use_toa, warnings), optional
        The pulse count (from :func:`pulse_count`); by default from this state's prediction.
    fold_period : bool
        Fold the updated period error into the returned ``period_s`` (and zero it in the mean).
    accel_sigma_mps2 : float, optional
        The acceleration noise of the prediction; ``config.accel_sigma_mps2`` by default.

    Returns
    -------
    JointEpoch
    """
    if count is None:
        count = predicted_pulse_count(mean, period_s, dt_s, dtoa_s)
    accel = config.accel_sigma_mps2 if accel_sigma_mps2 is None else accel_sigma_mps2
    batch = joint_epochs(np.array((mean,)), cov[None], (accel,), period_s, dt_s, dtoa_s, azimuth, elevation, rate,
                         config, count)
    mean, log_likelihood = batch.means[0].tolist(), float(batch.log_likelihoods[0])
    if fold_period and len(mean) == 8 and log_likelihood > -math.inf:
        mean, period_s = range_mixture.fold_period(mean, period_s, False)
    return JointEpoch(mean, batch.covariances[0], period_s, log_likelihood, batch.warnings[0])


def predicted_pulse_count(mean, period_s: float, dt_s: float, dtoa_s: float):
    """:func:`pulse_count` from the joint state ``mean`` (list of F floats) predicted over ``dt_s``, with its
    period error (if any) added to ``period_s``."""
    predicted = [mean[i] + dt_s * mean[i + 3] for i in range(3)] + list(mean[3:6])
    return pulse_count(predicted, period_s + (mean[6] / C if len(mean) == 8 else 0.0), dt_s, dtoa_s)


def range_prior_state(mean, cov, azimuth_rad: float, elevation_rad: float, config: TrackerConfig,
                      range_m: float | None = None, range_sigma_m: float | None = None):
    """The direct joint UKF's first state: a range prior along the measured angles (``joint_initial_range="prior"``).

    Position ``r0 u(B, E)`` with covariance ``sigma_r^2 u u^T + r0^2 (sigma_B^2
    u_B u_B^T + sigma_E^2 u_E u_E^T)`` (``u_B``, ``u_E`` the derivatives of the
    line of sight: the angle errors across it), followed by the step-1 prior
    ``[v, (period_error_m), toa_noise_m]`` (zero velocity +- the velocity prior;
    independent of the position). This epoch's azimuth rate is not used (there
    is no TOA difference yet either); its angles are, once, here.

    Parameters
    ----------
    mean : list of K floats
    cov : ndarray, shape (K, K)
        The step-1 prior (:func:`core.tracking.kinematic.kinematic_prior`).
    azimuth_rad, elevation_rad : float
    config : TrackerConfig
    range_m, range_sigma_m : float, optional
        The range prior; ``config.range_prior_m`` and ``config.range_prior_sigma_m`` by default.

    Returns
    -------
    mean : list of 3 + K floats
    cov : ndarray, shape (3 + K, 3 + K)
    """
    los, d_az, d_el = line_of_sight_derivatives(azimuth_rad, elevation_rad)
    r = config.range_prior_m if range_m is None else range_m
    sigma = config.range_prior_sigma_m if range_sigma_m is None else range_sigma_m
    u, a, e = np.array(los), np.array(d_az), np.array(d_el)
    k = len(mean)
    new_cov = np.zeros((3 + k, 3 + k))
    new_cov[:3, :3] = (sigma**2 * np.outer(u, u)
                       + r * r * (config.sigma_azimuth_rad**2 * np.outer(a, a)
                                  + config.sigma_elevation_rad**2 * np.outer(e, e)))
    new_cov[3:, 3:] = cov
    return [r * c for c in los] + list(mean), new_cov


def joint_epochs(means: np.ndarray, covariances: np.ndarray, accel_sigmas_mps2, period_s: float, dt_s: float,
                 dtoa_s: float, azimuth: float, elevation: float, rate: float, config: TrackerConfig, count):
    """Predict and update ``M`` joint states (the components of a mixture or an IMM, or the one state of
    :func:`joint_epoch`) with one epoch and one pulse count, the period error left unfolded.

    The arithmetic is :func:`core.tracking.joint_kernel.joint_update`'s; here
    its outcomes become warnings: a predicted or updated covariance that is
    not positive definite is repaired (``covariance_repaired``); an update
    that fails or is not finite is skipped, the state predicted only, with
    the TOA noise a fresh one (``numerical_failure``); a NIS above
    :data:`~core.tracking.unscented.NIS_LIMIT` raises ``innovation_outlier``.

    Parameters
    ----------
    means : ndarray, shape (M, F)
    covariances : ndarray, shape (M, F, F)
    accel_sigmas_mps2 : sequence of M floats
        Each state's acceleration noise.
    period_s, dt_s, dtoa_s, azimuth, elevation, rate, config
        As :func:`joint_epoch`.
    count : tuple (n_pulses, use_toa, warnings)
        From :func:`pulse_count`.

    Returns
    -------
    JointEpochs
    """
    m, f = means.shape
    n_pulses, use_toa, count_warnings = count
    phi, noises = transitions(f, (3,), True, dt_s, tuple(a * a for a in accel_sigmas_mps2))
    interval_s = n_pulses * period_s
    var_toa = (C * config.sigma_toa_s) ** 2
    measured = np.array((azimuth, elevation, C * (dtoa_s - interval_s) if use_toa else 0.0, rate))
    variances = np.array((config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2, var_toa,
                          config.sigma_azimuth_rate_rad_s**2))
    predicted_means, predicted_covs = np.array(means, dtype=float), np.array(covariances, dtype=float)
    new_means, new_covs = np.empty_like(predicted_means), np.empty_like(predicted_covs)
    nis, log_det, status = np.empty(m), np.empty(m), np.empty(m, dtype=np.int64)

    def update(i, j, predict):
        joint_ukf_kernel(predicted_means[i:j], predicted_covs[i:j], phi, noises[i:j], predict, int(n_pulses),
                         float(interval_s), bool(use_toa), measured, variances, new_means[i:j], new_covs[i:j],
                         nis[i:j], log_det[i:j], status[i:j])

    log_likelihoods = np.empty(m)
    log_likelihoods.fill(-math.inf)
    warnings = [tuple(count_warnings)] * m
    try:
        update(0, m, True)
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as error:
        for i in range(m):
            x, p = constant_velocity_predict(means[i].tolist(), covariances[i], dt_s, accel_sigmas_mps2[i] ** 2,
                                             (3,), True)
            new_means[i], new_covs[i] = fresh_toa_reference(x, symmetrized(p), config)
            warnings[i] = tuple(count_warnings) + (("numerical_failure", f"the update failed ({error})"),)
        return JointEpochs(new_means, new_covs, log_likelihoods, warnings)
    dof = 4 if use_toa else 3
    for i, outcome in enumerate(status.tolist()):
        if outcome == UPDATED:
            if nis[i] > NIS_LIMIT[dof]:
                warnings[i] = tuple(count_warnings) + (_outlier(nis[i], dof),)
            log_likelihoods[i] = -0.5 * (nis[i] + log_det[i])
            continue
        found = list(count_warnings)
        if outcome == PREDICTED_NOT_PD:
            _, predicted_covs[i], _ = cholesky_repaired(predicted_covs[i])
            found.append(("covariance_repaired", "predicted covariance was not positive definite"))
            update(i, i + 1, False)
            outcome = int(status[i])
        if outcome in (PREDICTED_NOT_PD, INNOVATION_NOT_PD):
            which = "predicted" if outcome == PREDICTED_NOT_PD else "innovation"
            found.append(("numerical_failure", f"the update failed ({which} covariance is not positive definite)"))
        else:
            if nis[i] > NIS_LIMIT[dof]:
                found.append(_outlier(nis[i], dof))
            if outcome == NOT_FINITE:
                found.append(("numerical_failure", "the update was not finite and was skipped"))
            else:
                log_likelihoods[i] = -0.5 * (nis[i] + log_det[i])
                if outcome == UPDATED_NOT_PD:
                    _, new_covs[i], _ = cholesky_repaired(new_covs[i])
                    found.append(("covariance_repaired", "updated covariance was not positive definite"))
        if log_likelihoods[i] == -math.inf:
            new_means[i], new_covs[i] = fresh_toa_reference(predicted_means[i].tolist(), predicted_covs[i], config)
        warnings[i] = tuple(found)
    return JointEpochs(new_means, new_covs, log_likelihoods, warnings)


def _outlier(nis: float, dof: int):
    return ("innovation_outlier", f"normalised innovation squared {nis:.1f} on {dof} degrees of freedom: a "
                                  "manoeuvre or a bad measurement")
