"""Posterior Cramer-Rao bound of the session model (Tichavsky, Muravchik and Nehorai 1998).

The model is the one the session filters assume (ALGORITHMS.md sections 6 and 10), written with the
emission offset as a state so that it is Markov:

``x = [x, y, z (m), vx, vy, vz (m/s), b (m), (pe (m))]``

- ``b = c (t_k - n_k Tr)``: ``c`` times the emission time of the reported pulse less ``n_k`` nominal
  periods (``n_k`` pulses since the first report); a constant when the period is known.
- ``pe = c (Tr_true - Tr)``, only when the period is unknown; then ``b`` grows by ``n pe`` over
  ``n`` pulses.

Motion is constant velocity with white acceleration of power spectral density ``q`` (the filters'
``accel_sigma_mps2**2``), the exact discretisation over each interval. Each report measures, with
independent Gaussian noise, the azimuth, elevation, azimuth rate and ``c TOA - c n_k Tr = b + r``.

The recursion on the information ``J`` is, for this linear-Gaussian motion,
``J_k = (F J_(k-1)^-1 F^T + Q)^-1 + E[H_k^T R^-1 H_k]``, computed as ``(I + M Q)^-1 M`` with
``M = F^-T J F^-1`` so that neither ``J`` (a diffuse prior on position and ``b``) nor ``Q`` (no noise on
``b`` and ``pe``) need be invertible. ``E[.]`` is the mean over the truths given (trajectories drawn
from the model, or one nominal trajectory).

Where it is attainable. One observer's angles and azimuth rate fix each report's line of sight, the TOA
the range differences, so one number, the first range, is left to the motion: the bound of one truth
(``each_truth``) grows with the process noise as the filters' errors do. The PCRB averages the
measurement information over the truths; once their lines of sight spread across runs by more than
the angle noise, that average holds range information that no run has (the runs together see the
emitter from several directions) and the bound falls instead. At q = 2 m/s^2 the runs' azimuths spread
by 19 to 29 mrad (standard deviation) over the last 50 reports, against 5 mrad of noise, and averaging
the first truth of seed 30000 with the second already takes the bound there from 17.1 to 3.8 km (50
truths: 1.3 km). On paper 001 (20 runs, seed 30000, the position RMS at reports 150, 175 and 200, known
period; ``report_figures oracle``):

=====  =======  =============  ==============================  =================
q      PCRB     own bounds     batch oracle (Laplace MMSE)     joint_ukf (dflt)
=====  =======  =============  ==============================  =================
0.5    6.6 km   8.2 km         7.2 km                          6.7 km
1      4.2 km   15.2 km        14.7 km                         12.2 km
2      1.3 km   26.7 km        36.2 km                         32.1 km
=====  =======  =============  ==============================  =================

The oracle (``tests/core/tracking/batch_map.py``) is the posterior mean over the first range of the
exact batch posterior of every report so far, with the filters' priors; it is no nearer the PCRB than
the filter. At q >= 1 the PCRB is not attainable; the own bounds (``AgainstBound.own_ratio``) are the
figure to compare with there. They are not a bound (``E[J^-1] >= E[J]^-1``, so their mean is above
the PCRB).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.measurements import Kind, azimuth_rate, predict
from core.tracking.config import SPEED_OF_LIGHT_MPS, TrackerConfig

C = SPEED_OF_LIGHT_MPS

#: Smallest eigenvalue of the unit-diagonal information below which the state counts as unobserved.
OBSERVABILITY_THRESHOLD = 1e-12

_KINDS = np.array([Kind.AZIMUTH, Kind.ELEVATION, Kind.TOA])


@dataclass(frozen=True)
class PosteriorBound:
    """The PCRB of a session model over a run of reports (with a leading run axis when per truth).

    Attributes
    ----------
    information : ndarray, shape (K, n, n)
        Bayesian information ``J_k`` after report ``k`` (state layout in the module docstring).
    covariance : ndarray, shape (K, n, n)
        ``J_k^-1``; NaN while ``J_k`` is singular (no position yet: the first reports).
    position_rmse_m : ndarray, shape (K,)
        ``sqrt(trace)`` of the position block: no unbiased estimator does better in RMS; inf while
        unobserved.
    velocity_rmse_mps : ndarray, shape (K,)
    """

    information: np.ndarray
    covariance: np.ndarray
    position_rmse_m: np.ndarray
    velocity_rmse_mps: np.ndarray


def information_predict(information, transition, process_noise):
    """Information of ``F x + w``, ``w ~ N(0, Q)``, from that of ``x``: ``(F J^-1 F^T + Q)^-1``.

    Parameters
    ----------
    information : ndarray, shape (..., n, n)
        May be singular (diffuse components).
    transition : ndarray, shape (..., n, n)
        Invertible.
    process_noise : ndarray, shape (..., n, n)
        May be singular (noise-free components) or zero.

    Returns
    -------
    ndarray, shape (..., n, n)
        Symmetric.
    """
    inverse = np.linalg.inv(transition)
    m = np.swapaxes(inverse, -1, -2) @ information @ inverse
    n = m.shape[-1]
    out = np.linalg.solve(np.eye(n) + m @ process_noise, m)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def pcrb_recursion(prior_information, transitions, process_noises, measurement_informations):
    """Tichavsky's recursion for linear-Gaussian motion: the information after each report.

    Parameters
    ----------
    prior_information : ndarray, shape (n, n)
        Of the state at the first report, before it.
    transitions, process_noises : ndarray, shape (K - 1, n, n)
        From report ``k`` to ``k + 1``.
    measurement_informations : ndarray, shape (..., K, n, n)
        ``E[H_k^T R^-1 H_k]``; leading axes for several recursions at once (one per truth).

    Returns
    -------
    ndarray, shape (..., K, n, n)
    """
    measurement_informations = np.asarray(measurement_informations, dtype=float)
    informations = np.empty_like(measurement_informations)
    current = np.asarray(prior_information, dtype=float) + measurement_informations[..., 0, :, :]
    informations[..., 0, :, :] = current
    for k in range(1, informations.shape[-3]):
        current = (information_predict(current, transitions[k - 1], process_noises[k - 1])
                   + measurement_informations[..., k, :, :])
        informations[..., k, :, :] = current
    return informations


def invert_information(information):
    """``J^-1`` per leading index, NaN where ``J`` is singular (scaled to unit diagonal first).

    Parameters
    ----------
    information : ndarray, shape (..., n, n)

    Returns
    -------
    ndarray, shape (..., n, n)
    """
    diagonal = np.diagonal(information, axis1=-2, axis2=-1)
    positive = np.all(diagonal > 0.0, axis=-1)
    scale = 1.0 / np.sqrt(np.where(diagonal > 0.0, diagonal, 1.0))
    unit = information * scale[..., :, None] * scale[..., None, :]
    smallest = np.linalg.eigvalsh(unit)[..., 0]
    observed = positive & (smallest > OBSERVABILITY_THRESHOLD)
    safe = np.where(observed[..., None, None], unit, np.eye(unit.shape[-1]))
    out = np.linalg.inv(safe) * scale[..., :, None] * scale[..., None, :]
    out[~observed] = np.nan
    return out


def state_size(config: TrackerConfig) -> int:
    """7 with a known period, 8 without."""
    return 7 if config.period_known else 8


def prior_information(config: TrackerConfig) -> np.ndarray:
    """The filters' prior as information ``(n, n)``: position and ``b`` diffuse, velocity
    ``velocity_prior_sigma_mps`` per component, ``pe`` ``c period_prior_sigma``."""
    diagonal = [0.0] * 3 + [config.velocity_prior_sigma_mps**-2] * 3 + [0.0]
    if not config.period_known:
        diagonal.append((C * config.period_prior_sigma) ** -2)
    return np.diag(diagonal)


def session_transition(config: TrackerConfig, dt_s: float, n_pulses: int,
                       accel_sigma_mps2: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``F`` and ``Q`` ``(n, n)`` of the session state over ``dt_s`` (``n_pulses`` pulses); the acceleration
    noise is ``config.accel_sigma_mps2`` unless ``accel_sigma_mps2`` is given."""
    n = state_size(config)
    transition = np.eye(n)
    transition[(0, 1, 2), (3, 4, 5)] = dt_s
    if n == 8:
        transition[6, 7] = n_pulses
    q = (config.accel_sigma_mps2 if accel_sigma_mps2 is None else accel_sigma_mps2) ** 2
    noise = np.zeros((n, n))
    for i in range(3):
        noise[i, i] = q * dt_s**3 / 3.0
        noise[i, i + 3] = noise[i + 3, i] = q * dt_s**2 / 2.0
        noise[i + 3, i + 3] = q * dt_s
    return transition, noise


