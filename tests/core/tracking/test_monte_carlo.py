"""Paper-001 Monte Carlo: accuracy, convergence, divergence and NEES consistency of the session filters.

Scenario (paper 001, section 4): Tr = 1 ms, N = 1000 (T = 1 s), emitter from (120, 100, 8) km (156.4 km) at
(-300, 100, 2) m/s, sigma_B = sigma_E = 5 mrad, sigma_Bdot = 0.2 mrad/s, sigma_TOA = 10 ns, 200 s.
Every configuration runs on the same 50 draws (common random numbers), so comparisons between
configurations are paired. ``python -m tests.core.tracking.report_figures 100`` prints the figures.

Three filters: ``velocity_kinematic`` (the paper's method), the direct joint UKF on the raw measurements
(``joint_ukf`` with ``joint_initial_range="prior"``: the paper's baseline, which has no range to start
from but a prior: by default 150 km +- 50 km, the middle of a detection range of the order of 300 km),
and the same joint UKF started from velocity_kinematic's first range (``joint_initial_range="kinematic"``,
the default before the range-mixture start; tests/core/tracking/test_at_the_bound.py measures that one, the
default now, against the posterior CRLB).

What the paper claims and what holds here:

- The velocity method locates the emitter to a few percent within a minute and does not diverge: holds.
- A known period converges faster than an unknown one: holds for every filter here.
- The velocity method converges faster than the direct joint UKF, and is the more accurate: it depends on
  where the direct filter's range prior lies, and above all on whether it is short of the truth.
  Figures from ``report_figures 100`` (last-50-s RMSE, % of range, known / unknown period; velocity
  method 1.23 / 2.02, converged to 5 % at 47 s / 76 s):

  * The default prior is 6.4 km (0.13 sigma) short of this emitter, a lucky draw: the direct joint UKF is
    the more accurate at every time and at the end (0.77 / 0.78) and converges sooner (32 s / 37 s). The
    paper's ranking does not hold. Halving or doubling the prior's sigma changes little (0.78, 0.77).
  * Started long, it loses little: with the prior's mean at the truth + 1 to 2.5 sigma it ends at
    0.79-0.89 and converges in 49-60 s.
  * Started short, it learns the range slowly through the full nonlinear model and is overconfident
    meanwhile: 1 sigma short it still ends ahead (1.08), 1.5 sigma short it ends behind the velocity
    method with a known period and level with an unknown one (1.75 / 2.02, converged at 88 s / 103 s),
    2 sigma short (56 km) it ends at 4.1 % and converges at about 155 s with a NEES far outside its
    interval, 2.5 sigma short it does not converge in 200 s. There the paper's ranking holds.
  * Weighting that sweep (prior mean at the truth + k sigma, k = -2.5 .. 2.5) by the normal density of k,
    i.e. what a prior of that width gives on average, the direct filter ends at 1.44 % / 1.48 %: behind
    the velocity method with a known period, ahead of it with an unknown one.
  * Started from velocity_kinematic's own first range, the joint UKF uses every measurement in one
    consistent model (in particular the TOA differences without the measured-angle noise that step 1 of
    the velocity method carries) and is at least as accurate as the velocity method.

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
from core.simulation.tracking import (PAPER_ACCEL_SIGMA_MPS2, PAPER_FIRST_RANGE_M, MonteCarlo, paper_config,
                                           run_monte_carlo)

RUNS = 50
#: RMSE (as a percentage of the range) below which a configuration counts as converged.
CONVERGED_PERCENT = 5.0
#: Window at the end of the run for the accuracy comparison (epochs, 1 s each).
LAST_50_S = 51

#: Two prior sigmas (the default's 50 km), the prior mean's offset for the short and long starts.
TWO_SIGMA_M = 100e3

#: The filters compared: name -> (model, config changes).
FILTERS = {
    "velocity_kinematic": ("velocity_kinematic", {}),
    "joint_kinematic": ("joint_ukf", {"joint_initial_range": "kinematic"}),
    "joint_prior": ("joint_ukf", {"joint_initial_range": "prior"}),
    "joint_prior_short": ("joint_ukf", {"joint_initial_range": "prior",
                                        "range_prior_m": PAPER_FIRST_RANGE_M - TWO_SIGMA_M}),
    "joint_prior_long": ("joint_ukf", {"joint_initial_range": "prior",
                                       "range_prior_m": PAPER_FIRST_RANGE_M + TWO_SIGMA_M}),
}

pytestmark = pytest.mark.slow


def filter_config(name: str, known: bool):
    model, changes = FILTERS[name]
    return paper_config(model, known, **changes)


@pytest.fixture(scope="module")
def paper_runs() -> dict[tuple[str, bool], MonteCarlo]:
    """Truth at constant velocity, as in the paper."""
    scenario = paper_001_scenario()
    return {(name, known): run_monte_carlo(filter_config(name, known), scenario, RUNS, seed=1000)
            for name in FILTERS for known in (True, False)}


@pytest.fixture(scope="module")
def consistency_runs() -> dict[tuple[str, bool], MonteCarlo]:
    """Truth with the filters' own acceleration noise, so that the covariance can be checked exactly."""
    scenario = paper_001_scenario(accel_sigma_mps2=PAPER_ACCEL_SIGMA_MPS2)
    runs = {(errors, known): run_monte_carlo(paper_config("velocity_kinematic", known, pseudo_range_errors=errors),
                                             scenario, RUNS, seed=5000)
            for errors in ("correlated", "independent") for known in (True, False)}
    for name in ("joint_kinematic", "joint_prior", "joint_prior_short"):
        runs[name, True] = run_monte_carlo(filter_config(name, True), scenario, RUNS, seed=5000)
    return runs


