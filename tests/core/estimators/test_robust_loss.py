"""Robust losses (``options.loss``, scipy's names and meanings) in the ML iteration.

The scene is the outlier one of ``test_outliers``: six stations, 0.5 deg bearings, one azimuth 20 deg off.
A redescending loss (cauchy) sets the culprit aside and reaches the CRLB of the other measurements; a
bounded-influence one (huber) only bounds its pull, and its covariance counts that pull. On clean data the
robust losses cost a few percent. Exclusion under any loss finds two gross bearings among eight.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from scipy.stats import binom
from scipy.stats import chi2 as chi2_distribution

from core.errors import InvalidInput
from core.estimators import EXCLUSION_P, SolveOptions, solve, solve_batch
from core.estimators.loss import LOSSES, loss_terms
from core.problem.build import Bearing, build_problem
from core.problem.frame import LocalPoint
from core.simulation.measurements import measure
from tests.core.estimators.test_outliers import (SIGMA, STATIONS, TARGET, _bound_without_culprit, _draws, _problem,
                                                 _rmse)

TRIALS = 300


def _nees(fixes):
    return float(np.mean([(f.position_enu_m - TARGET) @ np.linalg.solve(f.covariance_enu_m2, f.position_enu_m - TARGET)
                          for f in fixes]))


@pytest.mark.parametrize("loss", LOSSES[1:])
def test_loss_derivatives_match_finite_differences(loss):
    z = np.geomspace(1e-3, 1e3, 41)
    scale = 1.7
    rho, rho1, rho2 = loss_terms(z, loss, scale)
    h = 1e-4 * z
    up, down = loss_terms(z + h, loss, scale), loss_terms(z - h, loss, scale)
    assert rho1 == pytest.approx((up[0] - down[0]) / (2 * h), rel=1e-5, abs=1e-9)
    assert rho2 == pytest.approx((up[1] - down[1]) / (2 * h), rel=1e-5, abs=1e-9)
    small, one, _ = loss_terms(np.array([1e-12]), loss, scale)
    assert small[0] == pytest.approx(1e-12) and one[0] == pytest.approx(1.0)


def test_cauchy_sets_the_gross_bearing_aside_and_reaches_the_bound_without_it():
    problem = _problem()
    draws = _draws(problem, 7)[:TRIALS]
    bound = _bound_without_culprit(problem)
    linear = solve_batch(draws, "ml")
    cauchy = solve_batch(draws, "ml", SolveOptions(loss="cauchy", loss_scale=2.0))
    assert _rmse(linear) > 10 * bound
    assert _rmse(cauchy) <= 1.2 * bound
    assert cauchy[0].covariance_source == "robust"
    named = [w.message for w in cauchy[0].warnings if w.code == "measurement_downweighted"]
    assert len(named) == 1 and named[0].startswith("measurement 2 (azimuth")
    # The covariance follows the fit: the sandwich of the final weights is the bound without the culprit.
    assert 2.5 <= _nees(cauchy) <= 3.5


def test_huber_bounds_the_outlier_pull():
    problem = _problem()
    draws = _draws(problem, 7)[:TRIALS]
    bound = _bound_without_culprit(problem)
    huber = solve_batch(draws, "ml", SolveOptions(loss="huber", loss_scale=2.0))
    assert _rmse(huber) <= 2.0 * bound


@pytest.mark.parametrize(("loss", "scale"), [("huber", 1.345), ("soft_l1", 2.0), ("cauchy", 2.0)])
def test_clean_data_cost_a_robust_loss_a_few_percent(loss, scale):
    problem = _problem()
    draws = _draws(problem, 11, outlier=False)[:TRIALS]
    linear = solve_batch(draws, "ml")
    robust = solve_batch(draws, "ml", SolveOptions(loss=loss, loss_scale=scale))
    assert _rmse(robust) <= 1.05 * _rmse(linear)
    assert 2.6 <= _nees(robust) <= 3.4  # 3 within the scatter of 300 draws (sd of the mean NEES ~0.15)
    assert np.mean([any(w.code == "measurement_downweighted" for w in f.warnings) for f in robust]) <= 0.05


def _bearings(point):
    out = []
    for _, station in STATIONS:
        d = point - np.array([station.east_m, station.north_m, station.up_m])
        out += [np.arctan2(d[0], d[1]), np.arctan2(d[2], np.hypot(d[0], d[1]))]
    return np.array(out)


@pytest.mark.parametrize("loss", LOSSES)
@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_same_point_as_scipy_least_squares(loss, scale):
    """scipy's trust-region solver on the whitened residuals, started from our fix, stays there."""
    problem = _problem()
    noisy = _draws(problem, 21)[0]
    assert np.allclose(_bearings(TARGET), problem.with_values(_bearings(TARGET)).values)
    fix = solve(noisy, "ml", SolveOptions(loss=loss, loss_scale=scale, tolerance_m=1e-9, max_iterations=200))
    sigmas = noisy.sigmas

    def whitened(point):
        r = noisy.values - _bearings(point)
        r[0::2] = (r[0::2] + np.pi) % (2 * np.pi) - np.pi
        return r / sigmas

    reference = least_squares(whitened, fix.position_enu_m + [50.0, -30.0, 20.0], loss=loss, f_scale=scale,
                              x_scale=1e3, xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=10000)
    assert np.linalg.norm(fix.position_enu_m - reference.x) < 1e-3  # 1 mm, on a fix ~250 m from the truth
    assert fix.converged


