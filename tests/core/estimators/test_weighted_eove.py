"""Weighted EOVE against the CRLB on a generic 4-station scene with 1 deg on both angles.

Weighted EOVE is the small-noise BLUE of the orthogonal-vector equations, so
its RMSE should sit on the bound; plain EOVE and OVE are reported beside it.
"""

from __future__ import annotations

import numpy as np

from core.simulation.measurements import evaluate

from core.simulation import scenarios as sc
from tests.core.estimators.test_paper000 import nees_interval

TRIALS = 1000


def test_weighted_eove_is_within_15_percent_of_the_crlb():
    scene = sc.generic_3d(1.0)
    problem = scene.template()
    results = evaluate(problem, scene.target_enu_m(problem), ["weighted_eove", "eove", "ove"], TRIALS,
                       3000)
    for name, r in results.items():
        print(f"{name:14s} rmse {r.rmse_m:8.1f} m  crlb {r.crlb_rmse_m:8.1f} m  ratio {r.rmse_m / r.crlb_rmse_m:5.3f}"
              f"  nees {r.nees_mean:5.2f}  failures {r.failures}")
    weighted = results["weighted_eove"]
    assert weighted.failures == 0
    assert abs(weighted.rmse_m / weighted.crlb_rmse_m - 1) < 0.15
    low, high = nees_interval(3, TRIALS)
    assert low < weighted.nees_mean < high
    assert results["eove"].rmse_m > 0.95 * weighted.crlb_rmse_m
    assert results["ove"].rmse_m > 0.95 * weighted.crlb_rmse_m
