"""Angle and range, coarse then fine (paper 003)."""

from __future__ import annotations

import numpy as np
import pytest

from core.problem.batch import ProblemBatch
from core.crlb import information_at
from core.errors import LocalizationError, TooFewMeasurements
from core.estimators import REGISTRY, SolveOptions, solve
from core.estimators import solve_batch
from core.estimators.methods.angle_range import coarse_fix
from core.measurements import Kind
from core.problem.build import Bearing, Range, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint
from core.simulation.scenarios import PAPER_003_SIGMA_ANGLE_RAD, PAPER_003_STATIONS, PAPER_003_TARGET, paper_003_problem
from core.simulation.measurements import draw_noise, true_values

DEG = np.pi / 180.0
PAPER_SIGMA_ANGLE_RAD = PAPER_003_SIGMA_ANGLE_RAD
PAPER_STATIONS = list(PAPER_003_STATIONS)
PAPER_TARGET = PAPER_003_TARGET


def bearing(station, sigma=PAPER_SIGMA_ANGLE_RAD, elevation=True):
    return Bearing(station, 0.0, 0.0 if elevation else None, sigma, sigma if elevation else None)


paper_problem = paper_003_problem


def monte_carlo(problem, target_enu_m, trials, seed, noise="gaussian"):
    """Fine and coarse errors ``(T, 3)`` of angle_range, the fixes, and the draws ``(T, M)``."""
    draws = true_values(problem, target_enu_m) + draw_noise(np.random.default_rng(seed), problem.sigmas, noise,
                                                             size=trials)
    fixes = solve_batch([problem.with_values(v) for v in draws], "angle_range")
    assert not any(isinstance(f, LocalizationError) for f in fixes)
    fine = np.array([f.position_enu_m for f in fixes]) - target_enu_m
    coarse = np.array([f.coarse_position_enu_m for f in fixes]) - target_enu_m
    return fine, coarse, fixes, draws


def rmse(errors_enu_m):
    return float(np.sqrt(np.mean(np.sum(errors_enu_m**2, axis=1))))


def crlb_rmse(problem, target_enu_m):
    return float(np.sqrt(np.trace(information_at(problem, target_enu_m).covariance_enu_m2[0])))


def test_registered_under_its_api_name():
    assert REGISTRY["angle_range"].name == "angle_range" and "paper 003" in REGISTRY["angle_range"].summary


def test_noise_free_paper_scenario_is_exact_and_reports_the_polar_coarse_stage():
    problem = paper_problem()
    target = problem.frame.from_geodetic(*PAPER_TARGET)
    fix = solve(problem.with_values(true_values(problem, target)), "angle_range")
    np.testing.assert_allclose(fix.position_enu_m, target, atol=1e-6)  # a micrometre
    np.testing.assert_allclose(fix.coarse_position_enu_m, target, atol=1e-6)
    assert fix.method == "angle_range"
    assert fix.details["coarse"] == "polar"
    assert "coarse_polar_fallback" in {w.code for w in fix.warnings}


def test_two_stations_coarse_stage_is_the_papers_formulas():
    """In a flat frame the coarse point is eqs. (2)-(4) of paper 003 (math angle theta = pi/2 - azimuth)."""
    stations = [("a", LocalPoint(0.0, 0.0, 500.0)), ("b", LocalPoint(30_000.0, 0.0, 9_000.0))]
    problem = build_problem(stations, [bearing("a", 0.5 * DEG, elevation=False), Range("a", 1.0, 20.0),
                                       bearing("b", 0.5 * DEG, elevation=False), Range("b", 1.0, 20.0)])
    target = np.array([15_000.0, 25_000.0, 4_000.0])
    noisy = problem.with_values(true_values(problem, target) + draw_noise(np.random.default_rng(3), problem.sigmas))
    coarse = coarse_fix(ProblemBatch.from_problems([noisy]))
    assert coarse.method == ["range_difference"] and coarse.warnings == [()] and not coarse.errors

    (x1, y1, z1), (x2, y2, z2) = noisy.stations_enu_m
    az1, r1, az2, r2 = noisy.values
    tan1, tan2 = np.tan(np.pi / 2 - az1), np.tan(np.pi / 2 - az2)
    x0 = (x1 * tan1 - x2 * tan2 + y2 - y1) / (tan1 - tan2)
    y0 = (y1 / tan1 - y2 / tan2 + x2 - x1) / (1 / tan1 - 1 / tan2)
    h1, h2 = np.hypot(x0 - x1, y0 - y1), np.hypot(x0 - x2, y0 - y2)
    z0 = (r1**2 - r2**2 - h1**2 + h2**2 - z1**2 + z2**2) / (2 * (z2 - z1))
    np.testing.assert_allclose(coarse.position_enu_m[0], [x0, y0, z0], rtol=1e-9)
    fix = solve(noisy, "angle_range")
    assert fix.details["coarse"] == "range_difference"
    np.testing.assert_allclose(fix.coarse_position_enu_m, coarse.position_enu_m[0])


def test_needs_a_bearing_and_a_range():
    with pytest.raises(TooFewMeasurements, match="at least one bearing and one range"):
        solve(paper_problem(with_ranges=False), "angle_range")
    ranges_only = build_problem(PAPER_STATIONS, [Range("master", 5e4, 250.0), Range("helper", 5e4, 250.0)])
    with pytest.raises(TooFewMeasurements, match="at least one bearing and one range"):
        solve(ranges_only, "angle_range")


