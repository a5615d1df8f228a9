"""The session filters against the posterior CRLB, with truths drawn from the filter's own model.

Paper 001's geometry (emitter from (120, 100, 8) km at (-300, 100, 2) m/s, 5 mrad angles, 0.2 mrad/s
azimuth rate, 10 ns TOA, a report per second, 200 s); the truth's white acceleration is the filter's;
the figure is the position RMSE over runs and the last 50 reports over the RMS of the PCRB there
(:mod:`core.tracking.bound`), and the position NEES (3 dof) per report against its 99 % interval.

Measured with ``python -m tests.core.tracking.report_figures bound 200 40`` (seeds 30000 + 100 b, 50-run
blocks b; the ratio varies between blocks by up to +-0.15, because a few runs in a hundred end 2-3 sigma
off in range; pooled = RMS of the block ratios; NEES = position NEES over runs and the last 50 reports):

================================  ===========================  ===========================
ratio to the PCRB (NEES)          q = 0.05 m/s^2 known/unknown  q = 0.5 m/s^2 known/unknown
================================  ===========================  ===========================
joint_ukf, range mixture (dflt)   1.02 / 1.01 (2.5-3.7)         1.02 / 1.04 (2.3-3.3)
joint_ukf, kinematic start        0.95 / 1.00 (2.6-3.0) [100]   1.67 / 1.64 (3.6-5.6) [100]
joint_ukf, prior 150 +- 50 km     0.91 / 0.92 (2.5-2.8) [100]   1.02 / 1.08 (2.5-3.2) [100]
velocity_kinematic                1.29 / 2.15 (2.4-3.0) [100]   2.09 / 2.25 (3.8-5.3) [100]
================================  ===========================  ===========================

([100]: 100 runs, the first two blocks; the default's figures are 200 runs.) The prior start sits on
this emitter (156 km): it holds range information the bound, with a diffuse position prior, does not.
The 1.1x target holds at both (at q = 0.5 because the range mixture does not merge its components, see
:mod:`core.tracking.range_mixture`); the tests assert 1.1x on their fixed
seeds (1.07 / 1.07 and 1.03 / 1.03 there), and that no ratio is below 0.8 (below the bound by that much
is a bug in the bound or the bookkeeping, not luck).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from core.simulation.emitter import paper_001_scenario
from core.simulation.tracking import against_bound, paper_config

RUNS = 50
LAST_50 = slice(-50, None)

pytestmark = pytest.mark.slow


def nees_interval(runs: int, dof: int = 3) -> tuple[float, float]:
    """Two-sided 99 % interval of the mean over ``runs`` of a chi-square(``dof``) NEES."""
    low, high = chi2.ppf([0.005, 0.995], dof * runs) / runs
    return float(low), float(high)


@pytest.mark.parametrize("q, ceiling", [(0.05, 1.1), (0.5, 1.1)])
@pytest.mark.parametrize("period_known", [True, False])
def test_default_joint_ukf_is_near_the_bound_and_consistent(q, ceiling, period_known):
    config = paper_config("joint_ukf", period_known, accel_sigma_mps2=q)
    assert config.joint_initial_range == "range_mixture"
    result = against_bound(config, paper_001_scenario(accel_sigma_mps2=q), RUNS, seed=1000)
    ratio = result.ratio(LAST_50)
    assert 0.8 < ratio <= ceiling, ratio
    mean_nees = result.mean_nees(LAST_50)
    low, high = nees_interval(RUNS)
    assert low <= mean_nees.mean() <= high, mean_nees.mean()
    assert ((mean_nees >= low) & (mean_nees <= high)).mean() >= 0.9


@pytest.mark.parametrize("q", [1.0, 2.0])
@pytest.mark.parametrize("period_known", [True, False])
def test_where_the_pcrb_is_not_attainable_the_default_is_near_each_runs_own_bound_and_consistent(q, period_known):
    """At q >= 1 m/s^2 no estimator nears the PCRB (it averages the information over truths whose lines of
    sight spread far more than the angle noise; the batch oracle sits 3.5-28x above it: see
    :mod:`core.tracking.bound`); the yardstick there is the RMS of each run's own bound. 0.68-0.90x of
    it on these seeds (the PCRB ratio is 2.8-19x)."""
    config = paper_config("joint_ukf", period_known, accel_sigma_mps2=q)
    result = against_bound(config, paper_001_scenario(accel_sigma_mps2=q), RUNS, seed=1000)
    assert 0.5 < result.own_ratio(LAST_50) <= 1.2, result.own_ratio(LAST_50)
    mean_nees = result.mean_nees(LAST_50)
    low, high = nees_interval(RUNS)
    assert low <= mean_nees.mean() <= high, mean_nees.mean()


#: The switching target: quiet 70 s, manoeuvring 40 s, quiet 50 s, manoeuvring 40 s (m/s^2).
QUIET_MPS2, MANOEUVRE_MPS2 = 0.05, 1.0
SWITCHING_SCHEDULE = (QUIET_MPS2,) * 70 + (MANOEUVRE_MPS2,) * 40 + (QUIET_MPS2,) * 50 + (MANOEUVRE_MPS2,) * 40
FROM_60_S = slice(60, None)


@pytest.fixture(scope="module")
def switching_runs():
    scenario = paper_001_scenario(accel_sigma_by_interval_mps2=SWITCHING_SCHEDULE)
    imm = paper_config("joint_ukf", True, accel_sigma_mps2=MANOEUVRE_MPS2,
                       imm_accel_sigmas_mps2=(QUIET_MPS2, MANOEUVRE_MPS2))
    quiet = paper_config("joint_ukf", True, accel_sigma_mps2=QUIET_MPS2)
    return {name: against_bound(config, scenario, 40, seed=40000) for name, config in (("imm", imm), ("quiet", quiet))}


def test_imm_on_a_switching_target_is_within_1_3x_the_bound_of_the_true_model(switching_runs):
    """Quiet (0.05 m/s^2) and manoeuvring (1 m/s^2) legs of 70/40/50/40 s; the bound knows the schedule,
    the IMM over (0.05, 1) does not. From 60 s on: 1.15x on these seeds (1.12x on seeds 41000+)."""
    result = switching_runs["imm"]
    assert result.ratio(FROM_60_S) <= 1.3
    for leg in (slice(60, 110), slice(110, 160), slice(160, 201)):
        assert result.ratio(leg) <= 1.5, leg
    low, high = nees_interval(40)
    assert low <= result.mean_nees(FROM_60_S).mean() <= high


def test_a_single_quiet_level_is_overconfident_on_the_switching_target(switching_runs):
    """What the IMM is for: tuned to the quiet legs, one joint UKF's NEES leaves its interval in the
    manoeuvres and its RMSE is far from the bound."""
    result = switching_runs["quiet"]
    _, high = nees_interval(40)
    assert result.mean_nees(slice(160, 201)).mean() > 3.0 * high
    assert result.ratio(FROM_60_S) > 2.0 * switching_runs["imm"].ratio(FROM_60_S)
