"""An oracle for the session filters: the exact batch posterior of a whole simulated track.

Not a filter and not a test: evaluation tooling (``report_figures oracle``). Given every report up to
``k``, :func:`batch_map` maximises the joint posterior density of the session model over all the states
at once, ``[p_0, v_0, ..., p_k, v_k, b, (pe)]`` (the layout of :mod:`core.tracking.bound`, ``b`` the
emission offset, ``pe`` the period error per pulse when the period is unknown, ``b_j = b + n_j pe``):

``sum_j |R^-1/2 (z_j - h(x_j, b_j))|^2 + sum_j |Q^-1/2 (x_(j+1) - F x_j)|^2 + |v_0 / sigma_v|^2
+ (pe / (c sigma_Tr))^2``

by Gauss-Newton on the sparse normal equations: no linearisation of the motion, each report's range
from its own state (the exact TOA model).

The joint mode is not the oracle: with the range free it runs to short ranges at high process noise
(q = 2 m/s^2, started at the truth: 5 of 8 runs ended within 3 m of the observer), because a smaller
copy of the trajectory needs smaller accelerations, while the volume of trajectories the angles allow,
which grows with the range, does not enter a mode. So :func:`offset_marginal` holds ``b`` (given the
TOA differences, the first range) on a grid, takes the conditional mode and ``log p(b | z)`` by
Laplace's method (equal, to 0.05 in the log, to an extended Kalman filter's prediction-error
likelihood given ``b`` on one run at q = 2), and returns the posterior mean over ``b``: the MMSE
estimate of ``x_k`` with everything the reports hold, up to the Laplace approximation given ``b``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
import scipy.sparse.linalg as sparse_linalg
from scipy import sparse

from core.angles import wrap_to_pi
from core.measurements import Kind, azimuth_rate, predict
from core.tracking.bound import measurement_jacobian, session_transition
from core.tracking.config import SPEED_OF_LIGHT_MPS as C
from core.tracking.config import TrackerConfig

_KINDS = np.array([Kind.AZIMUTH, Kind.ELEVATION, Kind.TOA])
#: Standard deviation of the prior that holds the offset (m): far below anything the reports resolve.
HELD_SIGMA_M = 1e-3


class BatchMap(NamedTuple):
    """The MAP estimate over reports ``0..k``.

    Attributes
    ----------
    states_enu : ndarray, shape (k + 1, 6)
        ``[p (m), v (m/s)]`` at each report.
    last_covariance : ndarray, shape (6, 6)
        Laplace covariance of the last state.
    iterations : int
    converged : bool
    log_marginal : float
        With the offset held, ``log p(b | z)`` up to a constant, by Laplace's method:
        ``-(cost + log det H) / 2`` at the optimum, ``H`` the Gauss-Newton Hessian of the other variables.
    """

    states_enu: np.ndarray
    last_covariance: np.ndarray
    iterations: int
    converged: bool
    log_marginal: float


def measured(track, config: TrackerConfig) -> tuple[np.ndarray, np.ndarray]:
    """The reports as ``(azimuth, elevation, azimuth rate, c (TOA_j - TOA_0) - c n_j Tr_hat)`` ``(K, 4)``
    and the pulse counts ``n_j`` since the first report ``(K,)`` (the true ones)."""
    pulses = track.schedule_index * config.pulses_per_observation
    values = np.array([[e.azimuth_rad, e.elevation_rad, e.azimuth_rate_rad_s, e.toa_s] for e in track.epochs])
    values[:, 3] = C * (values[:, 3] - values[0, 3]) - C * pulses * config.period_s
    return values, pulses.astype(float)


def _model(states, b, pe, pulses, config):
    """Predicted reports ``(K, 4)`` and their Jacobian ``(K, 4, 8)`` w.r.t. ``(p, v, b, pe)``."""
    k = states.shape[0]
    origin = np.zeros((k, 3, 3))
    rotations = np.broadcast_to(np.eye(3), (k, 3, 3, 3))
    offsets = b + pulses * pe
    angles_range, _ = predict(states[:, :3], offsets, origin, rotations, np.broadcast_to(_KINDS, (k, 3)))
    rate, _ = azimuth_rate(states[:, :3], states[:, 3:6])
    values = np.column_stack([angles_range[:, 0], angles_range[:, 1], rate, angles_range[:, 2]])
    jacobian = np.zeros((k, 4, 8))
    jacobian[:, :, :7] = measurement_jacobian(states, replace(config, period_known=True))
    jacobian[:, 3, 7] = pulses
    return values, jacobian


def batch_map(track, config: TrackerConfig, last: int, start=None, offset_m: float | None = None,
              max_iterations: int = 50) -> BatchMap:
    """The MAP estimate of the states at reports ``0..last`` of ``track`` (see the module docstring).

    Parameters
    ----------
    track : core.simulation.emitter.EmitterTrack
    config : TrackerConfig
        Noise sigmas, acceleration noise, period and priors (the filters').
    last : int
        Index of the last report used.
    start : ndarray, shape (last + 1, 6), optional
        Starting states; the truth by default.
    offset_m : float, optional
        Hold ``b`` there (the range given the TOA differences): the conditional MAP and its
        :attr:`BatchMap.log_marginal`.
    max_iterations : int

    Returns
    -------
    BatchMap
    """
    values, pulses = measured(track, config)
    values, pulses = values[:last + 1], pulses[:last + 1]
    k = last + 1
    free_period = not config.period_known
    n_state = 6 * k
    n_var = n_state + 1 + int(free_period)
    transition, noise = session_transition(config, float(np.diff(track.emission_times_s)[0]), 0)
    whitening = np.linalg.inv(np.linalg.cholesky(noise[:6, :6]))
    process_next, process_this = whitening, -whitening @ transition[:6, :6]
    sigmas = np.array([config.sigma_azimuth_rad, config.sigma_elevation_rad, config.sigma_azimuth_rate_rad_s,
                       C * config.sigma_toa_s])
    velocity_sigma = config.velocity_prior_sigma_mps
    period_sigma = C * config.period_prior_sigma

    # Constant sparsity: measurement rows, process rows, prior rows.
    rows, cols = [], []
    m_rows = np.arange(4 * k).reshape(k, 4)
    m_cols = np.concatenate([6 * np.arange(k)[:, None] + np.arange(6), np.full((k, 1), n_state),
                             np.full((k, 1), n_state + 1 if free_period else n_state)], axis=1)
    width = 8 if free_period else 7
    rows.append(np.repeat(m_rows[:, :, None], width, axis=2).ravel())
    cols.append(np.repeat(m_cols[:, None, :width], 4, axis=1).ravel())
    p_rows = 4 * k + np.arange(6 * (k - 1)).reshape(k - 1, 6)
    blocks = np.concatenate([6 * np.arange(k - 1)[:, None] + np.arange(6), 6 * np.arange(1, k)[:, None]
                             + np.arange(6)], axis=1)
    rows.append(np.repeat(p_rows[:, :, None], 12, axis=2).ravel())
    cols.append(np.repeat(blocks[:, None, :], 6, axis=1).ravel())
    prior_row = 4 * k + 6 * (k - 1)
    rows.append(prior_row + np.arange(3))
    cols.append(np.arange(3, 6))
    if free_period:
        rows.append(np.array([prior_row + 3]))
        cols.append(np.array([n_state + 1]))
    held = offset_m is not None
    if held:
        rows.append(np.array([prior_row + 3 + int(free_period)]))
        cols.append(np.array([n_state]))
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    process_values = np.concatenate([process_this, process_next], axis=1)

    def residuals_and_jacobian(theta):
        states = theta[:n_state].reshape(k, 6)
        b = theta[n_state]
        pe = theta[n_state + 1] if free_period else 0.0
        predicted, jac = _model(states, b, pe, pulses, config)
        error = values - predicted
        error[:, :2] = wrap_to_pi(error[:, :2])
        meas_res = (error / sigmas).ravel()
        meas_jac = (jac[:, :, :width] / sigmas[:, None])
        proc_res = (states[1:] @ process_next.T + states[:-1] @ process_this.T).ravel()
        prior_res = [-states[0, 3:6] / velocity_sigma]
        prior_jac = [np.full(3, 1.0 / velocity_sigma)]
        if free_period:
            prior_res.append([-pe / period_sigma])
            prior_jac.append([1.0 / period_sigma])
        if held:
            prior_res.append([(offset_m - b) / HELD_SIGMA_M])
            prior_jac.append([1.0 / HELD_SIGMA_M])
        res = np.concatenate([meas_res, -proc_res] + [np.ravel(x) for x in prior_res])
        data = np.concatenate([meas_jac.ravel(), np.broadcast_to(process_values, (k - 1, 6, 12)).ravel()]
                              + [np.ravel(x) for x in prior_jac])
        # res is measured minus model (whitened); the Jacobian is of the model.
        return res, sparse.csc_matrix((data, (rows, cols)), shape=(res.size, n_var))

    truth = track.states_enu[:k] if start is None else start
    theta = np.concatenate([np.ravel(truth), [-np.linalg.norm(truth[0, :3]) if offset_m is None else offset_m],
                            [0.0] if free_period else []])
    res, jac = residuals_and_jacobian(theta)
    cost = res @ res
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        normal = (jac.T @ jac).tocsc()
        step = sparse_linalg.spsolve(normal, jac.T @ res)
        for _ in range(20):
            trial = theta + step
            trial_res, trial_jac = residuals_and_jacobian(trial)
            trial_cost = trial_res @ trial_res
            if trial_cost <= cost:
                break
            step = 0.5 * step
        else:
            break
        decrease = cost - trial_cost
        theta, res, jac, cost = trial, trial_res, trial_jac, trial_cost
        if decrease <= 1e-10 * max(cost, 1.0):
            converged = True
            break
    normal = (jac.T @ jac).tocsc()
    unit = np.zeros((n_var, 6))
    unit[n_state - 6:n_state] = np.eye(6)
    factor = sparse_linalg.splu(normal)
    last_columns = factor.solve(unit)
    log_det = float(np.sum(np.log(np.abs(factor.U.diagonal()))))
    if held:
        cost -= res[-1] ** 2
        log_det += 2.0 * np.log(HELD_SIGMA_M)
    return BatchMap(theta[:n_state].reshape(k, 6), last_columns[n_state - 6:n_state], iterations, converged,
                    -0.5 * (cost + log_det))


def offset_marginal(track, config: TrackerConfig, last: int, points: int = 41) -> tuple[np.ndarray, np.ndarray,
                                                                                      np.ndarray]:
    """The MMSE estimate of the state at report ``last`` over a grid of the offset ``b``.

    For each first range ``r_0`` of a grid, ``b = -r_0``: the conditional MAP given ``b`` (started at the
    truth moved along each line of sight by the change of ``r_0``) and ``log p(b | z)`` by Laplace's method;
    the estimate is the mean of the conditional ones under those weights times the filters' prior of the
    first range (log-uniform over ``config.range_min_m .. range_max_m``, that of the range mixture), its
    covariance that of the sum. The grid is first 0.3 to 2.7 times the true first range
    (geometric), then, while it is coarser than a third of the posterior's standard deviation of ``r_0``,
    +- 6 of those (at least 2 steps of the last grid) around the posterior mean.

    Parameters
    ----------
    track, config, last
        As :func:`batch_map`.
    points : int
        Grid size.

    Returns
    -------
    mean : ndarray, shape (6,)
    covariance : ndarray, shape (6, 6)
    first_range_sigma_m : float
        Posterior standard deviation of ``r_0`` on the last grid.
    """
    truth = track.states_enu[:last + 1]
    ranges = np.linalg.norm(truth[:, :3], axis=1)
    rate = np.einsum("ki,ki->k", truth[:, :3], truth[:, 3:]) / ranges
    grid = ranges[0] * np.exp(np.linspace(-1.2, 1.0, points))
    for _ in range(4):
        fits = []
        for r0 in grid:
            shift = float(r0) - ranges[0]
            scale = 1.0 + shift / ranges
            start = np.concatenate([truth[:, :3] * scale[:, None], truth[:, 3:] * scale[:, None]
                                    - truth[:, :3] * (shift * rate / ranges**2)[:, None]], axis=1)
            fits.append(batch_map(track, config, last, start, offset_m=-float(r0)))
        inside = (grid >= config.range_min_m) & (grid <= config.range_max_m)
        log_w = np.array([f.log_marginal for f in fits]) - np.log(grid) + np.log(np.gradient(grid))
        weights = np.where(inside, np.exp(log_w - log_w[inside].max()), 0.0)
        weights /= weights.sum()
        centre = float(weights @ grid)
        sigma = float(np.sqrt(weights @ (grid - centre) ** 2))
        spacing = float(np.max(np.diff(grid)))
        if spacing <= sigma / 3.0:
            break
        half = max(6.0 * sigma, 2.0 * spacing)
        grid = np.linspace(max(centre - half, 0.05 * ranges[0]), centre + half, points)
    means = np.array([f.states_enu[-1] for f in fits])
    mean = weights @ means
    spread = means - mean
    covariance = np.einsum("g,gij->ij", weights, np.array([f.last_covariance for f in fits])) + (
        spread.T * weights) @ spread
    return mean, covariance, sigma
