"""Details of ple3d, ws3d, taylor_wls, tls and ctls that the contract and paper tests do not reach."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from core.errors import InvalidInput
from core.estimators import SolveOptions, solve
from core.measurements import Kind, predict, residuals
from core.problem.frame import LocalPoint
from core.problem.build import build_problem
from core.simulation.measurements import evaluate

from core.simulation import scenarios as sc
from tests.core.estimators.test_paper000 import nees_interval


def paper_004_with_guess(guess_m, sigma_known=True):
    scene = sc.paper_004(5.0, sigma_known=sigma_known)
    measurements = scene.measurements(np.random.default_rng(1))
    return build_problem(list(scene.stations), measurements, altitude_m=0.0, initial_guess=LocalPoint(*guess_m),
                         require_sigmas=sigma_known)


def weighted_cost(problem, position_enu_m):
    s = problem.station_index
    predicted, _ = predict(np.asarray(position_enu_m)[None], np.zeros(1), problem.stations_enu_m[s][None],
                           problem.station_rotations[s][None], problem.kinds[None])
    r = residuals(problem.values, predicted[0], problem.kinds)
    return float(np.sum((r / problem.sigmas) ** 2))


@pytest.mark.parametrize(("guess", "iterate"), [((100e3, 35e3, 0.0), 0), ((30e3, -50e3, 0.0), 1)])
def test_taylor_wls_returns_the_last_good_iterate_when_it_diverges(guess, iterate):
    problem = paper_004_with_guess(guess)
    fix = solve(problem, "taylor_wls")
    assert not fix.converged and fix.iterations == iterate
    (warning,) = [w for w in fix.warnings if w.code == "not_converged"]
    assert f"diverged at iteration {iterate + 1}" in warning.message
    assert "iterate before it is returned" in warning.message
    assert weighted_cost(problem, fix.position_enu_m) <= weighted_cost(problem, np.array(guess))
    if iterate == 0:
        np.testing.assert_allclose(fix.position_enu_m, guess)


def test_taylor_wls_says_when_it_runs_out_of_iterations():
    problem = paper_004_with_guess((0.0, 0.0, 0.0))
    fix = solve(problem, "taylor_wls", SolveOptions(max_iterations=2))
    assert not fix.converged and fix.iterations == 2
    assert any(w.code == "not_converged" and "did not converge in 2 iterations" in w.message for w in fix.warnings)


def test_taylor_wls_covariance_is_the_bound_at_the_fix():
    problem = sc.paper_004(3.0).problem(np.random.default_rng(4))
    fix = solve(problem, "taylor_wls")
    assert fix.covariance_source == "information"
    assert not any(w.code == "sigma_estimated" for w in fix.warnings)
    np.testing.assert_allclose(fix.covariance_enu_m2, fix.crlb_enu_m2, rtol=1e-9, atol=1e-9)


def test_taylor_wls_scales_the_covariance_by_the_estimated_sigma():
    scene = sc.paper_004(3.0, sigma_known=False)
    problem = scene.problem(np.random.default_rng(4))
    fix = solve(problem, "taylor_wls")
    sigma = fix.details["estimated_sigma_azimuth_rad"]
    reference = solve(problem.with_sigmas(np.full(problem.n_measurements, sigma)), "taylor_wls")
    np.testing.assert_allclose(fix.position_enu_m, reference.position_enu_m, atol=1e-6)
    np.testing.assert_allclose(fix.covariance_enu_m2, reference.covariance_enu_m2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(fix.crlb_enu_m2, fix.covariance_enu_m2, rtol=1e-9, atol=1e-9)
    assert abs(fix.chi2 - fix.dof) < 1e-6 * fix.dof
    assert any(w.code == "sigma_estimated" for w in fix.warnings)


def test_taylor_wls_estimates_a_shared_sigma_among_known_ones():
    scene = sc.paper_004(4.0)
    truth = np.deg2rad(4.0)
    ratios = []
    for seed in range(20):
        measurements = scene.measurements(np.random.default_rng(seed))
        measurements = [m if i % 2 else type(m)(m.station_id, m.azimuth_rad) for i, m in enumerate(measurements)]
        problem = build_problem(list(scene.stations), measurements, altitude_m=0.0, require_sigmas=False)
        fix = solve(problem, "taylor_wls")
        assert any(w.code == "sigma_estimated" and "76 azimuths" in w.message for w in fix.warnings)
        ratios.append(fix.details["estimated_sigma_azimuth_rad"] / truth)
    # 76 unknown bearings: one estimate scatters by about 8 %, the mean of 20 by under 2 %
    assert abs(np.mean(ratios) - 1) < 0.06


def test_taylor_wls_uses_elevations_in_3d_without_an_altitude():
    scene = sc.generic_3d(1.0)
    problem = scene.problem()
    fix = solve(problem, "taylor_wls")
    assert np.linalg.norm(fix.position_enu_m - scene.target_enu_m(problem)) < 1e-6
    noisy = scene.problem(np.random.default_rng(8))
    fix = solve(noisy, "taylor_wls")
    ml = solve(noisy, "ml")
    assert np.linalg.norm(fix.position_enu_m - ml.position_enu_m) < 0.01
    assert fix.estimated_bearing_errors_rad.shape == (4,)
    assert np.all(np.isfinite(fix.details["estimated_elevation_errors_rad"]))


def test_taylor_wls_leaves_ranges_out_of_its_fit_and_says_so():
    problem = sc.generic_angle_range().problem()
    fix = solve(problem, "taylor_wls")
    ranges = problem.kinds == Kind.RANGE
    assert ranges.any() and not fix.used[ranges].any() and fix.used[~ranges].all()
    assert fix.dof == np.count_nonzero(~ranges) - 3
    assert "measurements_unused" in {w.code for w in fix.warnings}


def propagated_by_differences(problem, method, options=None, rows=None):
    """``G diag(sigma^2) G^T`` with ``G`` the central differences of the fix in the angles ``rows``."""
    if rows is None:
        rows = np.flatnonzero((problem.kinds == Kind.AZIMUTH) | (problem.kinds == Kind.ELEVATION))
    step = 1e-6
    gain = np.zeros((3, rows.size))
    for column, row in enumerate(rows):
        plus, minus = problem.values.copy(), problem.values.copy()
        plus[row] += step
        minus[row] -= step
        gain[:, column] = (solve(problem.with_values(plus), method, options).position_enu_m
                           - solve(problem.with_values(minus), method, options).position_enu_m) / (2 * step)
    return (gain * problem.sigmas[rows] ** 2) @ gain.T


def test_tls_covariance_is_the_first_order_propagation():
    problem = sc.paper_004(3.0).problem(np.random.default_rng(6))
    covariance = solve(problem, "tls").covariance_enu_m2
    numeric = propagated_by_differences(problem, "tls")
    np.testing.assert_allclose(covariance, numeric, rtol=1e-4, atol=1e-6 * np.trace(numeric))


def test_newton_ctls_covariance_is_the_first_order_propagation():
    problem = sc.generic_azimuth_only(1.0).problem(np.random.default_rng(6))
    tight = SolveOptions(tolerance_m=1e-9, max_iterations=100, variant="newton")
    fix = solve(problem, "ctls", tight)
    assert fix.converged
    numeric = propagated_by_differences(problem, "ctls", tight)
    np.testing.assert_allclose(fix.covariance_enu_m2, numeric, rtol=1e-4, atol=1e-6 * np.trace(numeric))


@pytest.mark.parametrize("method", ["ple3d", "ws3d"])
@pytest.mark.parametrize("altitude", [False, True], ids=["3d", "known-altitude"])
def test_pseudolinear_covariance_is_the_first_order_propagation(method, altitude):
    """The analytic derivative through the passes (and the foot on the altitude surface) against differences."""
    scene = sc.generic_3d(1.0)
    if altitude:
        scene = replace(scene, altitude_m=scene.target.alt_m)
    problem = scene.problem(np.random.default_rng(9))
    covariance = solve(problem, method).covariance_enu_m2
    numeric = propagated_by_differences(problem, method)
    np.testing.assert_allclose(covariance, numeric, rtol=1e-5, atol=1e-7 * np.trace(numeric))


def test_ctls_defaults_to_newton():
    problem = sc.generic_azimuth_only().problem(np.random.default_rng(2))
    assert solve(problem, "ctls").details["variant"] == "newton"
    np.testing.assert_allclose(solve(problem, "ctls").position_enu_m,
                               solve(problem, "ctls", SolveOptions(variant="newton")).position_enu_m)


@pytest.mark.parametrize("method", ["ple3d", "ws3d"])
def test_pseudolinear_covariance_predicts_the_error(method):
    scene = sc.generic_3d(1.0)
    problem = scene.template()
    trials = 500
    result = evaluate(problem, scene.target_enu_m(problem), [method], trials, 3100)[method]
    predicted = np.sqrt(np.trace(solve(scene.problem(), method).covariance_enu_m2))
    assert result.failures == 0
    # the rmse of 500 trials scatters about 3 % (1 sigma) around its expectation
    assert abs(result.rmse_m / predicted - 1) < 0.12
    low, high = nees_interval(3, trials)
    assert low < result.nees_mean < high
