"""Paper-001 Monte Carlo: accuracy, convergence, divergence and NEES consistency of the session filters.

Scenario (paper 001, section 4): Tr = 1 ms, N = 1000 (T = 1 s), emitter from (120, 100, 8) km at
(-300, 100, 2) m/s, sigma_B = sigma_E = 5 mrad, sigma_Bdot = 0.2 mrad/s, sigma_TOA = 10 ns, 200 s.
Every configuration runs on the same 50 draws (common random numbers), so comparisons between
configurations are paired.

What the paper claims and what holds here:

- The velocity method locates the emitter to a few percent within a minute and does not diverge: holds.
- A known period converges faster than an unknown one: holds for ``velocity_kinematic``.
- The velocity method converges faster than the direct joint UKF: does not hold against our
  ``joint_ukf``, which is started from the same first range (the velocity method's own bootstrap), so
  that the comparison is of the filters rather than of an arbitrary range prior. From that common start
  the joint UKF, which uses every measurement in one consistent model (in particular the TOA
  differences without the measured-angle noise that step 1 of the velocity method carries), is at
  least as accurate. The test below asserts that ordering; the figures are in the report.
- Consistency: the paper's step 3, taking each pseudo-range as independent, is overconfident (mean
  NEES far above its 99 % interval) because successive pseudo-ranges share the slowly varying
  velocity error. With that correlation carried (the default, ``pseudo_range_errors="correlated"``)
  the NEES is inside the interval.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from core.simulation.emitter import paper_001_scenario
from tests.core.tracking.scenarios import PAPER_ACCEL_SIGMA_MPS2, MonteCarlo, paper_config, run_monte_carlo

RUNS = 50
#: RMSE (as a percentage of the range) below which a configuration counts as converged.
CONVERGED_PERCENT = 5.0
#: Window at the end of the run for the accuracy comparison (epochs, 1 s each).
LAST_50_S = 51

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def paper_runs() -> dict[tuple[str, bool], MonteCarlo]:
    """Truth at constant velocity, as in the paper."""
    scenario = paper_001_scenario()
    return {(model, known): run_monte_carlo(paper_config(model, known), scenario, RUNS, seed=1000)
            for model in ("velocity_kinematic", "joint_ukf") for known in (True, False)}


@pytest.fixture(scope="module")
def consistency_runs() -> dict[tuple[str, bool], MonteCarlo]:
    """Truth with the filters' own acceleration noise, so that the covariance can be checked exactly."""
    scenario = paper_001_scenario(accel_sigma_mps2=PAPER_ACCEL_SIGMA_MPS2)
    runs = {(errors, known): run_monte_carlo(paper_config("velocity_kinematic", known, pseudo_range_errors=errors),
                                             scenario, RUNS, seed=5000)
            for errors in ("correlated", "independent") for known in (True, False)}
    runs["joint_ukf", True] = run_monte_carlo(paper_config("joint_ukf", True), scenario, RUNS, seed=5000)
    return runs


def tail_rmse_percent(mc: MonteCarlo) -> float:
    """Position RMSE over runs and the last 50 s, as a percentage of the mean range there."""
    errors = mc.position_errors_m[:, -LAST_50_S:]
    return 100.0 * float(np.sqrt(np.mean(errors**2)) / mc.ranges_m[:, -LAST_50_S:].mean())


@pytest.mark.parametrize("known", [True, False])
def test_velocity_kinematic_is_within_3_percent_of_range_over_the_last_50_s(paper_runs, known):
    assert tail_rmse_percent(paper_runs["velocity_kinematic", known]) < 3.0
    assert tail_rmse_percent(paper_runs["joint_ukf", known]) < 3.0


@pytest.mark.parametrize("known", [True, False])
def test_joint_ukf_from_the_same_start_is_at_least_as_accurate_over_the_last_50_s(paper_runs, known):
    """The paper's claim (velocity method ahead of the joint UKF) does not reproduce against a joint UKF
    started from the same first range: see the module docstring."""
    assert tail_rmse_percent(paper_runs["joint_ukf", known]) <= tail_rmse_percent(
        paper_runs["velocity_kinematic", known])


@pytest.mark.parametrize("model", ["velocity_kinematic", "joint_ukf"])
def test_known_period_converges_at_least_as_fast_as_unknown(paper_runs, model):
    """Convergence time: the first epoch from which the position RMSE over the runs (a run without a
    position yet counting as infinite error) stays at or below 5 % of the mean true range to the end."""
    known = paper_runs[model, True].convergence_time_s(CONVERGED_PERCENT)
    unknown = paper_runs[model, False].convergence_time_s(CONVERGED_PERCENT)
    assert np.isfinite(known) and np.isfinite(unknown)
    assert known <= unknown
    assert unknown <= 120.0


@pytest.mark.parametrize("known", [True, False])
def test_no_velocity_kinematic_run_diverges(paper_runs, known):
    mc = paper_runs["velocity_kinematic", known]
    initialised = ~np.isnan(mc.nees)
    assert initialised[:, 40:].all(), "every run has a position by 40 s"
    assert np.all(mc.min_eigenvalues[initialised] > 0.0), "every covariance positive definite"
    final = np.abs(mc.errors[:, -1]) / mc.sigmas[:, -1]
    assert final.max() <= 5.0, "every final error inside 5 sigma"


def nees_interval(runs: int, dof: int = 6) -> tuple[float, float]:
    """Two-sided 99 % interval of the mean over ``runs`` of a chi-square(``dof``) NEES."""
    low, high = chi2.ppf([0.005, 0.995], dof * runs) / runs
    return float(low), float(high)


@pytest.mark.parametrize("known", [True, False])
def test_velocity_kinematic_nees_is_inside_its_99_percent_interval_over_the_last_100_s(consistency_runs, known):
    """Per epoch, the mean over runs of the 6-dof NEES (position and velocity) against the chi-square
    interval. A consistent filter falls outside on 1 % of epochs; 90 % inside leaves room for the
    correlation between neighbouring epochs without hiding a real inconsistency (the paper's
    independent pseudo-ranges fall inside on none)."""
    mean_nees = consistency_runs["correlated", known].nees[:, -100:].mean(axis=0)
    low, high = nees_interval(RUNS)
    inside = (mean_nees >= low) & (mean_nees <= high)
    assert inside.mean() >= 0.9
    assert low <= mean_nees.mean() <= high


@pytest.mark.parametrize("known", [True, False])
def test_paper_independent_pseudo_ranges_are_overconfident(consistency_runs, known):
    """What is true of the paper's step 3 as written: the NEES sits above the interval on every epoch."""
    mean_nees = consistency_runs["independent", known].nees[:, -100:].mean(axis=0)
    _, high = nees_interval(RUNS)
    assert np.all(mean_nees > high)


def test_joint_ukf_nees_is_inside_its_99_percent_interval_over_the_last_100_s(consistency_runs):
    mean_nees = consistency_runs["joint_ukf", True].nees[:, -100:].mean(axis=0)
    low, high = nees_interval(RUNS)
    assert ((mean_nees >= low) & (mean_nees <= high)).mean() >= 0.9