def tail_rmse_percent(mc: MonteCarlo) -> float:
    """Position RMSE over runs and the last 50 s, as a percentage of the mean range there."""
    errors = mc.position_errors_m[:, -LAST_50_S:]
    return 100.0 * float(np.sqrt(np.mean(errors**2)) / mc.ranges_m[:, -LAST_50_S:].mean())


@pytest.mark.parametrize("known", [True, False])
def test_within_3_percent_of_range_over_the_last_50_s(paper_runs, known):
    for name in ("velocity_kinematic", "joint_kinematic", "joint_prior"):
        assert tail_rmse_percent(paper_runs[name, known]) < 3.0, name


@pytest.mark.parametrize("known", [True, False])
def test_joint_ukf_from_the_kinematic_start_is_at_least_as_accurate_over_the_last_50_s(paper_runs, known):
    """Against the joint UKF started from velocity_kinematic's own first range the paper's ranking does not
    hold: see the module docstring."""
    assert tail_rmse_percent(paper_runs["joint_kinematic", known]) <= tail_rmse_percent(
        paper_runs["velocity_kinematic", known])


@pytest.mark.parametrize("known", [True, False])
def test_direct_joint_ukf_with_the_default_prior_beats_the_velocity_method_here(paper_runs, known):
    """The default prior (150 km +- 50 km) is 0.13 sigma short of this emitter's 156.4 km: the direct joint
    UKF has a position from the first epoch, converges to 5 % of range first and is the more accurate over
    the last 50 s. What this says is that a good prior is worth a lot, not that the direct filter learns the
    range fast: see the two-sigma-short test."""
    direct, kinematic = paper_runs["joint_prior", known], paper_runs["velocity_kinematic", known]
    assert not np.isnan(direct.position_errors_m).any()
    assert direct.convergence_time_s(CONVERGED_PERCENT) < kinematic.convergence_time_s(CONVERGED_PERCENT)
    assert tail_rmse_percent(direct) < tail_rmse_percent(kinematic)


@pytest.mark.parametrize("known", [True, False])
def test_direct_joint_ukf_started_two_sigma_long_still_ends_ahead(paper_runs, known):
    """A prior 100 km (2 sigma) beyond the emitter costs the direct filter little."""
    assert tail_rmse_percent(paper_runs["joint_prior_long", known]) < tail_rmse_percent(
        paper_runs["velocity_kinematic", known])


@pytest.mark.parametrize("known", [True, False])
def test_velocity_method_beats_the_direct_joint_ukf_started_two_sigma_short(paper_runs, known):
    """Paper 001's claim holds against a direct joint UKF whose prior is 100 km (2 sigma) short of the
    emitter: the velocity method is the more accurate at 50, 100, 150 and 200 s and over the last 50 s,
    and converges to 5 % of range sooner."""
    direct, kinematic = paper_runs["joint_prior_short", known], paper_runs["velocity_kinematic", known]
    for t in (50, 100, 150, 200):
        assert kinematic.rmse_percent()[t] < direct.rmse_percent()[t], t
    assert tail_rmse_percent(kinematic) < tail_rmse_percent(direct)
    assert kinematic.convergence_time_s(CONVERGED_PERCENT) < direct.convergence_time_s(CONVERGED_PERCENT)


@pytest.mark.parametrize("name", ["velocity_kinematic", "joint_kinematic", "joint_prior"])
def test_known_period_converges_at_least_as_fast_as_unknown(paper_runs, name):
    """Convergence time: the first epoch from which the position RMSE over the runs (a run without a
    position yet counting as infinite error) stays at or below 5 % of the mean true range to the end."""
    known = paper_runs[name, True].convergence_time_s(CONVERGED_PERCENT)
    unknown = paper_runs[name, False].convergence_time_s(CONVERGED_PERCENT)
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


@pytest.mark.parametrize("name", ["joint_kinematic", "joint_prior"])
def test_joint_ukf_nees_is_inside_its_99_percent_interval_over_the_last_100_s(consistency_runs, name):
    mean_nees = consistency_runs[name, True].nees[:, -100:].mean(axis=0)
    low, high = nees_interval(RUNS)
    assert ((mean_nees >= low) & (mean_nees <= high)).mean() >= 0.9


def test_direct_joint_ukf_started_two_sigma_short_is_still_overconfident_after_100_s(consistency_runs):
    """Started 2 sigma short, the direct joint UKF has not recovered after 100 s: its mean NEES over the last
    100 s is above the 99 % interval on every epoch (the linearised covariance shrank faster than the range
    error)."""
    mean_nees = consistency_runs["joint_prior_short", True].nees[:, -100:].mean(axis=0)
    _, high = nees_interval(RUNS)
    assert np.all(mean_nees > high)
