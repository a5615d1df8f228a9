"""Outlier exclusion (RAIM fault detection and exclusion), unused measurements and ``absolute_sigma``.

Six stations around a target 3 km up, 0.5 deg bearings; a gross error is one azimuth 20 deg off
(a reflection or a wrong lobe). The bounds are the CRLB of the measurements that should be used.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2 as chi2_distribution

from core.crlb import information_at
from core.estimators import SolveOptions, solve_batch
from core.estimators.loss import loss_terms
from core.problem.build import Bearing, Range, build_problem
from core.problem.frame import LocalPoint
from core.simulation.measurements import measure

SIGMA = np.deg2rad(0.5)
TRIALS = 400
TARGET = np.array([4e3, 9e3, 3e3])
ANGLES = np.deg2rad(np.arange(6) * 60.0 + 10.0)
STATIONS = [(f"s{k}", LocalPoint(30e3 * np.cos(a), 30e3 * np.sin(a), 0.0)) for k, a in enumerate(ANGLES)]
CULPRIT = 2  # request index of the corrupted bearing


def _problem(with_ranges=False):
    bearings = [Bearing(sid, 0.0, 0.0, SIGMA, SIGMA) for sid, _ in STATIONS]
    ranges = [Range(sid, 0.0, 200.0) for sid, _ in STATIONS[:2]] if with_ranges else []
    return build_problem(STATIONS, bearings + ranges)


def _draws(problem, seed, outlier=True):
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(TRIALS):
        noisy = measure(problem, TARGET, rng)
        if outlier:
            values = noisy.values.copy()
            values[2 * CULPRIT] += np.deg2rad(20.0)  # the azimuth of bearing CULPRIT
            noisy = noisy.with_values(values)
        draws.append(noisy)
    return draws


def _rmse(fixes):
    errors = np.array([f.position_enu_m - TARGET for f in fixes])
    return float(np.sqrt(np.mean(np.sum(errors**2, axis=-1))))


def _bound_without_culprit(problem):
    sigmas = problem.sigmas.copy()
    sigmas[problem.source_index == CULPRIT] = np.inf
    return float(np.sqrt(np.trace(information_at(problem, TARGET, sigmas=sigmas).covariance_enu_m2[0])))


def test_one_gross_bearing_is_excluded_and_the_fix_reaches_the_bound_without_it():
    problem = _problem()
    fixes = solve_batch(_draws(problem, 7), "ml", SolveOptions(outliers="exclude"))
    assert all(not isinstance(f, Exception) for f in fixes)
    culprit_alone = [np.array_equal(np.flatnonzero(f.excluded), np.flatnonzero(problem.source_index == CULPRIT))
                     for f in fixes]
    assert np.mean(culprit_alone) >= 0.95
    assert _rmse(fixes) <= 1.2 * _bound_without_culprit(problem)
    named = [w for w in fixes[0].warnings if w.code == "measurement_excluded"]
    assert named and f"measurement {CULPRIT}" in named[0].message


def test_report_mode_keeps_the_outlier_and_is_far_from_the_bound():
    problem = _problem()
    fixes = solve_batch(_draws(problem, 7)[:100], "ml")
    assert _rmse(fixes) > 3 * _bound_without_culprit(problem)
    assert all(not f.excluded.any() for f in fixes)


def test_clean_data_are_rarely_touched_by_exclusion():
    problem = _problem()
    draws = _draws(problem, 11, outlier=False)
    report = solve_batch(draws, "ml")
    exclude = solve_batch(draws, "ml", SolveOptions(outliers="exclude"))
    touched = np.mean([f.excluded.any() for f in exclude])
    assert touched <= 0.05
    assert _rmse(exclude) == pytest.approx(_rmse(report), rel=0.05)


def test_relative_sigma_makes_the_covariance_honest_when_the_noise_is_three_times_larger():
    """With the scale estimated from ``dof`` residuals the NEES is ``3 F(3, dof)``, mean ``3 dof / (dof - 2)``:
    eight looks per station (93 dof) bring that within the chi-square interval of known covariances."""
    looks = [Bearing(sid, 0.0, 0.0, SIGMA, SIGMA) for sid, _ in STATIONS for _ in range(8)]
    problem = build_problem(STATIONS, looks)
    rng = np.random.default_rng(5)
    truth_sigmas = problem.with_sigmas(3.0 * problem.sigmas)
    draws = [measure(truth_sigmas, TARGET, rng).with_sigmas(problem.sigmas) for _ in range(TRIALS)]
    absolute = solve_batch(draws, "ml")
    relative = solve_batch(draws, "ml", SolveOptions(absolute_sigma=False))

    def mean_nees(fixes):
        return float(np.mean([(f.position_enu_m - TARGET) @ np.linalg.solve(f.covariance_enu_m2, f.position_enu_m - TARGET)
                              for f in fixes]))

    low, high = chi2_distribution.ppf([0.005, 0.995], 3 * TRIALS) / TRIALS
    assert low <= mean_nees(relative) <= high
    assert mean_nees(absolute) > 5.0
    assert relative[0].covariance_source == "information_scaled"


def test_measurements_a_method_does_not_use_are_left_out_of_its_verdicts():
    problem = _problem(with_ranges=True)
    draws = _draws(problem, 3, outlier=False)[:200]
    for fix in solve_batch(draws, "eove"):
        ranges = problem.kinds == 2
        assert not fix.used[ranges].any() and fix.used[~ranges].all()
        assert fix.dof == 12 - 3
        assert "measurements_unused" in {w.code for w in fix.warnings}
    flagged = np.mean([any(w.code in ("outlier_suspected", "sigma_mismatch") for w in f.warnings)
                       for f in solve_batch(draws, "eove")])
    assert flagged <= 0.05


# A far target on nearly parallel lines of sight: four stations within 15 km, the target 100 km out. One
# azimuth 20 deg off can pull the fit onto itself (a masked error: its own residual small) or send it off to
# infinity (no fit at all), so residuals at the fit cannot name it; leaving each bearing out in turn can.
FAR_TARGET = np.array([13e3, 100e3, 2e3])
FAR_STATIONS = [(f"f{k}", LocalPoint(e, n, 0.0)) for k, (e, n) in
                enumerate([(-15e3, 0.0), (15e3, 2e3), (0.0, -8e3), (5e3, 10e3)])]


@pytest.mark.parametrize("loss", ["linear", "huber"])
def test_a_gross_bearing_on_nearly_parallel_lines_is_found_by_leaving_each_out(loss):
    problem = build_problem(FAR_STATIONS, [Bearing(sid, 0.0, 0.0, SIGMA, SIGMA) for sid, _ in FAR_STATIONS])
    rng = np.random.default_rng(3)
    draws, culprits = [], []
    for _ in range(TRIALS):
        noisy = measure(problem, FAR_TARGET, rng)
        culprit = int(rng.integers(len(FAR_STATIONS)))
        values = noisy.values.copy()
        values[2 * culprit] += np.deg2rad(20.0)
        draws.append(noisy.with_values(values))
        culprits.append(culprit)
    fixes = solve_batch(draws, "ml", SolveOptions(outliers="exclude", loss=loss))
    assert all(not isinstance(f, Exception) for f in fixes)
    named = [np.array_equal(np.flatnonzero(f.excluded), np.flatnonzero(problem.source_index == c))
             for f, c in zip(fixes, culprits)]
    assert np.mean(named) >= 0.95
    # Each fix that excluded its culprit then sits within the chi-square (3 dof) 99.9 % region of the bound of
    # what it used; one that could not isolate it says so.
    outside = 0
    for f, c, right in zip(fixes, culprits, named):
        if not right:
            assert not f.excluded.any() and "fault_detected_not_isolable" in {w.code for w in f.warnings}
            continue
        sigmas = problem.sigmas.copy()
        sigmas[problem.source_index == c] = np.inf
        bound = information_at(problem, FAR_TARGET, sigmas=sigmas).covariance_enu_m2[0]
        error = f.position_enu_m - FAR_TARGET
        outside += error @ np.linalg.solve(bound, error) > chi2_distribution.ppf(0.999, 3)
    assert outside <= 0.01 * TRIALS


@pytest.mark.parametrize("loss", ["huber", "soft_l1", "cauchy"])
def test_a_robust_fit_is_not_left_in_the_basin_a_gross_bearing_pulled_its_start_into(loss):
    """Report mode on the nearly parallel lines above: the closed-form start leans toward the gross bearing,
    and a robust fit from there can settle in that bearing's basin. Its cost must be no higher than that of
    the fit started at the true target (an upper bound on the loss's minimum), beyond half a unit (the loss is
    flat along these lines of sight: fits that stop in the same valley differ in the fifth digit)."""
    problem = build_problem(FAR_STATIONS, [Bearing(sid, 0.0, 0.0, SIGMA, SIGMA) for sid, _ in FAR_STATIONS])
    rng = np.random.default_rng(3)
    draws = []
    for _ in range(TRIALS):
        noisy = measure(problem, FAR_TARGET, rng)
        values = noisy.values.copy()
        values[2 * int(rng.integers(len(FAR_STATIONS)))] += np.deg2rad(20.0)
        draws.append(noisy.with_values(values))
    options = SolveOptions(loss=loss)
    fixes = solve_batch(draws, "ml", options)
    from_truth = solve_batch([dataclasses.replace(d, initial_guess_enu_m=FAR_TARGET.copy()) for d in draws], "ml",
                             options)
    assert all(not isinstance(f, Exception) for f in fixes)

    def cost(fix):
        return float(loss_terms(fix.normalized_residuals[fix.used] ** 2, loss, 1.0)[0].sum())

    higher = [cost(f) > cost(t) + 0.5 for f, t in zip(fixes, from_truth) if not isinstance(t, Exception)]
    assert np.mean(higher) <= 0.01


def test_exclusion_asks_whether_to_stop_before_each_round():
    """A deadline can end exclusion between its rounds of refits (each round re-runs the method on every
    candidate), not only between parts of a batch."""
    from core.estimators import iter_solutions
    from core.parallel import Stopped
    from core.problem.batch import ProblemBatch

    batch = ProblemBatch.from_problems(_draws(_problem(), 7)[:20])
    asked = []

    def stop_at_the_first_round():
        asked.append(True)
        return len(asked) > 1  # the part itself may start; its first exclusion round may not

    with pytest.raises(Stopped):
        list(iter_solutions(batch, "ml", SolveOptions(outliers="exclude"), should_stop=stop_at_the_first_round))
    assert len(asked) == 2
    assert all(not isinstance(fixes, Exception) for _, fixes in
               iter_solutions(batch, "ml", SolveOptions(outliers="exclude"), should_stop=lambda: False))
