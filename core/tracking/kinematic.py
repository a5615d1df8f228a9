"""Steps 1 and 2 of paper 001: velocity from TOA differences, range from the azimuth rate.

Step 1 is a linear Kalman filter on ``[vx, vy, vz, period_error_m, toa_noise_m]``
(``period_error_m`` only when the period is unknown). Each TOA difference is a
scalar measurement, in metres,

``z = c (dTOA - n Tr_hat) = T u . v + n period_error_m + a_k - a_ref + w``

with ``n`` the number of pulses between the two TOAs, ``T = n Tr_hat`` the
emission interval, ``u`` the measured line of sight, ``a_k`` the (metre)
noise of ``TOA_k`` and ``w`` the error from using measured rather than true
angles in ``u``. The paper treats ``a_k - a_ref`` as white with variance
``2 sigma_toa^2``; successive differences share one TOA, so that noise is
correlated (lag-one correlation -1/2) and the white model both misweights
and throws away what the shared TOAs say. Here the reference TOA's noise is a
state (``toa_noise_m``): before each update the new TOA's noise is appended,
after it the old one is dropped. That is exact for this linear model and
costs one more row in a 5 x 5 filter.

The second-order term of the range change, ``-T^2 |v_perp|^2 / (2 r)`` (about
0.3 m per second at the paper's geometry, comparable to the angle noise), is
added back once a range estimate exists.

Step 2 turns the velocity into a range, ``r = (vx cos B - vy sin B) /
(Bdot cos E)``, and gives the pseudo-measurement ``(r, B, E)`` with its full
covariance by first-order (Jacobian) propagation of the joint errors of the
velocity estimate and the measured ``B``, ``E``, ``Bdot``. The velocity error
is itself correlated with this epoch's ``B`` and ``E`` errors (they entered
its update through ``u``); that correlation is carried, not dropped.

The step-1 block may sit at an offset inside a larger state (after step 3's
``[p, v]``); its update then leaves the rest of the state alone (zero gain)
and carries the cross-covariance exactly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from core.angles import line_of_sight_enu
from core.linalg import symmetrized
from core.tracking.config import SPEED_OF_LIGHT_MPS, TrackerConfig

C = SPEED_OF_LIGHT_MPS

#: Largest distance of ``dTOA / Tr_hat`` from an integer for the pulse count to be trusted.
MAX_PULSE_COUNT_FRACTION = 0.25
#: Relative disagreement of ``n Tr_hat`` with the ``time_s`` interval that raises ``pulse_count_mismatch``.
MAX_INTERVAL_MISMATCH = 0.1
#: Largest relative standard deviation of a range pseudo-measurement that still updates the filter.
MAX_RANGE_FRACTION = 1.0


def kinematic_prior(config: TrackerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Prior mean ``(K,)`` and covariance ``(K, K)`` of the step-1 state (m/s, m)."""
    velocity_var = config.velocity_prior_sigma_mps**2
    toa_var = (C * config.sigma_toa_s) ** 2
    if config.period_known:
        diagonal = [velocity_var] * 3 + [toa_var]
    else:
        diagonal = [velocity_var] * 3 + [(C * config.period_prior_sigma) ** 2, toa_var]
    return np.zeros(len(diagonal)), np.diag(diagonal)


def line_of_sight_derivatives(azimuth_rad: float, elevation_rad: float):
    """Line of sight ``u`` (as :func:`core.angles.line_of_sight_enu`) and its derivatives by azimuth and
    elevation, as 3-tuples of floats (scalar arithmetic: this runs every epoch)."""
    sb, cb = math.sin(azimuth_rad), math.cos(azimuth_rad)
    se, ce = math.sin(elevation_rad), math.cos(elevation_rad)
    return (ce * sb, ce * cb, se), (ce * cb, -ce * sb, 0.0), (-se * sb, -se * cb, ce)


def count_pulses(dtoa_s: float, period_s: float, expected_range_change_m: float) -> tuple[int, float]:
    """Number of pulses between two TOAs and how far the ratio was from an integer.

    Parameters
    ----------
    dtoa_s : float
        TOA difference (s).
    period_s : float
        Current period estimate (s).
    expected_range_change_m : float
        Predicted range change over the interval (m), removed before rounding.

    Returns
    -------
    n : int
    fraction : float
        ``ratio - n``, in [-0.5, 0.5].
    """
    ratio = (dtoa_s - expected_range_change_m / C) / period_s
    n = round(ratio)
    return n, ratio - n


