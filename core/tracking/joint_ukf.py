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
  reweighted by each update's innovation density, pruned and merged
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
from core.tracking.linalg import cholesky_repaired, inverse_cholesky
from core.tracking.motion import constant_velocity_predict, transition
from core.tracking.unscented import NIS_LIMIT, TWO_PI

_WITHOUT_TOA = np.array([0, 1, 3])


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
    pruned and merged; a single survivor continues as the joint UKF or the IMM (see :mod:`range_mixture`)."""
    time_s, azimuth, elevation, rate, toa_s = values
    dt_s, dtoa_s = time_s - state.time_s, toa_s - state.toa_s
    period_s = state.pulse_period_s
    levels = _levels(config)
    modes = len(levels)
    merged = state.mean.tolist()
    predicted = [merged[i] + dt_s * merged[i + 3] for i in range(3)] + merged[3:]
    count = pulse_count(predicted, period_s + (0.0 if config.period_known else merged[6] / C), dt_s, dtoa_s)
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
    results = joint_epochs(means.reshape(-1, size), covariances.reshape(-1, size, size), levels * weights.shape[0],
                           period_s, dt_s, dtoa_s, azimuth, elevation, rate, config, count)
    posterior = range_mixture.reweighted(prior_weights, np.array([r.log_likelihood for r in results]))
    if posterior is None:
        posterior = prior_weights
    warnings = warnings + results[int(np.argmax(posterior))].warnings
    weights = posterior.reshape(-1, modes)
    kept = range_mixture.pruned(weights.sum(axis=1))
    weights = np.array([imm.floored(w) * w.sum() for w in weights[kept]]) if modes > 1 else weights[kept]
    weights = weights / weights.sum()
    means = np.array([r.mean for r in results]).reshape(-1, modes, size)[kept]
    covariances = np.array([r.cov for r in results]).reshape(-1, modes, size, size)[kept]
    covariances = 0.5 * (covariances + np.swapaxes(covariances, -1, -2))
    weights, means, covariances = range_mixture.merge_neighbours(weights, means, covariances)
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
    merged = state.mean.tolist()
    predicted = [merged[i] + dt_s * merged[i + 3] for i in range(3)] + merged[3:]
    count = pulse_count(predicted, period_s + (0.0 if config.period_known else merged[6] / C), dt_s, dtoa_s)
    results = joint_epochs(start_means, start_covs, levels, period_s, dt_s, dtoa_s, azimuth, elevation, rate,
                           config, count)
    weights = range_mixture.reweighted(prior, np.array([r.log_likelihood for r in results]))
    if weights is None:
        weights = prior
    weights = imm.floored(weights)
    warnings = warnings + results[int(np.argmax(weights))].warnings
    means = np.array([r.mean for r in results])
    covariances = np.array([r.cov for r in results])
    covariances = 0.5 * (covariances + np.swapaxes(covariances, 1, 2))
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
        Symmetric to rounding.
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
    warnings = []
    k = len(mean) - 3
    accel = config.accel_sigma_mps2 if accel_sigma_mps2 is None else accel_sigma_mps2
    mean, cov = constant_velocity_predict(mean, cov, dt_s, accel * accel, (3,), True)
    if count is None:
        effective = period_s + (mean[6] / C if k == 5 else 0.0)
        count = pulse_count(mean, effective, dt_s, dtoa_s)
    n_pulses, use_toa, count_warnings = count
    warnings += count_warnings
    measured = (azimuth, elevation, C * (dtoa_s - n_pulses * period_s) if use_toa else 0.0, rate)
    log_likelihood = -math.inf
    try:
        chol, cov, repaired = cholesky_repaired(cov)
        if repaired:
            warnings.append(("covariance_repaired", "predicted covariance was not positive definite"))
        new_mean, new_cov, nis, log_det = joint_update(mean, cov, chol, measured, n_pulses, period_s, use_toa,
                                                       config)
        log_likelihood = -0.5 * (nis + log_det)
    except (np.linalg.LinAlgError, ArithmeticError, ValueError) as error:
        new_mean, new_cov = [math.nan], np.full(1, math.nan)
        nis = 0.0
        warnings.append(("numerical_failure", f"the update failed ({error})"))
    dof = 4 if use_toa else 3
    if nis > NIS_LIMIT[dof]:
        warnings.append(("innovation_outlier", f"normalised innovation squared {nis:.1f} on {dof} degrees of "
                                               "freedom: a manoeuvre or a bad measurement"))
    if math.isfinite(sum(new_mean) + float(np.add.reduce(new_cov, None))):
        _, new_cov, repaired = cholesky_repaired(new_cov)
        if repaired:
            warnings.append(("covariance_repaired", "updated covariance was not positive definite"))
        mean, cov = new_mean, new_cov
        if k == 5 and fold_period:
            period_s = period_s + mean[6] / C
            mean[6] = 0.0
    else:
        if not any(code == "numerical_failure" for code, _ in warnings):
            warnings.append(("numerical_failure", "the update was not finite and was skipped"))
        mean, cov = fresh_toa_reference(mean, cov, config)
        log_likelihood = -math.inf
    return JointEpoch(mean, cov, period_s, log_likelihood, tuple(warnings))


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


def joint_update(mean, cov, chol, measured, n_pulses: int, period_s: float, use_toa: bool,
                 config: TrackerConfig):
    """Unscented update with ``(B, E, c (dTOA - n Tr_hat), Bdot)``.

    The new TOA's noise enters the TOA row additively and is also the next
    reference's noise: it is appended to the state for the update (prior
    ``N(0, (c sigma_toa)^2)``, so its posterior is correlated with the rest)
    and replaces the old ``toa_noise_m`` afterwards. Without a usable TOA the
    TOA row is left out and ``toa_noise_m`` becomes a fresh, independent noise.

    Parameters
    ----------
    mean : list of F floats
    cov : ndarray, shape (F, F)
    chol : ndarray, shape (F, F)
        Cholesky factor of ``cov``.
    measured : tuple of 4 floats
        Azimuth (rad), elevation (rad), TOA difference less ``n Tr_hat`` in
        metres, azimuth rate (rad/s).
    n_pulses : int
    period_s : float
    use_toa : bool
    config : TrackerConfig

    Returns
    -------
    mean : list of F floats
    cov : ndarray, shape (F, F)
        Updated state (covariance symmetric to rounding); the last component is now the new TOA's noise.
    nis : float
        Normalised innovation squared (chi-square with 4, or 3 without the
        TOA, degrees of freedom when the model holds).
    log_det : float
        ``log det S`` of the innovation covariance.
    """
    f = len(mean)
    spread = math.sqrt(f)
    weight = 1.0 / (2 * f)
    interval_s = n_pulses * period_s
    points = chol.dot(_sigma_directions(f))
    points += np.array(mean)[:, None]
    predicted = _measurement_model(points, n_pulses, interval_s, f == 8)

    state = mean
    x, y, z, vx, vy, vz = state[:6]
    rho2 = x * x + y * y
    qx, qy, qz = x - interval_s * vx, y - interval_s * vy, z - interval_s * vz
    change = math.sqrt(rho2 + z * z) - math.sqrt(qx * qx + qy * qy + qz * qz) - state[-1]
    if f == 8:
        change += n_pulses * state[6]
    azimuth0 = math.atan2(x, y)
    rate0 = (y * vx - x * vy) / rho2
    centre = (azimuth0, math.atan2(z, math.sqrt(rho2)), change, rate0) if use_toa else (
        azimuth0, math.atan2(z, math.sqrt(rho2)), rate0)

    if not use_toa:
        predicted = predicted[_WITHOUT_TOA]
    deviation = predicted - np.array(centre)[:, None]
    wrapped = deviation[0]
    wrapped += math.pi
    wrapped %= TWO_PI
    wrapped -= math.pi
    var_toa = (C * config.sigma_toa_s) ** 2
    if use_toa:
        innovation = (math.remainder(measured[0] - centre[0], TWO_PI), measured[1] - centre[1],
                      measured[2] - centre[2], measured[3] - centre[3])
        noise = _noise(config, True)
    else:
        innovation = (math.remainder(measured[0] - centre[0], TWO_PI), measured[1] - centre[1],
                      measured[3] - centre[2])
        noise = _noise(config, False)
    mean_deviation = deviation.sum(axis=1)
    mean_deviation *= weight
    centred = deviation - mean_deviation[:, None]
    innovation_cov = centred.dot(centred.T)
    innovation_cov *= weight
    innovation_cov += noise
    # Covariance of the state with the measurement; with a usable TOA its last row is that of the new
    # TOA's noise (it enters the TOA row additively and becomes the next reference's noise).
    cross_cov = chol.dot((deviation[:, :f] - deviation[:, f:]).T)
    cross_cov *= spread * weight
    if use_toa:
        cross_cov[f - 1] = (0.0, 0.0, var_toa, 0.0)
    innovation = np.subtract(innovation, mean_deviation)

    # Whitened form: with S = L L^T, v = cross_cov L^-T and t = L^-1 innovation, the gain is v L^-1,
    # the state moves by v t and the covariance loses v v^T; the NIS is |t|^2.
    whitening = np.array(inverse_cholesky(innovation_cov.tolist()))
    v_t = whitening.dot(cross_cov.T)
    t = whitening.dot(innovation)
    nis = float(t.dot(t))
    log_det = -2.0 * float(np.log(np.diagonal(whitening)).sum())
    x = list(mean)
    p = cov.copy()
    if use_toa:
        x[f - 1] = 0.0
        p[f - 1] = 0.0
        p[:, f - 1] = 0.0
        p[f - 1, f - 1] = var_toa
    for i, change in enumerate(t.dot(v_t).tolist()):
        x[i] += change
    p -= v_t.T.dot(v_t)
    if not use_toa:
        x, p = fresh_toa_reference(x, p, config)
    return x, p, nis, log_det


_DIRECTIONS: dict = {}


def _sigma_directions(f: int) -> np.ndarray:
    """``sqrt(f) [I, -I]``, shape ``(f, 2 f)``: ``chol @`` it gives the sigma-point offsets."""
    found = _DIRECTIONS.get(f)
    if found is None:
        eye = np.eye(f) * math.sqrt(f)
        found = _DIRECTIONS[f] = np.hstack((eye, -eye))
        found.flags.writeable = False
    return found


_NOISES: dict = {}


def _noise(config: TrackerConfig, use_toa: bool) -> np.ndarray:
    """Diagonal measurement noise ``(B, E, [c dTOA,] Bdot)`` as a matrix, memoised per config."""
    key = (config.sigma_azimuth_rad, config.sigma_elevation_rad, config.sigma_toa_s, config.sigma_azimuth_rate_rad_s,
           use_toa)
    found = _NOISES.get(key)
    if found is None:
        variances = [config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2]
        if use_toa:
            variances.append((C * config.sigma_toa_s) ** 2)
        variances.append(config.sigma_azimuth_rate_rad_s**2)
        if len(_NOISES) >= 64:
            _NOISES.clear()
        found = _NOISES[key] = np.diag(variances)
        found.flags.writeable = False
    return found


def _measurement_model(points, n_pulses: int, interval_s: float, has_period_error: bool):
    """``(B, E, c dS, Bdot)`` of the state columns ``points`` ``(F, m)``, shape ``(4, m)``."""
    position = points[:3]
    squares = position * position
    rho2 = squares[0] + squares[1]
    previous = position - interval_s * points[3:6]
    out = np.empty((4, points.shape[1]))
    out[0] = np.arctan2(position[0], position[1])
    out[1] = np.arctan2(position[2], np.sqrt(rho2))
    out[2] = np.sqrt(rho2 + squares[2]) - np.sqrt((previous * previous).sum(axis=0)) - points[-1]
    if has_period_error:
        out[2] += n_pulses * points[6]
    out[3] = (position[1] * points[3] - position[0] * points[4]) / rho2
    return out


def joint_epochs(means: np.ndarray, covariances: np.ndarray, accel_sigmas_mps2, period_s: float, dt_s: float,
                 dtoa_s: float, azimuth: float, elevation: float, rate: float, config: TrackerConfig, count):
    """:func:`joint_epoch` for ``M`` joint states at once (the components of a mixture or an IMM), with one
    pulse count and the period error left unfolded; the same arithmetic in batched form.

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
    list of JointEpoch
        One per state (``period_s`` unchanged).
    """
    m, f = means.shape
    n_pulses, use_toa, count_warnings = count
    phis, noises = zip(*(transition(f, (3,), True, dt_s, a * a) for a in accel_sigmas_mps2))
    phi = phis[0]
    cov = np.matmul(np.matmul(phi, covariances), phi.T) + np.array(noises)
    mean = means.copy()
    mean[:, :3] += dt_s * mean[:, 3:6]
    warnings = [list(count_warnings) for _ in range(m)]
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        chol = np.empty_like(cov)
        for i in range(m):
            chol[i], cov[i], repaired = cholesky_repaired(cov[i])
            if repaired:
                warnings[i].append(("covariance_repaired", "predicted covariance was not positive definite"))
    interval_s = n_pulses * period_s
    spread, weight = math.sqrt(f), 1.0 / (2 * f)
    points = np.matmul(chol, _sigma_directions(f)) + mean[:, :, None]
    columns = np.concatenate((points.transpose(1, 0, 2).reshape(f, -1), mean.T), axis=1)
    modelled = _measurement_model(columns, n_pulses, interval_s, f == 8)
    rows = slice(None) if use_toa else _WITHOUT_TOA
    predicted = modelled[rows, :m * 2 * f].reshape(-1, m, 2 * f).transpose(1, 0, 2)
    centre = modelled[rows, m * 2 * f:].T
    deviation = predicted - centre[:, :, None]
    deviation[:, 0] = np.remainder(deviation[:, 0] + math.pi, TWO_PI) - math.pi
    measured = np.array((azimuth, elevation, C * (dtoa_s - interval_s), rate) if use_toa else
                        (azimuth, elevation, rate))
    innovation = measured - centre
    innovation[:, 0] = np.remainder(innovation[:, 0] + math.pi, TWO_PI) - math.pi
    mean_deviation = deviation.mean(axis=2)
    centred = deviation - mean_deviation[:, :, None]
    innovation_cov = np.matmul(centred, centred.transpose(0, 2, 1)) * weight + _noise(config, use_toa)
    cross_cov = np.matmul(chol, (deviation[:, :, :f] - deviation[:, :, f:]).transpose(0, 2, 1)) * (spread * weight)
    var_toa = (C * config.sigma_toa_s) ** 2
    # The last state becomes the new TOA's noise: with a usable TOA it enters the TOA row additively; without,
    # it is a fresh independent noise (zero covariance with everything).
    cross_cov[:, f - 1] = (0.0, 0.0, var_toa, 0.0) if use_toa else 0.0
    innovation -= mean_deviation
    predicted_mean, predicted_cov = mean.copy(), cov.copy()
    results = []
    for i in range(m):
        try:
            whitening = np.array(inverse_cholesky(innovation_cov[i].tolist()))
        except np.linalg.LinAlgError as error:
            x, p = fresh_toa_reference(predicted_mean[i].tolist(), predicted_cov[i], config)
            results.append(JointEpoch(x, p, period_s, -math.inf, tuple(warnings[i]) + (
                ("numerical_failure", f"the update failed ({error})"),)))
            continue
        v_t = whitening.dot(cross_cov[i].T)
        t = whitening.dot(innovation[i])
        nis = float(t.dot(t))
        log_det = -2.0 * float(np.log(np.diagonal(whitening)).sum())
        x, p = mean[i], cov[i]
        x[f - 1] = 0.0
        p[f - 1] = 0.0
        p[:, f - 1] = 0.0
        p[f - 1, f - 1] = var_toa
        x += t.dot(v_t)
        p -= v_t.T.dot(v_t)
        dof = 4 if use_toa else 3
        if nis > NIS_LIMIT[dof]:
            warnings[i].append(("innovation_outlier", f"normalised innovation squared {nis:.1f} on {dof} degrees "
                                                      "of freedom: a manoeuvre or a bad measurement"))
        if not math.isfinite(float(x.sum()) + float(p.sum())):
            x, p = fresh_toa_reference(predicted_mean[i].tolist(), predicted_cov[i], config)
            results.append(JointEpoch(x, p, period_s, -math.inf, tuple(warnings[i]) + (
                ("numerical_failure", "the update was not finite and was skipped"),)))
            continue
        _, p, repaired = cholesky_repaired(p)
        if repaired:
            warnings[i].append(("covariance_repaired", "updated covariance was not positive definite"))
        results.append(JointEpoch(x.tolist(), p, period_s, -0.5 * (nis + log_det), tuple(warnings[i])))
    return results
