"""Every method's verdicts on clean data raise false alarms at their nominal rates.

A fix's chi-square and studentized residuals judge the residuals the ML fit of the used measurements leaves
(a closed form's own residuals also carry its distance from that fit). On clean Gaussian data the chi-square
on ``dof`` is then chi-square distributed and each studentized residual standard normal, so
``outlier_suspected`` (``|t| > OUTLIER_SIGMAS``) fires on at most ``M 2 Q(OUTLIER_SIGMAS)`` of the fixes and
``p_value < 0.1`` on 10 % of them: both within a binomial interval over the trials, for every registered method.

The scene is the wide one where the closed forms' residuals differ most from ML's: four azimuth-only stations
300 km apart, 1 deg, the target 75 km from one of them at a known altitude. A method that cannot serve it
gets its contract scene (:func:`tests.core.estimators.test_contract.scene_for`).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom, norm

from core.errors import LocalizationError
from core.estimators import SolveOptions, solve_batch
from core.estimators.finish import OUTLIER_SIGMAS
from core.simulation import scenarios as sc
from tests.core.estimators.test_contract import CASES, IDS, scene_for

TRIALS = 600
#: Two-sided risk of each binomial interval.
RISK = 1e-3
P_LEVEL = 0.1

WIDE = sc.Scene(
    "4 azimuth-only stations 300 km apart, 1 deg, known altitude",
    (("w-sw", sc.geodetic(34.0, 9.0, 100.0)), ("w-se", sc.geodetic(34.0, 12.3, 80.0)),
     ("w-ne", sc.geodetic(36.7, 12.3, 120.0)), ("w-nw", sc.geodetic(36.7, 9.0, 60.0))),
    tuple(sc.Sensor(i, 1.0 * sc.DEG) for i in ("w-sw", "w-se", "w-ne", "w-nw")),
    sc.geodetic(36.2, 11.7, 500.0), altitude_m=500.0)


def _scene(name, variant) -> sc.Scene:
    (fix,) = solve_batch([WIDE.problem()], name, SolveOptions(variant=variant))
    return scene_for(name) if isinstance(fix, LocalizationError) else WIDE


@pytest.mark.parametrize(("name", "variant"), CASES, ids=IDS)
def test_clean_data_raise_outlier_and_chi_square_alarms_at_their_nominal_rates(name, variant):
    scene = _scene(name, variant)
    rng = np.random.default_rng(20261204)
    draws = [scene.problem(rng) for _ in range(TRIALS)]
    fixes = [f for f in solve_batch(draws, name, SolveOptions(variant=variant))
             if not isinstance(f, LocalizationError)]
    assert len(fixes) >= 0.99 * TRIALS
    count = int(np.count_nonzero(fixes[0].used))
    outliers = sum("outlier_suspected" in {w.code for w in f.warnings} for f in fixes)
    nominal = count * 2.0 * norm.sf(OUTLIER_SIGMAS)
    assert outliers <= binom.ppf(1.0 - RISK, len(fixes), nominal), (scene.name, outliers)
    assert fixes[0].dof > 0
    low = sum(f.p_value < P_LEVEL for f in fixes)
    lower, upper = binom.interval(1.0 - RISK, len(fixes), P_LEVEL)
    assert lower <= low <= upper, (scene.name, low / len(fixes))