def measurement_jacobian(states_enu, config: TrackerConfig) -> np.ndarray:
    """Jacobian ``(..., 4, n)`` of ``(azimuth, elevation, azimuth rate, b + r)`` at the true states.

    Parameters
    ----------
    states_enu : ndarray, shape (..., 6)
        ``[p (m), v (m/s)]`` in the observer's ENU.
    config : TrackerConfig
    """
    states = np.asarray(states_enu, dtype=float)
    batch = states.shape[:-1]
    n = state_size(config)
    origin = np.zeros(batch + (3, 3))
    rotations = np.broadcast_to(np.eye(3), batch + (3, 3, 3))
    _, angles_range = predict(states[..., :3], np.zeros(batch), origin, rotations,
                              np.broadcast_to(_KINDS, batch + (3,)))
    _, rate = azimuth_rate(states[..., :3], states[..., 3:6])
    jacobian = np.zeros(batch + (4, n))
    jacobian[..., 0:2, :3] = angles_range[..., 0:2, :3]
    jacobian[..., 2, :6] = rate
    jacobian[..., 3, :3] = angles_range[..., 2, :3]
    jacobian[..., 3, 6] = angles_range[..., 2, 3]
    return jacobian


def measurement_weights(config: TrackerConfig) -> np.ndarray:
    """``1 / sigma^2`` ``(4,)`` of ``(azimuth, elevation, azimuth rate, c TOA)``."""
    return 1.0 / np.array([config.sigma_azimuth_rad, config.sigma_elevation_rad, config.sigma_azimuth_rate_rad_s,
                           C * config.sigma_toa_s]) ** 2


