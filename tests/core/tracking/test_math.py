"""The filters' algebra against plain reference implementations and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform

from core.angles import line_of_sight_enu, wrap_to_pi
from core.simulation.emitter import paper_001_scenario, simulate_emitter
from core.tracking import new_state, step
from core.tracking.config import SPEED_OF_LIGHT_MPS
from core.tracking.kinematic import (RangePseudoMeasurement, kinematic_update, line_of_sight_derivatives,
                                     range_pseudo_measurement)
from core.tracking.unscented import constant_velocity_predict, polar_update, transition
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
    los, d_az, d_el = line_of_sight_derivatives(epoch.azimuth_rad, epoch.elevation_rad)
    mean, cov, period_s, _ = kinematic_update(state.mean.tolist(), state.covariance, offset, n_pulses, dtoa,
                                              state.pulse_period_s, los, d_az, d_el, None, config)
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


@pytest.mark.parametrize("period_known", [True, False])
@pytest.mark.parametrize("pseudo_range_errors", ["correlated", "independent"])
def test_the_fused_tracking_step_equals_steps_1_2_3_one_after_another(period_known, pseudo_range_errors):
    """velocity_kinematic's tracking step folds step 1's covariance change into step 3's; doing the steps
    with the general functions, each forming its covariance, gives the same state to rounding."""
    config, state, epoch = tracking_state(period_known, pseudo_range_errors=pseudo_range_errors)
    fused = step(state, epoch, config)
    correlated = pseudo_range_errors == "correlated"
    dt = epoch.time_s - state.time_s
    q = config.accel_sigma_mps2**2
    blocks = ((3, 6), True) if correlated else ((3,), True, 6)
    mean, cov = constant_velocity_predict(state.mean.tolist(), state.covariance, dt, q, *blocks)
    range_m = float(np.linalg.norm(mean[:3]))
    dtoa = epoch.toa_s - state.toa_s
    los, d_az, d_el = line_of_sight_derivatives(epoch.azimuth_rad, epoch.elevation_rad)
    mean, cov, period_s, cross = kinematic_update(mean, cov, 6, round(dtoa / state.pulse_period_s), dtoa,
                                                  state.pulse_period_s, los, d_az, d_el, range_m, config)
    pseudo = range_pseudo_measurement(mean, cov, 6, cross, epoch.azimuth_rad, epoch.elevation_rad,
                                      epoch.azimuth_rate_rad_s, config, range_m)
    assert isinstance(pseudo, RangePseudoMeasurement)
    mean, cov, _ = polar_update(mean, cov, 6, cross, pseudo, epoch.azimuth_rad, epoch.elevation_rad,
                                config.sigma_azimuth_rad**2, config.sigma_elevation_rad**2)
    if not correlated:
        cov[:6, 6:] = 0.0
        cov[6:, :6] = 0.0
    scale = np.sqrt(np.diag(cov))
    assert fused.pulse_period_s == pytest.approx(period_s, rel=1e-15)
    assert fused.last_range_measurement_m == pytest.approx(pseudo.range_m, rel=1e-13)
    np.testing.assert_allclose(fused.mean, mean, rtol=0, atol=1e-12 * (np.abs(mean).max()))
    np.testing.assert_allclose(fused.covariance / np.outer(scale, scale), cov / np.outer(scale, scale), rtol=0,
                               atol=1e-12)
    assert np.all(fused.covariance == fused.covariance.T)


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
