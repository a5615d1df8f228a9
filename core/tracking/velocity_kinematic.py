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

In the tracking stage the three steps share one pass over the joint
covariance when the TOA is usable and a range is observable (the common
case): step 1's update is kept in factored form and folded into step 3's
(:func:`_tracking_update`); otherwise the covariance after step 1 is formed
and the general functions run. Both give the same numbers (to rounding);
the split only saves numpy calls, which dominate a step of this size.

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
from core.tracking.kinematic import (RangePseudoMeasurement, ToaUpdate, fresh_toa_reference,
                                     initial_position_state, kinematic_epoch, line_of_sight_derivatives,
                                     range_from_velocity, range_pseudo_measurement, toa_update, usable_pulse_count)
from core.tracking.state import TrackState, freeze, symmetric
from core.tracking.linalg import repaired_block
from core.tracking.motion import constant_velocity_predict
from core.tracking.unscented import NIS_LIMIT, consider_downdate, polar_transform, polar_update


def advance(state: TrackState, values, config: TrackerConfig) -> TrackState:
    """Apply one validated epoch ``(time_s, azimuth_rad, elevation_rad, azimuth_rate_rad_s, toa_s)``."""
    time_s, azimuth, elevation, rate, toa_s = values
    if state.time_s is None:
        return TrackState(config.model, state.stage, state.updates + 1, time_s, toa_s, state.pulse_period_s,
                          state.mean, state.covariance)
    dt_s = time_s - state.time_s
    correlated = config.pseudo_range_errors == "correlated"
    q = config.accel_sigma_mps2**2
    warnings: list = []
    tracking = state.stage == "tracking"
    mean = state.mean.tolist()
    if tracking:
        if correlated:
            mean, cov = constant_velocity_predict(mean, state.covariance, dt_s, q, (3, 6), True)
        else:
            mean, cov = constant_velocity_predict(mean, state.covariance, dt_s, q, (3,), True, 6)
        x, y, z = mean[0], mean[1], mean[2]
        range_m = math.sqrt(x * x + y * y + z * z)
        los, d_az, d_el = line_of_sight_derivatives(azimuth, elevation)
        n_pulses = usable_pulse_count(mean, 6, state.pulse_period_s, dt_s, toa_s - state.toa_s, los, warnings)
        if n_pulses is not None:
            # The common case, steps 1-3 with both covariance changes in one pass (_tracking_update).
            top = cov[:9, :9].tolist()
            velocity_block = (*top[6][6:9], *top[7][7:9], top[8][8])
            update = toa_update(mean, cov, 6, n_pulses, toa_s - state.toa_s, state.pulse_period_s, los, d_az, d_el,
                                range_m, config, velocity_block)
            mean, cov, pseudo, exact = _tracking_update(update, cov, top, azimuth, elevation, rate, range_m, config,
                                                        warnings)
            if not correlated:
                cov[:6, 6:] = 0.0
                cov[6:, :6] = 0.0
            return TrackState(config.model, "tracking", state.updates + 1, time_s, toa_s, update.period_s,
                              freeze(np.array(mean)), freeze(cov) if exact else symmetric(cov),
                              None if pseudo is None else pseudo.range_m, tuple(warnings))
        mean, cov = fresh_toa_reference(mean, cov, config)
        period_s, cross, offset = state.pulse_period_s, None, 6
    else:
        mean, cov = constant_velocity_predict(mean, state.covariance, dt_s, q, (0,), False)
        range_m = None
        offset = 0
        mean, cov, period_s, cross = kinematic_epoch(mean, cov, offset, state.pulse_period_s, dt_s,
                                                     toa_s - state.toa_s, azimuth, elevation, range_m, config,
                                                     warnings)
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
            if _finite(new_mean, new_cov, warnings):
                mean, cov, stage = new_mean, new_cov, "tracking"
                cov = _position_checked(cov, warnings)
    elif pseudo is not None:
        updated = _position_update(mean, cov, cross, pseudo, azimuth, elevation, config, warnings)
        if updated is not None:
            new_mean, new_cov, nis = updated
            if nis > NIS_LIMIT[3]:
                warnings.append(("innovation_outlier", f"normalised innovation squared {nis:.1f} on 3 degrees "
                                                       "of freedom: a manoeuvre or a bad measurement"))
            if not correlated:
                new_cov[:6, 6:] = 0.0
                new_cov[6:, :6] = 0.0
            if _finite(new_mean, new_cov, warnings):
                mean, cov = new_mean, _position_checked(new_cov, warnings)

    return TrackState(config.model, stage, state.updates + 1, time_s, toa_s, period_s, freeze(np.array(mean)),
                      symmetric(cov), None if pseudo is None else pseudo.range_m, tuple(warnings))


_FIVE = np.array([0, 1, 2, 6, 7])


