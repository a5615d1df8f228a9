"""The network tracker against the posterior CRLB on the three scenes (fixed seeds).

Judged from each scene's ``converged_after_s``: the position RMSE (root of the mean squared error over the
epochs and trials) at most 1.1x the PCRB's (root of its mean square), and the position NEES averaged over
those epochs and the trials inside the chi-square 99 % interval of a per-epoch mean over the trials (3 degrees
of freedom per trial); the per-epoch means inside it at nine epochs in ten at least.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from core.simulation.network import START_TIME_S, airborne_df_scene, df_network_scene, evaluate_network, \
    toa_network_scene

TRIALS = 40


def _judge(evaluation):
    lo, hi = evaluation.nees_interval_99
    after = evaluation.times_s >= START_TIME_S + evaluation.converged_after_s
    assert np.all(evaluation.tracked_fraction[after] == 1.0)
    assert evaluation.rmse_over_pcrb <= 1.1, evaluation.summary()
    assert lo <= evaluation.nees_after <= hi, evaluation.summary()
    inside = (evaluation.nees_position[after] >= lo) & (evaluation.nees_position[after] <= hi)
    assert inside.mean() >= 0.8, evaluation.summary()


def test_direction_finder_network_tracks_a_ground_vehicle_at_the_bound():
    evaluation = evaluate_network(df_network_scene(), TRIALS, seed=31_000)
    _judge(evaluation)
    after = evaluation.times_s >= START_TIME_S + evaluation.converged_after_s
    assert np.all(evaluation.confirmed_fraction[after] == 1.0)


def test_toa_network_tracks_an_aircraft_at_the_bound():
    evaluation = evaluate_network(toa_network_scene(), TRIALS, seed=32_000)
    _judge(evaluation)


def test_airborne_direction_finder_is_tentative_before_the_turn_and_at_the_bound_after():
    scene = airborne_df_scene()
    evaluation = evaluate_network(scene, TRIALS, seed=33_000)
    _judge(evaluation)
    before_turn = evaluation.times_s <= START_TIME_S + scene.platform.straight_s
    assert np.all(evaluation.confirmed_fraction[before_turn] == 0.0)  # never confident before the turn
    _, hi = evaluation.nees_interval_99
    assert np.mean(evaluation.nees_position[before_turn & (evaluation.times_s > START_TIME_S + 10)]) <= hi


@pytest.mark.slow
@pytest.mark.parametrize("scene", [df_network_scene, toa_network_scene, airborne_df_scene])
@pytest.mark.parametrize("variant", [1, 2])
def test_other_variants_of_each_scene_at_the_bound(scene, variant):
    _judge(evaluate_network(scene(variant=variant), TRIALS, seed=34_000 + variant))


@pytest.mark.slow
@pytest.mark.parametrize("variant", [0, 3])
def test_four_toa_stations_track_an_aircraft_at_each_truths_bound_with_an_honest_height(variant):
    # Three TOA differences for three coordinates: the height is known only to hundreds of metres, along a
    # ridge that turns across the truths' spread; the PCRB of their mean information is reached by no tracker
    # (toa_network_scene), so the position RMSE is judged against the RMS of each truth's own bound. Each
    # trial's height error stays correlated for a minute: 100 trials.
    trials = 100
    evaluation = evaluate_network(toa_network_scene(variant, station_count=4), trials, seed=37_000 + variant)
    after = evaluation.times_s >= START_TIME_S + evaluation.converged_after_s
    assert np.all(evaluation.tracked_fraction[after] == 1.0)
    # Still a Gaussian sum over altitude, and placed: confirmed once its height's standard deviation is
    # inside confirm_relative_sigma of the nearest station's distance (a low aircraft's may take a minute more).
    assert evaluation.confirmed_fraction[-1] == 1.0
    lo, hi = evaluation.nees_interval_99
    assert lo <= evaluation.nees_after <= hi, evaluation.summary()
    errors = evaluation.estimates_enu[:, after, 2] - evaluation.truths_enu[:, after, 2]
    height_nees = np.mean(errors ** 2 / evaluation.covariances_enu[:, after, 2, 2])
    assert chi2.ppf(0.005, trials) / trials <= height_nees <= chi2.ppf(0.995, trials) / trials, height_nees
    assert evaluation.rmse_over_own_bound <= 1.1, evaluation.summary()


@pytest.mark.slow
def test_an_imm_over_two_levels_stays_at_the_bound_of_the_truths_level():
    scene = df_network_scene()
    config = replace(scene.config, imm_accel_sigmas_mps2=(0.05, 0.4))
    evaluation = evaluate_network(scene, 30, seed=35_000, config=config)
    assert evaluation.rmse_over_pcrb <= 1.1, evaluation.summary()
    lo, hi = evaluation.nees_interval_99
    assert lo <= evaluation.nees_after <= hi, evaluation.summary()