def test_batch_equals_one_problem_at_a_time():
    problem = paper_problem()
    target = problem.frame.from_geodetic(*PAPER_TARGET)
    fine, coarse, fixes, draws = monte_carlo(problem, target, 4, seed=2)
    for k, values in enumerate(draws):
        single = solve(problem.with_values(values), "angle_range")
        np.testing.assert_allclose(single.position_enu_m, fixes[k].position_enu_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(single.coarse_position_enu_m, fixes[k].coarse_position_enu_m, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_paper_003_angle_and_range_reach_the_crlb_and_beat_angles_alone():
    problem = paper_problem()
    target = problem.frame.from_geodetic(*PAPER_TARGET)
    trials = 5000
    fine, coarse, fixes, draws = monte_carlo(problem, target, trials, seed=3003)
    bound = crlb_rmse(problem, target)
    # 5000 trials: the RMSE's sampling sd is below 1.1 % here
    assert rmse(fine) == pytest.approx(bound, rel=0.10)

    angles = problem.kinds != Kind.RANGE
    angle_only = paper_problem(with_ranges=False)
    ml = solve_batch([angle_only.with_values(v[angles]) for v in draws], "ml")
    angle_errors = np.array([f.position_enu_m for f in ml]) - target
    assert rmse(fine) <= 0.6 * rmse(angle_errors)

    # one height: the paper's z0 divides by ~0 and hands over to the polar points
    assert all(f.details["coarse"] == "polar" for f in fixes)
    assert all("coarse_polar_fallback" in {w.code for w in f.warnings} for f in fixes)
    # the fused polar points are first-order efficient too, so the fine stage gains
    # only at second order (~0.1 % of the MSE, about 3.3 standard errors at 5000
    # paired trials): the coarse fix is worse, but barely
    assert rmse(coarse) > rmse(fine)


MIXED_SIGMA_ANGLE_RAD = 0.5 * DEG
MIXED_SIGMA_RANGE_M = 100.0


def three_stations():
    """a: bearing and range; b: bearing only; c: range only (local frame)."""
    stations = [("a", LocalPoint(0.0, 0.0, 1_000.0)), ("b", LocalPoint(40_000.0, 0.0, 3_000.0)),
                ("c", LocalPoint(20_000.0, 30_000.0, 8_000.0))]
    measurements = [bearing("a", MIXED_SIGMA_ANGLE_RAD), Range("a", 1.0, MIXED_SIGMA_RANGE_M),
                    bearing("b", MIXED_SIGMA_ANGLE_RAD), Range("c", 1.0, MIXED_SIGMA_RANGE_M)]
    problem = build_problem(stations, measurements)
    return problem, np.array([25_000.0, 45_000.0, 6_000.0])


def five_stations():
    """a, b: bearing and range; c: bearing only; d: azimuth only; e: range only (wgs84)."""
    stations = [("a", GeodeticPoint(34.0 * DEG, 108.0 * DEG, 500.0)),
                ("b", GeodeticPoint(34.3 * DEG, 108.5 * DEG, 2_500.0)),
                ("c", GeodeticPoint(33.8 * DEG, 108.6 * DEG, 100.0)),
                ("d", GeodeticPoint(34.5 * DEG, 108.1 * DEG, 1_500.0)),
                ("e", GeodeticPoint(33.9 * DEG, 108.9 * DEG, 9_000.0))]
    s, r = MIXED_SIGMA_ANGLE_RAD, MIXED_SIGMA_RANGE_M
    measurements = [bearing("a", s), Range("a", 1.0, r), bearing("b", s), Range("b", 1.0, r),
                    bearing("c", s), bearing("d", s, elevation=False), Range("e", 1.0, r)]
    problem = build_problem(stations, measurements)
    return problem, problem.frame.from_geodetic(34.1 * DEG, 108.4 * DEG, 7_000.0)


@pytest.mark.parametrize("scenario, seed", [(three_stations, 33), (five_stations, 55)])
def test_mixed_stations_fine_fix_reaches_the_crlb(scenario, seed):
    problem, target = scenario()
    fine, coarse, fixes, _ = monte_carlo(problem, target, 1500, seed=seed)
    # 1500 trials: the RMSE's sampling sd is at most 1.8 %
    assert rmse(fine) == pytest.approx(crlb_rmse(problem, target), rel=0.10)
    assert rmse(fine) < rmse(coarse)
    assert all(f.coarse_position_enu_m is not None and f.details["coarse"] for f in fixes)


def test_polar_points_fuse_by_their_information_even_when_a_covariance_is_singular_in_float64():
    """A 1e9 m range of sigma 0.1 m with a 178 deg azimuth sigma: across the line of sight the polar point's
    sd is 3e9 m, along it 0.1 m, a covariance conditioned at 1e21 that ``inv`` called singular (a 500 on the
    fix routes). Its information, built from the same axes, fuses exactly: with an exact second point the
    fused position is the information-weighted mean, computed here on axes where it is diagonal."""
    from core.estimators.starting_points import fuse_points

    turn = np.array([[np.cos(0.3), -np.sin(0.3), 0.0], [np.sin(0.3), np.cos(0.3), 0.0], [0.0, 0.0, 1.0]])
    sd_m = np.array([[0.1, 3e9, 17.0], [5.0, 5.0, 5.0]])
    information = turn[None] @ np.stack([np.diag(1.0 / s**2) for s in sd_m]) @ turn.T[None]
    points = np.array([[1e9, 2.0, 3.0], [1e9 + 4.0, -7.0, 11.0]]) @ turn.T
    fused, covariance = fuse_points(points, information)
    on_axes = points @ turn  # each point in the frame where both informations are diagonal
    weights = 1.0 / sd_m**2
    expected = turn @ (np.sum(weights * on_axes, axis=0) / np.sum(weights, axis=0))
    np.testing.assert_allclose(fused, expected, rtol=0, atol=1e-6 * np.abs(expected).max())
    np.testing.assert_allclose(np.diag(turn.T @ covariance @ turn), 1.0 / np.sum(weights, axis=0), rtol=1e-9)
