"""The network tracker against Stone Soup's unscented Kalman filter on the same reports (a yardstick).

Stone Soup's UKF (its default unscented parameters, ``UnscentedKalmanPredictor`` and ``UnscentedKalmanUpdater``)
runs with core's measurement model (``bench/network_core.py``) on each trial's reports in time order, started
from core's estimate part-way in (it has no start for a line of sight of its own); the position RMSE of both
over the scene's converged epochs is compared on the same reports.
"""

from __future__ import annotations

import pytest

pytest.importorskip("stonesoup")

from bench.network_core import stonesoup_accuracy  # noqa: E402
from core.simulation.network import airborne_df_scene, df_network_scene, toa_network_scene  # noqa: E402


@pytest.mark.parametrize("scene, trials, start_after_s", [
    pytest.param(df_network_scene, 3, 10.0, marks=pytest.mark.slow),
    (toa_network_scene, 6, 10.0),
    (airborne_df_scene, 6, 100.0),
])
def test_at_least_as_accurate_as_stonesoup_ukf_on_the_same_reports(scene, trials, start_after_s):
    core_rmse_m, stonesoup_rmse_m = stonesoup_accuracy(scene(), trials, seed=36_000, start_after_s=start_after_s)
    # The same reports and start: the filters differ only in their unscented rule (core's cubature over the
    # position, Stone Soup's scaled points over the state); a relative 1e-3 is far below the Monte Carlo spread.
    assert core_rmse_m <= stonesoup_rmse_m * (1.0 + 1e-3), (core_rmse_m, stonesoup_rmse_m)