def _tracking_update(update: ToaUpdate, cov, top, azimuth, elevation, rate, range_m, config, warnings):
    """Steps 2 and 3 after step 1's ``update`` of a tracking-stage state, both covariance changes in one product.

    ``cov`` is the predicted covariance (owned: it is changed) and ``top`` its ``[:9, :9]`` block as lists,
    read before the change. The covariance after step 1 is ``P' - D1`` (:class:`ToaUpdate`); step 3 needs
    of it the position block, the step-1 velocity block and their cross terms, a few scalars from
    ``top``, and ``(P' - D1)[:, five] A`` for its whitened state-innovation covariance ``v``, formed
    from ``P'`` and the two factors of ``D1`` without forming ``P' - D1``. Rare cases (no range, a
    position block that is not positive definite) form it and take the general path
    (:func:`_position_update`).

    Returns
    -------
    mean : list of floats
    cov : ndarray
    pseudo : RangePseudoMeasurement or None
    exact : bool
        True when ``cov`` is exactly symmetric (after a step-3 update), else it is so only to rounding.
    """
    w, u = update.w, update.u
    inverse = update.inverse
    c0, c1 = update.angle_sensitivity
    w6, w7 = w[6], w[7]
    g6, g7 = w6 * inverse, w7 * inverse
    mean = update.mean
    velocity_cov = (top[6][6] - w6 * w6 * inverse, top[6][7] - w6 * w7 * inverse, top[7][7] - w7 * w7 * inverse)
    pseudo = range_from_velocity(mean[6], mean[7], velocity_cov, (g6 * c0, g6 * c1, g7 * c0, g7 * c1), azimuth,
                                 elevation, rate, config, range_m)
    if not isinstance(pseudo, RangePseudoMeasurement):
        warnings.append(("range_unobservable", pseudo.message))
        return mean, update.covariance(cov), None, False
    (p00, p01, p02), (_, p11, p12), (_, _, p22) = top[0][:3], top[1][:3], top[2][:3]
    w0, w1, w2 = w[0] * inverse, w[1] * inverse, w[2] * inverse
    step1_position = (top[6][0] - w6 * w0, top[6][1] - w6 * w1, top[6][2] - w6 * w2,
                      top[7][0] - w7 * w0, top[7][1] - w7 * w1, top[7][2] - w7 * w2)
    try:
        transform = polar_transform(mean, (p00, p01, p02, p11, p12, p22), step1_position, pseudo, azimuth,
                                    elevation, config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2)
    except np.linalg.LinAlgError:
        updated = _position_update(mean, update.covariance(cov), update.angle_cross(), pseudo, azimuth, elevation,
                                   config, warnings)
        if updated is None:
            return mean, update.covariance(cov), pseudo, False
        new_mean, new_cov, nis = updated
        _outlier(nis, warnings)
        if _finite(new_mean, new_cov, warnings):
            return new_mean, _position_checked(new_cov, warnings), pseudo, True
        return mean, update.covariance(cov), pseudo, False

    _outlier(transform.nis, warnings)
    # v^T = A P'[five, :] - [on_w, on_u] [w; u]: the share of D1 = F^T G in P'[:, five] (w u^T / S in
    # the step-1 columns, u w^T / S in the position ones) and the angle cross-covariance ((u / S) x c),
    # folded onto w and u.
    on_w_u = tuple((g6 * x6 + g7 * x7, w0 * x0 + w1 * x1 + w2 * x2 + (c0 * a + c1 * b) * inverse)
                   for (x0, x1, x2, x6, x7), (a, b) in zip(transform.to_innovation, transform.from_angles))
    base = update.base(cov)
    first, second = update.factors()
    v_t = np.array(transform.to_innovation).dot(base.take(_FIVE, axis=0))
    v_t -= np.array(on_w_u).dot(first)
    base -= first.T.dot(second)
    new_mean = list(mean)
    for i, change in enumerate(np.dot(transform.whitened, v_t[:, :6]).tolist()):
        new_mean[i] += change
    new_cov = consider_downdate(base, v_t)
    if _finite(new_mean, new_cov, warnings):
        return new_mean, _position_checked(new_cov, warnings), pseudo, True
    return mean, base, pseudo, False  # base is now P' - D1: step 1 applied, step 3 skipped


def _outlier(nis, warnings):
    if nis > NIS_LIMIT[3]:
        warnings.append(("innovation_outlier", f"normalised innovation squared {nis:.1f} on 3 degrees "
                                               "of freedom: a manoeuvre or a bad measurement"))


def _position_update(mean, cov, cross, pseudo, azimuth, elevation, config, warnings):
    """Step 3's update; on a covariance that is not positive definite, repair and retry once, then give up
    (the caller keeps the prediction) rather than fail."""
    variances = (config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2)
    try:
        return polar_update(mean, cov, 6, cross, pseudo, azimuth, elevation, *variances)
    except np.linalg.LinAlgError:
        pass
    try:
        cov = _position_checked(cov, warnings)
        return polar_update(mean, cov, 6, cross, pseudo, azimuth, elevation, *variances)
    except (np.linalg.LinAlgError, ArithmeticError, ValueError) as error:
        warnings.append(("numerical_failure", f"the position update failed ({error}) and was skipped"))
        return None


def _finite(mean, cov, warnings) -> bool:
    if math.isfinite(sum(mean) + float(np.add.reduce(cov, None))):
        return True
    warnings.append(("numerical_failure", "the position update was not finite and was skipped"))
    return False


def _position_checked(cov, warnings):
    """``cov`` with its ``[p, v]`` block positive definite (repaired and reported if it was not)."""
    cov, repaired = repaired_block(cov, 6)
    if repaired:
        warnings.append(("covariance_repaired", "the position-velocity covariance was not positive definite"))
    return cov