class ToaEpoch(NamedTuple):
    """One epoch as step 1 sees it.

    Attributes
    ----------
    dt_s : float
        ``time_s`` interval since the previous epoch (s).
    dtoa_s : float
        TOA difference to the reference TOA (s).
    azimuth_rad, elevation_rad : float
        This epoch's measured angles (the line of sight of the TOA difference).
    range_m : float or None
        Predicted range (m) for the curvature correction; None before there is a position.
    """

    dt_s: float
    dtoa_s: float
    azimuth_rad: float
    elevation_rad: float
    range_m: float | None = None


class VelocityUpdate(NamedTuple):
    """Step 1's result at one epoch.

    Attributes
    ----------
    mean : list of n floats
        Updated state, any period error folded into ``period_s``.
    cov : ndarray, shape (n, n)
        A new array; symmetric to rounding (the caller symmetrises once per step).
    period_s : float
    cross : ndarray, shape (K, 2) or None
        Covariance of the updated step-1 error with this epoch's azimuth and elevation errors (None when
        the TOA was not used).
    warnings : tuple of (str, str)
        ``pulse_count_ambiguous`` (the TOA was not used and becomes the new reference) or
        ``pulse_count_mismatch``.
    """

    mean: list
    cov: np.ndarray
    period_s: float
    cross: np.ndarray | None
    warnings: tuple


