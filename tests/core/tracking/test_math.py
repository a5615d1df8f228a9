"""The filters' algebra against plain (brute-force) reference implementations and finite differences: each piece
of a step that test_regression's golden vectors only see as a whole."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform

from core.angles import line_of_sight_enu, wrap_to_pi
from core.linalg import EIGENVALUE_FLOOR, cholesky_lower, lower_inverse_into, repaired_block, symmetrized
from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking import new_state, step
from core.tracking.config import SPEED_OF_LIGHT_MPS
from core.tracking.joint_ukf import joint_epoch
from core.tracking.kinematic import (RangePseudoMeasurement, ToaEpoch, initial_position_state,
                                     line_of_sight_derivatives, range_pseudo_measurement, velocity_update)
from core.tracking.motion import constant_velocity_predict, transition
from core.tracking.unscented import polar_update
from core.simulation.tracking import paper_config

C = SPEED_OF_LIGHT_MPS


def tracking_state(period_known: bool, epochs: int = 80, pseudo_range_errors: str = "correlated"):
    """A realistic joint ``velocity_kinematic`` state, and the next epoch of its track."""
    config = paper_config("velocity_kinematic", period_known, pseudo_range_errors=pseudo_range_errors)
    track = simulate_emitter(paper_001_scenario(epochs=epochs + 1), np.random.default_rng(11))
    state = new_state(config)
    for epoch in track.epochs[:-1]:
        state = step(state, epoch, config)
    assert state.initialized
    return config, state, track.epochs[-1]


def polar(points):
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    rho = np.hypot(x, y)
    return np.stack((np.sqrt(rho**2 + z**2), np.arctan2(x, y), np.arctan2(z, rho)), axis=-1)


def reference_consider_update(mean, cov, offset, errors, error_map, measured, rows):
    """Schmidt update by brute force: a 12-point unscented transform of [p, v] for ``h(p) + M G (x - mean)``
    (``G`` the regression of the step-2 errors on the state) and the rest of ``M e`` as independent noise."""
    n = 6
    p3 = cov[:n, :n]
    k = cov.shape[0] - offset
    cov_e_x = np.zeros((errors.shape[0], n))
    cov_e_x[:k] = -cov[offset:, :n]
    regression = cov_e_x @ np.linalg.inv(p3)
    chol = np.linalg.cholesky(p3)
    offsets = math.sqrt(n) * chol
    points = np.vstack((mean[:n] + offsets.T, mean[:n] - offsets.T))
    centre = polar(mean[:3])
    predicted = polar(points[:, :3]) + (points - mean[:n]) @ (error_map @ regression).T
    predicted[:, 1] = centre[1] + wrap_to_pi(predicted[:, 1] - centre[1])
    weight = 1.0 / (2 * n)
    z_mean = predicted.mean(axis=0)
    dz = predicted - z_mean
    dx = points - mean[:n]
    residual = errors - regression @ p3 @ regression.T
    s = weight * dz.T @ dz + error_map @ residual @ error_map.T
    cross_x = weight * dx.T @ dz
    cross_e = regression @ cross_x + residual @ error_map.T
    innovation = np.asarray(measured) - z_mean
    innovation[1] = wrap_to_pi(innovation[1])
    s, cross_x, cross_e, innovation = s[rows, rows], cross_x[:, rows], cross_e[:, rows], innovation[rows]
    gain = cross_x @ np.linalg.inv(s)
    x = mean.copy()
    x[:n] += gain @ innovation
    p = cov.copy()
    p[:n, :n] -= gain @ s @ gain.T
    p[:n, offset:] += gain @ cross_e[:k].T
    p[offset:, :n] = p[:n, offset:].T
    return x, p


def error_model(state, cross, pseudo, config):
    """The step-2 error covariance and its map to (range, B, E), as explicit matrices."""
    offset = 6
    k = state.mean.shape[0] - offset
    errors = np.zeros((k + 3, k + 3))
    errors[:k, :k] = state.covariance[offset:, offset:]
    errors[:k, k:k + 2] = cross
    errors[k:k + 2, :k] = cross.T
    errors[k, k] = config.sigma_azimuth_rad**2
    errors[k + 1, k + 1] = config.sigma_elevation_rad**2
    errors[k + 2, k + 2] = config.sigma_azimuth_rate_rad_s**2
    error_map = np.zeros((3, k + 3))
    if pseudo is not None:
        error_map[0, :2] = pseudo.d_vx, pseudo.d_vy
        error_map[0, k:] = pseudo.d_azimuth, pseudo.d_elevation, pseudo.d_rate
    error_map[1, k] = error_map[2, k + 1] = 1.0
    return errors, error_map


@pytest.mark.parametrize("period_known", [True, False])
@pytest.mark.parametrize("with_range", [True, False])
def test_consider_update_equals_the_brute_force_transform(period_known, with_range):
    config, state, epoch = tracking_state(period_known)
    k = state.mean.shape[0] - 6
    cross = np.random.default_rng(1).normal(scale=1e-4, size=(k, 2)) * np.sqrt(np.diag(state.covariance)[6:, None])
    pseudo = RangePseudoMeasurement(float(np.linalg.norm(state.mean[:3])) * 1.02, 450.0, -380.0, 2.0e5, 9.0e3,
                                    -6.0e7, (0.0,) * 6, 0.1) if with_range else None
    errors, error_map = error_model(state, cross, pseudo, config)
    if pseudo is not None:
        rr, rb, re = (error_map @ errors @ error_map.T)[0]
        pseudo = pseudo._replace(covariance=(rr, rb, re, errors[k, k], 0.0, errors[k + 1, k + 1]))
    measured = (pseudo.range_m if pseudo else 0.0, epoch.azimuth_rad, epoch.elevation_rad)
    rows = slice(0, 3) if with_range else slice(1, 3)
    got_mean, got_cov, _ = polar_update(state.mean.tolist(), state.covariance, 6, cross, pseudo, epoch.azimuth_rad,
                                        epoch.elevation_rad, errors[k, k], errors[k + 1, k + 1])
    want_mean, want_cov = reference_consider_update(state.mean, state.covariance, 6, errors, error_map, measured,
                                                    rows)
    scale = np.sqrt(np.diag(state.covariance))
    np.testing.assert_allclose(got_mean, want_mean, rtol=0, atol=1e-9 * scale.max())
    np.testing.assert_allclose(got_cov / np.outer(scale, scale), want_cov / np.outer(scale, scale), rtol=0,
                               atol=1e-9)


def test_uncorrelated_update_equals_filterpy_unscented_transform():
    config, state, epoch = tracking_state(True, pseudo_range_errors="independent")
    assert not state.covariance[:6, 6:].any()
    pseudo = RangePseudoMeasurement(float(np.linalg.norm(state.mean[:3])) * 0.97, 0.0, 0.0, 0.0, 0.0, 0.0,
                                    (4e6, 0.3, -0.02, 2.5e-5, 0.0, 2.5e-5), 0.01)
    got_mean, got_cov, _ = polar_update(state.mean.tolist(), state.covariance, 6, None, pseudo, epoch.azimuth_rad,
                                        epoch.elevation_rad, 2.5e-5, 2.5e-5)
    noise = np.array([[4e6, 0.3, -0.02], [0.3, 2.5e-5, 0.0], [-0.02, 0.0, 2.5e-5]])
    mean, cov = state.mean[:6], state.covariance[:6, :6]
    points = MerweScaledSigmaPoints(6, alpha=1.0, beta=0.0, kappa=0.0)
    sigmas = points.sigma_points(mean, cov)
    z_sigmas = polar(sigmas[:, :3])
    centre = polar(mean[:3])
    z_sigmas[:, 1] = centre[1] + wrap_to_pi(z_sigmas[:, 1] - centre[1])
    z_mean, s = unscented_transform(z_sigmas, points.Wm, points.Wc, noise)
    cross = (sigmas - mean).T @ np.diag(points.Wc) @ (z_sigmas - z_mean)
    gain = cross @ np.linalg.inv(s)
    innovation = np.array([pseudo.range_m, epoch.azimuth_rad, epoch.elevation_rad]) - z_mean
    innovation[1] = wrap_to_pi(innovation[1])
    assert np.all(got_cov == got_cov.T)
    np.testing.assert_allclose(got_mean[:6], mean + gain @ innovation, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(got_cov[:6, :6], cov - gain @ s @ gain.T, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(got_mean[6:], state.mean[6:])


def reference_toa_update(mean, cov, offset, n_pulses, dtoa_s, period_s, azimuth, elevation, config):
    """Textbook Kalman update of the step-1 block, on the state explicitly augmented with the new TOA noise."""
    n = mean.shape[0]
    k = n - offset
    los, d_az, d_el = (np.array(v) for v in line_of_sight_derivatives(azimuth, elevation))
    interval = n_pulses * period_s
    y = np.append(mean, 0.0)
    p = np.zeros((n + 1, n + 1))
    p[:n, :n] = cov
    p[n, n] = (C * config.sigma_toa_s) ** 2
    h = np.zeros(n + 1)
    h[offset:offset + 3] = interval * los
    if k == 5:
        h[offset + 3] = n_pulses
    h[n - 1], h[n] = -1.0, 1.0
    v = mean[offset:offset + 3]
    pv = cov[offset:offset + 3, offset:offset + 3]
    r = (config.sigma_azimuth_rad**2 * interval**2 * ((d_az @ v) ** 2 + d_az @ pv @ d_az)
         + config.sigma_elevation_rad**2 * interval**2 * ((d_el @ v) ** 2 + d_el @ pv @ d_el))
    s = h @ p @ h + r
    gain = p @ h / s
    gain[:offset] = 0.0
    y = y + gain * (C * (dtoa_s - interval) - h @ y)
    a = np.eye(n + 1) - np.outer(gain, h)
    p = a @ p @ a.T + r * np.outer(gain, gain)
    keep = [i for i in range(n + 1) if i != n - 1]
    return y[keep], p[np.ix_(keep, keep)]


@pytest.mark.parametrize("period_known", [True, False])
def test_toa_update_equals_the_augmented_textbook_filter(period_known):
    config, state, epoch = tracking_state(period_known)
    offset = 6
    dtoa = epoch.toa_s - state.toa_s
    n_pulses = round(dtoa / state.pulse_period_s)
    mean, cov, period_s, _, warnings = velocity_update(
        state.mean.tolist(), state.covariance, offset, state.pulse_period_s,
        ToaEpoch(epoch.time_s - state.time_s, dtoa, epoch.azimuth_rad, epoch.elevation_rad), config)
    assert warnings == ()
    want_mean, want_cov = reference_toa_update(state.mean, state.covariance, offset, n_pulses, dtoa,
                                               state.pulse_period_s, epoch.azimuth_rad, epoch.elevation_rad, config)
    if not period_known:
        assert period_s == state.pulse_period_s + want_mean[offset + 3] / C
        want_mean[offset + 3] = 0.0
    scale = np.sqrt(np.diag(want_cov))
    np.testing.assert_allclose(mean, want_mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cov / np.outer(scale, scale), want_cov / np.outer(scale, scale), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(mean[:offset], state.mean[:offset])
    np.testing.assert_array_equal(cov[:offset, :offset], state.covariance[:offset, :offset])


def test_range_jacobian_matches_finite_differences():
    config = paper_config("velocity_kinematic", True)
    mean = np.array([-300.0, 100.0, 2.0, 0.0])
    cov = np.diag([4.0, 4.0, 100.0, 9.0])
    azimuth, elevation, rate = 0.87, 0.05, -1.7e-3

    def range_of(vx, vy, b, e, bdot):
        got = range_pseudo_measurement(np.array([vx, vy, 2.0, 0.0]), cov, 0, None, b, e, bdot, config)
        return got.range_m

    pseudo = range_pseudo_measurement(mean, cov, 0, None, azimuth, elevation, rate, config)
    assert isinstance(pseudo, RangePseudoMeasurement)
    base = (-300.0, 100.0, azimuth, elevation, rate)
    steps = (1e-3, 1e-3, 1e-7, 1e-7, 1e-9)
    numeric = []
    for i, h in enumerate(steps):
        up = list(base)
        down = list(base)
        up[i] += h
        down[i] -= h
        numeric.append((range_of(*up) - range_of(*down)) / (2 * h))
    analytic = (pseudo.d_vx, pseudo.d_vy, pseudo.d_azimuth, pseudo.d_elevation, pseudo.d_rate)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6)
    variance = (np.array(analytic[:2]) @ cov[:2, :2] @ np.array(analytic[:2])
                + analytic[2] ** 2 * config.sigma_azimuth_rad**2 + analytic[3] ** 2 * config.sigma_elevation_rad**2
                + analytic[4] ** 2 * config.sigma_azimuth_rate_rad_s**2)
    assert pseudo.covariance[0] == pytest.approx(variance, rel=1e-12)


def test_debiased_range_is_unbiased_to_second_order_where_the_plain_one_is_not():
    config = paper_config("velocity_kinematic", True)
    rng = np.random.default_rng(5)
    true_rate = 1.7e-3
    tangential = -268.0
    rates = true_rate + config.sigma_azimuth_rate_rad_s * rng.standard_normal(400_000)
    true_range = tangential / (-true_rate)
    plain = tangential / (-rates)
    debiased = plain * rates**2 / (rates**2 + config.sigma_azimuth_rate_rad_s**2)
    standard_error = plain.std() / math.sqrt(plain.size)
    relative_bias_plain = (plain.mean() - true_range) / true_range
    assert relative_bias_plain > 0.01
    assert abs(debiased.mean() - true_range) < 4 * standard_error


def test_prediction_over_a_gap_equals_the_steps_it_skips():
    mean = [1e5, 8e4, 5e3, -300.0, 100.0, 2.0, -299.0, 99.0, 2.5, 0.0]
    base = np.diag([1e6, 1e6, 1e6, 25.0, 25.0, 25.0, 30.0, 30.0, 30.0, 9.0])
    base[3, 6] = base[6, 3] = 20.0
    once = constant_velocity_predict(mean, base, 5.0, 0.04, (3, 6), True)
    stepped = (mean, base)
    for _ in range(5):
        stepped = constant_velocity_predict(*stepped, 1.0, 0.04, (3, 6), True)
    np.testing.assert_allclose(once[0], stepped[0], rtol=1e-15, atol=1e-9)
    np.testing.assert_allclose(once[1], stepped[1], rtol=1e-12, atol=1e-9)
    phi, noise = transition(10, (3, 6), True, 5.0, 0.04)
    assert not noise.flags.writeable and not phi.flags.writeable
    assert np.linalg.eigvalsh(noise).min() > -1e-12


@pytest.mark.parametrize("azimuth, elevation", [(0.0, 0.0), (0.87, 0.05), (-2.9, -0.4), (3.1, 1.2)])
def test_line_of_sight_derivatives_agree_with_the_angles_module(azimuth, elevation):
    los, d_az, d_el = line_of_sight_derivatives(azimuth, elevation)
    np.testing.assert_allclose(los, line_of_sight_enu(azimuth, elevation), rtol=0, atol=1e-15)
    h = 1e-6
    numeric_az = (line_of_sight_enu(azimuth + h, elevation) - line_of_sight_enu(azimuth - h, elevation)) / (2 * h)
    numeric_el = (line_of_sight_enu(azimuth, elevation + h) - line_of_sight_enu(azimuth, elevation - h)) / (2 * h)
    np.testing.assert_allclose(d_az, numeric_az, atol=1e-9)
    np.testing.assert_allclose(d_el, numeric_el, atol=1e-9)


def joint_measurement(points, n_pulses, interval_s, has_period_error):
    """``(B, E, c dTOA - n Tr_hat, Bdot)`` of joint states ``(m, F)``, written out from the model."""
    x, y, z, vx, vy = points[:, :5].T
    rho = np.hypot(x, y)
    previous = points[:, :3] - interval_s * points[:, 3:6]
    change = np.linalg.norm(points[:, :3], axis=1) - np.linalg.norm(previous, axis=1) - points[:, -1]
    if has_period_error:
        change = change + n_pulses * points[:, 6]
    return np.stack((np.arctan2(x, y), np.arctan2(z, rho), change, (y * vx - x * vy) / rho**2), axis=1)


def reference_joint_update(mean, cov, measured, n_pulses, period_s, use_toa, config):
    """The joint UKF's update by brute force: filterpy's Merwe points (alpha 1, beta 0, kappa 0: 2F points of
    weight 1/2F) and unscented transform, the new TOA noise ``b`` as an explicit state (it enters the TOA row
    additively), Gaussian conditioning with an explicit inverse, then ``b`` in the old TOA noise's place."""
    f = mean.shape[0]
    rows = [0, 1, 2, 3] if use_toa else [0, 1, 3]
    var_toa = (C * config.sigma_toa_s) ** 2
    points = MerweScaledSigmaPoints(f, alpha=1.0, beta=0.0, kappa=0.0)
    sigmas = points.sigma_points(mean, cov)
    z_sigmas = joint_measurement(sigmas, n_pulses, n_pulses * period_s, f == 8)[:, rows]
    centre = joint_measurement(mean[None], n_pulses, n_pulses * period_s, f == 8)[0, rows]
    z_sigmas[:, 0] = centre[0] + wrap_to_pi(z_sigmas[:, 0] - centre[0])
    noise = np.diag([config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2, var_toa,
                     config.sigma_azimuth_rate_rad_s**2])[np.ix_(rows, rows)]
    z_mean, s = unscented_transform(z_sigmas, points.Wm, points.Wc, noise)
    joint = np.zeros((f + 1, f + 1))
    joint[:f, :f] = cov
    joint[f, f] = var_toa
    cross = np.zeros((f + 1, len(rows)))
    cross[:f] = (sigmas - mean).T @ np.diag(points.Wc) @ (z_sigmas - z_mean)
    if use_toa:
        cross[f, 2] = var_toa
    innovation = np.asarray(measured)[rows] - z_mean
    innovation[0] = wrap_to_pi(innovation[0])
    gain = cross @ np.linalg.inv(s)
    x = np.append(mean, 0.0) + gain @ innovation
    p = joint - gain @ s @ gain.T
    keep = list(range(f - 1)) + [f]
    x, p = x[keep], p[np.ix_(keep, keep)]
    nis = innovation @ np.linalg.inv(s) @ innovation
    return x, p, nis, np.linalg.slogdet(s)[1]