@pytest.mark.parametrize(("options", "field"), [
    (SolveOptions(loss="bogus"), "loss"), (SolveOptions(loss="huber", loss_scale=0.0), "loss_scale"),
    (SolveOptions(loss="huber", loss_scale=float("nan")), "loss_scale")])
def test_bad_loss_options_are_invalid_input(options, field):
    with pytest.raises(InvalidInput) as raised:
        solve(_problem().with_values(_bearings(TARGET)), "ml", options)
    assert raised.value.loc == (field,)


def test_a_method_without_the_loss_refuses_it():
    with pytest.raises(InvalidInput) as raised:
        solve(_problem().with_values(_bearings(TARGET)), "weighted_eove", SolveOptions(loss="huber"))
    assert raised.value.loc == ("loss",) and "ml" in str(raised.value)


@pytest.mark.parametrize(("loss", "scale"), [("huber", 1.0), ("huber", 1.345), ("soft_l1", 1.0)])
def test_a_bounded_influence_fit_under_a_gross_bearing_has_an_honest_covariance(loss, scale):
    """huber and soft_l1 keep a bent measurement's pull on the fix; their covariance says so: the mean NEES over
    the seeded draws is inside the chi-square interval of a covariance that matches the errors."""
    problem = _problem()
    draws = _draws(problem, 7)
    fixes = solve_batch(draws, "ml", SolveOptions(loss=loss, loss_scale=scale))
    lower, upper = chi2_distribution.ppf([0.0005, 0.9995], 3 * len(draws)) / len(draws)
    assert lower <= _nees(fixes) <= upper


EIGHT = [(f"r{k}", LocalPoint(30e3 * np.cos(a), 30e3 * np.sin(a), 0.0))
         for k, a in enumerate(np.deg2rad(np.arange(8) * 45.0 + 10.0))]
BAD = (2, 5)


@pytest.mark.parametrize("loss", ["linear", "huber", "soft_l1"])
def test_exclusion_names_both_gross_bearings_among_eight_and_no_innocent(loss):
    problem = build_problem(EIGHT, [Bearing(sid, 0.0, 0.0, SIGMA, SIGMA) for sid, _ in EIGHT])
    rng = np.random.default_rng(8)
    draws = []
    for _ in range(200):
        values = measure(problem, TARGET, rng).values.copy()
        for bad in BAD:
            values[2 * bad] += np.deg2rad(20.0)
        draws.append(problem.with_values(values))
    fixes = solve_batch(draws, "ml", SolveOptions(outliers="exclude", loss=loss))
    named = [set(problem.source_index[f.excluded].tolist()) for f in fixes]
    assert np.mean([set(BAD) <= n for n in named]) >= 0.95
    assert sum(bool(n - set(BAD)) for n in named) <= binom.ppf(0.999, len(draws), EXCLUSION_P)