def velocity_update(mean, cov, offset: int, period_s: float, epoch: ToaEpoch,
                    config: TrackerConfig) -> VelocityUpdate:
    """Step 1 for one predicted epoch: count the pulses, then the Kalman update of the step-1 block with the
    TOA difference (exactly the Joseph form, written as a rank-one downdate), or a new TOA reference when
    the count is ambiguous.

    The update runs on the state augmented with the new TOA's noise ``b``
    (last), with the row ``h = [0, T u, (n), -1, 1]`` (``-1`` on the old TOA
    noise ``a``) and the angle-induced error as measurement noise ``r``; ``a``
    is then dropped, so ``b`` takes its place. The gain ``g`` is zero outside
    the step-1 block ``s`` (the rest ``o`` of the state is considered, not
    estimated). With ``w = P h`` and ``S = h^T P h + r``, the Joseph form
    ``(I - g h^T) P (I - g h^T)^T + r g g^T`` for that gain is, block by block,

    - ``P_ss - w_s w_s^T / S`` (the optimal update of ``s``),
    - ``P_os - w_o w_s^T / S`` (the cross-covariance follows the zero gain),
    - ``P_oo`` (unchanged),

    and ``b``'s row is ``-w var_b / S`` with variance ``var_b - var_b^2 / S``.
    In the layout after the update that is ``P' - (w u^T + u w^T - u u^T) / S``,
    ``P'`` the predicted covariance with the old TOA noise's row and column
    replaced by the new one's prior (zero, ``var_b``), ``w`` with ``w_b = var_b``
    and ``u`` equal to ``w`` on the kept step-1 components and ``b``, zero
    elsewhere. The ``ss`` block is a rank-one downdate with ``S`` larger than
    ``w_s^T P_ss^-1 w_s`` by the noise ``r + var_b > 0``, so it stays positive
    definite.

    Parameters
    ----------
    mean : list of n floats
    cov : ndarray, shape (n, n)
        Predicted state and covariance; the step-1 block is ``[offset:]``.
    offset : int
        Where the step-1 block starts (0, or 6 after step 3's ``[p, v]``).
    period_s : float
        Period estimate (s).
    epoch : ToaEpoch
    config : TrackerConfig

    Returns
    -------
    VelocityUpdate
        New arrays (the inputs are not changed).
    """
    los, d_az, d_el = line_of_sight_derivatives(epoch.azimuth_rad, epoch.elevation_rad)
    values = list(mean)
    vx, vy, vz = values[offset:offset + 3]
    ux, uy, uz = los
    radial = ux * vx + uy * vy + uz * vz
    n_pulses, fraction = count_pulses(epoch.dtoa_s, period_s, epoch.dt_s * radial)
    if not (n_pulses >= 1 and abs(fraction) <= MAX_PULSE_COUNT_FRACTION):
        values, cov = fresh_toa_reference(values, cov, config)
        return VelocityUpdate(values, cov, period_s, None, (("pulse_count_ambiguous",
            f"TOA difference {epoch.dtoa_s:.9g} s is {n_pulses + fraction:.3f} periods; TOA not used"),))
    warnings = ()
    if abs(n_pulses * period_s - epoch.dt_s) > MAX_INTERVAL_MISMATCH * epoch.dt_s:
        warnings = (("pulse_count_mismatch", f"{n_pulses} pulses of {period_s:.9g} s between TOAs, but time_s "
                                             f"advanced {epoch.dt_s:.6g} s"),)

    n = len(values)
    interval_s = n_pulses * period_s
    z = C * (epoch.dtoa_s - interval_s)
    if epoch.range_m is not None:
        perpendicular2 = max(vx * vx + vy * vy + vz * vz - radial * radial, 0.0)
        z += interval_s * interval_s * perpendicular2 / (2.0 * epoch.range_m)
    z -= interval_s * radial - values[-1]
    has_period = n - offset == 5
    if has_period:
        h = (interval_s * ux, interval_s * uy, interval_s * uz, float(n_pulses), -1.0)
        z -= n_pulses * values[offset + 3]
    else:
        h = (interval_s * ux, interval_s * uy, interval_s * uz, -1.0)

    # The angle-induced noise r: the TOA difference's sensitivity to B and E, through u, at the velocity
    # estimate and over its spread.
    (p00, p01, p02), (_, p11, p12), (_, _, p22) = cov[offset:offset + 3, offset:offset + 3].tolist()
    ax, ay = d_az[0], d_az[1]
    ex, ey, ez = d_el
    spread_az = ax * ax * p00 + 2.0 * ax * ay * p01 + ay * ay * p11
    spread_el = (ex * ex * p00 + ey * ey * p11 + ez * ez * p22
                 + 2.0 * (ex * ey * p01 + ex * ez * p02 + ey * ez * p12))
    gb = interval_s * (ax * vx + ay * vy)
    ge = interval_s * (ex * vx + ey * vy + ez * vz)
    var_b = config.sigma_azimuth_rad * config.sigma_azimuth_rad
    var_e = config.sigma_elevation_rad * config.sigma_elevation_rad
    t2 = interval_s * interval_s
    r_angles = var_b * (gb * gb + t2 * spread_az) + var_e * (ge * ge + t2 * spread_el)
    var_toa = (C * config.sigma_toa_s) ** 2

    w = cov[:, offset:].dot(h).tolist()
    innovation_var = var_toa + r_angles
    for hi, wi in zip(h, w[offset:]):
        innovation_var += hi * wi
    inverse = 1.0 / innovation_var
    w[-1] = var_toa
    u = [0.0] * offset + w[offset:]
    step = z * inverse
    for i in range(offset, n - 1):
        values[i] += w[i] * step
    values[-1] = var_toa * step
    if has_period:
        period_s = period_s + values[offset + 3] / C
        values[offset + 3] = 0.0

    new_cov = cov.copy()
    new_cov[-1] = 0.0
    new_cov[:, -1] = 0.0
    new_cov[-1, -1] = var_toa
    first = np.array((w, u))
    second = first[::-1] * inverse
    second[1] -= second[0]
    new_cov -= first.T.dot(second)
    cross = np.multiply.outer(np.array(u[offset:]) * inverse, (-gb * var_b, -ge * var_e))
    return VelocityUpdate(values, new_cov, period_s, cross, warnings)


def fresh_toa_reference(mean, cov, config: TrackerConfig):
    """Make the last component a new, independent TOA noise (the reference TOA changed unused).

    ``mean`` is a list (returned as a new list), ``cov`` an array (returned as a new array)."""
    mean = list(mean)
    cov = cov.copy()
    mean[-1] = 0.0
    cov[-1, :] = 0.0
    cov[:, -1] = 0.0
    cov[-1, -1] = (C * config.sigma_toa_s) ** 2
    return mean, cov


class NoRange(NamedTuple):
    """Why step 2 gives no range this epoch.

    Attributes
    ----------
    message : str
    near_radial : bool
        True when the azimuth rate itself is too small for its noise (the
        geometry); False when the step-1 velocity is not yet good enough.
    """

    message: str
    near_radial: bool


