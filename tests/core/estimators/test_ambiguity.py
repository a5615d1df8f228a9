"""Ties are declared only against a rival that is itself a converged fit of the data.

The ground scene: an azimuth-only bearing at station a, TOAs at b and c (no TOA at the bearing station, so
the line of sight may cross the TDOA hyperbola twice), the altitude known. Where the line of sight runs
nearly along the hyperbola (target at (8, 8) km) the search's iterates crawl and stop unconverged on either
side of the one crossing; further iterations from any of them converge onto it, so the fix is unique. At
(3, 25) km and (20, -3) km the line crosses twice, both crossings exact fits: a genuine tie.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from core.errors import LocalizationError
from core.estimators import solve_batch
from core.estimators.ambiguity import PLAUSIBLE_COST
from core.estimators.ties import (
    DISTINCT_MAHALANOBIS2,
    DISTINCT_UNCONVERGED_MAHALANOBIS2,
    Fits,
    rivals,
)
from core.problem.build import Bearing, TimeOfArrival, build_problem
from core.problem.frame import GeodeticPoint
from core.simulation.measurements import measure, true_values

SIGMA_RAD = np.deg2rad(0.5)
SIGMA_TOA_S = 1e-8
GROUND = [("a", GeodeticPoint(0.6, 1.9, 100.0)), ("b", GeodeticPoint(0.601, 1.905, 50.0)),
          ("c", GeodeticPoint(0.605, 1.899, 10.0))]
TRIALS = 200


def ground_scene(east_m: float, north_m: float):
    """The problem (bearing at a, TOAs at b and c, altitude 0 known) and its target on the altitude surface."""
    measurements = [Bearing("a", 0.0, None, SIGMA_RAD)] + [TimeOfArrival(s, 0.0, SIGMA_TOA_S) for s in "bc"]
    problem = build_problem(GROUND, measurements, altitude_m=0.0)
    return problem, problem.frame.onto_altitude(np.array([east_m, north_m, 0.0]), 0.0)


def test_a_unique_crossing_that_the_search_only_crawls_to_is_answered_at_the_truth():
    problem, target = ground_scene(8e3, 8e3)
    (fix,) = solve_batch([problem.with_values(true_values(problem, target))], "auto")
    assert not isinstance(fix, LocalizationError), fix
    assert fix.converged and "ambiguous_solution" not in {w.code for w in fix.warnings}
    assert np.linalg.norm(fix.position_enu_m - target) < 1e-2  # 1 cm


@pytest.mark.parametrize("east_m, north_m", [(3e3, 25e3), (20e3, -3e3)])
def test_two_exact_crossings_stay_refused(east_m, north_m):
    problem, target = ground_scene(east_m, north_m)
    (refused,) = solve_batch([problem.with_values(true_values(problem, target))], "auto")
    assert isinstance(refused, LocalizationError) and refused.code == "ambiguous_geometry"
    assert refused.message.count("lat ") == 2
    assert f"({east_m:.0f}, {north_m:.0f}," in refused.message  # the target is one of the two named


def test_noisy_draws_of_the_unique_crossing_are_answered_with_the_data_s_ml_fix():
    """Over seeded draws almost none is refused, and every answered fix is the ML fit that an iteration
    started at the truth reaches (the data's solution, not an iterate the search stopped on)."""
    problem, target = ground_scene(8e3, 8e3)
    rng = np.random.default_rng(11)
    draws = [measure(problem, target, rng) for _ in range(TRIALS)]
    fixes = solve_batch(draws, "auto")
    refused = [f for f in fixes if isinstance(f, LocalizationError)]
    assert len(refused) <= 0.05 * TRIALS
    reference = solve_batch([replace(d, initial_guess_enu_m=target) for d in draws], "ml")
    compared = 0
    for fix, ref in zip(fixes, reference):
        if isinstance(fix, LocalizationError) or isinstance(ref, LocalizationError) or not ref.converged:
            continue
        assert fix.converged
        assert np.linalg.norm(fix.position_enu_m - ref.position_enu_m) < 1.0  # 1 m
        compared += 1
    assert compared >= 0.9 * TRIALS


def _fits(position_enu_m, cost, converged, sigma_m=10.0):
    size = len(cost)
    return Fits(np.array(position_enu_m, dtype=float), np.array(cost, dtype=float), np.array(converged),
                np.ones(size, dtype=bool), np.tile(np.eye(3) * sigma_m**2, (size, 1, 1)))


def test_the_rival_rule():
    """Against a converged best: only a converged, distinct fit that its cost does not reject is a rival (an
    unconverged iterate never is, a fit onto the best neither). Against an unconverged best, an unconverged
    iterate far off is."""
    far = 10.0 * np.sqrt(DISTINCT_UNCONVERGED_MAHALANOBIS2)  # sigmas
    near = 0.5 * np.sqrt(DISTINCT_MAHALANOBIS2)
    candidates = _fits([[far * 10, 0, 0], [far * 10, 0, 0], [near * 10, 0, 0], [far * 10, 0, 0]],
                       [0.5, 0.5, 0.0, PLAUSIBLE_COST + 1.0], [True, False, True, True])
    best = _fits(np.zeros((4, 3)), np.zeros(4), np.ones(4, dtype=bool))
    assert rivals(best, candidates).tolist() == [True, False, False, False]
    unconverged_best = _fits(np.zeros((4, 3)), np.zeros(4), np.zeros(4, dtype=bool))
    assert rivals(unconverged_best, candidates).tolist() == [True, True, False, False]


def test_a_rival_must_be_distinct_under_its_own_bound_too():
    """A converged fit whose own covariance covers the best is the same solution seen from a flatter spot."""
    best = _fits([[0.0, 0.0, 0.0]], [0.0], [True], sigma_m=10.0)
    wide = _fits([[100.0, 0.0, 0.0]], [0.0], [True], sigma_m=1000.0)
    assert not rivals(best, wide)[0]
    assert rivals(best, _fits([[100.0, 0.0, 0.0]], [0.0], [True], sigma_m=10.0))[0]


def test_where_the_bound_holds_the_answered_fixes_are_consistent_with_it():
    """At a hundredth of the scene's noise (0.005 deg, 0.1 ns) the crossing's linearisation holds: no draw is
    refused and the answered fixes' NEES (2 dof: the altitude is known) has its mean in the chi-square interval.
    At the scene's own noise ML is far from its bound here (a line of sight almost along the hyperbola), and
    the NEES says so whichever start ML takes; the other test checks those fixes are ML's."""
    problem, target = ground_scene(8e3, 8e3)
    problem = problem.with_sigmas(np.asarray(problem.sigmas) / 100.0)
    rng = np.random.default_rng(7)
    fixes = solve_batch([measure(problem, target, rng) for _ in range(TRIALS)], "auto")
    answered = [f for f in fixes if not isinstance(f, LocalizationError)]
    assert len(answered) >= 0.95 * TRIALS
    errors = np.array([f.position_enu_m - target for f in answered])
    precision = np.linalg.pinv(np.array([f.covariance_enu_m2 for f in answered]), rcond=1e-9, hermitian=True)
    nees = np.einsum("ki,kij,kj->k", errors, precision, errors)
    low, high = chi2.ppf([0.005, 0.995], 2 * len(answered)) / len(answered)
    assert low <= nees.mean() <= high
