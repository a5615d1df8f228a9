"""A covariance is a promise: the truth lies inside a fix's stated 99 % region 99 times in 100.

The class is the hybrid with no degree of freedom to spare (one bearing and two TOAs, the altitude known; one
bearing and ranges), where the fix's error is no Gaussian: near (8, 8) km of the ground scene of
test_ambiguity.py the line of sight runs almost along the TDOA hyperbola and the fix slides kilometres along
the curve, off the straight ellipse of its second moment; with a plausible second solution the error is a
two-point mixture. Over seeded draws the share of answered fixes whose truth falls outside the 99 % region
``d^T P^-1 d <= chi2_99(dof)`` must lie in the binomial interval of 1 % (at 99.5 %), on the scene the rule
was built on and on held-out ones (emitter behind the stations' baseline, other sigmas, a 3D scene, bearing
and ranges with a plausible mirror), without refusing more of them than the tie rule does.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom, chi2

from core.errors import LocalizationError
from core.estimators import solve_batch
from core.problem.build import Bearing, Range, TimeOfArrival, build_problem
from core.problem.frame import LocalPoint
from core.simulation.measurements import measure
from tests.core.estimators.test_ambiguity import GROUND, ground_scene

TRIALS = 300
LEVEL = 0.99


def _ground(east_m, north_m, sigma_deg, sigma_ns):
    measurements = [Bearing("a", 0.0, None, np.deg2rad(sigma_deg))] + [TimeOfArrival(s, 0.0, sigma_ns * 1e-9)
                                                                         for s in "bc"]
    problem = build_problem(GROUND, measurements, altitude_m=0.0)
    return problem, problem.frame.onto_altitude(np.array([east_m, north_m, 0.0]), 0.0)


def _three_d():
    stations = [("a", LocalPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(20e3, 0.0, 0.0)),
                ("c", LocalPoint(0.0, 25e3, 100.0))]
    sigma = np.deg2rad(0.5)
    measurements = [Bearing("a", 0.0, 0.0, sigma, sigma)] + [TimeOfArrival(s, 0.0, 1e-8) for s in "bc"]
    return build_problem(stations, measurements), np.array([30e3, 30e3, 1e3])


def _mirror():
    """Airborne stations, one raised by 700 m: an azimuth and three ranges fit the emitter's mirror through their
    plane nearly as well (a plausible second solution in most draws, a tie in many)."""
    offsets = [(0.0, 0.0, 10e3), (30e3, 5e3, 10.7e3), (8e3, 35e3, 10e3)]
    stations = [(f"s{k}", LocalPoint(e, n, u)) for k, (e, n, u) in enumerate(offsets)]
    measurements = [Bearing("s0", 0.0, None, np.deg2rad(0.5))] + [Range(s, 0.0, 10.0) for s, _ in stations]
    return build_problem(stations, measurements), np.array([14e3, 12e3, 2e3])


SCENES = {
    "along the hyperbola, (8, 8) km": lambda: ground_scene(8e3, 8e3),
    "behind the baseline, (25, 30) km": lambda: _ground(25e3, 30e3, 0.5, 10.0),
    "(8, 8) km at 1 deg and 30 ns": lambda: _ground(8e3, 8e3, 1.0, 30.0),
    "(6, 10) km, partly curved": lambda: _ground(6e3, 10e3, 0.5, 10.0),
    "3d, (30, 30, 1) km": _three_d,
    "bearing and ranges with a mirror": _mirror,
}
#: The refused share of the scenes where a tie is no rare event (the tie rule's, measured at this seed; a test
#: of the region may not buy its coverage by refusing answerable fixes).
REFUSED_AT_MOST = {"bearing and ranges with a mirror": 0.55}


@pytest.mark.slow
@pytest.mark.parametrize("scene", list(SCENES))
def test_the_stated_99_percent_region_holds_its_promise(scene):
    problem, target = SCENES[scene]()
    dof = 2 if problem.altitude_m is not None else 3
    rng = np.random.default_rng(4242)
    fixes = solve_batch([measure(problem, target, rng) for _ in range(TRIALS)], "auto")
    answered = [f for f in fixes if not isinstance(f, LocalizationError)]
    assert len(answered) >= (1.0 - REFUSED_AT_MOST.get(scene, 0.02)) * TRIALS
    errors = np.array([f.position_enu_m - target for f in answered])
    precision = np.linalg.pinv(np.array([f.covariance_enu_m2 for f in answered]), rcond=1e-9, hermitian=True)
    nees = np.einsum("ki,kij,kj->k", errors, precision, errors)
    outside = int(np.count_nonzero(nees > chi2.ppf(LEVEL, dof)))
    assert outside <= binom.ppf(0.995, len(answered), 1.0 - LEVEL), (outside, len(answered))
    # Widened to keep the promise, never below the error's second moment: the NEES mean is at most the dof.
    assert nees.mean() <= chi2.ppf(0.995, dof * nees.size) / nees.size