class RangePseudoMeasurement(NamedTuple):
    """Step 2's output at one epoch.

    The error of ``range_m`` is, to first order,
    ``d_vx e_vx + d_vy e_vy + d_azimuth n_B + d_elevation n_E + d_rate n_Bdot``
    (step-1 velocity errors and this epoch's measurement errors).

    Attributes
    ----------
    range_m : float
        Range pseudo-measurement (m), corrected for the ``1/Bdot`` bias.
    d_vx, d_vy : float
        Sensitivity to the step-1 velocity errors (s).
    d_azimuth, d_elevation : float
        Sensitivity to the azimuth and elevation errors (m/rad).
    d_rate : float
        Sensitivity to the azimuth-rate error (m s/rad).
    covariance : tuple of 6 floats
        Upper triangle of the ``(range, B, E)`` covariance:
        ``(rr, rB, rE, BB, BE, EE)`` (m^2, m rad, rad^2).
    relative_sigma : float
        Standard deviation of ``range_m`` over the range.
    """

    range_m: float
    d_vx: float
    d_vy: float
    d_azimuth: float
    d_elevation: float
    d_rate: float
    covariance: tuple
    relative_sigma: float


def range_pseudo_measurement(mean, cov, offset: int, cross, azimuth_rad: float, elevation_rad: float,
                             azimuth_rate_rad_s: float, config: TrackerConfig,
                             predicted_range_m: float | None = None):
    """Range from the horizontal tangential speed and the azimuth rate (paper 001, eq. 9).

    ``r = (vx cos B - vy sin B) Bdot / ((Bdot^2 + sigma_Bdot^2) cos E)``: the
    paper's ``V_H / (Bdot cos E)`` with ``1/Bdot`` replaced by
    ``Bdot / (Bdot^2 + sigma_Bdot^2)``, which removes the ``(sigma_Bdot /
    Bdot)^2`` relative bias of ``1/Bdot`` under noise (1.3 % at the paper's
    geometry) to second order.

    The error's Jacobian is evaluated at the predicted range when there is
    one: the azimuth rate it implies, ``V_H / (r_pred cos E)``, replaces the
    measured one. Evaluated at the measurement, the stated standard deviation
    (about ``r sigma_Bdot / Bdot``) shrinks exactly when the noise makes the
    range small, and a filter weighting by it drifts low by about twice the
    squared relative error (some 3 % at the paper's geometry); this is the
    usual remedy for converted polar measurements. The implied rate must
    itself clear the near-radial threshold: a measured rate that clears it by
    noise alone would otherwise feed a meaningless range.

    Parameters
    ----------
    mean : list of n floats
    cov : ndarray, shape (n, n)
        State after this epoch's step-1 update; the step-1 block is ``[offset:]``.
    offset : int
    cross : ndarray, shape (K, 2) or None
        Step-1 error covariance with this epoch's azimuth and elevation errors.
    azimuth_rad, elevation_rad, azimuth_rate_rad_s : float
        This epoch's measurements.
    config : TrackerConfig
    predicted_range_m : float, optional
        The position filter's predicted range (m).

    Returns
    -------
    RangePseudoMeasurement or NoRange
    """
    sigma_rate = config.sigma_azimuth_rate_rad_s
    rate = azimuth_rate_rad_s
    if abs(rate) < config.min_azimuth_rate_snr * sigma_rate:
        return NoRange(f"|azimuth rate| {abs(rate):.3g} rad/s is below {config.min_azimuth_rate_snr:g} sigma "
                       f"({sigma_rate:.3g} rad/s): near-radial motion", True)
    vx, vy = mean[offset], mean[offset + 1]
    sb, cb = math.sin(azimuth_rad), math.cos(azimuth_rad)
    ce = math.cos(elevation_rad)
    horizontal_tangential = vx * cb - vy * sb
    variance_rate = sigma_rate * sigma_rate
    range_m = horizontal_tangential * rate / ((rate * rate + variance_rate) * ce)
    if not range_m > 0.0:
        return NoRange("the estimated tangential velocity and the azimuth rate disagree in sign", False)

    at_range = range_m
    if predicted_range_m is not None and predicted_range_m > 0.0:
        at_range = predicted_range_m
        rate = horizontal_tangential / (predicted_range_m * ce)
        if abs(rate) < config.min_azimuth_rate_snr * sigma_rate:
            return NoRange(f"the predicted azimuth rate {abs(rate):.3g} rad/s is below "
                           f"{config.min_azimuth_rate_snr:g} sigma ({sigma_rate:.3g} rad/s): near-radial motion", True)
    rate2 = rate * rate + variance_rate
    scale = rate / (rate2 * ce)
    d_vx = cb * scale
    d_vy = -sb * scale
    d_azimuth = (-vx * sb - vy * cb) * scale
    d_elevation = at_range * math.tan(elevation_rad)
    d_rate = horizontal_tangential * (variance_rate - rate * rate) / (rate2 * rate2 * ce)

    (pxx, pxy), (_, pyy) = cov[offset:offset + 2, offset:offset + 2].tolist()
    var_b = config.sigma_azimuth_rad**2
    var_e = config.sigma_elevation_rad**2
    if cross is None:
        velocity_b = velocity_e = 0.0
    else:
        (cxb, cxe), (cyb, cye) = cross[:2].tolist()
        velocity_b = d_vx * cxb + d_vy * cyb
        velocity_e = d_vx * cxe + d_vy * cye
    covariance_rb = velocity_b + d_azimuth * var_b
    covariance_re = velocity_e + d_elevation * var_e
    variance = (d_vx * d_vx * pxx + 2.0 * d_vx * d_vy * pxy + d_vy * d_vy * pyy
                + 2.0 * (d_azimuth * velocity_b + d_elevation * velocity_e)
                + d_azimuth * d_azimuth * var_b + d_elevation * d_elevation * var_e + d_rate * d_rate * variance_rate)
    relative_sigma = math.sqrt(max(variance, 0.0)) / at_range
    if not relative_sigma <= MAX_RANGE_FRACTION:
        return NoRange(f"the range pseudo-measurement is too uncertain (sigma {min(relative_sigma, 99.0):.0%} "
                       "of the range)", False)
    return RangePseudoMeasurement(range_m, d_vx, d_vy, d_azimuth, d_elevation, d_rate,
                                  (variance, covariance_rb, covariance_re, var_b, 0.0, var_e), relative_sigma)