@pytest.mark.parametrize("period_known", [True, False])
@pytest.mark.parametrize("use_toa", [True, False])
def test_joint_epoch_is_the_prediction_then_the_brute_force_transform(period_known, use_toa):
    config = paper_config("joint_ukf", period_known, joint_initial_range="kinematic")
    track = simulate_emitter(paper_001_scenario(epochs=61), np.random.default_rng(11))
    state = new_state(config)
    for epoch in track.epochs[:-1]:
        state = step(state, epoch, config)
    assert state.stage == "tracking"
    epoch = track.epochs[-1]
    dt = epoch.time_s - state.time_s
    mean, cov = constant_velocity_predict(state.mean.tolist(), state.covariance, dt, config.accel_sigma_mps2**2,
                                          (3,), True)
    dtoa = epoch.toa_s - state.toa_s
    n_pulses = round(dtoa / state.pulse_period_s)
    measured = (epoch.azimuth_rad, epoch.elevation_rad, C * (dtoa - n_pulses * state.pulse_period_s),
                epoch.azimuth_rate_rad_s)
    got = joint_epoch(state.mean.tolist(), state.covariance, state.pulse_period_s, dt, dtoa, epoch.azimuth_rad,
                      epoch.elevation_rad, epoch.azimuth_rate_rad_s, config, (n_pulses, use_toa, ()), False)
    got_mean, got_cov = got.mean, got.cov
    want_mean, want_cov, want_nis, want_log_det = reference_joint_update(np.array(mean), cov, measured, n_pulses,
                                                                         state.pulse_period_s, use_toa, config)
    if not use_toa:
        want_mean[-1] = 0.0
        want_cov[-1] = want_cov[:, -1] = 0.0
        want_cov[-1, -1] = (C * config.sigma_toa_s) ** 2
    scale = np.sqrt(np.diag(want_cov))
    np.testing.assert_allclose(got_mean, want_mean, rtol=0, atol=1e-9 * scale.max())
    np.testing.assert_allclose(got_cov / np.outer(scale, scale), want_cov / np.outer(scale, scale), rtol=0,
                               atol=1e-9)
    assert got.log_likelihood == pytest.approx(-0.5 * (want_nis + want_log_det), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("size", [1, 2, 3, 4, 5, 8])
def test_cholesky_and_triangular_inverse_are_numpys_and_refuse_an_indefinite_or_nan_matrix(size):
    rng = np.random.default_rng(size)
    a = rng.normal(size=(size, size))
    scale = np.logspace(0, 6, size)
    matrix = (a @ a.T + np.eye(size)) * np.outer(scale, scale)
    got = cholesky_lower(matrix)
    np.testing.assert_array_equal(got, np.tril(got))
    np.testing.assert_allclose(got / scale[:, None], np.linalg.cholesky(matrix) / scale[:, None], rtol=0, atol=1e-12)
    inverse = np.full((size, size), np.nan)
    lower_inverse_into(got, inverse)
    np.testing.assert_array_equal(inverse, np.tril(inverse))
    np.testing.assert_allclose(inverse * scale[None, :], np.linalg.inv(got) * scale[None, :], rtol=0, atol=1e-12)
    indefinite = matrix.copy()
    indefinite[-1, -1] = -1.0
    assert cholesky_lower(indefinite) is None
    poisoned = matrix.copy()
    poisoned[-1, 0] = poisoned[0, -1] = math.nan
    assert size == 1 or cholesky_lower(poisoned) is None


def test_repaired_block_floors_the_correlation_eigenvalues_of_that_block_only():
    """Brute force: the block's correlation matrix with its eigenvalues floored at EIGENVALUE_FLOOR times the
    largest (by numpy's eigh), scaled back; the rest of the matrix follows its rows' new scale."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(9, 9)) * np.logspace(0, 4, 9)
    cov = a @ a.T
    cov[3, 4] = cov[4, 3] = 2.0 * math.sqrt(cov[3, 3] * cov[4, 4])
    assert np.linalg.eigvalsh(cov[:6, :6]).min() < 0
    got, repaired = repaired_block(cov, 6)
    assert repaired
    scale = np.sqrt(np.diag(cov[:6, :6]))
    values, vectors = np.linalg.eigh(cov[:6, :6] / np.outer(scale, scale))
    fixed = (vectors * np.maximum(values, EIGENVALUE_FLOOR * values[-1])) @ vectors.T * np.outer(scale, scale)
    np.testing.assert_allclose(got[:6, :6], fixed, rtol=1e-9, atol=1e-12 * cov.max())
    new_scale = np.sqrt(np.diag(got[:6, :6]))
    np.testing.assert_allclose(got[:6, 6:], cov[:6, 6:] * (new_scale / scale)[:, None], rtol=1e-12)
    np.testing.assert_array_equal(got[6:, 6:], cov[6:, 6:])
    np.testing.assert_array_equal(got[6:, :6], got[:6, 6:].T)
    np.linalg.cholesky(got[:6, :6])
    same, repaired = repaired_block(got, 6)
    assert same is got and not repaired
    np.testing.assert_array_equal(symmetrized(cov + np.triu(cov, 1)), cov + 0.5 * (np.triu(cov, 1) + np.tril(cov, -1)))


def test_initial_position_state_is_the_first_order_propagation_by_finite_differences():
    """The tracking state from the first range: ``p = r(v, B, E, Bdot) u(B, E)`` with the step-1 state carried,
    its covariance ``G E G^T`` with ``G`` the Jacobian, here by central differences of that map."""
    config = paper_config("velocity_kinematic", True)
    mean = [-300.0, 100.0, 2.0, 0.0]
    rng = np.random.default_rng(8)
    a = rng.normal(size=(4, 4)) * (2.0, 2.0, 10.0, 3.0)
    cov = a @ a.T
    cross = rng.normal(scale=1e-3, size=(4, 2))
    azimuth, elevation, rate = 0.87, 0.05, -1.7e-3
    pseudo = range_pseudo_measurement(mean, cov, 0, cross, azimuth, elevation, rate, config)
    assert isinstance(pseudo, RangePseudoMeasurement)
    got_mean, got_cov = initial_position_state(pseudo, mean, cov, cross, azimuth, elevation, config, True)

    def position(inputs):
        vx, vy, vz, toa, b, e, bdot = inputs
        r = range_pseudo_measurement([vx, vy, vz, toa], cov, 0, cross, b, e, bdot, config).range_m
        return r * np.array(line_of_sight_enu(b, e))

    base = np.array(mean + [azimuth, elevation, rate])
    steps = np.array([1e-2, 1e-2, 1e-2, 1e-2, 1e-6, 1e-6, 1e-8])
    jacobian = np.zeros((13, 7))
    for i, h in enumerate(steps):
        up, down = base.copy(), base.copy()
        up[i] += h
        down[i] -= h
        jacobian[:3, i] = (position(up) - position(down)) / (2 * h)
    jacobian[3:6, :3] = np.eye(3)
    jacobian[6:10, :4] = np.eye(4)
    errors = np.zeros((7, 7))
    errors[:4, :4] = cov
    errors[:4, 4:6] = cross
    errors[4:6, :4] = cross.T
    errors[4:, 4:] = np.diag([config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2,
                              config.sigma_azimuth_rate_rad_s**2])
    want_cov = (jacobian @ errors @ jacobian.T)[:10, :10]
    np.testing.assert_allclose(got_mean, list(position(base)) + mean[:3] + mean, rtol=1e-13)
    scale = np.sqrt(np.diag(want_cov))
    np.testing.assert_allclose(got_cov / np.outer(scale, scale), want_cov / np.outer(scale, scale), atol=1e-9)
