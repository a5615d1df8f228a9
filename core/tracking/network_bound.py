"""Posterior Cramer-Rao bound of the network tracker's model (Tichavsky, Muravchik and Nehorai 1998).

State ``[east_m, north_m, up_m, east_mps, north_mps, up_mps]`` in the common ENU frame, constant velocity with
white acceleration of power spectral density ``accel_sigma_mps2**2`` (the exact discretisation,
:func:`core.tracking.motion.transition`), reports at any times from any stations. Each report's information
is ``E[H^T W H]`` with ``H`` the Jacobian of :func:`core.measurements.predict` (the one measurement model) at
the true position and ``W`` its noise weights; a report's TOAs share an unknown emission time, eliminated
exactly: their weights become ``W - W 1 1^T W / (1^T W 1)`` (the information of the TOA differences, or of
the TOAs with the emission time marginalised; a lone TOA gives none). The recursion is
:func:`core.tracking.bound.pcrb_recursion` (``J_k = (F J_(k-1)^-1 F^T + Q)^-1 + E[H^T W H]``, computed
without inverting ``J`` or ``Q``); ``E[.]`` is the mean over the truths given.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from core.measurements import SPEED_OF_LIGHT_MPS, TOA, predict
from core.tracking.bound import PosteriorBound, information_predict, invert_information, pcrb_recursion
from core.tracking.motion import transition
from core.tracking.network_kernel import STATE_SIZE


def report_information(report, positions_enu_m) -> np.ndarray:
    """Fisher information ``(..., 6, 6)`` of one report's measurements about the state, at true positions.

    Parameters
    ----------
    report : core.tracking.network.Report
        Its stations, rotations, kinds and sigmas (its values are not used).
    positions_enu_m : ndarray, shape (..., 3)
        True emitter positions (one per truth).

    Returns
    -------
    ndarray, shape (..., 6, 6)
        Only the position block is non-zero.
    """
    positions = np.asarray(positions_enu_m, dtype=float)
    _, jacobian = predict(positions, np.zeros(positions.shape[:-1]), report.stations_enu_m, report.rotations,
                          report.kinds)
    h = jacobian[..., :3]
    is_toa = report.kinds == TOA
    scale = np.where(is_toa, SPEED_OF_LIGHT_MPS, 1.0)
    weights = 1.0 / (report.sigmas * scale) ** 2
    weight_matrix = np.diag(np.where(is_toa, 0.0, weights))
    toa_weights = np.where(is_toa, weights, 0.0)
    if np.count_nonzero(is_toa) >= 2:
        weight_matrix = weight_matrix + np.diag(toa_weights) - np.outer(toa_weights, toa_weights) / toa_weights.sum()
    out = np.zeros(positions.shape[:-1] + (STATE_SIZE, STATE_SIZE))
    out[..., :3, :3] = np.swapaxes(h, -1, -2) @ weight_matrix @ h
    return out


def network_prior_information(velocity_prior_sigma_mps: float,
                              vertical_velocity_prior_sigma_mps: float | None = None) -> np.ndarray:
    """The tracker's start as information ``(6, 6)``: position diffuse, each horizontal velocity component
    ``velocity_prior_sigma_mps``, the vertical one ``vertical_velocity_prior_sigma_mps`` (default the same)."""
    vertical = velocity_prior_sigma_mps if vertical_velocity_prior_sigma_mps is None else \
        vertical_velocity_prior_sigma_mps
    return np.diag([0.0] * 3 + [velocity_prior_sigma_mps ** -2] * 2 + [vertical ** -2])


def network_pcrb(states_enu, reports: Sequence, accel_sigma_mps2: float, velocity_prior_sigma_mps: float,
                 times_s=None, each_truth: bool = False, vertical_accel_sigma_mps2: float | None = None,
                 vertical_velocity_prior_sigma_mps: float | None = None) -> PosteriorBound:
    """The PCRB of the network model along truths, after each report (or at given times).

    Parameters
    ----------
    states_enu : ndarray, shape (R, K, 6) or (K, 6)
        True state at each report's time, ``R`` truths (the expectation is their mean).
    reports : sequence of Report, length K
        In time order (their geometry and sigmas; values unused).
    accel_sigma_mps2 : float
        White-acceleration intensity of the model.
    velocity_prior_sigma_mps : float
        The prior on velocity at the first report (position diffuse: the tracker's start).
    times_s : ndarray, shape (E,), optional
        Report the bound at these times instead (each from the last report at or before it, predicted;
        a time before the first report: unobserved).
    each_truth : bool
        One bound per truth instead (fields gain a leading truth axis): the expectation over that one
        trajectory. Where the truths' geometries differ by more than the measurement noise, the PCRB's mean
        information holds what no single run has and is not attainable; the RMS of the per-truth bounds is
        then the figure filters approach (it is not itself a bound: ``E[J^-1] >= E[J]^-1``).
    vertical_accel_sigma_mps2, vertical_velocity_prior_sigma_mps : float, optional
        The up axis's acceleration intensity and start sigma when they differ from the horizontal ones (as
        :class:`core.tracking.network.NetworkConfig`).

    Returns
    -------
    PosteriorBound
        Fields per report ``(K, ...)``, or per time ``(E, ...)``; the position RMSE is inf while the
        position is not determined.
    """
    states = np.asarray(states_enu, dtype=float)
    if states.ndim == 2:
        states = states[None]
    report_times = np.array([r.time_s for r in reports], dtype=float)
    measurement = np.stack([report_information(r, states[:, k, :3]) for k, r in enumerate(reports)], axis=1)
    if not each_truth:
        measurement = measurement.mean(axis=0)
    q = accel_sigma_mps2 ** 2
    scale = np.ones(STATE_SIZE)
    if vertical_accel_sigma_mps2 is not None:
        scale[[2, 5]] = vertical_accel_sigma_mps2 / accel_sigma_mps2
    scale = np.outer(scale, scale)
    pairs = [transition(STATE_SIZE, (3,), True, float(dt), q) for dt in np.diff(report_times)]
    transitions = np.array([f for f, _ in pairs]).reshape(-1, STATE_SIZE, STATE_SIZE)
    noises = np.array([n * scale for _, n in pairs]).reshape(-1, STATE_SIZE, STATE_SIZE)
    information = pcrb_recursion(network_prior_information(velocity_prior_sigma_mps,
                                                           vertical_velocity_prior_sigma_mps),
                                 transitions, noises, measurement)
    if times_s is not None:
        times = np.asarray(times_s, dtype=float)
        last = np.searchsorted(report_times, times, side="right") - 1
        at_times = np.zeros(information.shape[:-3] + (times.size, STATE_SIZE, STATE_SIZE))
        for j, (t, k) in enumerate(zip(times.tolist(), last.tolist())):
            if k < 0:
                continue
            phi, noise = transition(STATE_SIZE, (3,), True, t - report_times[k], q)
            at_times[..., j, :, :] = information_predict(information[..., k, :, :], phi, noise * scale)
        information = at_times
    covariance = invert_information(information)
    position = np.trace(covariance[..., :3, :3], axis1=-2, axis2=-1)
    velocity = np.trace(covariance[..., 3:, 3:], axis1=-2, axis2=-1)
    return PosteriorBound(information, covariance, np.where(np.isnan(position), np.inf, np.sqrt(position)),
                          np.where(np.isnan(velocity), np.inf, np.sqrt(velocity)))