def initial_position_state(pseudo: RangePseudoMeasurement, mean, cov, cross, azimuth_rad: float,
                           elevation_rad: float, config: TrackerConfig, keep_velocity_filter: bool):
    """The tracking-stage state from the first usable range, by first-order propagation.

    Parameters
    ----------
    pseudo : RangePseudoMeasurement
    mean : list of K floats
    cov : ndarray, shape (K, K)
        Step-1 state and covariance (stage ``"velocity"``).
    cross : ndarray, shape (K, 2) or None
        Step-1 error covariance with this epoch's azimuth and elevation errors.
    azimuth_rad, elevation_rad : float
        This epoch's measured angles.
    config : TrackerConfig
    keep_velocity_filter : bool
        True (``velocity_kinematic``): the new state is ``[p, v]`` followed by
        the step-1 state, with the cross-covariance between the two.
        False (``joint_ukf``): the new state is ``[p]`` followed by the step-1
        state (which then is the joint filter's ``[v, (period_error_m), toa_noise_m]``).

    Returns
    -------
    mean : list of 6 + K or 3 + K floats
    cov : ndarray, shape matching
    """
    k = len(mean)
    errors = np.zeros((k + 3, k + 3))
    errors[:k, :k] = cov
    if cross is not None:
        errors[:k, k:k + 2] = cross
        errors[k:k + 2, :k] = cross.T
    errors[k, k] = config.sigma_azimuth_rad**2
    errors[k + 1, k + 1] = config.sigma_elevation_rad**2
    errors[k + 2, k + 2] = config.sigma_azimuth_rate_rad_s**2

    _, d_az, d_el = line_of_sight_derivatives(azimuth_rad, elevation_rad)
    los = line_of_sight_enu(azimuth_rad, elevation_rad)
    r = pseudo.range_m
    range_row = np.zeros(k + 3)
    range_row[:2] = (pseudo.d_vx, pseudo.d_vy)
    range_row[k:] = (pseudo.d_azimuth, pseudo.d_elevation, pseudo.d_rate)
    position_rows = np.outer(los, range_row)
    position_rows[:, k] += r * np.array(d_az)
    position_rows[:, k + 1] += r * np.array(d_el)
    carried = np.eye(k, k + 3)
    position = (r * los).tolist()
    if keep_velocity_filter:
        g = np.vstack((position_rows, carried[:3], carried))
        x = position + mean[:3] + mean
    else:
        g = np.vstack((position_rows, carried))
        x = position + list(mean)
    p = g @ errors @ g.T
    return x, symmetrized(p)
