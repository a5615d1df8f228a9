"""Measured honesty of the one-bearing + 2-TOA fixes: how many are refused, and the NEES of the answered ones.

The scenes of tests/core/estimators/test_ambiguity.py (an azimuth at a, TOAs at b and c, the altitude known)
at three targets, and the 3D one of test_second_solutions.py (azimuth and elevation at a, TOAs at b and c),
each over seeded draws at the scenes' noise (0.5 deg, 10 ns); with ``--held-out``, the scenes of
tests/core/estimators/test_stated_regions.py too (behind the baseline, other sigmas, a partly curved target,
another 3D target, bearing and ranges with a plausible mirror). For the answered fixes: the NEES of the truth
under each fix's covariance (mean, median; 2 dof with the altitude known, else 3), the share outside the
stated 99 % region (and the most a 1 % share allows at 99.5 %: the binomial bound), how many are over 2 km
off, and the warnings.

Usage: ``.venv/bin/python scripts/accuracy_second_solutions.py [--trials N] [--seed S] [--held-out]``.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.stats import binom, chi2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.errors import LocalizationError  # noqa: E402
from core.estimators import solve_batch  # noqa: E402
from core.problem.build import Bearing, TimeOfArrival, build_problem  # noqa: E402
from core.problem.frame import GeodeticPoint, LocalPoint  # noqa: E402
from core.simulation.measurements import measure  # noqa: E402

SIGMA_RAD, SIGMA_TOA_S = np.deg2rad(0.5), 1e-8
GROUND = [("a", GeodeticPoint(0.6, 1.9, 100.0)), ("b", GeodeticPoint(0.601, 1.905, 50.0)),
          ("c", GeodeticPoint(0.605, 1.899, 10.0))]


def ground(east_m: float, north_m: float):
    measurements = [Bearing("a", 0.0, None, SIGMA_RAD)] + [TimeOfArrival(s, 0.0, SIGMA_TOA_S) for s in "bc"]
    problem = build_problem(GROUND, measurements, altitude_m=0.0)
    return problem, problem.frame.onto_altitude(np.array([east_m, north_m, 0.0]), 0.0)


def in_3d():
    stations = [("a", LocalPoint(0.0, 0.0, 0.0)), ("b", LocalPoint(20e3, 0.0, 0.0)),
                ("c", LocalPoint(0.0, 25e3, 100.0))]
    measurements = [Bearing("a", 0.0, 0.0, SIGMA_RAD, SIGMA_RAD)] + [TimeOfArrival(s, 0.0, SIGMA_TOA_S) for s in "bc"]
    return build_problem(stations, measurements), np.array([12e3, 30e3, 2e3])


def report(name, problem, target, trials, seed):
    rng = np.random.default_rng(seed)
    fixes = solve_batch([measure(problem, target, rng) for _ in range(trials)], "auto")
    refused = Counter(f.code for f in fixes if isinstance(f, LocalizationError))
    answered = [f for f in fixes if not isinstance(f, LocalizationError)]
    dof = 2 if problem.altitude_m is not None else 3
    line = f"{name:24s} trials {trials} answered {len(answered):3d} refused {dict(refused)}"
    if answered:
        errors = np.array([f.position_enu_m - target for f in answered])
        precision = np.linalg.pinv(np.array([f.covariance_enu_m2 for f in answered]), rcond=1e-9, hermitian=True)
        nees = np.einsum("ki,kij,kj->k", errors, precision, errors)
        line += (f" NEES mean {nees.mean():.2f} median {np.median(nees):.2f} (dof {dof}) outside 99 % "
                 f"{np.mean(nees > chi2.ppf(0.99, dof)):.3f} "
                 f"(bound {binom.ppf(0.995, nees.size, 0.01) / nees.size:.3f})"
                 f" over 2 km {np.sum(np.linalg.norm(errors, axis=1) > 2e3)}"
                 f" warnings {dict(Counter(w.code for f in answered for w in f.warnings))}")
    print(line, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=300)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--held-out", action="store_true", help="the held-out scenes of test_stated_regions too")
    args = parser.parse_args()
    for east_m, north_m in [(8e3, 8e3), (3e3, 25e3), (20e3, -3e3)]:
        report(f"ground ({east_m / 1e3:.0f}, {north_m / 1e3:.0f}) km", *ground(east_m, north_m), args.trials, args.seed)
    report("3d (12, 30, 2) km", *in_3d(), args.trials, args.seed)
    if args.held_out:
        from tests.core.estimators.test_stated_regions import SCENES
        for name, scene in SCENES.items():
            report(name[:24], *scene(), args.trials, args.seed)


if __name__ == "__main__":
    main()
