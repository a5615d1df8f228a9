"""The batched closed forms (los_intersection, angle_range, taylor_wls) give every problem of a mixed batch
exactly what it gets alone: their sums run in measurement order, so padding to the batch's widest problem
and whatever else is in the batch change nothing (details and warnings included)."""

from __future__ import annotations

import numpy as np
import pytest

from core.estimators import solve_batch
from core.problem.build import Bearing, Range, build_problem
from core.problem.frame import GeodeticPoint, LocalPoint
from core.simulation.measurements import measure

from core.simulation import scenarios as sc
from tests.core.test_ml_batch import assert_same_fix, mixed_problems

SIGMA = 0.01
FLAT = [(f"s{i}", LocalPoint(x, y, z)) for i, (x, y, z) in
        enumerate([(0.0, 0.0, 0.0), (10e3, 0.0, 300.0), (5e3, 9e3, 0.0), (12e3, 7e3, 900.0), (-3e3, 6e3, 50.0)])]
CURVED = [(k, GeodeticPoint(np.deg2rad(a), np.deg2rad(b), c)) for k, (a, b, c) in
          {"a": (34.0, 108.5, 300.0), "b": (34.4, 108.9, 500.0), "c": (33.8, 109.1, 100.0)}.items()]


def bearings(stations, elevation=True, sigma=SIGMA):
    return [Bearing(k, 0.0, 0.0 if elevation else None, sigma, sigma if elevation else None) for k, _ in stations]


def problems():
    rng = np.random.default_rng(90)
    target = np.array([4e3, 5e3, 2e3])
    out = []
    for n in (2, 3, 5):
        out.append(measure(build_problem(FLAT[:n], bearings(FLAT[:n])), target, rng))
        out.append(measure(build_problem(FLAT[:n], bearings(FLAT[:n]) + [Range(k, 1.0, 20.0) for k, _ in FLAT[:n]]),
                           target, rng))
    out.append(measure(build_problem(FLAT, bearings(FLAT[:2]) + [Range("s0", 1.0, 20.0), Range("s4", 1.0, 20.0)]),
                       target, rng))
    surface = build_problem(CURVED, bearings(CURVED, elevation=False), altitude_m=3000.0)
    out.append(measure(surface, surface.frame.onto_altitude(np.array([2e4, 3e4, 3e3]), 3000.0), rng))
    unknown = build_problem(FLAT, bearings(FLAT, elevation=False, sigma=None), altitude_m=2e3, require_sigmas=False)
    out.append(measure(unknown.with_sigmas(np.full(5, SIGMA)), target, rng).with_sigmas(unknown.sigmas))
    mixed = unknown.with_sigmas(np.where(np.arange(5) % 2, SIGMA, np.nan))
    out.append(measure(mixed.with_sigmas(np.full(5, 2 * SIGMA)), target, rng).with_sigmas(mixed.sigmas))
    over = build_problem(FLAT[:1], bearings(FLAT[:1]) + [Range("s0", 1.0, 20.0)])
    out.append(measure(over, np.array([0.0, 0.0, 3e3]), rng))  # at the station's zenith
    scene = sc.paper_004(2.0, sigma_known=False)
    out.append(sc.build(scene, scene.measurements(rng)))
    return out + mixed_problems()


@pytest.mark.parametrize("method", ["los_intersection", "angle_range", "taylor_wls"])
def test_each_problem_gets_what_it_gets_alone(method):
    every = problems()
    together = solve_batch(every, method)
    assert sum(not isinstance(r, Exception) for r in together) >= 5
    for problem, batched in zip(every, together):
        assert_same_fix(batched, solve_batch([problem], method)[0])


def test_los_intersection_chunks_do_not_change_results(monkeypatch):
    import core.estimators.methods.line_of_sight_intersection as los
    from core.problem.batch import ProblemBatch
    from core.estimators import SolveOptions
    from core.estimators.base import get_estimator

    batch = ProblemBatch.from_problems(problems())
    spec = get_estimator("los_intersection")
    whole = spec.solve_batch(batch, SolveOptions())
    monkeypatch.setattr(los, "CHUNK_PAIRS", 20)
    chunked = spec.solve_batch(batch, SolveOptions())
    assert whole.errors.keys() == chunked.errors.keys() and len(whole.errors) < batch.size
    for b in range(batch.size):
        assert_same_fix(whole.fix(b), chunked.fix(b))
