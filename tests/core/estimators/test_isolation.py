"""A fault is detected with one degree of freedom, isolated only with two or more (RAIM's rule).

TOAs at 20 ns from stations 15-25 km apart, one of them 1 us off (50 sigma). With five TOAs (one dof) every
studentized residual is as large: the fault is detected, no measurement is named or excluded, the fix says
``fault_detected_not_isolable`` and the iteration converges on the inconsistent data. With six (two dof) the
faulty one is named where the residuals single it out, and an innocent is named no more often than the
exclusion test's false-alarm rate allows.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom

from core.errors import LocalizationError
from core.estimators import EXCLUSION_P, SolveOptions, solve_batch
from core.problem.build import TimeOfArrival, build_problem
from core.problem.frame import LocalPoint
from core.simulation.measurements import measure

SIGMA_S = 20e-9
FAULT_S = 1e-6
TRIALS = 240
POSITIONS_M = [(0.0, 0.0, 0.0), (20e3, 0.0, 50.0), (0.0, 25e3, 3000.0), (-15e3, -5e3, 30.0), (10e3, 15e3, 1500.0),
               (-8e3, 20e3, 400.0)]
TARGET = np.array([5e3, 8e3, 3e3])


def _faulty_draws(count, seed):
    stations = [(f"s{k}", LocalPoint(*xyz)) for k, xyz in enumerate(POSITIONS_M[:count])]
    problem = build_problem(stations, [TimeOfArrival(sid, 0.0, SIGMA_S) for sid, _ in stations])
    rng = np.random.default_rng(seed)
    draws, culprits = [], []
    for trial in range(TRIALS):
        noisy = measure(problem, TARGET, rng)
        values = noisy.values.copy()
        values[trial % count] += FAULT_S
        draws.append(noisy.with_values(values))
        culprits.append(trial % count)
    return draws, culprits


def _named(fix) -> set[int]:
    """The measurements a fix blames: excluded, or named by ``outlier_suspected``."""
    named = {int(m) for m in np.flatnonzero(fix.excluded)}
    named |= {int(w.message.split()[1]) for w in fix.warnings if w.code == "outlier_suspected"}
    return named


@pytest.mark.parametrize("outliers", ["report", "exclude"])
def test_one_degree_of_freedom_detects_a_fault_and_names_no_one(outliers):
    draws, _ = _faulty_draws(5, 30)
    fixes = solve_batch(draws, "ml", SolveOptions(outliers=outliers))
    assert not any(isinstance(f, LocalizationError) for f in fixes)
    assert all(f.dof == 1 for f in fixes)
    assert all(not _named(f) for f in fixes)
    assert all(f.converged for f in fixes)
    detected = [f for f in fixes if f.p_value < EXCLUSION_P]
    assert len(detected) >= 0.9 * TRIALS
    for fix in detected:
        codes = {w.code for w in fix.warnings}
        assert "fault_detected_not_isolable" in codes
        assert "outlier_suspected" not in codes and "measurement_excluded" not in codes


@pytest.mark.parametrize("outliers", ["report", "exclude"])
def test_two_degrees_of_freedom_name_the_faulty_one_and_never_an_innocent(outliers):
    draws, culprits = _faulty_draws(6, 31)
    fixes = solve_batch(draws, "ml", SolveOptions(outliers=outliers))
    named = [_named(f) for f in fixes]
    innocents = sum(bool(n - {c}) for n, c in zip(named, culprits))
    assert innocents <= binom.ppf(0.999, TRIALS, EXCLUSION_P)
    assert sum(n == {c} for n, c in zip(named, culprits)) >= 0.6 * TRIALS
    for fix, n in zip(fixes, named):
        if not n and fix.p_value < EXCLUSION_P:
            assert "fault_detected_not_isolable" in {w.code for w in fix.warnings}
