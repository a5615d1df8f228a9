"""Paper 001's method: velocity first, range from the azimuth rate, then a UKF on position.

Per epoch: step 1 updates the velocity Kalman filter with the TOA difference;
step 2 turns its velocity, with the measured ``B``, ``E`` and ``Bdot``, into
the pseudo-measurement ``(r_hat, B, E)``, whose error is mapped to first
order (Jacobian) from the joint errors of the velocity estimate and the
measured angles and azimuth rate, correlations included (see
:mod:`core.tracking.kinematic`); step 3 predicts the constant-velocity state
``[p, v]`` and updates it with that pseudo-measurement by the unscented
transform (:func:`core.tracking.unscented.polar_update`).

Successive pseudo-measurements share the step-1 velocity error, which changes
slowly. With ``pseudo_range_errors="correlated"`` (default) the state carries
the joint covariance of both filters' errors and step 3 makes a Schmidt
consider update with it; with ``"independent"`` the cross-covariance is kept
at zero, i.e. each pseudo-measurement is treated as independent, as the paper
does (its covariance is then optimistic; the tests give the figures).

The filter initialises at the first epoch whose pseudo-range is known to
``max_initial_range_fraction``. When the range is unobservable at an epoch
(near-radial motion: ``|Bdot|`` under ``min_azimuth_rate_snr`` sigma, or a
pseudo-range of the wrong sign or worse than 100 %), nothing is fed to step
3: the position is predicted only and its covariance grows. (Feeding the
angles alone would be a bearings-only update from a fixed observer, whose
linearised covariance collapses along the line of sight without any range
information: the filter would become confidently wrong.)
"""

from __future__ import annotations

import math

import numpy as np

from core.tracking.config import TrackerConfig
from core.tracking.kinematic import (RangePseudoMeasurement, ToaEpoch, initial_position_state,
                                     range_pseudo_measurement, velocity_update)
from core.linalg import repaired_block
from core.tracking.motion import constant_velocity_predict
from core.tracking.state import TrackState, freeze, symmetric
from core.tracking.unscented import NIS_LIMIT, polar_update


def advance(state: TrackState, values, config: TrackerConfig) -> TrackState:
    """Apply one validated epoch ``(time_s, azimuth_rad, elevation_rad, azimuth_rate_rad_s, toa_s)``."""
    time_s, azimuth, elevation, rate, toa_s = values
    if state.time_s is None:
        return TrackState(config.model, state.stage, state.updates + 1, time_s, toa_s, state.pulse_period_s,
                          state.mean, state.covariance)
    dt_s = time_s - state.time_s
    correlated = config.pseudo_range_errors == "correlated"
    q = config.accel_sigma_mps2**2
    tracking = state.stage == "tracking"
    mean = state.mean.tolist()
    if tracking:
        blocks = ((3, 6), True) if correlated else ((3,), True, 6)
        mean, cov = constant_velocity_predict(mean, state.covariance, dt_s, q, *blocks)
        range_m = math.sqrt(mean[0] * mean[0] + mean[1] * mean[1] + mean[2] * mean[2])
        offset = 6
    else:
        mean, cov = constant_velocity_predict(mean, state.covariance, dt_s, q, (0,), False)
        range_m = None
        offset = 0
    mean, cov, period_s, cross, step1_warnings = velocity_update(
        mean, cov, offset, state.pulse_period_s, ToaEpoch(dt_s, toa_s - state.toa_s, azimuth, elevation, range_m),
        config)
    warnings = list(step1_warnings)
    pseudo = range_pseudo_measurement(mean, cov, offset, cross, azimuth, elevation, rate, config, range_m)
    if not isinstance(pseudo, RangePseudoMeasurement):
        if tracking or pseudo.near_radial:
            warnings.append(("range_unobservable", pseudo.message))
        pseudo = None

    stage = state.stage
    if not tracking:
        if pseudo is not None and pseudo.relative_sigma <= config.max_initial_range_fraction:
            new_mean, new_cov = initial_position_state(pseudo, mean, cov, cross, azimuth, elevation, config, True)
            if not correlated:
                new_cov[:6, 6:] = 0.0
                new_cov[6:, :6] = 0.0
            if _finite(new_mean, new_cov):
                mean, stage = new_mean, "tracking"
                cov, repaired = _position_checked(new_cov)
                warnings += repaired
            else:
                warnings.append(_NOT_FINITE)
    elif pseudo is not None:
        updated, failed = _position_update(mean, cov, cross, pseudo, azimuth, elevation, config)
        warnings += failed
        if updated is not None:
            new_mean, new_cov, nis = updated
            if nis > NIS_LIMIT[3]:
                warnings.append(("innovation_outlier", f"normalised innovation squared {nis:.1f} on 3 degrees "
                                                       "of freedom: a manoeuvre or a bad measurement"))
            if not correlated:
                new_cov[:6, 6:] = 0.0
                new_cov[6:, :6] = 0.0
            if _finite(new_mean, new_cov):
                mean = new_mean
                cov, repaired = _position_checked(new_cov)
                warnings += repaired
            else:
                warnings.append(_NOT_FINITE)

    return TrackState(config.model, stage, state.updates + 1, time_s, toa_s, period_s, freeze(np.array(mean)),
                      symmetric(cov), None if pseudo is None else pseudo.range_m, tuple(warnings))


_NOT_FINITE = ("numerical_failure", "the position update was not finite and was skipped")


def _position_update(mean, cov, cross, pseudo, azimuth, elevation, config):
    """Step 3's update ``(mean, cov, nis)`` and the warnings it raised; on a covariance that is not positive
    definite, repair and retry once, then give up (None: the caller keeps the prediction) rather than fail."""
    variances = (config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2)
    try:
        return polar_update(mean, cov, 6, cross, pseudo, azimuth, elevation, *variances), ()
    except np.linalg.LinAlgError:
        pass
    repaired = ()
    try:
        cov, repaired = _position_checked(cov)
        return polar_update(mean, cov, 6, cross, pseudo, azimuth, elevation, *variances), repaired
    except (np.linalg.LinAlgError, ArithmeticError, ValueError) as error:
        return None, repaired + (("numerical_failure", f"the position update failed ({error}) and was skipped"),)


def _finite(mean, cov) -> bool:
    return math.isfinite(sum(mean) + float(np.add.reduce(cov, None)))


def _position_checked(cov):
    """``cov`` with its ``[p, v]`` block positive definite, and the warning when it had to be repaired."""
    cov, repaired = repaired_block(cov, 6)
    if repaired:
        return cov, (("covariance_repaired", "the position-velocity covariance was not positive definite"),)
    return cov, ()