def session_pcrb(states_enu, emission_times_s, config: TrackerConfig, accel_sigmas_mps2=None,
                 each_truth: bool = False) -> PosteriorBound:
    """The PCRB of the session model along truths drawn from it.

    With ``each_truth``, instead, the bound of each truth on its own (the expectation over that one
    trajectory; every field gains a leading run axis). The PCRB's ``E[H^T R^-1 H]`` averages the
    information over the truths' lines of sight: where those spread across runs by more than the angle
    noise (process noise of 1 m/s^2 and more on paper 001), the average holds range information that no
    single run has, as if several observers looked at once, and no estimator comes near the bound. The
    RMS over runs of the per-truth bounds is then near what estimators reach (the batch oracle of
    ``tests/core/tracking/batch_map.py`` and the filters: see the module docstring); it is not itself a
    bound (``E[J^-1] >= E[J]^-1``).

    Parameters
    ----------
    states_enu : ndarray, shape (R, K, 6) or (K, 6)
        True ``[p, v]`` at each report of ``R`` runs (or one nominal run); the expectation over the truth
        is the mean over runs.
    emission_times_s : ndarray, shape (K,)
        Emission time of each reported pulse (s); gaps allowed.
    config : TrackerConfig
        Noise sigmas, ``accel_sigma_mps2``, ``period_s``, ``period_known`` and the priors.
    accel_sigmas_mps2 : array_like, shape (K - 1,), optional
        The truth's acceleration noise over each interval (a target switching between quiet and
        manoeuvring legs), instead of ``config.accel_sigma_mps2``.
    each_truth : bool
        One bound per truth, fields of shape ``(R, K, ...)``.

    Returns
    -------
    PosteriorBound
    """
    states = np.asarray(states_enu, dtype=float)
    if states.ndim == 2:
        states = states[None]
    times = np.asarray(emission_times_s, dtype=float)
    jacobian = measurement_jacobian(states, config)
    weighted = jacobian * measurement_weights(config)[:, None]
    if each_truth:
        measurement = np.einsum("rkmi,rkmj->rkij", weighted, jacobian)
    else:
        measurement = np.einsum("rkmi,rkmj->kij", weighted, jacobian) / states.shape[0]
    steps = np.diff(times)
    if accel_sigmas_mps2 is None:
        accel_sigmas_mps2 = np.full(steps.size, config.accel_sigma_mps2)
    pairs = [session_transition(config, float(dt), int(round(dt / config.period_s)), float(a))
             for dt, a in zip(steps, accel_sigmas_mps2)]
    n = state_size(config)
    transitions = np.array([f for f, _ in pairs]).reshape(-1, n, n)
    noises = np.array([q for _, q in pairs]).reshape(-1, n, n)
    information = pcrb_recursion(prior_information(config), transitions, noises, measurement)
    covariance = invert_information(information)
    position = np.trace(covariance[..., :3, :3], axis1=-2, axis2=-1)
    velocity = np.trace(covariance[..., 3:6, 3:6], axis1=-2, axis2=-1)
    return PosteriorBound(information, covariance, np.where(np.isnan(position), np.inf, np.sqrt(position)),
                          np.where(np.isnan(velocity), np.inf, np.sqrt(velocity)))
