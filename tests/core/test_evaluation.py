"""Monte Carlo evaluation (core.simulation.measurements.evaluate): accuracy, noise models, chunking, Dask.

Bars from theory: the ML is efficient (MSE / tr CRLB near 1; with 2,000 trials the ratio's sampling sd is
below 3.2 %, so 0.9 .. 1.1 is over 3 sd); uniform noise of the same sigma has the same covariance, so the
first-order RMSE is the same; a seeded result does not depend on how the trials are chunked or run.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom

from core.estimators import SolveOptions
from core.parallel import Stopped
from core.problem.build import Bearing, build_problem
from core.problem.frame import LocalPoint
from core.simulation.measurements import OUTLIER_PROBABILITY, OUTLIER_SCALE, draw_noise, evaluate

DEG = np.pi / 180.0
STATIONS = [("a", LocalPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(20_000.0, 0.0, 100.0)),
            ("c", LocalPoint(10_000.0, 18_000.0, 300.0))]
TARGET_ENU_M = np.array([9_000.0, 7_000.0, 3_000.0])


def three_stations(sigma_deg: float = 0.5):
    sigma = sigma_deg * DEG
    return build_problem(STATIONS, [Bearing(i, 0.0, 0.0, sigma, sigma) for i, _ in STATIONS])


@pytest.fixture(scope="module")
def gaussian_and_uniform():
    problem = three_stations()
    return {noise: evaluate(problem, TARGET_ENU_M, ["ml"], 2000, 14, noise)["ml"] for noise in ("gaussian", "uniform")}


def test_ml_is_efficient_on_three_stations_with_2000_trials(gaussian_and_uniform):
    ml = gaussian_and_uniform["gaussian"]
    assert ml.failures == 0
    assert 0.9 <= ml.efficiency <= 1.1


def test_uniform_noise_of_the_same_sigma_gives_the_gaussian_rmse_within_10_percent(gaussian_and_uniform):
    uniform, gaussian = gaussian_and_uniform["uniform"], gaussian_and_uniform["gaussian"]
    assert uniform.failures == 0
    assert abs(uniform.rmse_m / gaussian.rmse_m - 1) < 0.10


def test_uniform_draws_have_the_stated_sigma_and_bounded_support():
    sigmas = np.array([1.0, 3.0])
    draws = draw_noise(np.random.default_rng(1), sigmas, "uniform", size=200_000)
    assert np.all(np.abs(draws) <= np.sqrt(3.0) * sigmas)
    # the sample sd of 200k uniforms scatters by about 0.2 %
    np.testing.assert_allclose(draws.std(axis=0), sigmas, rtol=0.01)


def test_outlier_draws_are_a_contaminated_gaussian():
    n = 400_000
    draws = draw_noise(np.random.default_rng(2), np.array([2.0]), "outlier", size=n)[:, 0] / 2.0
    variance = (1 - OUTLIER_PROBABILITY) + OUTLIER_PROBABILITY * OUTLIER_SCALE**2
    assert draws.var() == pytest.approx(variance, rel=0.03)
    # beyond 5 sigma: almost only the gross errors (P(|N(0, scale^2)| > 5) of them)
    from scipy.stats import norm

    p = (1 - OUTLIER_PROBABILITY) * 2 * norm.sf(5.0) + OUTLIER_PROBABILITY * 2 * norm.sf(5.0 / OUTLIER_SCALE)
    low, high = binom.ppf([0.0005, 0.9995], n, p)
    assert low <= np.count_nonzero(np.abs(draws) > 5.0) <= high


def test_exclusion_removes_gross_errors_that_reporting_keeps():
    problem = three_stations()
    report = evaluate(problem, TARGET_ENU_M, ["ml"], 600, 21, "outlier")["ml"]
    exclude = evaluate(problem, TARGET_ENU_M, ["ml"], 600, 21, "outlier", SolveOptions(outliers="exclude"))["ml"]
    assert report.excluded_trials == 0
    # P(some gross error among 6 measurements) = 1 - 0.95^6 = 26 %: many of those trials exclude one; the others
    # hold errors too small to detect or, with the one dof a bearing's exclusion leaves, to isolate (exclusion
    # names a measurement only where its refit alone passes the test)
    assert exclude.excluded_trials > 0.4 * (1 - 0.95**6) * 600
    assert exclude.rmse_m < 0.8 * report.rmse_m


def test_the_draws_do_not_depend_on_the_chunk_size():
    problem = three_stations()
    small = evaluate(problem, TARGET_ENU_M, ["eove", "ml"], 300, 5, chunk_trials=10)
    large = evaluate(problem, TARGET_ENU_M, ["ml", "eove"], 300, 5, chunk_trials=1000)
    for method in ("eove", "ml"):
        np.testing.assert_array_equal(small[method].errors_enu_m, large[method].errors_enu_m)
    alone = evaluate(problem, TARGET_ENU_M, ["ml"], 300, 5, chunk_trials=100)
    np.testing.assert_array_equal(alone["ml"].errors_enu_m, large["ml"].errors_enu_m)


def test_should_stop_raises_the_one_stopped_exception():
    calls = []

    def stop_after_one_chunk():
        calls.append(1)
        return len(calls) > 1

    with pytest.raises(Stopped):
        evaluate(three_stations(), TARGET_ENU_M, ["ml"], 500, 1, should_stop=stop_after_one_chunk, chunk_trials=64)
    assert len(calls) == 2


def test_progress_reports_every_chunk():
    seen = []
    evaluate(three_stations(), TARGET_ENU_M, ["eove"], 200, 1, chunk_trials=64, progress=lambda d, t: seen.append((d, t)))
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)]


def test_session_filter_runs_do_not_depend_on_the_chunking():
    from core.simulation.emitter import paper_001_scenario
    from core.simulation.tracking import monte_carlo_tracks, paper_config

    config = paper_config("velocity_kinematic", True)
    scenario = paper_001_scenario(epochs=40)
    one = monte_carlo_tracks(config, scenario, 3, 70, chunk_runs=1)
    all_ = monte_carlo_tracks(config, scenario, 3, 70, chunk_runs=3)
    for key in ("estimates", "covariances", "truths", "ranges_m"):
        np.testing.assert_array_equal(one[key], all_[key])


@pytest.mark.slow
def test_a_two_worker_local_cluster_gives_the_in_process_result_bit_for_bit():
    distributed = pytest.importorskip("distributed")
    from core.simulation.emitter import paper_001_scenario
    from core.simulation.tracking import against_bound, paper_config

    problem = three_stations()
    here = evaluate(problem, TARGET_ENU_M, ["ml", "eove"], 400, 9, chunk_trials=64)
    config = paper_config("joint_ukf", True)
    scenario = paper_001_scenario(epochs=30)
    track_here = against_bound(config, scenario, 4, 3)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        there = evaluate(problem, TARGET_ENU_M, ["ml", "eove"], 400, 9, chunk_trials=64, scheduler=client)
        by_address = evaluate(problem, TARGET_ENU_M, ["ml"], 400, 9, chunk_trials=128, scheduler=cluster.scheduler_address)
        track_there = against_bound(config, scenario, 4, 3, scheduler=client)
        assert len(client.scheduler_info()["workers"]) == 2
    for method in ("ml", "eove"):
        np.testing.assert_array_equal(here[method].errors_enu_m, there[method].errors_enu_m)
        assert here[method].nees_mean == there[method].nees_mean
    np.testing.assert_array_equal(here["ml"].errors_enu_m, by_address["ml"].errors_enu_m)
    np.testing.assert_array_equal(track_here.squared_errors_m2, track_there.squared_errors_m2)
    np.testing.assert_array_equal(track_here.bound_m2, track_there.bound_m2)


def test_failed_trials_are_counted_by_error_code_with_the_earliest_trials_message_whatever_the_chunking():
    """tls has no altitude here and ove sees two lines of sight: every trial of both fails, and says why."""
    problem = build_problem(STATIONS[:2], [Bearing(i, 0.0, 0.0, 0.5 * DEG, 0.5 * DEG) for i, _ in STATIONS[:2]])
    small = evaluate(problem, TARGET_ENU_M, ["tls", "ove", "ml"], 60, 5, chunk_trials=7)
    large = evaluate(problem, TARGET_ENU_M, ["ml", "ove", "tls"], 60, 5, chunk_trials=1000)
    for method in ("tls", "ove"):
        (code, (count, message)), = small[method].failure_reasons.items()
        assert small[method].failures == count == 60
        assert large[method].failure_reasons == small[method].failure_reasons
    assert small["tls"].failure_reasons["too_few_measurements"][1].startswith("tls locates from azimuths only")
    assert small["ml"].failures == 0 and small["ml"].failure_reasons == {}
