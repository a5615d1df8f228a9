"""One rule for a second solution, and honest answers on the one-bearing + 2-TOA class.

The scenes are those of test_ambiguity.py (an azimuth at a, TOAs at b and c, the altitude known) at three
targets, and a 3D one (azimuth and elevation at a, TOAs at b and c). With no degree of freedom left, a line
of sight that crosses the TDOA hyperbola twice is a tie (422); near (8, 8) km it runs almost along the
hyperbola, the crossing is unique and slides kilometres along the curved hyperbola with the bearing's noise:
the bound at the fix is a straight, metres-thin ellipse there, and the fix's covariance must be the
estimator's own spread (``curved_uncertainty``). Whatever is answered must be consistent with what it states.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom, chi2, norm

from core.crlb import batch_information
from core.errors import LocalizationError
from core.estimators import SolveOptions, solve_batch
from core.estimators.ambiguity import (
    AMBIGUITY_COST,
    PLAUSIBLE_COST,
    RIVAL_PROBABILITY,
    axis_starts,
    mixture_covariance,
    rival_probability,
)
from core.estimators.lm import iterate, levenberg_marquardt
from core.estimators.ties import second_solution
from core.estimators.unscented_fix import never_below, unscented_covariance
from core.problem.batch import ProblemBatch
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import LocalPoint
from core.simulation.measurements import measure, true_values
from tests.core.estimators.test_ambiguity import SIGMA_RAD, SIGMA_TOA_S, ground_scene

TRIALS = 300
#: Warnings that say a fix's error may exceed its inverse-information bound.
CAVEATS = {"curved_uncertainty", "second_solution_plausible", "ambiguous_solution", "not_converged"}


def scene_3d():
    stations = [("a", LocalPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(20e3, 0.0, 0.0)),
                ("c", LocalPoint(0.0, 25e3, 100.0))]
    measurements = [Bearing("a", 0.0, 0.0, SIGMA_RAD, SIGMA_RAD)] + [TimeOfArrival(s, 0.0, SIGMA_TOA_S) for s in "bc"]
    return build_problem(stations, measurements), np.array([12e3, 30e3, 2e3])


def _nees(fixes, target):
    errors = np.array([f.position_enu_m - target for f in fixes])
    precision = np.linalg.pinv(np.array([f.covariance_enu_m2 for f in fixes]), rcond=1e-9, hermitian=True)
    return np.einsum("ki,kij,kj->k", errors, precision, errors)


def test_the_rule_s_thresholds_are_its_stated_probabilities():
    assert rival_probability(0.0) == pytest.approx(0.5)
    assert rival_probability(AMBIGUITY_COST) == pytest.approx(1.0 / (1.0 + np.e**2))
    assert rival_probability(PLAUSIBLE_COST) == pytest.approx(RIVAL_PROBABILITY)


def test_the_mixture_covariance_is_the_second_moment_about_the_fix():
    """Sampled from the two-component mixture, the mean outer product of the offsets from the fix."""
    rng = np.random.default_rng(5)
    fix, rival = np.zeros(3), np.array([3e3, -1e3, 0.0])
    own, other = np.diag([100.0, 400.0, 1.0]), np.diag([900.0, 25.0, 4.0])
    w = 0.2
    count = 200_000
    second = rng.random(count) < w
    samples = np.where(second[:, None], rng.multivariate_normal(rival, other, count),
                       rng.multivariate_normal(fix, own, count))
    empirical = samples.T @ samples / count
    expected = mixture_covariance(fix, own, rival, other, w)
    assert np.allclose(empirical, expected, rtol=0.02, atol=20.0)


def test_axis_starts_straddle_the_fix_along_its_principal_axes():
    problem, target = scene_3d()
    batch = ProblemBatch.from_problems([problem])
    covariance = np.diag([4e6, 1e4, 0.0])  # the third axis has no spread: no starts along it
    owners, starts = axis_starts(batch, np.array([0]), target[None], covariance[None])
    offsets = starts - target
    assert owners.tolist() == [0] * len(starts) and len(starts) == 2 * 2 * 4
    assert np.allclose(offsets[:, 2], 0.0)
    assert np.allclose(np.sort(np.abs(offsets[:, 0][offsets[:, 0] != 0])) / 2e3, np.repeat([0.5, 1.5, 4.0, 12.0], 2))


def _judged(cost_above):
    """The fix of the noise-free 3D scene judged against a rival 3 km away whose cost is ``cost_above`` more."""
    problem, target = scene_3d()
    problem = problem.with_values(true_values(problem, target))
    batch = ProblemBatch.from_problems([problem])
    solution = iterate(batch, target[None], SolveOptions())
    failures, starts, names, covariance = {}, target[None].copy(), ["closed"], np.full((1, 3, 3), np.nan)
    rival = target + [3e3, 0.0, 500.0]
    warnings = second_solution(batch, 0, rival, solution.cost[0] + cost_above, starts, names, failures, solution,
                                SolveOptions(), covariance)
    return warnings, failures, covariance[0], rival - target


def test_a_rival_within_the_ambiguity_cost_is_a_tie():
    warnings, failures, covariance, _ = _judged(0.5 * AMBIGUITY_COST)
    assert failures[0].code == "ambiguous_geometry" and not warnings and np.isnan(covariance).all()


def test_a_plausible_worse_rival_warns_and_widens_the_covariance_to_cover_it():
    delta = 0.5 * (AMBIGUITY_COST + PLAUSIBLE_COST)
    warnings, failures, covariance, apart = _judged(delta)
    assert not failures
    (warning,) = warnings
    assert warning.code == "second_solution_plausible" and f"{rival_probability(delta):.1%}" in warning.message
    w = rival_probability(delta)
    assert apart @ covariance @ apart / (apart @ apart) >= w * (apart @ apart)  # the rival's offset is covered


def test_a_rejected_rival_leaves_the_fix_alone():
    warnings, failures, covariance, _ = _judged(PLAUSIBLE_COST + 1.0)
    assert not warnings and not failures and np.isnan(covariance).all()


@pytest.mark.slow
@pytest.mark.parametrize("where", [(8e3, 8e3), (3e3, 25e3), (20e3, -3e3), "3d"])
def test_answered_fixes_are_consistent_with_what_they_state(where):
    """Over seeded draws at the scene's noise: every answered fix's truth lies inside its stated 99.99 % region
    unless the fix carries a caveat (``CAVEATS``), and the uncaveated fixes' NEES mean is in its 99 % chi-square
    interval. Where the crossing is unique, (8, 8) km, every fix is answered and its covariance is the
    estimator's spread over a curved region, widened until its 99 % region holds: the error there is no Gaussian
    (the NEES no chi-square), so the covariance states at least its second moment (the NEES's mean at most the
    dof, within a 99 % interval from the sample's own spread) and the share of truths outside the stated 99 %
    region is in the binomial interval of 1 %."""
    problem, target = scene_3d() if where == "3d" else ground_scene(*where)
    dof = 3 if where == "3d" else 2
    rng = np.random.default_rng(2026)
    fixes = solve_batch([measure(problem, target, rng) for _ in range(TRIALS)], "auto")
    answered = [f for f in fixes if not isinstance(f, LocalizationError)]
    assert all(f.code in {"ambiguous_geometry", "unobservable"} for f in fixes if isinstance(f, LocalizationError))
    if not answered:
        return
    nees = _nees(answered, target)
    caveated = np.array([bool({w.code for w in f.warnings} & CAVEATS) for f in answered])
    far = nees > chi2.ppf(0.9999, dof)
    assert not np.any(far & ~caveated), nees[far & ~caveated]
    plain = nees[~caveated]
    if plain.size >= 30:
        low, high = chi2.ppf([0.005, 0.995], dof * plain.size) / plain.size
        assert low <= plain.mean() <= high
    if where == (8e3, 8e3):
        assert len(answered) >= 0.95 * TRIALS
        margin = norm.ppf(0.995) * nees.std(ddof=1) / np.sqrt(nees.size)
        assert nees.mean() <= dof + margin, (nees.mean(), margin)
        region = chi2.ppf(0.99, dof)
        assert np.sum(nees > region) <= binom.ppf(0.995, nees.size, 0.01)


def test_the_unscented_covariance_is_the_bound_where_the_model_is_linear():
    """At a ten-thousandth of the 3D scene's noise the model is linear over the fix's uncertainty: the spread of
    the sigma-point fixes is the inverse information (to 1 %) along every axis. (At a hundredth it is not: the
    3 cm axis across the hyperboloid takes 2 cm of curvature from the 36 m one along it, and the ratio is 1.35.)"""
    problem, target = scene_3d()
    problem = problem.with_sigmas(np.asarray(problem.sigmas) / 1e4)
    batch = ProblemBatch.from_problems([problem.with_values(true_values(problem, target))])
    solution = iterate(batch, target[None], SolveOptions())
    spread = unscented_covariance(batch, solution.position_enu_m, solution.bias_m,
                                  lambda moved, starts: levenberg_marquardt(moved, starts, 500, 0.0).position_enu_m)
    bound = batch_information(batch, solution.position_enu_m).covariance_enu_m2
    assert np.allclose(spread, bound, rtol=0.01, atol=1e-6 * np.trace(bound[0]))
    raised, ratio = never_below(spread, bound)
    assert np.allclose(raised, spread, rtol=0.01) and ratio[0] == pytest.approx(1.0, abs=0.02)


def test_never_below_raises_a_covariance_to_the_bound_and_reports_the_excess():
    bound = np.diag([4.0, 1.0, 0.0])[None]  # rank 2, as with a known altitude
    covariance = np.diag([1.0, 9.0, 0.0])[None]
    raised, ratio = never_below(covariance, bound)
    assert np.allclose(raised[0], np.diag([4.0, 9.0, 0.0]))
    assert ratio[0] == pytest.approx(9.0)


def _tilted_mirror_problem(tilt_m):
    """Airborne stations at 10 km (one raised by ``tilt_m``), an azimuth and three ranges, an emitter at 2 km:
    the ranges fit its mirror through the stations' plane exactly, the azimuth (measured in the station's
    horizontal) less well the more the plane tilts. Noise-free."""
    offsets = [(0.0, 0.0, 10e3), (30e3, 5e3, 10e3 + tilt_m), (8e3, 35e3, 10e3)]
    stations = [(f"s{k}", LocalPoint(e, n, u)) for k, (e, n, u) in enumerate(offsets)]
    measurements = [Bearing("s0", 0.0, None, SIGMA_RAD)] + [Range(s, 0.0, 10.0) for s, _ in stations]
    problem = build_problem(stations, measurements)
    target = np.array([14e3, 12e3, 2e3])
    return problem.with_values(true_values(problem, target)), target


def test_a_mirror_worse_but_plausible_is_answered_with_the_warning_and_a_covariance_that_covers_it():
    """Tilted by 1 km the mirror's cost is 9.2 above the fix (between AMBIGUITY_COST and PLAUSIBLE_COST): the
    fix is the target, it names the mirror and its probability, and its stated region reaches the mirror (the
    mixture's variance along the line to it is at least the mirror's weight times the squared distance).
    Untilted the two tie (422); tilted by 2 km the mirror is rejected and the fix is alone."""
    problem, target = _tilted_mirror_problem(1e3)
    (fix,) = solve_batch([problem], "auto")
    assert np.linalg.norm(fix.position_enu_m - target) < 1e-3
    (warning,) = [w for w in fix.warnings if w.code == "second_solution_plausible"]
    delta = float(warning.message.split("chi2 ")[1].split(" ")[0])
    assert AMBIGUITY_COST < delta <= PLAUSIBLE_COST
    assert f"probability {rival_probability(delta):.1%}" in warning.message
    mirror = np.array([float(v) for v in warning.message.split("at (")[1].split(")")[0].split(",")])
    apart = mirror - fix.position_enu_m
    unit = apart / np.linalg.norm(apart)
    assert unit @ fix.covariance_enu_m2 @ unit >= 0.99 * rival_probability(delta) * (apart @ apart)
    assert unit @ fix.crlb_enu_m2 @ unit < 0.01 * unit @ fix.covariance_enu_m2 @ unit  # the bound alone would not
    (tie,) = solve_batch([_tilted_mirror_problem(0.0)[0]], "auto")
    assert isinstance(tie, LocalizationError) and tie.code == "ambiguous_geometry"
    (alone,) = solve_batch([_tilted_mirror_problem(2e3)[0]], "auto")
    assert not {w.code for w in alone.warnings} & CAVEATS
    assert np.allclose(alone.covariance_enu_m2, alone.crlb_enu_m2)
